"""A front's points refined by gradient steps: does a gradient pay once a derivative-free search
has found the front's basins?

For each given front (a ``fosmc front`` front.json or a ``tuning/reference_front.py build``
method json: its points' parameters and plain metrics) on a config, for ``--budget`` seconds
(compilation included):

- K points along the front (:func:`fosmc_jax.search.pick_starts`: spread evenly by rank, with the
  front's slope w_k = -d log E / d log C there);
- all K at once, Adam steps on f_k(y) = log E + w_k log C (:func:`fosmc_jax.search.scalarized`,
  the stage ``fosmc front --gradient-share`` runs: E and C the means over rollouts and joints of
  ``rms_error`` and ``chattering_hf`` on the config's plain problem, y = z ln 10 with z the log10
  factors of the config's parameters, :func:`fosmc_jax.search.to_factors`); one ``jax.vmap`` of the
  value and gradient per step (the generated adjoint folds the K candidates into its lanes); a
  candidate with a diverged rollout scores 1e3 with no gradient;
- every point the steps reach (evaluated by the next call: the value's by-products E, C) joins the
  front.

The polished front is scored against the config's reference (``tuning/reference_front.py``'s
epsilon in log10 over the reference points with chattering_hf in 0.1-10 V and 0.5-10 V, and the
hypervolume), beside the front itself; the equal-time comparison is the same method run for its
budget plus the polish's (``reference_front.py build --budget``), scored the same way.

    .venv/bin/python tuning/front_polish.py --config tuning/configs/realistic_arm.toml \\
        --fronts RUN1.json RUN2.json --budget 30 --out tuning/results/front_polish_realistic_arm
    .venv/bin/python tuning/front_polish.py --report-only --out tuning/results/front_polish_realistic_arm

Writes OUT.json (per front: the scores before and after, steps, the step's time, the load) and
OUT.md; progress lines go to stdout, prefixed by the time.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time

import fosmc_jax

fosmc_jax.use_all_cores()  # every evaluation split over every core, as `fosmc front` does
fosmc_jax.use_compilation_cache()  # warm programs, as `fosmc front` and the peers' runs get them
import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import optax  # noqa: E402

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
import reference_front  # noqa: E402

from fosmc_jax import config as _config  # noqa: E402
from fosmc_jax import search as fs  # noqa: E402
from fosmc_jax.io import jsonable, write_text  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[1]
log = reference_front.log


def polish(problem, p0, z, weights, budget: float, lr: float, box=None) -> dict:
    """Adam on the K scalarizations (:func:`fosmc_jax.search.scalarized`) from the log factors
    ``z`` (K, dim) of p0 until ``budget`` seconds have passed (compilation included); every
    evaluated candidate's E and C. ``box``: (lo, hi) of z, the steps kept inside."""
    t0 = time.perf_counter()
    Y, W = jnp.asarray(np.log(10.0) * z), jnp.asarray(weights)
    step = jax.jit(jax.vmap(jax.value_and_grad(fs.scalarized(problem, p0), has_aux=True)))
    opt = optax.chain(optax.clip_by_global_norm(1.0), optax.adam(lr))
    state = jax.vmap(opt.init)(Y)
    lo, hi = (-np.inf, np.inf) if box is None else (np.log(10.0) * b for b in box)

    @jax.jit
    def update(Y, state, g):
        d, state = jax.vmap(opt.update)(jnp.where(jnp.isfinite(g), g, 0.0), state, Y)
        return jnp.clip(Y + d, lo, hi), state

    E, C, bad, steps, first = [], [], [], 0, None
    while True:
        (_, (e, c, b)), g = step(Y, W)
        E.append(np.asarray(e)), C.append(np.asarray(c)), bad.append(np.asarray(b))
        first = first or time.perf_counter() - t0
        if time.perf_counter() - t0 > budget:
            break
        Y, state = update(Y, state, g)
        steps += 1
    # the first call re-evaluates the start points: only what the steps reached counts
    E, C, bad = (np.concatenate(x[1:]) if len(x) > 1 else np.zeros(0) for x in (E, C, bad))
    per_step = (time.perf_counter() - t0 - first) / max(1, steps)
    return {"E": np.where(bad, np.nan, E), "C": C, "steps": steps, "first_call_s": first, "s_per_step": per_step}


