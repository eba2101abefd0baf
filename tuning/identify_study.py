"""From a log to a tuned front, checked on the arm that made the log (issue 26, part 2).

    .venv/bin/python tuning/identify_study.py [--budget 60] [--seed 0] [--out tuning/results/identify_study]
                                              [--keep-fronts]

1. A hidden arm: the calibrated one (``fosmc_jax.ARM_PARAMS``) with F, R, L, Kt = Kb, Jm and m3
   moved by 20-30% (sizes and signs drawn with ``--seed``).
2. Its log: the realistic preset's loop (the FOSMC at 1 kHz, a 2.6M-count encoder, one sample of
   delay, 24 V) tracking the paper's cycloid with 5 kg for 4 s, simulated at the preset's dt =
   1e-4 s and logged as a drive logs it: the encoder's reading, the voltage computed at each
   sample (applied one sample later).
3. ``fosmc identify`` (the command line, in a subprocess) of F, R, L, Kt, Kb, Jm and m3 from the
   calibrated arm: from angles and voltages each joint's R, L and Kt are one group (R fixed, L
   and Kt scaled with it), and friction too small beside the motors' back-EMF damping stays as
   configured.
4. ``fosmc front`` (``fosmc_jax.run_front``, ``--budget`` s each) on the realistic preset (payloads
   0 and 10 kg) with three arms: the identified one, the calibrated one (tuning without
   identification), and the hidden one itself (the best a front can do).
5. Every front's points re-evaluated on the hidden arm (``fosmc_jax.search.Evaluator``): the
   error obtained against the error predicted, per point (the same parameters), and at the same
   chattering: the front the points make on the hidden arm (their non-dominated ones), its error
   interpolated in log-log at each point's predicted chattering, over the predicted error.

Prints the comparison and writes ``summary.json`` (with every front point's two axes, predicted
and obtained), ``summary.md``, the log (``log.npz``) and the identification (``identify/``) to
``--out``, and with ``--keep-fronts`` the fronts (``front_<arm>/``, 1-2 MB each).
"""

from __future__ import annotations

import argparse
import copy
import json
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

import fosmc_jax as fj  # noqa: E402
import fosmc_jax.search as fs  # noqa: E402

fj.use_all_cores()  # as the command line: the fronts' chunks split over the cores

try:  # Python >= 3.11
    import tomllib
except ModuleNotFoundError:  # pragma: no cover - Python 3.10
    import tomli as tomllib

PERTURBED = ("F", "R", "L", "Kt", "Jm", "m3")
FITTED = "F,R,L,Kt,Kb,Jm,m3"
PAYLOAD = 5.0  # kg, the experiment's (known)


def hidden_arm(seed: int) -> dict:
    """The calibrated arm with each entry of PERTURBED times 1 +- U(0.2, 0.3); Kb = Kt (SI)."""
    rng = np.random.default_rng(seed)
    arm = {}
    for k in PERTURBED:
        v = np.asarray(getattr(fj.ARM_PARAMS, k), float)
        arm[k] = (v * (1 + rng.choice([-1.0, 1.0], v.shape) * rng.uniform(0.2, 0.3, v.shape))).tolist()
    arm["Kb"] = arm["Kt"]
    return arm


def write_log(arm: dict, path: Path) -> None:
    """The realistic preset's closed loop on ``arm`` at PAYLOAD for 4 s, logged to an NPZ file."""
    cfg = fj.config.load("realistic_arm").as_dict()
    cfg["arm"].update(arm)
    cfg["plant"]["payloads"] = [PAYLOAD]
    m = round(cfg["controller"]["sample_period"] / cfg["sim"]["dt"])
    cfg["sim"]["save_every"] = m
    trace = fj.build(cfg).simulate().trace
    t, X, U = (np.asarray(a[0]) for a in (trace.t, trace.X, trace.U))
    counts = jnp.asarray(cfg["sensors"]["encoder_counts"], float)
    theta = np.asarray(fj.quantize(jnp.asarray(X[:, 0::3]), counts))
    u = np.concatenate([U[1:], U[-1:]])  # the voltage computed at t_j reaches the motor at t_j+1
    np.savez(path, t=t, theta=theta, u=u)


def config_with(arm: dict) -> dict:
    """The realistic preset (payloads 0 and 10 kg) with ``arm``'s [arm] entries."""
    cfg = fj.config.load("realistic_arm").as_dict()
    cfg["arm"].update(copy.deepcopy(arm))
    return fj.config.resolve(cfg)


