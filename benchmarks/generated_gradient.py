"""Value and gradient against the forward through the public default path (issue 32), one command:

    python benchmarks/generated_gradient.py                    # the three shapes below
    python benchmarks/generated_gradient.py --only ideal --steps 500 --rounds 1   # a short trial
    python benchmarks/generated_gradient.py --out /tmp/generated_gradient.json

Shapes (the issue's): ``ideal``, 64 arm rollouts x 4,000 RK4 float64 steps of
``tuning/configs/arm_ideal_set2.toml`` (8 payloads in [0, 10] kg x 8 initial offsets, as
benchmarks/arm_gradient.py builds them); ``digital``, the same batch in the ``realistic_arm``
preset's 1 kHz digital loop (dt 0.1 ms: m = 10, encoder, delay, voltage limit); ``euler32``,
1,024 rollouts (32 payloads x 32 offsets) x 1,000 Euler float32 steps of arm_ideal_set2.

For each, timed after compilation (the compile time recorded), in ``--rounds`` rounds that time
each function in turn for ``--round-s`` seconds at least (interleaved, so that the machine's load
reaches both alike; the ratio is the median of the rounds' ratios):
- ``forward``: ``problem.simulate(p)`` (the default path: the generated kernel's forward), jitted;
- ``value_and_grad``: ``jax.value_and_grad`` of the loss mean(rms_error) + 1e-3 mean(chattering)
  over ``problem.simulate(p)`` in the FOSMC's 15 parameters (delta, gamma, the poles): the
  generated adjoint kernel;
- ``generated_forward``: the same loss through ``generated.simulate_batch`` called directly
  (white-box; the hand-written kernel it was measured against retired at 56dfce3, so that both
  columns now time the generated forward);
- ``vmap_value_and_grad`` (``--vmap``): the same through ``simulate(p, fast=False)`` (the
  ``vmap`` path, what a gradient cost before; slow: off by default).
With ``--arm``, every function takes the arm's 19 calibrated parameters too (the
:class:`fosmc_jax.ArmParams` fields ``d1`` ... ``Kb``, through ``problem.with_arm``) and the value
and gradient is in both (the issue's 5x bound: 15 + 19 parameters).
The gradients of the two paths are compared (max relative difference) where both run. The
1-minute load average is recorded with every round; ``--out`` writes all as JSON.

``--build`` times the generated model's cold builds instead, per shape, each in a process of
its own with a fresh kernel cache (``FOSMC_JAX_CACHE``, a new temporary folder): the value and
gradient alone (the default path's first derivative: the adjoint's
library), then the generated forward compiled and run once (the forward's library alone)
followed by its value and gradient (the adjoint's library on top), each with its XLA
compilation: wall seconds and CPU seconds (the process's and the compiler's, less swayed by
other work on the machine than the wall time), and the load:

    python benchmarks/generated_gradient.py --build --steps 100
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def load() -> float:
    return round(os.getloadavg()[0], 2)


def build(shape: str, steps: int | None):
    import numpy as np

    import fosmc_jax as fj
    from fosmc_jax import config as _config

    if shape == "digital":
        cfg = _config.load("realistic_arm").as_dict()
        payloads, offsets, integrator, precision, default_steps = 8, 8, "rk4", "float64", 4000
    else:
        cfg = _config.load(ROOT / "tuning" / "configs" / "arm_ideal_set2.toml").as_dict()
        if shape == "ideal":
            payloads, offsets, integrator, precision, default_steps = 8, 8, "rk4", "float64", 4000
        else:
            payloads, offsets, integrator, precision, default_steps = 32, 32, "euler", "float32", 1000
    steps = steps or default_steps
    lo, hi = cfg["plant"].get("payload_range", [0.0, 10.0]) if shape == "digital" else (0.0, 10.0)
    cfg["plant"]["payloads"] = np.linspace(lo, hi, payloads).tolist()
    cfg["plant"].pop("uncertainty", None)
    cfg["sim"].update(integrator=integrator, precision=precision, t_final=steps * cfg["sim"]["dt"],
                      initial_offset=np.random.default_rng(1).uniform(-0.05, 0.05, (offsets, 9)).tolist())  # fmt: skip
    problem = fj.build(cfg)
    assert problem.rollouts == payloads * offsets, (problem.rollouts, payloads * offsets)
    return problem, steps


def generated_loss(problem, p):
    """The loss through the generated kernel's forward (white-box: the default path runs the
    hand-written kernel forward, the generated one under differentiation)."""
    import jax
    import jax.numpy as jnp

    from fosmc_jax._plants.arm import without_idle_terms
    from fosmc_jax._simulator import generated

    dtype = problem.X0s.dtype
    args = (without_idle_terms(problem.plants), problem.controller(p), problem.reference, problem.X0s,
            jnp.asarray(problem.dt, dtype), jax.random.PRNGKey(0)[None], jnp.asarray(1e6, dtype),
            jnp.asarray(10.0, dtype))  # fmt: skip
    res = generated.simulate_batch(args, n_steps=problem.options["n_steps"], integrator=problem.options["integrator"],
                                   paired=False)  # fmt: skip
    m = res.mean()
    return jnp.mean(m.rms_error) + 1e-3 * jnp.mean(m.chattering)


def compiled(fn, args) -> tuple:
    """``jax.jit(fn)`` compiled for ``args``, its compile time and one warm call's time."""
    import jax

    t0 = time.perf_counter()
    run = jax.jit(fn).lower(*args).compile()
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    out = jax.block_until_ready(run(*args))
    return run, compile_s, time.perf_counter() - t0, out


