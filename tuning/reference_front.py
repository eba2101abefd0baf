"""Reference fronts per config, and scores against them.

A config's reference front is the non-dominated union, in (mean ``rms_error``, mean
``chattering_hf``) on the config's plain problem, of long runs of every method: ``fosmc front``,
CMA-ES (:func:`fosmc_jax.search.cma_front`) and NSGA-II (:func:`fosmc_jax.search.nsga2`),
every candidate re-evaluated with the current code (the metric definitions change: the
committed fronts of tuning/results/front_realistic_15min_* predate today's ``chattering_hf``).
A front is scored by the additive epsilon indicator in log10 of both axes against the
reference points with ``chattering_hf`` in [0.1, 10] V (and [0.5, 10] V): the smallest eps
such that for every such reference point r some point a of the front has log10 a_err <=
log10 r_err + eps and log10 a_chat <= log10 r_chat + eps (0: the front reaches the
reference everywhere; 0.02: it misses it by 10^0.02 = 4.7% somewhere, in one metric or the
other, and nowhere by more); points with a diverged rollout never count.

    # one method's run: its non-dominated candidates (plain metrics) to
    # tuning/results/reference/<config>/<method>.json (the front: its front.json's points; the
    # CLI's own files in <config>/front/), every candidate to --save-all's .npz
    .venv/bin/python tuning/reference_front.py build --config tuning/configs/realistic_arm.toml \\
        --method nsga2 --budget 900 --save-all /tmp/ref_realistic_arm_nsga2_all.npz
    .venv/bin/python tuning/reference_front.py build --config tuning/configs/realistic_arm.toml --method front --budget 900
    .venv/bin/python tuning/reference_front.py build --config tuning/configs/realistic_arm.toml --method cma \\
        --budget 900 --weights-from tuning/results/reference/realistic_arm/front/front.json
    .venv/bin/python tuning/reference_front.py build --config tuning/configs/unseen_arm.toml --method front --budget 600
    .venv/bin/python tuning/reference_front.py build --config tuning/configs/unseen_arm.toml --method cma --budget 600 \\
        --weights-from tuning/results/reference/unseen_arm/front/front.json
    .venv/bin/python tuning/reference_front.py build --config tuning/configs/unseen_arm.toml --method nsga2 --budget 600

    # the non-dominated union, re-evaluated: tuning/results/reference/<config>/reference.json
    .venv/bin/python tuning/reference_front.py merge --config tuning/configs/realistic_arm.toml \\
        tuning/results/front_realistic_15min_polish/front.json tuning/results/front_realistic_15min_cma/front.json \\
        tuning/results/front_realistic_15min_plaincma/front.json tuning/results/frontier_realistic_15min_polish.json \\
        tuning/results/frontier_realistic_15min_cma.json tuning/results/frontier_realistic_15min_plaincma.json \\
        tuning/results/frontier_realistic_15min.json tuning/results/reference/realistic_arm/{nsga2,front,cma}.json
    .venv/bin/python tuning/reference_front.py merge --config tuning/configs/unseen_arm.toml \\
        tuning/results/reference/unseen_arm/{front,cma,nsga2}.json

    # scores: a front.json, a method's json, a frontier_<name>.json (each of its methods) or a
    # fosmc tune result.json (also by how much the reference beats its one point)
    .venv/bin/python tuning/reference_front.py score tuning/results/reference/unseen_arm/cma.json \\
        --reference tuning/results/reference/unseen_arm/reference.json

A method's json holds its non-dominated points only (no diverged rollout): they are all that
can enter the union, and a candidate costs 2-3 ms on the arm's native kernel, so a 15-minute
run evaluates some 10^5 candidates (``--save-all`` keeps them all, compressed, outside the
repository). CMA-ES is restarted with the next seed while budget is left (pycma stops a run at
its own criteria). Inputs of ``merge``: a ``fosmc front`` front.json (its ``points``), a
``frontier_<name>.json`` (every method's ``points``, labelled by method) or a method's json of
``build``; every point is re-evaluated on the plain problem (for a method's json, built with
the current code, the largest relative change of its stored axes is printed: a check). Each
file records the commit and a hash of the uncommitted diff of fosmc_jax/ it ran with. Progress
lines go to stdout, prefixed by the time.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import pathlib
import shlex
import subprocess
import sys
import time

import fosmc_jax

fosmc_jax.use_all_cores()  # every chunk split over every core, as `fosmc front` does
import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from fosmc_jax import METRIC_NAMES  # noqa: E402
from fosmc_jax import config as _config  # noqa: E402
from fosmc_jax import search as fs  # noqa: E402
from fosmc_jax.io import jsonable, write_text  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[1]
OUT = ROOT / "tuning" / "results" / "reference"
#: chattering_hf bands (V) the epsilon is taken over: the reference points inside count
BANDS = ((0.1, 10.0), (0.5, 10.0))
CHUNK = 64
METHODS = ("front", "cma", "nsga2", "optuna_nsga2")


def log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)


def cache_env() -> dict[str, str]:
    """The environment for a child process that shares the package's persistent compilation
    cache (``fosmc_jax.use_compilation_cache``'s folder and compile-time threshold), as the CLI
    uses it: every method of a study then runs from the same warm caches."""
    folder = fosmc_jax.use_compilation_cache()
    if folder is None:
        return dict(os.environ)
    threshold = jax.config.jax_persistent_cache_min_compile_time_secs
    return dict(
        os.environ, JAX_COMPILATION_CACHE_DIR=str(folder), JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS=str(threshold)
    )


def load_text() -> str:
    """The 1-, 5- and 15-minute load averages, as ``uptime`` gives them."""
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


# ---------------------------------------------------------------------------- scores


def hv_reference(e: np.ndarray, c: np.ndarray) -> tuple[float, float]:
    """The hypervolume's fixed reference point of a reference front (log10 c, log10 e): the
    upper end of the scored band (10 V) and half a decade above the largest error of the
    reference points in it."""
    band = (c >= BANDS[0][0]) & (c <= BANDS[0][1])
    return float(np.log10(BANDS[0][1])), float(np.log10(e[band].max()) + 0.5)


def score(front: tuple[np.ndarray, np.ndarray], reference: dict) -> dict:
    """Epsilons over :data:`BANDS` and hypervolume of a front (errors, chatterings; no
    diverged points) against a reference.json's content; ``epsilon_at``: the reference point
    (chattering_hf, rms_error) where the first band's epsilon is reached; ``median_gap``: the
    median over the front's non-dominated points in the first band of how far the reference
    beats each (``fosmc_jax.search.dominated_by``, log10; <= 0: on or past the reference). The
    epsilon is the worst place the front covers, the median gap how close its typical point is."""
    re, rc = axes(reference["points"])
    out = {}
    for lo, hi in BANDS:
        band = (rc >= lo) & (rc <= hi)
        out[f"epsilon_{lo:g}_{hi:g}"] = fs.additive_epsilon(front, (re[band], rc[band]))
    # where the first band's epsilon is reached: the reference point the front is farthest from
    band = (rc >= BANDS[0][0]) & (rc <= BANDS[0][1])
    if band.any() and len(front[0]):
        (ae, ac), (be, bc) = np.log10(front), np.log10((re[band], rc[band]))
        worst = int(np.argmax(np.min(np.maximum(ae[:, None] - be, ac[:, None] - bc), axis=0)))
        out["epsilon_at"] = [float(rc[band][worst]), float(re[band][worst])]  # (chattering_hf V, rms_error rad)
    e, c = (np.asarray(x, float) for x in front)
    own = fs.nondominated(e, c) & (c >= BANDS[0][0]) & (c <= BANDS[0][1])
    if own.any():
        out["median_gap"] = float(np.median([fs.dominated_by(pt, (re, rc)) for pt in zip(e[own], c[own])]))
    out["hypervolume"] = fs.hypervolume(*front, tuple(reference["hv_reference_log10"]))
    out["reference_hypervolume"] = fs.hypervolume(re, rc, tuple(reference["hv_reference_log10"]))
    return out


def axes(points: list[dict]) -> tuple[np.ndarray, np.ndarray]:
    """Mean rms_error and chattering_hf of JSON points."""
    return tuple(np.array([np.mean(p["metrics"][k]) for p in points], float) for k in fs.AXES)


# ---------------------------------------------------------------------------- files


def points_of(path: str | pathlib.Path) -> dict[str, list[dict]]:
    """The points of a file by label: a front.json's (label: its folder), a frontier_<name>.json's
    (one label per method) or a method's json of ``build`` (its method; ``method (folder)`` where
    ``build --out`` put it in a folder of its own, as the references' seeds); each point {params,
    metrics, diverged}."""
    path = pathlib.Path(path)
    data = json.loads(path.read_text())
    if "methods" in data:  # frontier_<name>.json
        name = path.stem.removeprefix("frontier_")
        return {f"{name}: {label}": m["points"] for label, m in data["methods"].items()}
    if "method" in data:  # a method's json of build
        own = path.resolve().parent.parent == OUT  # <OUT>/<config>/<method>.json
        return {data["method"] if own else f"{data['method']} ({path.parent.name})": data["points"]}
    if "final" in data:  # a fosmc tune result.json: its one point
        return {f"{path.parent.name} (tune)": [data["final"]]}
    return {path.parent.name: data["points"]}


def params_of(points: list[dict], p0):
    """Parameter sets of p0's kind (leading axis n) from JSON points."""
    return type(p0)(*(np.array([p["params"][k] for p in points], float) for k in p0._fields))


