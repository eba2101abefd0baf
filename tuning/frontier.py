"""The front of ``fosmc front`` against derivative-free baselines at equal wall time.

For one config, each method gets the same wall time on the same machine, one after the other
(the baselines get what the front actually took, its references and held-out evaluation
included; every method pays its own compilation): ``fosmc front`` (:func:`fosmc_jax.config.study`),
CMA-ES (pycma) on the weighted log objective at four slopes of the front, uniform random search
and a log grid over the same search space (:mod:`fosmc_jax.search`), and with ``--peers`` NSGA-II,
pymoo's and optuna's (``nsga2``, ``optuna_nsga2``: optuna from ``pip install -e .[peers]``; each generation of
``--popsize`` in one batched call). Every method's non-dominated set is compared in (mean
``rms_error``, mean ``chattering_hf``): the hypervolume of log10 of the two metrics against a
reference point (beyond the worst of Table 1's sets and SGN), how many of the
front's points some baseline point dominates, and the epsilon indicator both ways (by how
much, at most, one set beats the other: :func:`fosmc_jax.search.epsilon`). The front's held-out evaluation (fresh payloads
or box samples, fresh noise seeds) is reported beside its training metrics.

    .venv/bin/python tuning/frontier.py --config tuning/configs/realistic_arm.toml --budget 300 --name realistic
    .venv/bin/python tuning/frontier.py --config tuning/configs/realistic_arm.toml --budget 300 --name realistic_peers \
        --peers  # also NSGA-II (pymoo) and NSGA-II (optuna); --peers nsga2: pymoo's only

Writes tuning/results/frontier_<name>.{json,md,png} (and the front in tuning/results/front_<name>/).
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import time

import jax

import fosmc_jax  # noqa: E402

fosmc_jax.use_all_cores()  # every method evaluates its chunks on every core, as `fosmc front` does
jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from fosmc_jax import config as _config  # noqa: E402
from fosmc_jax import search as fs  # noqa: E402
from fosmc_jax.io import jsonable, save_figure, write_text  # noqa: E402

HERE = pathlib.Path(__file__).parent
OUT = HERE / "results"


def log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)


def axes_of(metrics: dict) -> tuple[np.ndarray, np.ndarray]:
    return np.mean(metrics["rms_error"], axis=-1), np.mean(metrics["chattering_hf"], axis=-1)


def axes_of_points(points: list[dict], key: str = "metrics") -> tuple[np.ndarray, np.ndarray]:
    """Mean rms_error and chattering_hf of JSON front points (their ``key`` metrics)."""
    return tuple(np.array([np.mean(p[key][k]) for p in points]) for k in ("rms_error", "chattering_hf"))


def dominated_pairs(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]) -> list[tuple[int, int]]:
    """(i, j) for every point i of b = (errors, chatterings) that some point of a dominates, j
    the one of lowest error among them."""
    (ae, ac), (be, bc) = a, b
    pairs = []
    for i in range(len(be)):
        dom = np.flatnonzero((ae <= be[i]) & (ac <= bc[i]) & ((ae < be[i]) | (ac < bc[i])))
        if len(dom):
            pairs.append((i, int(dom[np.argmin(ae[dom])])))
    return pairs


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--config")
    ap.add_argument("--budget", type=float, default=300.0, help="wall time per method, s")
    ap.add_argument("--name")
    ap.add_argument("--points", type=int, default=8)
    ap.add_argument("--methods", default="front,cma,random,grid")
    ap.add_argument("--peers", nargs="?", const="nsga2,optuna_nsga2", default="",
                    help="also these NSGA-II baselines (default both: nsga2,optuna_nsga2; fosmc_jax[peers])")  # fmt: skip
    ap.add_argument("--popsize", type=int, default=64, help="NSGA-II's population, one batched call each (default 64)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a fosmc_jax.search.FrontSettings field for the front (ablations), e.g. global_share=1")  # fmt: skip
    ap.add_argument("--check", action="store_true",
                    help="only the cost and surrogate check (check_costs), then exit")  # fmt: skip
    ap.add_argument("--epsilon", nargs="+", metavar="FRONTIER_JSON",
                    help="only compare the front of these studies with each baseline (compare_study), then exit")  # fmt: skip
    ap.add_argument("--score", nargs="+", metavar="FRONT_JSON",
                    help="only score these front.json files (score_fronts), then exit")  # fmt: skip
    ap.add_argument("--dominance-check", metavar="FRONTIER_JSON",
                    help="only re-evaluate the CMA-ES-dominated front points of a study on its training problem "
                    "(dominance_check), then exit")  # fmt: skip
    args = ap.parse_args(argv)
    if args.score:
        return score_fronts(args.score)
    if args.epsilon:
        for path in args.epsilon:
            compare_study(path)
        return
    if args.dominance_check:
        return dominance_check(args.dominance_check)
    if not args.config or not (args.name or args.check):
        ap.error(
            "--config and --name are required (but with --score, --epsilon, --dominance-check; --check needs no --name)"
        )
    cfg = _config.load(args.config)
    if args.check:
        return check_costs(cfg)
    plain, train, p0 = _config.tuning_problems(cfg)
    methods = args.methods.split(",") + [m for m in args.peers.split(",") if m]
    unknown = [m for m in args.peers.split(",") if m and m not in ("nsga2", "optuna_nsga2")]
    if unknown:
        ap.error(f"--peers: unknown {unknown}; expected nsga2, optuna_nsga2")
    out: dict = {"config": args.config, "budget_s": args.budget, "methods": {}}
    front_dir = OUT / f"front_{args.name}"

    start, load = time.perf_counter(), os.getloadavg()[0]
    settings = fs.FrontSettings(points=args.points, budget=args.budget)
    for item in args.set:  # KEY=1.5 or KEY=0.1,0.01 (a tuple)
        key, value = item.split("=", 1)
        parsed = json.loads(f"[{value}]")
        value = parsed[0] if len(parsed) == 1 else parsed
        settings = settings._replace(**{key: type(getattr(settings, key))(value)})
    out["settings"] = settings._asdict()
    front = _config.study(cfg, settings, out=front_dir, log=log)
    out["methods"]["fosmc front"] = {"wall_s": time.perf_counter() - start, "points": front["points"],
                                     "evaluations": front["stages"]["evaluations"],
                                     "load": [load, os.getloadavg()[0]]}  # fmt: skip
    front_m = {k: np.array([p["metrics"][k] for p in front["points"]]) for k in ("rms_error", "chattering_hf")}
    front_m["diverged"] = np.array([p["diverged"] for p in front["points"]])
    weights = fs.pick_starts(front_m, 4)[1].tolist()  # the front's slopes at four points along it
    budget = out["methods"]["fosmc front"]["wall_s"]  # the baselines get the front's actual wall time
    out["baseline_budget_s"], out["cma_weights"] = budget, weights
    log(f"fosmc front: {len(front['points'])} points in {budget:.0f} s")

    runs = {
        "cma": ("CMA-ES (pycma)", lambda: fs.cma_front(plain, p0, weights, budget, log=log)),
        "random": ("random search", lambda: fs.random_search(plain, p0, budget, log=log)),
        "grid": ("log grid", lambda: fs.log_grid(plain, p0, grid_size(plain, p0, budget), log=log)),
        "nsga2": ("NSGA-II (pymoo)", lambda: fs.nsga2(plain, p0, budget, args.popsize, log=log)),
        "optuna_nsga2": ("NSGA-II (optuna)", lambda: fs.optuna_nsga2(plain, p0, budget, args.popsize, log=log)),
    }
    for key in methods:
        if key not in runs:
            continue
        label, fn = runs[key]
        t0, load = time.perf_counter(), os.getloadavg()[0]
        r = fn()
        e, c = axes_of(r["metrics"])
        keep = np.flatnonzero(fs.nondominated(e, c))
        params = fs.from_factors(p0, r["z"][keep])
        out["methods"][label] = {
            "wall_s": time.perf_counter() - t0, "evaluations": len(e), "load": [load, os.getloadavg()[0]],
            "points": [fs.point_of(jax.tree.map(lambda x, i=i: x[i], params), r["metrics"], j)
                       for i, j in enumerate(keep)],
        }  # fmt: skip
        log(f"{label}: {len(e)} evaluations, {len(keep)} non-dominated, {out['methods'][label]['wall_s']:.0f} s")

    refs = front["references"]
    ref_point = reference_point(refs)
    fe, fc = axes_of_points(front["points"])
    summary = []
    for label, m in out["methods"].items():
        e, c = axes_of_points(m["points"])
        dominating = len(dominated_pairs((e, c), (fe, fc)))
        m["hypervolume"] = fs.hypervolume(e, c, ref_point)
        m["front_points_dominated"] = dominating if label != "fosmc front" else 0
        m["beats_front_by"], m["front_beats_it_by"] = fs.epsilon((fe, fc), (e, c)), fs.epsilon((e, c), (fe, fc))
        summary.append((label, m["wall_s"], m["evaluations"], len(m["points"]), m["hypervolume"],
                        m["front_points_dominated"], m["beats_front_by"], m["front_beats_it_by"],
                        e.min(), c.min(), m["load"]))  # fmt: skip
    dominated_refs = {k: bool(dominated_pairs((fe, fc), axes_of_points([v]))) for k, v in refs.items()}
    he, hc = axes_of_points(front["points"], "held_out")
    held = list(zip((he / fe).tolist(), (hc / fc).tolist()))
    out.update(reference_point_log10=ref_point, references=refs, references_dominated_by_front=dominated_refs,
               held_out_ratios=held, held_out_batch=front["held_out_batch"])  # fmt: skip

    lines = [f"Config `{args.config}`, `fosmc front` budget {args.budget:.0f} s; each baseline then gets the front's "
             f"actual wall time ({budget:.0f} s), one after the other on the same "
             f"machine (`.venv/bin/python tuning/frontier.py --config {args.config} --budget {args.budget:.0f} "
             f"--name {args.name}`). Hypervolume: area dominated in (log10 mean chattering_hf, log10 mean rms_error) "
             f"up to the reference point {np.round(ref_point, 2).tolist()} (0.5 decade beyond the worst reference).",
             "Epsilon: the multiplicative epsilon indicator (`fosmc_jax.search.epsilon`), the largest "
             "factor by which one set beats the other anywhere (1 or less: nowhere).",
             "", "| method | wall s | load (1-min, start/end) | evaluations | front points | hypervolume | "
             "`fosmc front` points it dominates | epsilon: it beats the front by | epsilon: the front beats it by | "
             "best rms_error (rad) | lowest chattering_hf (V) |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]  # fmt: skip
    for label, wall, n, k, hv, dom, eps_f, eps_b, emin, cmin, ld in summary:
        lines.append(f"| {label} | {wall:.0f} | {ld[0]:.1f} / {ld[1]:.1f} | {n} | {k} | {hv:.3f} | {dom} | {eps_f:.3f} "
                     f"| {eps_b:.3f} | {emin:.3g} | {cmin:.3g} |")  # fmt: skip
    lines += ["", f"CMA-ES weights (the front's slopes): {np.round(weights, 2).tolist()}.",
              "", "`fosmc front` dominates: " + ", ".join(f"{k}: {'yes' if v else 'no'}" for k, v in dominated_refs.items()) + ".",
              "", "Held-out batch " + json.dumps(front["held_out_batch"]) + ": ratio held-out / training, per front "
              "point (rms_error, chattering_hf): " + ", ".join(f"({a:.2f}, {b:.2f})" for a, b in held) + "."]  # fmt: skip
    OUT.mkdir(exist_ok=True)
    write_text(OUT / f"frontier_{args.name}.json", json.dumps(jsonable(out), indent=1))
    write_text(OUT / f"frontier_{args.name}.md", "\n".join(lines) + "\n")
    plot(out, OUT / f"frontier_{args.name}.png", args.config)
    print("\n".join(lines))


def reference_point(refs: dict) -> tuple[float, float]:
    """The hypervolume's reference point (log10 chattering_hf, log10 rms_error): half a decade
    beyond the worst of the references (Table 1's sets, SGN)."""
    pts = np.array(
        [[np.mean(v["metrics"]["rms_error"]), np.mean(v["metrics"]["chattering_hf"])] for v in refs.values()]
    )
    return float(np.log10(pts[:, 1].max()) + 0.5), float(np.log10(pts[:, 0].max()) + 0.5)


def compare_study(path: str) -> None:
    """Print, for a study's result (``frontier_<name>.json``), each baseline's count of front
    points it dominates, the epsilon indicator both ways (:func:`fosmc_jax.search.epsilon`), and
    by chattering_hf band where it wins."""
    study = json.loads(pathlib.Path(path).read_text())
    sets = {label: axes_of_points(m["points"]) for label, m in study["methods"].items()}
    fe, fc = sets.pop("fosmc front")
    for label, (e, c) in sets.items():
        beaten = {i for i, _ in dominated_pairs((e, c), (fe, fc))}
        print(
            f"{path}: {label} dominates {len(beaten)} of {len(fe)} front points; it beats the front by at most "
            f"{fs.epsilon((fe, fc), (e, c)):.3f}x, the front beats it by at most {fs.epsilon((e, c), (fe, fc)):.3f}x"
        )
        # by chattering_hf band: front points, those beaten, and the median over the band's points of
        # (the lowest error of this method at no more chattering) / (the front point's error)
        edges = (0, 0.1, 0.2, 0.5, 2, 10, np.inf)
        for lo, hi in zip(edges[:-1], edges[1:]):
            band = np.flatnonzero((fc >= lo) & (fc < hi))
            ratio = [e[c <= fc[i]].min() / fe[i] if np.any(c <= fc[i]) else np.nan for i in band]
            median = f"{np.nanmedian(ratio):.2f}" if len(band) and not np.all(np.isnan(ratio)) else "-"
            print(f"  {lo:g}-{hi:g} V: {len(band)} front points, {len(beaten.intersection(band))} beaten, "
                  f"median ratio {median}")  # fmt: skip


def score_fronts(paths: list[str]) -> None:
    """Print, for each ``fosmc front`` result, its size, hypervolume (at the reference point of
    its own references), best rms_error, the lowest chattering_hf at rms_error <= 0.1, 0.01
    and 0.001 rad, and the range of its points' held-out / training ratios."""
    for path in paths:
        front = json.loads(pathlib.Path(path).read_text())
        e, c = axes_of_points(front["points"])
        low = ["-" if not np.any(e <= t) else f"{c[e <= t].min():.3g}" for t in (0.1, 0.01, 0.001)]
        he, hc = axes_of_points(front["points"], "held_out")
        re, rc = he / e, hc / c
        print(f"{path}: {front['stages'].get('evaluations', front['stages'].get('candidates'))} evaluations, "
              f"{len(e)} points, hypervolume {fs.hypervolume(e, c, reference_point(front['references'])):.2f}, best "
              f"rms_error {e.min():.2g} rad at {c[e.argmin()]:.3g} V, lowest chattering_hf at rms_error <= 0.1 / "
              f"0.01 / 0.001 rad: {' / '.join(low)} V; held out / training: rms_error {re.min():.2f}-{re.max():.2f}, "
              f"chattering_hf {rc.min():.2f}-{rc.max():.2f}, {int(np.sum((re > 1.25) | (rc > 1.25)))} points beyond "
              f"1.25x")  # fmt: skip


def dominance_check(path: str) -> None:
    """For a study's result (``frontier_<name>.json``): each front point some CMA-ES point
    dominates, with its dominator of lowest rms_error, both evaluated on the config's training
    problem: does the CMA-ES point still dominate there (a search the surrogate could have
    done better), or do the two problems disagree (what only the plain problem shows)?"""
    study = json.loads(pathlib.Path(path).read_text())
    plain, train, p0 = _config.tuning_problems(_config.load(study["config"]))
    points = [study["methods"][k]["points"] for k in ("fosmc front", "CMA-ES (pycma)")]
    (fe, fc), (ce, cc) = (axes_of_points(pts) for pts in points)
    pairs = dominated_pairs((ce, cc), (fe, fc))
    if not pairs:
        return print(f"{path}: no front point is dominated by a CMA-ES point")
    as_params = lambda pts: type(p0)(*(np.array([p["params"][k] for p in pts]) for k in p0._fields))
    train = fs.Evaluator(train)  # one compilation for both sets
    ma = train(as_params([points[0][i] for i, _ in pairs]), 16, log=lambda _: None)
    mb = train(as_params([points[1][j] for _, j in pairs]), 16, log=lambda _: None)
    (ea, ca), (eb, cb) = axes_of(ma), axes_of(mb)
    still = int(np.sum((eb <= ea) & (cb <= ca) & ((eb < ea) | (cb < ca))))
    print(f"{path}: {len(pairs)} front points dominated by a CMA-ES point on the plain problem; on the training "
          f"problem the CMA-ES point still dominates {still} of them")  # fmt: skip


def check_costs(cfg: dict, n_random: int = 64) -> None:
    """Print what one evaluation costs (a chunk of 16 compiled afresh, as ``evaluate_many`` did
    on every call before it kept its compilation, and warm) on the plain and the training
    problem, and how the training problem ranks a grid of 4^3 common factors and ``n_random``
    per-joint draws against the plain one (Spearman's rho of each axis; non-dominated sets)."""
    from scipy.stats import spearmanr

    plain, train, p0 = _config.tuning_problems(cfg)
    lo, hi = fs.bounds()
    z = np.concatenate([fs.grid_factors(4), np.random.default_rng(1).uniform(lo, hi, size=(n_random, fs.DIM))])
    params = fs.from_factors(p0, z)
    first = jax.tree.map(lambda x: x[:16], params)
    times = []
    for _ in range(2):  # a fresh compilation each time (a fresh evaluator), as before
        t = time.perf_counter()
        fs.evaluate_many(plain, first, 16, log=lambda _: None)
        times.append(time.perf_counter() - t)
    print(f"load {os.getloadavg()[0]:.1f}: 16 plain evaluations compiled afresh {times[1]:.2f} s "
          f"({times[1] / 16:.3f} s each)")  # fmt: skip
    metrics = {}
    for label, problem in (("plain", plain), ("training", train)):
        problem = fs.Evaluator(problem)
        problem(first, 16, log=lambda _: None)
        t = time.perf_counter()
        metrics[label] = problem(params, 16, log=lambda _: None)
        dt = time.perf_counter() - t
        print(
            f"load {os.getloadavg()[0]:.1f}: {len(z)} {label} evaluations, warm: {dt:.1f} s ({dt / len(z):.3f} s each)"
        )
    (ep, cp), (et, ct) = axes_of(metrics["plain"]), axes_of(metrics["training"])
    ok = np.isfinite(ep + cp + et + ct)
    both = fs.nondominated(ep, cp) & fs.nondominated(et, ct)
    print(f"Spearman rho, training against plain: rms_error {spearmanr(ep[ok], et[ok])[0]:.3f}, chattering_hf "
          f"{spearmanr(cp[ok], ct[ok])[0]:.3f}; non-dominated: plain {fs.nondominated(ep, cp).sum()}, training "
          f"{fs.nondominated(et, ct).sum()}, both {both.sum()}")  # fmt: skip


def grid_size(problem, p0, budget: float) -> int:
    """Values per axis of a log grid that fits the budget (from one timed chunk)."""
    z, problem = np.zeros((16, fs.DIM)), fs.Evaluator(problem)
    problem(fs.from_factors(p0, z), 16, log=lambda _: None)
    t0 = time.perf_counter()
    problem(fs.from_factors(p0, z), 16, log=lambda _: None)
    per = (time.perf_counter() - t0) / 16
    return max(2, int((0.9 * budget / per) ** (1 / 3)))


def plot(out: dict, path: pathlib.Path, config: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 6))
    for i, (label, m) in enumerate(out["methods"].items()):
        pts = sorted((np.mean(p["metrics"]["chattering_hf"]), np.mean(p["metrics"]["rms_error"])) for p in m["points"])
        x, y = zip(*pts)
        ax.plot(x, y, "o-" if i == 0 else "x:", color=f"C{i}", label=f"{label} ({m['wall_s']:.0f} s)")
    for j, (label, v) in enumerate(out["references"].items()):
        ax.plot(np.mean(v["metrics"]["chattering_hf"]), np.mean(v["metrics"]["rms_error"]), "s" if label != "SGN" else "X",
                ms=9, color=f"C{j + 5}", label=label)  # fmt: skip
    ax.set_xscale("log"), ax.set_yscale("log")
    ax.set_xlabel("mean chattering_hf (V)"), ax.set_ylabel("mean rms_error (rad)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    ax.set_title(f"{config}: fronts at equal wall time\n(front budget {out['budget_s']:.0f} s; each baseline "
                 f"gets the front's {out['baseline_budget_s']:.0f} s)")  # fmt: skip
    fig.tight_layout()
    save_figure(fig, path)


if __name__ == "__main__":
    main()
