"""Why the robust realistic front's aggressive points fail held-out: new payloads, fresh arms, or both.

``fosmc front`` checks every front point on :func:`fosmc_jax._problems.front_problems.held_out_config`'s
batch, which changes two things at once: the payloads (1, 3, 5, 7, 9 kg instead of 0 and 10 kg) and the
sampled arms (``[arm.uncertainty] seed`` + 1: fresh F, Kt, Kb draws). This script splits the two: it
evaluates the reference front's points whose mean chattering_hf lies in ``--band`` on four plain
problems (:func:`fosmc_jax._problems.build.plain_problem`):

    (a) training   the config itself (0 and 10 kg, arm seed 0): must reproduce the stored metrics
    (b) payloads   the held-out payloads, the training arms (arm seed 0)
    (c) arms       the training payloads, the fresh arms (arm seed 1)
    (d) held-out   both: held_out_config(cfg)

(b) and (c) are made from (d) by putting one factor back, so (b), (c), (d) differ in nothing else
(the sensors' seed of the held-out config is kept; the config's noise is zero, so it draws nothing).
Per point and batch: the mean rms_error over the surviving rollouts and the joints, divided by the
stored training one; per chattering band: points, share within 25%, median and max ratio, diverged
rollouts. For the worst points of (d): per rollout its payload, its arm draw (F, Kt, Kb factors) and
the joint carrying the error; per arm draw and payload the median ratio over the points. Two probes
(``--no-probes`` skips them): the worst points and points that hold, at every corner of the +-20% box
(``sampling = "vertices"``: would corner training have seen the failure?); and the fresh arms that fail
most, edited one factor at a time (clipped into the training draws' range, or put back to nominal:
which factor carries the failure, and is it being beyond the training draws?). Writes
``tuning/results/held_out_split_realistic_robust.md`` and ``.json``.

    .venv/bin/python tuning/held_out_split.py                      # band 0.5-3.3 V, every point in it
    .venv/bin/python tuning/held_out_split.py --band 1 2 --max-points 40
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import pathlib
import subprocess
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from fosmc_jax import METRIC_NAMES, mean_over_survivors  # noqa: E402
from fosmc_jax import config as fconfig  # noqa: E402
from fosmc_jax.io import write_text  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parent
CONFIG = ROOT / "configs/realistic_arm_robust.toml"
REFERENCE = ROOT / "results/reference/realistic_arm_robust/reference.json"
BANDS = ((0.5, 1.0), (1.0, 2.0), (2.0, 3.3))  # V, mean chattering_hf bands of the table
FACTORS = ("F", "Kt", "Kb")  # the [arm.uncertainty] fields that vary
BATCHES = {"a": "training", "b": "new payloads only", "c": "new arms only", "d": "held-out (both)"}
WITHIN = 0.25  # a point "holds" where |ratio - 1| <= WITHIN


def batch_configs(cfg):
    """The four configs (a)-(d): (b) and (c) are the held-out config with one factor put back."""
    held = fconfig.held_out_config(cfg)
    payloads = fconfig.replace(held, arm={"uncertainty": {"seed": cfg.arm.uncertainty.seed}})
    arms = fconfig.replace(held, plant={"payloads": list(cfg.plant.payloads)})
    return {"a": cfg, "b": payloads, "c": arms, "d": held}


def factors_of(cfg) -> np.ndarray:
    """The sampled arms' relative factors (arms, 9): F, Kt, Kb of joints 1-3, each drawn / nominal."""
    drawn, nominal = fconfig.arm_samples(cfg), cfg.arm.params
    return np.concatenate([drawn[k] / np.asarray(getattr(nominal, k), float) for k in FACTORS], axis=1)