def evaluate(plain, p0, points: list[dict], what: str) -> dict:
    """Plain metrics of JSON points, in chunks of :data:`CHUNK`, with progress lines."""
    t0 = time.perf_counter()
    last = [t0]

    def progress(msg):
        if time.perf_counter() - last[0] > 30:
            last[0] = time.perf_counter()
            log(f"{what}: {msg}")

    m = fs.evaluate_many(plain, params_of(points, p0), CHUNK, log=progress, what="re-evaluating")
    log(f"{what}: {len(points)} points re-evaluated in {time.perf_counter() - t0:.0f} s (load {load_text()})")
    return m


def code_state() -> dict:
    """The commit and a SHA-1 of ``git diff HEAD -- fosmc_jax`` (None: no uncommitted change)
    the run used."""
    git = lambda *a: subprocess.run(["git", *a], cwd=ROOT, capture_output=True, text=True).stdout
    diff = git("diff", "HEAD", "--", "fosmc_jax")
    return {"commit": git("rev-parse", "HEAD").strip(), "fosmc_jax_diff_sha1": hashlib.sha1(diff.encode()).hexdigest()
            if diff else None}  # fmt: skip


def config_name(path: str) -> str:
    return pathlib.Path(path).stem


# ---------------------------------------------------------------------------- build