def interleaved(runs: dict, args, rounds: int, round_s: float) -> dict:
    """``rounds`` rounds, each timing every compiled function in turn for ``round_s`` seconds at
    least (interleaved: a change of the machine's load reaches all of them alike): per function
    the median seconds per call, every round's, and the loads."""
    import jax

    out = {name: {"all_s": [], "loads": []} for name in runs}
    for _ in range(rounds):
        for name, (run, _, warm, _) in runs.items():
            calls = max(1, int(round_s / max(warm, 1e-6)))
            t0 = time.perf_counter()
            for _ in range(calls):
                jax.block_until_ready(run(*args))
            out[name]["all_s"].append((time.perf_counter() - t0) / calls)
            out[name]["loads"].append(load())
    for name, (_, compile_s, _, _) in runs.items():
        out[name].update(s=statistics.median(out[name]["all_s"]), compile_s=compile_s)
    return out


def cold_builds(args) -> None:
    """``--build``: per shape, the cold builds (see the docstring), each sequence in a process of
    its own (``--build-run``) with a fresh kernel cache."""
    import tempfile

    info = {"command": "python benchmarks/generated_gradient.py " + " ".join(sys.argv[1:]), "shapes": {}}
    for shape in args.only or ["ideal", "digital", "euler32"]:
        row = {"load_start": load()}
        for sequence in ("gradient_alone", "forward,gradient_after_forward"):
            with tempfile.TemporaryDirectory() as cache:
                cmd = [sys.executable, __file__, "--only", shape, "--build-run", sequence]
                cmd += ["--steps", str(args.steps)] if args.steps else []
                run = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "FOSMC_JAX_CACHE": cache})
                if run.returncode:
                    raise SystemExit(run.stderr)
                row.update(json.loads(run.stdout.strip().splitlines()[-1]))
        row["load_end"] = load()
        print(f"{shape}: cold value and gradient alone {row['gradient_alone_s']:.1f} s "
              f"({row['gradient_alone_cpu_s']:.1f} CPU s); cold forward {row['forward_s']:.1f} s "
              f"({row['forward_cpu_s']:.1f} CPU s), then value and gradient {row['gradient_after_forward_s']:.1f} s "
              f"({row['gradient_after_forward_cpu_s']:.1f} CPU s); load {row['load_start']}-{row['load_end']}",
              flush=True)  # fmt: skip
        info["shapes"][shape] = row
    if args.out:
        Path(args.out).write_text(json.dumps(info, indent=1, default=float))