def per_rollout(problem, params: dict, chunk: int, label: str) -> dict[str, np.ndarray]:
    """Every rollout's metrics (n, rollouts, 3) and ``diverged`` (n, rollouts) of the parameter sets
    ``params`` (leading axis n) on ``problem``: ``problem.simulate`` jitted and vmapped over ``chunk``
    sets at a time (the last chunk padded)."""

    def one(p):
        r = problem.simulate(p, checkpoint_every=0)
        return dict(r.metrics._asdict(), diverged=r.diverged)

    run = jax.jit(jax.vmap(one))
    n = len(params["delta"])
    parts, start = [], time.perf_counter()
    for i in range(0, n, chunk):
        part = {k: v[i : i + chunk] for k, v in params.items()}
        size = len(part["delta"])
        if size < chunk:
            part = {k: np.concatenate([v, np.repeat(v[-1:], chunk - size, 0)]) for k, v in part.items()}
        out = jax.tree.map(lambda x, size=size: np.asarray(x)[:size], run(part))
        parts.append(out)
        print(f"held_out_split: ({label}) {min(i + chunk, n)}/{n} points  {time.perf_counter() - start:7.1f} s",
              flush=True)  # fmt: skip
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def survivors_mean(x: np.ndarray, diverged: np.ndarray) -> np.ndarray:
    """Per point: mean over the surviving rollouts (:func:`mean_over_survivors`) and the joints."""
    return np.array([np.mean(mean_over_survivors(xi, di)) for xi, di in zip(x, diverged)])


def select(points: list, band: tuple[float, float], max_points: int | None) -> np.ndarray:
    """Indices of the points whose mean chattering_hf lies in [band), by chattering; at most
    ``max_points`` of them, evenly spaced in that order."""
    c = np.array([np.mean(p["metrics"]["chattering_hf"]) for p in points])
    idx = np.flatnonzero((c >= band[0]) & (c < band[1]))
    idx = idx[np.argsort(c[idx], kind="stable")]
    if max_points and len(idx) > max_points:
        idx = idx[np.round(np.linspace(0, len(idx) - 1, max_points)).astype(int)]
    return idx


def fmt_factors(f: np.ndarray) -> str:
    """F, Kt, Kb factors of joints 1-3 as 'F .97/.81/.85 Kt ... Kb ...'."""
    return " ".join(f"{k} " + "/".join(f"{x:.2f}" for x in f[3 * i : 3 * i + 3]) for i, k in enumerate(FACTORS))


def run_on_plants(problem, params: dict, label: str) -> tuple:
    """A function plants -> (rms_error (n, rollouts, 3), diverged (n, rollouts)) of the parameter
    sets ``params`` on ``problem`` with its plants replaced (one compilation for every set of plants
    of the same shape): ``problem.simulate`` jitted and vmapped over the sets."""
    one = lambda p, plants: problem._replace(plants=plants).simulate(p, checkpoint_every=0)
    run = jax.jit(jax.vmap(lambda p, plants: (lambda r: (r.metrics.rms_error, r.diverged))(one(p, plants)),
                           in_axes=(0, None)))  # fmt: skip

    def call(plants):
        t = time.perf_counter()
        rms, div = run(params, plants)
        print(f"held_out_split: {label}  {time.perf_counter() - t:6.1f} s", flush=True)
        return np.asarray(rms), np.asarray(div)

    return call


def corner_check(cfg, params: dict, train_rms: np.ndarray, chunk: int) -> dict:
    """Every corner of the +-20% box (``sampling = "vertices"``, all 2^9 corners) at the training
    payloads: per point its worst rollout ratio and the rollouts above 2x; over the failing
    rollouts, the share at each factor's low corner and at the heaviest payload."""
    vcfg = fconfig.replace(cfg, arm={"uncertainty": {"sampling": "vertices", "samples": 0}})
    problem = fconfig.build(vcfg)
    f = factors_of(vcfg)
    pays = np.asarray(vcfg.plant.payloads, float)
    f_roll, p_roll = np.repeat(f, len(pays), axis=0), np.tile(pays, len(f))
    res = per_rollout(problem, params, chunk, f"corners ({problem.rollouts} rollouts)")
    r = np.where(res["diverged"], np.nan, res["rms_error"].mean(2)) / train_rms[:, None]
    bad = r > 2
    low = {f"{FACTORS[k // 3]}{k % 3 + 1}": float(np.mean(np.broadcast_to(f_roll[:, k] < 1, bad.shape)[bad]))
           for k in range(9)}  # fmt: skip
    heavy = float(np.mean(np.broadcast_to(p_roll == pays.max(), bad.shape)[bad])) if bad.any() else np.nan
    return {"rollouts": int(problem.rollouts), "worst_ratio": np.nanmax(r, 1).tolist(),
            "above_2x": bad.sum(1).astype(int).tolist(), "diverged": res["diverged"].sum(1).astype(int).tolist(),
            "failing_share_at_low_corner": low, "failing_share_at_heaviest_payload": heavy}  # fmt: skip