def throttled(every: float = 10.0):
    """:func:`log`, at most one line per ``every`` seconds (a generation costs 0.1-0.2 s)."""
    last = [-np.inf]

    def out(msg: str) -> None:
        if time.perf_counter() - last[0] >= every:
            last[0] = time.perf_counter()
            log(msg)

    return out


def build(args) -> dict:
    """Run one method on the config's plain problem for the budget; write its non-dominated
    candidates (no diverged rollout) with their plain metrics to <OUT>/<config>/<method>.json
    (the front: its front.json's points), and every candidate it evaluated to ``--save-all``
    (.npz) when given; ``--out``: another folder than <OUT>/<config>. CMA-ES
    (:func:`fosmc_jax.search.cma_front`) is restarted with the next seed while budget is left:
    pycma stops a run at its own criteria (tolfun, ...)."""
    cfg = _config.load(args.config)
    name = config_name(args.config)
    folder = pathlib.Path(args.out) if args.out else OUT / name
    folder.mkdir(parents=True, exist_ok=True)
    start, load0 = time.perf_counter(), load_text()
    command = " ".join(shlex.quote(a) for a in [".venv/bin/python", "tuning/reference_front.py", *sys.argv[1:]])
    extra, code = {}, code_state()
    plain, _, p0 = _config.tuning_problems(cfg)
    if args.method == "front":  # the CLI, as a user runs it; its files in <config>/front/
        cli = [str(ROOT / ".venv" / "bin" / "fosmc"), "front", "--config", args.config, "--budget", f"{args.budget:g}",
               "--seed", str(args.seed), "--out", str(folder / "front"), "--force"]  # fmt: skip
        log("running " + " ".join(cli))
        subprocess.run(cli, check=True)
        front = json.loads((folder / "front" / "front.json").read_text())
        pts = front["points"]
        z, m = None, {k: np.array([p["metrics"][k] for p in pts]) for k in METRIC_NAMES}
        params, m["diverged"] = params_of(pts, p0), np.array([p["diverged"] for p in pts])
        extra = {"evaluations": front["stages"]["evaluations"] + front["stages"].get("plain_evaluations", 0),
                 "stages": front["stages"], "cli": "fosmc " + " ".join(cli[1:]).replace(f"{ROOT}/", ""),
                 "note": "evaluations: training + plain; points: its front.json's"}  # fmt: skip
        (folder / "front" / "checkpoint.npz").unlink(missing_ok=True)
    else:
        if args.method == "cma":
            if args.weights:
                weights = [float(w) for w in args.weights.split(",")]
            else:  # tuning/frontier.py's: the slopes of the front at four points along it
                pts = json.loads(pathlib.Path(args.weights_from).read_text())["points"]
                front_m = {k: np.array([p["metrics"][k] for p in pts]) for k in fs.AXES}
                weights = fs.pick_starts(dict(front_m, diverged=np.array([p["diverged"] for p in pts])), 4)[1].tolist()
            runs, seed = [], args.seed
            while not runs or time.perf_counter() - start < args.budget - 1.0:
                left = args.budget - (time.perf_counter() - start)
                runs.append(fs.cma_front(plain, p0, weights, left, seed=seed, log=throttled()))
                log(f"cma: seed {seed}: {len(runs[-1]['z'])} evaluations, {time.perf_counter() - start:.0f} s")
                seed += 1
            r = {
                "z": np.concatenate([x["z"] for x in runs]),
                "metrics": {k: np.concatenate([x["metrics"][k] for x in runs]) for k in runs[0]["metrics"]},
            }
            extra.update(cma_weights=weights, cma_seeds=list(range(args.seed, seed)))
        elif args.method == "nsga2":
            r = fs.nsga2(plain, p0, args.budget, popsize=args.popsize, seed=args.seed, log=throttled())
        else:
            r = fs.optuna_nsga2(plain, p0, args.budget, popsize=args.popsize, seed=args.seed, log=throttled())
        z, m = r["z"], r["metrics"]
        params = fs.from_factors(p0, z)
        extra["evaluations"] = len(z)
    wall = time.perf_counter() - start
    e, c = np.mean(m["rms_error"], -1), np.mean(m["chattering_hf"], -1)
    ok = np.asarray(m["diverged"]) == 0
    keep = np.flatnonzero(fs.nondominated(np.where(ok, e, np.nan), c))
    if args.save_all:
        np.savez_compressed(args.save_all, **({} if z is None else {"z": z}),
                            **{f"params_{k}": np.asarray(v) for k, v in params._asdict().items()},
                            **{f"metrics_{k}": np.asarray(v) for k, v in m.items()})  # fmt: skip
        log(f"build {args.method}: every candidate to {args.save_all}")
    out = {"method": args.method, "config": args.config, "budget_s": args.budget, "wall_s": wall,
           "popsize": args.popsize if "nsga2" in args.method else None, "seed": args.seed,
           "load_start_end": [load0, load_text()], "command": command, "code": code, **extra,
           "diverged_candidates": int((~ok).sum()), "non_dominated": len(keep),
           "points": [fs.point_of(jax.tree.map(lambda x, i=i: np.asarray(x)[i], params), m, i) for i in keep]}  # fmt: skip
    path = folder / f"{args.method}.json"
    write_text(path, json.dumps(jsonable(out), indent=1))
    log(f"build {args.method}: {out['evaluations']} evaluations, {len(keep)} non-dominated, {wall:.0f} s, "
        f"load {out['load_start_end']}: wrote {path}")  # fmt: skip
    return out