def build_run(args) -> None:
    """``--build-run``: one sequence of cold builds in this process; prints its times as JSON."""
    import jax

    jax.config.update("jax_enable_x64", True)
    problem, steps = build(args.only[0], args.steps)
    p0 = problem.params()
    loss = lambda p: generated_loss(problem, p)
    row = {"rollouts": problem.rollouts, "steps": steps}

    def cpu() -> float:  # this process's and its finished children's (the compiler's) CPU seconds
        return sum(resource.getrusage(who).ru_utime + resource.getrusage(who).ru_stime
                   for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN))  # fmt: skip

    for name in args.build_run.split(","):
        t0, c0 = time.perf_counter(), cpu()
        jax.block_until_ready(jax.jit(loss if name == "forward" else jax.value_and_grad(loss))(p0))
        row[name + "_s"], row[name + "_cpu_s"] = time.perf_counter() - t0, cpu() - c0
        row[name + "_libraries"] = len(list(Path(os.environ["FOSMC_JAX_CACHE"]).glob("generated-*.so")))
    print(json.dumps(row))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--only", choices=["ideal", "digital", "euler32"], action="append", help="shapes (default all)")
    ap.add_argument("--steps", type=int, help="steps per rollout (default: the shape's)")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--round-s", type=float, default=1.0)
    ap.add_argument("--vmap", action="store_true", help="also time the vmap path's value and gradient (slow)")
    ap.add_argument("--arm", action="store_true", help="differentiate in the arm's 19 calibrated parameters too")
    ap.add_argument("--build", action="store_true", help="time the cold builds of the forward and the adjoint")
    ap.add_argument("--build-run", help=argparse.SUPPRESS)  # one sequence of --build, in its own process
    ap.add_argument("--out", help="write the results as JSON")
    args = ap.parse_args(argv)
    if args.build_run:
        return build_run(args)
    if args.build:
        return cold_builds(args)
    import jax
    import jax.numpy as jnp
    import numpy as np

    import fosmc_jax as fj

    jax.config.update("jax_enable_x64", True)
    uptime = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    info = {"command": "python benchmarks/generated_gradient.py " + " ".join(sys.argv[1:] if argv is None else argv),
            "uptime_start": uptime, "cpus": os.cpu_count(), "shapes": {}}  # fmt: skip
    print(f"start: {uptime}", flush=True)
    for shape in args.only or ["ideal", "digital", "euler32"]:
        problem, steps = build(shape, args.steps)
        p0 = problem.params()
        calibrated = fj.ArmParams._fields[: fj.ArmParams._fields.index("Kb") + 1]  # d1 ... Kb: 19
        x0 = (p0, {k: v for k, v in problem.arm_params().items() if k in calibrated}) if args.arm else p0
        of = lambda x: (problem.with_arm(x[1]), x[0]) if args.arm else (problem, x)  # (problem, params)

        def loss(x, fast=True):
            prob, p = of(x)
            m = prob.simulate(p, fast=fast).mean()
            return jnp.mean(m.rms_error) + 1e-3 * jnp.mean(m.chattering)

        row = {"rollouts": problem.rollouts, "steps": steps, "arm_params": bool(args.arm)}
        runs = {
            "forward": compiled(lambda x: loss(x), (x0,)),
            "value_and_grad": compiled(jax.value_and_grad(loss), (x0,)),
            "generated_forward": compiled(lambda x: generated_loss(*of(x)), (x0,)),
        }
        times = interleaved(runs, (x0,), args.rounds, args.round_s)
        fwd, vg = times["forward"], times["value_and_grad"]
        row.update(times)
        ratios = [b / a for a, b in zip(fwd["all_s"], vg["all_s"])]
        row["ratio"] = statistics.median(ratios)
        row["ratios"] = ratios
        v_out = runs["value_and_grad"][3]
        row["value_match"] = float(abs(v_out[0] - runs["forward"][3]) / abs(runs["forward"][3]))
        gen = times["generated_forward"]
        row["generated_over_hand"] = statistics.median([b / a for a, b in zip(fwd["all_s"], gen["all_s"])])
        line = (f"{shape}: {problem.rollouts} x {steps}: forward {fwd['s'] * 1e3:.1f} ms (generated forward "
                f"{row['generated_over_hand']:.2f}x it), value and gradient "
                f"{vg['s'] * 1e3:.1f} ms = {row['ratio']:.2f}x (rounds {min(ratios):.2f}-{max(ratios):.2f}x; "
                f"compile {fwd['compile_s']:.1f} / {vg['compile_s']:.1f} s), load {vg['loads']}")  # fmt: skip
        if args.vmap:
            vm = compiled(jax.value_and_grad(lambda x: loss(x, fast=False)), (x0,))
            t0 = time.perf_counter()
            jax.block_until_ready(vm[0](x0))
            row["vmap_value_and_grad"] = {"s": time.perf_counter() - t0, "compile_s": vm[1], "load": load()}
            diffs = jax.tree.map(lambda a, b: float(np.max(np.abs(a - b) / np.maximum(np.abs(b), 1e-300))),
                                 v_out[1], vm[3][1])  # fmt: skip
            row["grad_rel_diff_vs_vmap"] = max(jax.tree.leaves(diffs))
            vs = row["vmap_value_and_grad"]["s"]
            line += (f"; vmap path {vs * 1e3:.0f} ms = {vs / fwd['s']:.0f}x, gradients within "
                     f"{row['grad_rel_diff_vs_vmap']:.1e} relative")  # fmt: skip
        print(line, flush=True)
        info["shapes"][shape] = row
    info["uptime_end"] = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    if args.out:
        Path(args.out).write_text(json.dumps(info, indent=1, default=float))


if __name__ == "__main__":
    main()