def arm_edits(held, train_cfg, arm: int, params: dict, train_rms: np.ndarray) -> dict[str, np.ndarray]:
    """The fresh arm ``arm`` of the held-out batch at its payloads, as drawn and edited: each drawn
    factor outside the training draws' range clipped into it (alone, then all nine at once), and
    each of the nine put back to nominal alone; per edit, per point the worst rollout ratio."""
    problem = fconfig.build(held)
    n_pay = len(held.plant.payloads)
    rows = np.arange(arm * n_pay, (arm + 1) * n_pay)
    plants = jax.tree.map(lambda x: x[rows], problem.plants)
    problem = problem._replace(plants=plants)
    call = run_on_plants(problem, params, f"arm {arm}")
    f1, f0, nominal = factors_of(held)[arm], factors_of(train_cfg), held.arm.params
    lo, hi = f0.min(0), f0.max(0)

    def edited(changes: dict[int, float]):
        new = {}
        for k, factor in changes.items():
            field, j = FACTORS[k // 3], k % 3
            x = np.array(new.get(field, getattr(plants.params, field)))
            x[:, j] = np.asarray(getattr(nominal, field), float)[j] * factor
            new[field] = jax.numpy.asarray(x, x.dtype)
        return plants._replace(params=plants.params._replace(**new))

    name = lambda k: f"{FACTORS[k // 3]}{k % 3 + 1}"
    edits = {"as drawn": {}}
    outside = [k for k in range(9) if not lo[k] <= f1[k] <= hi[k]]
    for k in outside:
        edits[f"{name(k)} {f1[k]:.3f} -> {np.clip(f1[k], lo[k], hi[k]):.3f} (training range)"] = {
            k: float(np.clip(f1[k], lo[k], hi[k]))
        }
    if outside:
        edits["all nine clipped to the training range"] = {k: float(np.clip(f1[k], lo[k], hi[k])) for k in outside}
    for k in range(9):
        edits[f"{name(k)} {f1[k]:.3f} -> 1 (nominal)"] = {k: 1.0}
    out = {}
    for label, changes in edits.items():
        rms, div = call(edited(changes))
        out[label] = np.nanmax(np.where(div, np.nan, rms.mean(2)) / train_rms[:, None], 1)
    return out


def finite_or_none(x):
    """``x`` (nested lists, dicts, floats) with NaN and infinities as None: strict JSON."""
    if isinstance(x, dict):
        return {k: finite_or_none(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [finite_or_none(v) for v in x]
    return None if isinstance(x, float) and not np.isfinite(x) else x


def git_commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                              check=True).stdout.strip()  # fmt: skip
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--config", default=str(CONFIG))
    ap.add_argument("--reference", default=str(REFERENCE))
    ap.add_argument("--band", type=float, nargs=2, default=(0.5, 3.3), metavar=("LO", "HI"),
                    help="mean chattering_hf band (V) of the points evaluated")  # fmt: skip
    ap.add_argument("--max-points", type=int, default=0, help="at most this many points, evenly spaced (0: all)")
    ap.add_argument("--chunk", type=int, default=16, help="parameter sets per vmapped call")
    ap.add_argument("--worst", type=int, default=10, help="the worst points of (d) analysed per rollout")
    ap.add_argument("--no-probes", action="store_true", help="skip the corner check and the arm edits")
    ap.add_argument("--edit-arms", type=int, default=3, help="the fresh arms with most failures, edited")
    ap.add_argument("--edit-points", type=int, default=8, help="points per edited arm: those failing worst on it")
    ap.add_argument("--stem", default="held_out_split_realistic_robust")
    ap.add_argument("--out", default=str(ROOT / "results"))
    args = ap.parse_args(argv)
    command = " ".join([".venv/bin/python tuning/held_out_split.py", *(argv if argv is not None else sys.argv[1:])])
    load0, t0 = os.getloadavg(), time.perf_counter()
    date = datetime.datetime.now().astimezone().isoformat(timespec="seconds")
    commit = git_commit()
    print(f"held_out_split: {command}  (commit {commit}, load {load0[0]:.2f})", flush=True)

    cfg = fconfig.load(args.config)
    configs = batch_configs(cfg)
    assert configs["d"] == fconfig.held_out_config(cfg)
    reference = json.loads(pathlib.Path(args.reference).read_text())
    points = reference["points"]
    idx = select(points, tuple(args.band), args.max_points)
    chosen = [points[i] for i in idx]
    params = {k: np.array([p["params"][k] for p in chosen], float) for k in ("delta", "gamma", "poles")}
    stored = {k: np.array([p["metrics"][k] for p in chosen], float) for k in METRIC_NAMES}
    chat = stored["chattering_hf"].mean(1)
    train_rms = stored["rms_error"].mean(1)
    print(
        f"held_out_split: {len(idx)} points with mean chattering_hf in [{args.band[0]}, {args.band[1]}) V", flush=True
    )

    # the batches' layout: every arm draw with every payload, the arm first (fosmc_jax._problems.build._plants)
    layout, factors = {}, {}
    for b, c in configs.items():
        factors[b] = factors_of(c)
        pay = np.asarray(c.plant.payloads, float)
        layout[b] = (np.repeat(np.arange(len(factors[b])), len(pay)), np.tile(pay, len(factors[b])))

    results = {}
    for b, c in configs.items():
        problem = fconfig.build(c)
        assert problem.rollouts == len(layout[b][0]), (problem.rollouts, len(layout[b][0]))
        print(f"held_out_split: ({b}) {BATCHES[b]}: payloads {list(c.plant.payloads)}, arm seed "
              f"{c.arm.uncertainty.seed}, {problem.rollouts} rollouts", flush=True)  # fmt: skip
        results[b] = per_rollout(problem, params, args.chunk, b)

    # (a) against the stored training metrics
    rel = {}
    for k in METRIC_NAMES:
        mine = np.stack([mean_over_survivors(x, d) for x, d in zip(results["a"][k], results["a"]["diverged"])])
        scale = np.maximum(np.abs(stored[k]), 1e-12)
        rel[k] = float(np.max(np.where(np.abs(stored[k]) > 0, np.abs(mine - stored[k]) / scale, np.abs(mine))))
    worst_rel = max(rel.values())
    print(f"held_out_split: (a) vs stored training metrics, max relative difference {worst_rel:.2e} "
          f"({max(rel, key=rel.get)})", flush=True)  # fmt: skip

    ratio = {b: survivors_mean(r["rms_error"], r["diverged"]) / train_rms for b, r in results.items()}
    diverged = {b: r["diverged"].sum(1).astype(int) for b, r in results.items()}

    # per band
    rows = []
    for lo, hi in BANDS:
        sel = (chat >= lo) & (chat < hi)
        for b in "abcd":
            r = ratio[b][sel]
            if not sel.any():
                rows.append(f"| {lo:g}-{hi:g} | ({b}) {BATCHES[b]} | 0 | - | - | - | - |")
                continue
            within = np.mean(np.abs(r - 1) <= WITHIN)
            rows.append(f"| {lo:g}-{hi:g} | ({b}) {BATCHES[b]} | {sel.sum()} | {100 * within:.0f}% | "
                        f"{np.nanmedian(r):.3f} | {np.nanmax(r):.3g} | {diverged[b][sel].sum()} "
                        f"({np.sum(diverged[b][sel] > 0)} pts) |")  # fmt: skip

    # per rollout: each rollout's rms_error (mean over joints) over the point's training mean
    per_roll = {b: np.where(r["diverged"], np.nan, r["rms_error"].mean(2)) / train_rms[:, None]
                for b, r in results.items()}  # fmt: skip

    def arm_payload_table(b: str) -> list[str]:
        """Median over the points of each rollout's ratio, as a table arm draw x payload, and the
        share of points whose ratio there exceeds 2."""
        arms, pays = layout[b]
        ups = sorted(set(pays))
        med = np.nanmedian(per_roll[b], axis=0)
        bad = np.mean(per_roll[b] > 2, axis=0)  # NaN (diverged) counts as not > 2; diverged listed apart
        lines = ["| arm | factors F / Kt / Kb (joints 1/2/3) | " + " | ".join(f"{p:g} kg" for p in ups) + " |",
                 "|---|---|" + "---|" * len(ups)]  # fmt: skip
        for j in range(len(factors[b])):
            cells = []
            for p in ups:
                k = np.flatnonzero((arms == j) & (pays == p))[0]
                cells.append(f"{med[k]:.2f} ({100 * bad[k]:.0f}%)")
            lines.append(f"| {j} | {fmt_factors(factors[b][j])} | " + " | ".join(cells) + " |")
        return lines

    # the worst points of (d)
    order = np.argsort(-np.nan_to_num(ratio["d"], nan=np.inf))[: args.worst]
    worst_lines, worst_json = [], []
    arms_d, pays_d = layout["d"]
    for i in order:
        rr = per_roll["d"][i]
        top = np.argsort(-np.nan_to_num(rr, nan=np.inf))[:3]
        per_joint = results["d"]["rms_error"][i]
        desc = []
        for k in top:
            joint = int(np.argmax(per_joint[k])) + 1
            desc.append(f"{pays_d[k]:g} kg, arm {arms_d[k]} [{fmt_factors(factors['d'][arms_d[k]])}], "
                        f"{rr[k]:.3g}x, joint {joint} ({per_joint[k][joint - 1]:.3g} rad)")  # fmt: skip
        n_bad = int(np.sum(rr > 2))
        worst_lines.append(f"| {idx[i]} | {chat[i]:.2f} | {train_rms[i]:.3g} | {ratio['b'][i]:.3g} | "
                           f"{ratio['c'][i]:.3g} | {ratio['d'][i]:.3g} | {n_bad}/{len(rr)} | "
                           + "<br>".join(desc) + " |")  # fmt: skip
        worst_json.append({"point": int(idx[i]), "rollout_ratio": rr.tolist(),
                           "rollout_joint_rms": per_joint.tolist(), "diverged": results["d"]["diverged"][i].tolist()})  # fmt: skip

    # which arm draws and payloads carry the error: count over all points of rollouts above 2x
    def counts(b: str) -> tuple[dict, dict]:
        arms, pays = layout[b]
        over = per_roll[b] > 2
        by_arm = {int(j): int(over[:, arms == j].sum()) for j in range(len(factors[b]))}
        by_pay = {float(p): int(over[:, pays == p].sum()) for p in sorted(set(pays))}
        return by_arm, by_pay

    # correlation of each arm draw's median (over points and payloads) log ratio with its factors
    def correlations(b: str) -> dict[str, float]:
        arms, _ = layout[b]
        logs = np.log(np.where(per_roll[b] > 0, per_roll[b], np.nan))
        m = np.array([np.nanmedian(logs[:, arms == j]) for j in range(len(factors[b]))])
        rank = lambda x: np.argsort(np.argsort(x)).astype(float)
        out = {}
        for f in range(9):
            name = f"{FACTORS[f // 3]}{f % 3 + 1}"
            out[name] = float(np.corrcoef(rank(factors[b][:, f]), rank(m))[0, 1])
        return out

    # per joint: each rollout's rms_error on joint j over the point's stored training one on j; per arm
    # draw the median over points and payloads of its log, rank-correlated with the 9 factors
    stored_joint = stored["rms_error"]

    def joint_lines(b: str) -> list[str]:
        arms, _ = layout[b]
        r = np.where(results[b]["diverged"][..., None], np.nan, results[b]["rms_error"]) / stored_joint[:, None, :]
        rank = lambda x: np.argsort(np.argsort(x)).astype(float)
        names = [f"{FACTORS[f // 3]}{f % 3 + 1}" for f in range(9)]
        lines = ["| joint | rollouts > 2x | " + " | ".join(names) + " |", "|---|---|" + "---|" * 9]
        for j in range(3):
            m = np.array([np.nanmedian(np.log(r[:, arms == a, j])) for a in range(len(factors[b]))])
            corr = [np.corrcoef(rank(factors[b][:, f]), rank(m))[0, 1] for f in range(9)]
            lines.append(f"| {j + 1} | {int(np.sum(r[..., j] > 2))} | " + " | ".join(f"{c:+.2f}" for c in corr) + " |")
        return lines

    hull = []
    f0, f1 = factors["a"], factors["d"]
    for f in range(9):
        name = f"{FACTORS[f // 3]}{f % 3 + 1}"
        outside = [j for j in range(len(f1)) if f1[j, f] < f0[:, f].min() or f1[j, f] > f0[:, f].max()]
        hull.append(f"| {name} | {f0[:, f].min():.3f} - {f0[:, f].max():.3f} | {f1[:, f].min():.3f} - "
                    f"{f1[:, f].max():.3f} | {', '.join(map(str, outside)) or '-'} |")  # fmt: skip
    print("\n".join(hull), flush=True)

    count_lines = []
    for b in "bcd":
        by_arm, by_pay = counts(b)
        corr = correlations(b)
        count_lines += [f"- ({b}) {BATCHES[b]}: rollouts above 2x, by arm draw "
                        + ", ".join(f"{j}: {n}" for j, n in by_arm.items() if n)
                        + "; by payload " + ", ".join(f"{p:g} kg: {n}" for p, n in by_pay.items())
                        + ". Spearman of each arm's median log ratio with its factors: "
                        + ", ".join(f"{k} {v:+.2f}" for k, v in corr.items())]  # fmt: skip

    probe_lines, probes = [], {}
    if not args.no_probes:
        # corners: the worst points of (d) and as many points that hold in (d) at the same chattering
        c_lo, c_hi = chat[order].min(), chat[order].max()
        held_ok = np.flatnonzero((chat >= c_lo) & (chat <= c_hi) & (np.abs(ratio["d"] - 1) <= WITHIN))
        controls = held_ok[np.round(np.linspace(0, len(held_ok) - 1, min(len(order), len(held_ok)))).astype(int)]
        which = np.concatenate([order, controls]).astype(int)
        sub = {k: v[which] for k, v in params.items()}
        corners = corner_check(cfg, sub, train_rms[which], args.chunk)
        probes["corners"] = dict(corners, points=idx[which].tolist(), worst_of_d=len(order))
        probe_lines += [
            "## Probe 1: the corners of the box",
            "",
            f"Every corner of the +-20% box in F, Kt, Kb ({corners['rollouts']} rollouts: 512 corners x the training "
            f"payloads), for the {len(order)} worst points of (d) and {len(controls)} points of the same chattering "
            "range that hold in (d) (within 25%): the worst rollout's ratio (rollout rms_error, mean over joints, over "
            "the point's training mean), the rollouts above 2x, diverged rollouts.",
            "",
            "| point | in (d) | chattering_hf (V) | (d) ratio | worst corner ratio | corner rollouts > 2x | diverged |",
            "|---|---|---|---|---|---|---|",
            *[f"| {idx[w]} | {'worst' if n < len(order) else 'holds'} | {chat[w]:.2f} | {ratio['d'][w]:.3g} | "
              f"{corners['worst_ratio'][n]:.3g} | {corners['above_2x'][n]} | {corners['diverged'][n]} |"
              for n, w in enumerate(which)],
            "",
            "Over all the failing (> 2x) corner rollouts of these points: share at each factor's low corner (0.8): "
            + ", ".join(f"{k} {100 * v:.0f}%" for k, v in corners["failing_share_at_low_corner"].items())
            + f"; share at {max(cfg.plant.payloads):g} kg: {100 * corners['failing_share_at_heaviest_payload']:.0f}%.",
            "",
        ]  # fmt: skip
        # arm edits: the fresh arms with most failing rollouts in (d)
        by_arm, _ = counts("d")
        arms_d_, _ = layout["d"]
        top_arms = [a for a, n in sorted(by_arm.items(), key=lambda kv: -kv[1]) if n][: args.edit_arms]
        probe_lines += [
            "## Probe 2: the failing fresh arms, edited",
            "",
            f"For each of the {len(top_arms)} fresh arms with most rollouts above 2x in (d): the {args.edit_points} "
            "points failing worst on it, run on that arm at the held-out payloads as drawn and with one edit at a "
            "time: a factor outside the training draws' range clipped into it (then all of them), or a factor put "
            "back to nominal. Cells: the worst ratio over the payloads, per point.",
            "",
        ]
        probes["arm_edits"] = {}
        for a in top_arms:
            worst_on = np.argsort(-np.nan_to_num(np.nanmax(per_roll["d"][:, arms_d_ == a], 1), nan=np.inf))
            pick = worst_on[: args.edit_points]
            sub = {k: v[pick] for k, v in params.items()}
            edits = arm_edits(configs["d"], cfg, a, sub, train_rms[pick])
            probes["arm_edits"][str(a)] = {"points": idx[pick].tolist(), "factors": factors["d"][a].tolist(),
                                           "worst_ratio": {k: v.tolist() for k, v in edits.items()}}  # fmt: skip
            probe_lines += [
                f"Fresh arm {a} [{fmt_factors(factors['d'][a])}], points {', '.join(map(str, idx[pick]))}:",
                "",
                "| edit | " + " | ".join(str(idx[i]) for i in pick) + " | points within 2x |",
                "|---|" + "---|" * (len(pick) + 1),
                *[f"| {k} | " + " | ".join(f"{x:.3g}" for x in v) + f" | {int(np.sum(v <= 2))}/{len(v)} |"
                  for k, v in edits.items()],
                "",
            ]  # fmt: skip

    load1, wall = os.getloadavg(), time.perf_counter() - t0
    text = "\n".join([
        "# Held-out split: new payloads vs fresh arms (realistic_arm_robust)",
        "",
        f"`{command}`, commit {commit} (working tree as it was), {date}; load average {load0[0]:.2f} / "
        f"{load0[1]:.2f} / {load0[2]:.2f} at the start, {load1[0]:.2f} / {load1[1]:.2f} / {load1[2]:.2f} at the end; "
        f"{os.cpu_count()} cores; wall {wall:.0f} s.",
        "",
        f"Reference front {args.reference} ({len(points)} points); the {len(idx)} points with mean chattering_hf in "
        f"[{args.band[0]:g}, {args.band[1]:g}) V" + (f", at most {args.max_points} evenly spaced" if args.max_points
                                                  else "") + ", each evaluated on four plain problems:",
        "(a) the training batch (payloads "
        f"{list(configs['a'].plant.payloads)}, arm seed {configs['a'].arm.uncertainty.seed}, "
        f"{len(layout['a'][0])} rollouts), (b) the held-out payloads {list(configs['b'].plant.payloads)} on the training "
        f"arms ({len(layout['b'][0])}), (c) the training payloads on the fresh arms (arm seed "
        f"{configs['c'].arm.uncertainty.seed}, {len(layout['c'][0])}), (d) both: `held_out_config` "
        f"({len(layout['d'][0])}).",
        "",
        f"(a) against the stored training metrics: max relative difference {worst_rel:.2e} over the 8 metrics "
        f"({max(rel, key=rel.get)}; rms_error {rel['rms_error']:.2e}, chattering_hf {rel['chattering_hf']:.2e}).",
        "",
        "Ratio: the point's mean rms_error over the batch's surviving rollouts and the joints, divided by its stored "
        f"training one; within: |ratio - 1| <= {WITHIN:g}; diverged: rollouts (points with any).",
        "",
        "| chattering_hf (V) | batch | points | within 25% | median ratio | max ratio | diverged |",
        "|---|---|---|---|---|---|---|",
        *rows,
        "",
        "## Drawn arm factors (drawn / nominal), seed 0 (training) vs seed 1 (held-out)",
        "",
        "| factor | seed 0 min - max | seed 1 min - max | seed-1 arms outside seed 0's range |",
        "|---|---|---|---|",
        *hull,
        "",
        f"## The {len(order)} worst points of (d)",
        "",
        "Ratios of the point in (b), (c), (d); rollouts of (d) above 2x its training mean; its three worst rollouts "
        "of (d): payload, arm draw and its factors, the rollout's rms_error (mean over joints) over the training mean, "
        "the joint with the largest rms_error.",
        "",
        "| point | chattering_hf (V) | training rms (rad) | (b) | (c) | (d) | rollouts > 2x | worst rollouts of (d) |",
        "|---|---|---|---|---|---|---|---|",
        *worst_lines,
        "",
        "## Where the error sits: all points",
        "",
        *count_lines,
        "",
        "Per joint: rollouts (over all points) whose rms_error on the joint exceeds 2x the point's training "
        "rms_error on that joint, and the Spearman correlation over the 16 arm draws of each draw's median (over "
        "points and payloads) log ratio on the joint with each drawn factor (|rho| > 0.5: p < 0.05 roughly).",
        "",
        "(d) held-out:",
        "",
        *joint_lines("d"),
        "",
        "(c) fresh arms at 0 and 10 kg:",
        "",
        *joint_lines("c"),
        "",
        "(b) training arms at the new payloads:",
        "",
        *joint_lines("b"),
        "",
        "Per arm draw and payload of (d): median over the points of the rollout's rms_error (mean over joints) over "
        "the point's training mean, and (in brackets) the share of points where it exceeds 2.",
        "",
        *arm_payload_table("d"),
        "",
        "The same for (b) (training arms at the new payloads):",
        "",
        *arm_payload_table("b"),
        "",
        "The same for (c) (fresh arms at 0 and 10 kg):",
        "",
        *arm_payload_table("c"),
        "",
        "The same for (a) (training arms and payloads: the spread the training CVaR saw):",
        "",
        *arm_payload_table("a"),
        "",
        *probe_lines,
    ])  # fmt: skip
    data = {
        "command": command, "commit": commit, "date": date, "load_start_end": [load0, load1], "wall_s": wall,
        "band": list(args.band), "max_relative_difference_training": rel,
        "batches": {b: {"payloads": list(c.plant.payloads), "arm_seed": c.arm.uncertainty.seed,
                        "rollout_arm": layout[b][0].tolist(), "rollout_payload": layout[b][1].tolist(),
                        "arm_factors_F_Kt_Kb": factors[b].tolist()} for b, c in configs.items()},
        "points": [{"index": int(i), "chattering_hf": float(chat[n]), "training_rms_error": float(train_rms[n]),
                    **{f"ratio_{b}": float(ratio[b][n]) for b in "abcd"},
                    **{f"diverged_{b}": int(diverged[b][n]) for b in "abcd"}} for n, i in enumerate(idx)],
        "worst": worst_json,
        "probes": probes,
    }  # fmt: skip
    out = pathlib.Path(args.out)
    write_text(out / f"{args.stem}.md", text)
    write_text(out / f"{args.stem}.json", json.dumps(finite_or_none(data), indent=1, allow_nan=False))
    print(text, flush=True)


if __name__ == "__main__":
    main()