# ---------------------------------------------------------------------------- merge


def merge(args) -> dict:
    """Re-evaluate the inputs' candidates on the config's plain problem; write the
    non-dominated union (no diverged point) to <OUT>/<config>/reference.json, with each input's
    score (:func:`score`) on its re-evaluated points, and each input's own re-evaluated front to
    reevaluated.json (a file ``score`` reads)."""
    cfg = _config.load(args.config)
    plain, _, p0 = _config.tuning_problems(cfg)
    t0, load0 = time.perf_counter(), load_text()
    pts, labels, sources, change = [], [], [], {}
    for path in args.inputs:
        for label, group in points_of(path).items():
            m = evaluate(plain, p0, group, label)
            # how far the stored metrics are from the current code's (a method's json: a check, ~1e-7)
            old, new = (np.array([np.mean(p["metrics"][k]) for p in group]) for k in fs.AXES), fs.axes(m)
            ratios = [n / o for o, n in zip(old, new)]
            change[label] = {f"{k}_new_over_stored": [float(np.nanmin(r)), float(np.nanmedian(r)), float(np.nanmax(r))]
                             for k, r in zip(fs.AXES, ratios)}  # fmt: skip
            log(f"{label}: re-evaluated / stored (min, median, max): {change[label]}")
            for i, p in enumerate(group):
                pts.append(fs.point_of(type(p0)(*(np.asarray(p["params"][k]) for k in p0._fields)), m, i))
                labels.append(label)
                sources.append(str(path))
    e, c = axes(pts)
    ok = np.array([p["diverged"] == 0 for p in pts])
    keep = np.flatnonzero(fs.nondominated(np.where(ok, e, np.nan), c))
    keep = keep[np.unique(np.stack([c[keep], e[keep]], 1), axis=0, return_index=True)[1]]  # sorted, no repeats
    ref = [dict(pts[i], method=labels[i], source=sources[i]) for i in keep]
    re, rc = e[keep], c[keep]
    per_label = {lab: {"candidates": labels.count(lab), "reference_points": sum(p["method"] == lab for p in ref),
                       **change[lab]} for lab in dict.fromkeys(labels)}  # fmt: skip
    # each input's own front, re-evaluated (no diverged point), and its score against the union
    fronts = {}
    for lab in per_label:
        idx = np.flatnonzero((np.array(labels) == lab) & ok)
        idx = idx[fs.nondominated(e[idx], c[idx])]
        fronts[lab] = {"points": [pts[i] for i in idx]}
    out = {"config": args.config, "inputs": list(args.inputs), "code": code_state(), "candidates": len(pts),
           "diverged_candidates": int((~ok).sum()), "wall_s": time.perf_counter() - t0,
           "load_start_end": [load0, load_text()], "by_method": per_label,
           "chattering_hf_range": [float(rc.min()), float(rc.max())],
           "rms_error_range": [float(re.min()), float(re.max())],
           "points_in_band": {f"{lo:g}-{hi:g}": int(np.sum((rc >= lo) & (rc <= hi))) for lo, hi in BANDS},
           "hv_reference_log10": hv_reference(re, rc), "points": ref}  # fmt: skip
    for lab, f in fronts.items():
        per_label[lab].update(front_points=len(f["points"]), **score(axes(f["points"]), out))
        log(f"{lab}: {per_label[lab]}")
    path = OUT / config_name(args.config) / "reference.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    write_text(path, json.dumps(jsonable(out), indent=1))
    write_text(path.parent / "reevaluated.json", json.dumps(jsonable({"config": args.config, "methods": fronts})))
    log(f"merge: {len(pts)} candidates, {len(ref)} reference points, chattering_hf {rc.min():.3g}-{rc.max():.3g} V "
        f"({out['points_in_band']}), by method {per_label}: wrote {path}")  # fmt: skip
    return out