def evaluate(points: list[dict], cfg: dict) -> tuple[np.ndarray, np.ndarray]:
    """Mean rms_error (rad) and chattering_hf (V) of each front point's parameters on ``cfg``."""
    plain, _, p0 = fj.config.tuning_problems(cfg)
    batch = type(p0)(*(jnp.asarray(np.stack([np.asarray(pt["params"][n]) for pt in points])) for n in p0._fields))
    m = fs.Evaluator(plain)(batch, chunk=16, log=lambda _: None)
    return fs.axes(m)


def at_same_chattering(c_pred, e_pred, c_got, e_got) -> np.ndarray:
    """The front obtained on the hidden arm (the non-dominated ones of the evaluated points) over
    the predicted one, at each point's predicted chattering: the obtained front's error,
    interpolated in log-log at c_pred, over e_pred; NaN outside the obtained front's range."""
    keep = fs.nondominated(e_got, c_got)
    order = np.argsort(c_got[keep])
    lc, le = np.log(c_got[keep][order]), np.log(e_got[keep][order])
    inside = (c_pred >= np.exp(lc[0])) & (c_pred <= np.exp(lc[-1]))
    return np.where(inside, np.exp(np.interp(np.log(c_pred), lc, le)) / e_pred, np.nan)


def spread(x) -> dict:
    """Median, least and largest of the finite values of ``x``, and how many there are."""
    x = np.asarray(x)[np.isfinite(x)]
    return {"median": float(np.median(x)), "min": float(x.min()), "max": float(x.max()), "compared": int(x.size)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--budget", type=float, default=60.0, help="fosmc front's budget per arm, s (default 60)")
    ap.add_argument("--seed", type=int, default=0, help="the hidden arm's draw (default 0)")
    ap.add_argument("--out", default="tuning/results/identify_study", help="output folder")
    ap.add_argument("--keep-fronts", action="store_true", help="keep the fronts' folders (1-2 MB each)")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    hidden = hidden_arm(args.seed)
    log_path = out / "log.npz"
    write_log(hidden, log_path)
    print(f"identify_study: the hidden arm's log, {log_path} ({time.perf_counter() - start:.0f} s)")

    config = out / "experiment.toml"
    config.write_text(
        f'[plant]\nkind = "arm"\npayloads = [{PAYLOAD}]\n[controller]\nsample_period = 1e-3\ndelay_samples = 1\n'
        "[sensors]\nencoder_counts = 2621440\n"
    )
    t0 = time.perf_counter()
    cmd = [sys.executable, "-m", "fosmc_jax", "identify", "--config", str(config), "--data", str(log_path),
           "--params", FITTED, "--out", str(out / "identify"), "--force"]  # fmt: skip
    done = subprocess.run(cmd, capture_output=True, text=True)
    print(done.stdout)
    if done.returncode:
        print(done.stderr, file=sys.stderr)
        return done.returncode
    identify_s = time.perf_counter() - t0
    report = json.loads((out / "identify" / "identify.json").read_text())
    identified = tomllib.loads((out / "identify" / "identified.toml").read_text())["arm"]
    entries = []
    for e in report["entries"]:
        truth = np.ravel(hidden.get(e["field"], getattr(fj.ARM_PARAMS, e["field"])))[e["index"]]
        entries.append({**{k: e[k] for k in ("name", "status", "initial", "estimate", "relative_std")},
                        "hidden": float(truth), "error": e["estimate"] / truth - 1})  # fmt: skip
    invariants = {}
    for j in range(3):  # what the angles see of each R, L, Kt group
        for k in ("L", "Kt"):
            got = identified[k][j] / identified["R"][j]
            invariants[f"{k}[{j + 1}]/R[{j + 1}]"] = got / (hidden[k][j] / hidden["R"][j]) - 1

    arms = {"identified": {k: v for k, v in identified.items() if k != "payload_range"},
            "calibrated": {}, "hidden": hidden}  # fmt: skip
    hidden_cfg = config_with(hidden)
    rows = {}
    for name, arm in arms.items():
        t0 = time.perf_counter()
        folder = out / f"front_{name}" if args.keep_fronts else None
        front = fj.run_front(config_with(arm), budget=args.budget, out=folder, force=True)
        pts = front["points"]
        e_pred = np.array([np.mean(p["metrics"]["rms_error"]) for p in pts])
        c_pred = np.array([np.mean(p["metrics"]["chattering_hf"]) for p in pts])
        e_got, c_got = (np.asarray(x) for x in evaluate(pts, hidden_cfg))
        same = at_same_chattering(c_pred, e_pred, c_got, e_got)
        rows[name] = {
            "points": len(pts),
            "front_s": time.perf_counter() - t0,
            "error_ratio_per_point": spread(e_got / e_pred),
            "chattering_ratio_per_point": spread(c_got / c_pred),
            "error_ratio_same_chattering": spread(same),
            "within_25_percent": int(np.sum(np.abs(same[np.isfinite(same)] - 1) <= 0.25)),
            "within_25_percent_per_point": int(np.sum(np.abs(e_got / e_pred - 1) <= 0.25)),
            "worst": [
                {
                    "predicted_chattering_hf": float(c_pred[i]),
                    "predicted_rms_error": float(e_pred[i]),
                    "ratio": float(same[i]),
                }
                for i in np.argsort(-np.abs(np.nan_to_num(same, nan=1.0) - 1))[:3]
            ],  # fmt: skip
            "diverged_on_hidden_arm": int(np.sum(~np.isfinite(e_got))),
            "predicted": {"rms_error": e_pred.tolist(), "chattering_hf": c_pred.tolist()},
            "on_hidden_arm": {"rms_error": e_got.tolist(), "chattering_hf": c_got.tolist()},
        }
        print(f"identify_study: front on the {name} arm: {len(pts)} points; on the hidden arm the error is "
              f"{rows[name]['error_ratio_same_chattering']['median']:.3f} x predicted at the same chattering (median; "
              f"range {rows[name]['error_ratio_same_chattering']['min']:.3f}-"
              f"{rows[name]['error_ratio_same_chattering']['max']:.3f}), "
              f"{rows[name]['within_25_percent']} of {rows[name]['error_ratio_same_chattering']['compared']} "
              f"points within 25% (per point, the same parameters: {rows[name]['within_25_percent_per_point']} of "
              f"{len(pts)})")  # fmt: skip

    summary = {"seed": args.seed, "budget": args.budget, "hidden_arm": hidden, "payload": PAYLOAD, "fitted": FITTED,
               "identify_s": identify_s, "entries": entries, "invariants": invariants,
               "groups": report["groups"], "fronts": rows, "wall_s": time.perf_counter() - start}  # fmt: skip
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    (out / "summary.md").write_text(markdown(summary))
    print(markdown(summary))
    return 0


def markdown(s: dict) -> str:
    lines = [f"# From a log to a tuned front (seed {s['seed']}, budget {s['budget']:g} s per front)", "",
             f"fosmc identify of {s['fitted']} took {s['identify_s']:.0f} s (load-dependent).", "",
             "| entry | status | calibrated | identified | hidden | error | relative std |", "|---|---|---:|---:|---:|---:|---:|"]  # fmt: skip
    for e in s["entries"]:
        std = "" if e["relative_std"] is None else f"{100 * e['relative_std']:.2g}%"
        lines.append(f"| {e['name']} | {e['status']} | {e['initial']:.5g} | {e['estimate']:.5g} | {e['hidden']:.5g} "
                     f"| {100 * e['error']:+.2f}% | {std} |")  # fmt: skip
    lines += ["", "What the angles see of each R, L, Kt group (identified / hidden - 1): "
              + ", ".join(f"{k} {100 * v:+.2f}%" for k, v in s["invariants"].items()), "",
              "| front tuned on | points | error on the hidden arm / predicted, same chattering: median [min, max] "
              "| within 25% | per point: error | within 25% | per point: chattering |", "|---|---:|---|---:|---|---:|---|"]  # fmt: skip
    for name, r in s["fronts"].items():
        a, p, c = r["error_ratio_same_chattering"], r["error_ratio_per_point"], r["chattering_ratio_per_point"]
        lines.append(f"| {name} arm | {r['points']} | {a['median']:.3f} [{a['min']:.3f}, {a['max']:.3f}] "
                     f"({a['compared']} compared) | {r['within_25_percent']} | {p['median']:.3f} "
                     f"[{p['min']:.3f}, {p['max']:.3f}] | {r['within_25_percent_per_point']} | {c['median']:.3f} "
                     f"[{c['min']:.3f}, {c['max']:.3f}] |")  # fmt: skip
    lines += ["", "Per point: obtained / predicted of the same parameters (error; chattering_hf). Same chattering: "
              "the front the points make on the hidden arm (their non-dominated ones), its error interpolated "
              "(log-log) at each point's predicted chattering, over the predicted error. Farthest points, by "
              "predicted chattering_hf (V) and that ratio:", ""]  # fmt: skip
    for name, r in s["fronts"].items():
        worst = ", ".join(f"{w['predicted_chattering_hf']:.3g} V: {w['ratio']:.3f}" for w in r["worst"])
        lines.append(f"- {name} arm: {worst}")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
