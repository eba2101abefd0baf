"""A research script written from the README alone, with public names only (``fosmc_jax``,
``fosmc_jax.config``, ``fosmc_jax.search``), on the realistic preset (the arm at 0 and 10 kg
behind a 1 kHz digital loop with an encoder, one sample of delay and a 24 V limit):

1. a Monte Carlo of ``--samples`` rollouts, each with its own payload, uniform in [0, 10] kg,
   and its own initial offset, normal with a standard deviation of 0.01 rad on each angle
   (a ``[sample]`` table, ``pairing = "paired"``): percentiles of rms_error and chattering_hf;
2. the gradient of the mean rms_error over the preset's two payloads with respect to delta,
   by ``jax.grad`` through the whole closed loop, checked against central differences (with
   the encoder's rounding off, where the loss is smooth: see :func:`gradient`);
3. the Pareto front of mean rms_error against mean chattering_hf within ``--budget`` seconds,
   and the point of least chattering within an error bound (``fosmc_jax.search.select``).

Writes ``summary.json``, ``summary.md`` and the front (``front/front.json``, ``front.png``) to
``--out``; prints a progress line per stage.

    .venv/bin/python tuning/research_example.py [--t-final T] [--samples 200] [--budget 60]
        [--max-error E] [--out tuning/results/research_example]

Without ``--t-final`` the preset's own horizon (4 s) is used; ``--t-final 0.2 --samples 20
--budget 20`` is a one-minute look (tests/test_research_example.py runs it on a shorter one).
"""

from __future__ import annotations

import argparse
import json
import pathlib
import time

import jax

jax.config.update("jax_enable_x64", True)  # the configs run in float64

import numpy as np  # noqa: E402

import fosmc_jax as fj  # noqa: E402
import fosmc_jax.config  # noqa: E402, F401  (fj.config)
import fosmc_jax.search  # noqa: E402, F401  (fj.search)

OUT = pathlib.Path(__file__).parent / "results" / "research_example"
PRESET = "realistic_arm"
#: The Monte Carlo's draws: payloads uniform in [low, high] kg, initial angle offsets N(0, 0.01^2) rad.
PAYLOADS = [0.0, 10.0]
OFFSETS = [0.01, 0.0, 0.0, 0.01, 0.0, 0.0, 0.01, 0.0, 0.0]
#: Relative steps of the central differences (h_i = step * delta_i): the check without the
#: encoder's rounding, and the secant on the preset itself.
STEP = 1e-4
SECANT = 0.3
#: The check's tolerance: largest |grad - central| over largest |central| (1e-6 is typical).
TOLERANCE = 1e-3


def log(msg: str) -> None:
    print(f"research_example: {msg}", flush=True)


def preset(t_final: float | None) -> dict:
    """The preset's config, with ``t_final`` (s) when given."""
    cfg = fj.config.load(PRESET)
    return cfg if t_final is None else fj.config.replace(cfg, sim={"t_final": t_final})


def monte_carlo(cfg: dict, samples: int, seed: int) -> dict:
    """``samples`` rollouts, the i-th plant (payload) from the i-th initial state: the summary
    (mean, max, p5, p50, p95 per metric and joint, over the rollouts that did not diverge)."""
    mc = dict(cfg, sim=dict(cfg["sim"], pairing="paired"),
              sample={"count": samples, "seed": seed, "payloads": PAYLOADS, "offsets": OFFSETS})  # fmt: skip
    problem = fj.build(mc)
    return problem.simulate().summary()


def _central(loss, delta, step: float) -> np.ndarray:
    """Central differences of ``loss`` at ``delta`` (3,), h_i = step * delta_i."""
    out = []
    for i in range(delta.shape[0]):
        h = step * delta[i]
        out.append(float((loss(delta.at[i].add(h)) - loss(delta.at[i].add(-h))) / (2 * h)))
    return np.asarray(out)


def gradient(cfg: dict) -> dict:
    """d(mean rms_error over rollouts and joints)/d(delta) at the preset's delta, by reverse
    mode through the whole loop, and its check against central differences.

    The encoder rounds theta to whole counts, so the preset's loss is piecewise smooth: small
    steps of delta flip counts, and its central differences do not converge (they measure the
    flips), while reverse mode differentiates with the counts held. The check is therefore made
    on the same preset with the rounding off (``[sensors] encoder_counts = 0``; the same
    compiled program, the counts being an input), at relative step :data:`STEP`; on the preset
    itself the gradient is compared with a secant over :data:`SECANT` of delta, for scale."""
    out = {}
    for name, counts in (("preset", None), ("no_rounding", 0)):
        c = dict(cfg, sensors=dict(cfg["sensors"], **({} if counts is None else {"encoder_counts": counts})))
        problem = fj.build(c)
        delta = problem.params()["delta"]
        loss = lambda d, problem=problem: problem.simulate({"delta": d}, fast=False).mean().rms_error.mean()
        value, grad = jax.value_and_grad(loss)(delta)
        step = SECANT if counts is None else STEP
        central = _central(loss, delta, step)
        grad = np.asarray(grad)
        gap = float(np.max(np.abs(grad - central)) / np.max(np.abs(central)))
        out[name] = {"loss": float(value), "grad": grad.tolist(), "central": central.tolist(),
                     "relative_step": step, "max_relative_gap": gap}  # fmt: skip
    out["delta"] = np.asarray(delta).tolist()
    return out