# ---------------------------------------------------------------------------- score


def score_files(paths: list[str], reference_path: str) -> dict[str, dict]:
    """Scores (:func:`score`) of every front in the files (a front.json, a method's json, every
    method of a frontier_<name>.json; points with a diverged rollout left out), printed."""
    reference = json.loads(pathlib.Path(reference_path).read_text())
    out = {}
    for path in paths:
        for label, pts in points_of(path).items():
            pts = [p for p in pts if p.get("diverged", 0) == 0]
            s = score(axes(pts), reference)
            if len(pts) == 1:  # one point (a tune result): also how far the reference beats it
                s["dominated_by"] = fs.dominated_by(tuple(float(a[0]) for a in axes(pts)), axes(reference["points"]))
                print(f"{path} ({label}): the reference beats its point by {s['dominated_by']:.4f} (log10) at most")
            out[f"{path}: {label}"] = s
            print(f"{path} ({label}, {len(pts)} points): epsilon (log10) over 0.1-10 V {s['epsilon_0.1_10']:.4f}, "
                  f"over 0.5-10 V {s['epsilon_0.5_10']:.4f}; hypervolume {s['hypervolume']:.4f} (reference front "
                  f"{s['reference_hypervolume']:.4f})")  # fmt: skip
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="command", required=True)
    b = sub.add_parser("build", help="run one method; every candidate to <config>/<method>.json")
    b.add_argument("--config", required=True)
    b.add_argument("--method", choices=METHODS, required=True)
    b.add_argument("--budget", type=float, required=True, help="wall time, s")
    b.add_argument("--popsize", type=int, default=64, help="NSGA-II's population (default 64)")
    b.add_argument("--seed", type=int, default=0)
    b.add_argument("--weights", help="CMA-ES: the weights w of log E + w log C, comma-separated")
    b.add_argument("--out", metavar="DIR", help="<method>.json's folder (default: tuning/results/reference/<config>)")
    b.add_argument("--save-all", metavar="NPZ", help="every candidate evaluated (z, params, metrics) to this .npz")
    b.add_argument("--weights-from", metavar="FRONT_JSON",
                   help="CMA-ES: the weights from a front's slopes at four points, as tuning/frontier.py picks them")  # fmt: skip
    m = sub.add_parser("merge", help="re-evaluate and write the non-dominated union: <config>/reference.json")
    m.add_argument("--config", required=True)
    m.add_argument("inputs", nargs="+")
    s = sub.add_parser("score", help="epsilon and hypervolume of fronts against a reference.json")
    s.add_argument("fronts", nargs="+")
    s.add_argument("--reference", required=True)
    args = ap.parse_args(argv)
    if args.command == "build":
        if args.method == "cma" and not (args.weights or args.weights_from):
            ap.error("--method cma needs --weights or --weights-from")
        return build(args)
    if args.command == "merge":
        return merge(args)
    return score_files(args.fronts, args.reference)


if __name__ == "__main__":
    main()