def run_one(cfg, plain, p0, path: str, reference: dict, budget: float, k: int, lr: float, box: bool) -> dict:
    points = next(iter(reference_front.points_of(path).values()))
    points = [p for p in points if not p["diverged"]]
    m = {a: np.array([p["metrics"][a] for p in points]) for a in fs.AXES}
    e0, c0 = np.mean(m["rms_error"], -1), np.mean(m["chattering_hf"], -1)
    idx, w = fs.pick_starts(dict(m, diverged=np.zeros(len(points))), k)
    z = fs.to_factors(p0, reference_front.params_of([points[i] for i in idx], p0))
    load0 = reference_front.load_text()
    r = polish(plain, p0, z, w, budget, lr, fs.bounds(fs.space_of(p0)) if box else None)
    e, c = np.concatenate([e0, r["E"]]), np.concatenate([c0, r["C"]])
    keep = fs.nondominated(e, c)
    before = reference_front.score((e0, c0), reference)
    after = reference_front.score((e[keep], c[keep]), reference)
    log(
        f"{path}: {len(idx)} points, {r['steps']} steps ({r['s_per_step']:.3f} s each, first call {r['first_call_s']:.1f} s); "
        f"epsilon {before['epsilon_0.1_10']:.4f} -> {after['epsilon_0.1_10']:.4f}"
    )
    return {
        "front": path,
        "points": len(points),
        "polished_points": int(len(idx)),
        "weights": w.tolist(),
        "budget_s": budget,
        "learning_rate": lr,
        "box": box,
        "steps": r["steps"],
        "s_per_step": r["s_per_step"],
        "first_call_s": r["first_call_s"],
        "before": before,
        "after": after,
        "improved_points": int(keep[len(e0) :].sum()),
        "load_start_end": [load0, reference_front.load_text()],
    }


def _shown(path: pathlib.Path) -> str:
    return str(path.relative_to(ROOT)) if path.is_relative_to(ROOT) else str(path)


def report(data: dict, out: pathlib.Path) -> None:
    lines = [
        f"# A front's points refined by gradient steps ({data['config']})",
        "",
        f"Generated by `tuning/front_polish.py` from `{_shown(out.with_suffix('.json'))}` "
        "(`--report-only` regenerates it). Command: `"
        + data["command"]
        + "`; code "
        + data["code"]["commit"][:10]
        + ".",
        "",
        "| front | points (polished) | steps, s/step (first call) | epsilon 0.1-10 V before -> after | 0.5-10 V | HV before -> after | points added to the front | load (start, end) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in data["runs"]:
        b, a = r["before"], r["after"]
        lines.append(
            f"| `{r['front']}` | {r['points']} ({r['polished_points']}) | {r['steps']}, {r['s_per_step']:.3f} "
            f"({r['first_call_s']:.1f} s) | {b['epsilon_0.1_10']:.4f} -> **{a['epsilon_0.1_10']:.4f}** | "
            f"{b['epsilon_0.5_10']:.4f} -> {a['epsilon_0.5_10']:.4f} | {b['hypervolume']:.3f} -> {a['hypervolume']:.3f} | "
            f"{r['improved_points']} | {r['load_start_end'][0]}; {r['load_start_end'][1]} |"
        )
    if data.get("findings"):
        lines += ["", "## Findings", "", data["findings"]]
    write_text(out.with_suffix(".md"), "\n".join(lines) + "\n")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config")
    ap.add_argument("--fronts", nargs="+", default=[])
    ap.add_argument("--budget", type=float, default=30.0, help="seconds of polish per front, compilation included")
    ap.add_argument("--points", type=int, default=16, help="points polished at once (default 16)")
    ap.add_argument("--box", action="store_true", help="keep the steps in the front's box of factors of p0")
    ap.add_argument("--lr", type=float, help="Adam's rate in u (default: fosmc tune's for the config)")
    ap.add_argument("--out", required=True, help="output stem (OUT.json, OUT.md)")
    ap.add_argument("--findings", help="a markdown file whose text the report keeps as its findings")
    ap.add_argument("--report-only", action="store_true")
    args = ap.parse_args()
    out = pathlib.Path(args.out).resolve()
    if args.report_only:
        data = json.loads(out.with_suffix(".json").read_text())
        if args.findings:
            data["findings"] = pathlib.Path(args.findings).read_text()
            write_text(out.with_suffix(".json"), json.dumps(jsonable(data), indent=1))
        report(data, out)
        return 0
    cfg = _config.load(args.config)
    plain, _, p0 = _config.tuning_problems(cfg)
    lr = args.lr or fs.learning_rate(cfg.tune.learning_rate, _config.rough_loop(cfg))
    ref_path = reference_front.OUT / reference_front.config_name(args.config) / "reference.json"
    reference = json.loads(ref_path.read_text())
    command = " ".join([".venv/bin/python", "tuning/front_polish.py", *sys.argv[1:]])
    runs = [run_one(cfg, plain, p0, f, reference, args.budget, args.points, lr, args.box) for f in args.fronts]
    data = {"config": args.config, "command": command, "code": reference_front.code_state(), "runs": runs}
    write_text(out.with_suffix(".json"), json.dumps(jsonable(data), indent=1))
    report(data, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