def front_and_point(cfg: dict, budget: float, max_error: float | None, out: pathlib.Path) -> dict:
    """The front within ``budget`` seconds (written to ``out``) and the point of least mean
    chattering_hf with mean rms_error <= ``max_error`` (None: the front's median error)."""
    front = fj.run_front(cfg, budget=budget, out=out, force=True, log=lambda m: log(m))
    errors = [float(np.mean(p["metrics"]["rms_error"])) for p in front["points"]]
    bound = float(np.nanmedian(errors)) if max_error is None else max_error
    point = fj.search.select(front, max_error=bound)
    return {"points": len(front["points"]), "max_error": bound, "selected": point,
            "controller_toml": fj.search.controller_toml(point["params"])}  # fmt: skip


def markdown(summary: dict) -> str:
    """``summary.md``: the three results in short tables."""
    mc, g, f = summary["monte_carlo"], summary["gradient"], summary["front"]
    fmt = lambda xs: " ".join(f"{x:.4e}" for x in xs)
    lines = [
        f"# Research example ({PRESET}, t_final = {summary['t_final']} s)",
        "",
        f"## Monte Carlo: {mc['rollouts']} rollouts, {mc['diverged_excluded']} diverged (left out)",
        "",
        "| metric | p5 | p50 | p95 |",
        "|---|---|---|---|",
        *(
            f"| {name} | {fmt(mc['p5'][name])} | {fmt(mc['p50'][name])} | {fmt(mc['p95'][name])} |"
            for name in ("rms_error", "chattering_hf")
        ),  # fmt: skip
        "",
        "## Gradient of the mean rms_error (rad) with respect to delta",
        "",
        f"at delta = {g['delta']}; the check is made without the encoder's rounding, whose loss is smooth",
        "",
        "| case | loss (rad) | jax.grad | central differences (relative step) | largest relative gap |",
        "|---|---|---|---|---|",
        *(
            f"| {case} | {g[case]['loss']:.6e} | {fmt(g[case]['grad'])} | {fmt(g[case]['central'])} "
            f"({g[case]['relative_step']:g}) | {g[case]['max_relative_gap']:.2e} |"
            for case in ("preset", "no_rounding")
        ),  # fmt: skip
        "",
        f"## Front: {f['points']} points; least chattering with mean rms_error <= {f['max_error']:.4e} rad",
        "",
        f"point {f['selected']['index']}: mean rms_error {f['selected']['mean']['rms_error']:.4e} rad, "
        f"mean chattering_hf {f['selected']['mean']['chattering_hf']:.4e} V",
        "",
        "```toml",
        f["controller_toml"],
        "```",
        "",
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--t-final", type=float, default=None, help="horizon, s (default: the preset's, 4 s)")
    parser.add_argument("--samples", type=int, default=200, help="Monte-Carlo rollouts (default 200)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the Monte-Carlo draws")
    parser.add_argument("--budget", type=float, default=60.0, help="the front's wall-time budget, s (default 60)")
    parser.add_argument("--max-error", type=float, default=None,
                        help="bound on the selected point's mean rms_error, rad (default: the front's median)")  # fmt: skip
    parser.add_argument("--out", type=pathlib.Path, default=OUT, help=f"output folder (default {OUT})")
    args = parser.parse_args(argv)
    cfg = preset(args.t_final)
    args.out.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    clock = lambda: f"{time.perf_counter() - started:.1f} s"

    log(f"Monte Carlo: {args.samples} rollouts of {PRESET}, t_final = {cfg['sim']['t_final']} s ...")
    mc = monte_carlo(cfg, args.samples, args.seed)
    log(f"Monte Carlo done ({clock()}): rms_error p50 {mc['p50']['rms_error']}, p95 {mc['p95']['rms_error']} rad")

    log("gradient with respect to delta (reverse mode, then central differences; compiling ...)")
    g = gradient(cfg)
    p, s = g["preset"], g["no_rounding"]
    log(f"gradient done ({clock()}): {p['grad']} rad per unit of delta (secant over {SECANT:g} of delta: "
        f"{p['central']})")  # fmt: skip
    verdict = "PASS" if s["max_relative_gap"] <= TOLERANCE else "FAIL"
    log(f"check without the encoder's rounding: jax.grad {s['grad']}, central {s['central']}, "
        f"relative gap {s['max_relative_gap']:.1e} (tolerance {TOLERANCE:g}): {verdict}")  # fmt: skip

    log(f"front within {args.budget:g} s ...")
    f = front_and_point(cfg, args.budget, args.max_error, args.out / "front")
    sel = f["selected"]
    log(f"front done ({clock()}): {f['points']} points; point {sel['index']} has mean rms_error "
        f"{sel['mean']['rms_error']:.4e} rad <= {f['max_error']:.4e}, chattering_hf {sel['mean']['chattering_hf']:.4e} V")  # fmt: skip

    summary = {"fosmc_jax_version": fj.__version__, "preset": PRESET, "t_final": cfg["sim"]["t_final"], "samples": args.samples,
               "monte_carlo": mc, "gradient": g, "front": f, "wall_time_s": time.perf_counter() - started}  # fmt: skip
    (args.out / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    (args.out / "summary.md").write_text(markdown(summary))
    log(f"wrote summary.json, summary.md, front/ to {args.out} ({clock()})")
    return summary


if __name__ == "__main__":
    main()
