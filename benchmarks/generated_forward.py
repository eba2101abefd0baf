"""The generated forward kernel against the hand-written one it is to replace, in every cell of
``bench.py``'s arm table (issue 32: "within 1.2x in every cell"), in one run:

    python benchmarks/generated_forward.py                  # every cell, a fresh kernel cache
    python benchmarks/generated_forward.py --quick          # batch 1,024 only, digital 500 steps
    python benchmarks/generated_forward.py --out benchmarks/results/issue32/generated_forward.json

Cells (bench.py's ``arm_table``): the ideal loop (Euler and RK4, float32 and float64, 1,024 and
4,096 rollouts: ``bench.problem``'s payloads x offsets, 1,000 steps at dt 1e-4) and the
realistic preset's 1 kHz digital loop (RK4, float64 and float32, 1,024 rollouts, 4,000 steps).
Per cell, each path compiled first (the generated model's first build, printing and C++
compilation, timed apart: ``--cache`` names the kernel cache, default a fresh temporary folder,
so the build is a cold one), then timed in ``--rounds`` interleaved rounds of ``--round-s`` s
each on both cores; the ratio is the median of the rounds' (generated / hand-written). The
rollouts' rms errors of the two paths are compared (max relative difference). The 1-minute load
average is recorded with every round.

``--flags "-fschedule-insns -fsched-pressure"`` adds a third path to every cell: the generated
kernel built again with those extra compiler flags (``FOSMC_JAX_GENERATED_FLAGS``; its build
timed too), in the same interleaved rounds; its ratio to the plain generated one, and whether
its rms errors equal the plain one's bit for bit. ``--terms`` turns Coulomb friction and a
sinusoidal disturbance on in every cell's arm (bench.py's arms have neither).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="batch 1,024 only; the digital loop over 500 steps")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--round-s", type=float, default=0.5)
    ap.add_argument("--cache", help="the kernel cache folder (default: a fresh temporary one: cold builds)")
    ap.add_argument("--flags", help="extra compiler flags for a third path, the generated kernel built with them")
    ap.add_argument(
        "--terms",
        action="store_true",
        help="Coulomb friction and a sinusoidal disturbance on in every arm (the cells have neither)",
    )
    ap.add_argument("--only", help="the cells whose 'loop integrator dtype' contains this (e.g. 'digital rk4')")
    ap.add_argument("--out", help="write the rows as JSON")
    args = ap.parse_args(argv)
    tmp = tempfile.TemporaryDirectory()
    os.environ["FOSMC_JAX_CACHE"] = args.cache or tmp.name

    import jax
    import numpy as np

    jax.config.update("jax_enable_x64", True)
    sys.path.insert(0, str(HERE))
    import bench

    import fosmc_jax as fj
    from fosmc_jax._plants.arm import without_idle_terms
    from fosmc_jax._simulator import generated, rollout

    cells = [dict(loop="ideal", integrator=i, dtype=d, batch=b, steps=bench.ARM_STEPS, case=None)
             for i in ("euler", "rk4") for d in ("float32", "float64") for b in ((1024,) if args.quick else (1024, 4096))]  # fmt: skip
    cells += [dict(loop="digital", integrator="rk4", dtype=d, batch=1024, steps=500 if args.quick else 4000, case=None)
              for d in ("float64", "float32")]  # fmt: skip
    if args.only:
        cells = [c for c in cells if args.only in f"{c['loop']} {c['integrator']} {c['dtype']}"]
    rows = []
    print(f"start: load {os.getloadavg()[0]:.2f}", flush=True)
    for cell in cells:
        (plants, ctrl, ref, X0s, dt), dynamic, static = bench.arm_cell_inputs(cell)
        # the arm's zero friction and disturbance terms left out before the jit, as the public path
        # does (inside it the plants are traced, and the generated step would compute the zero
        # terms that the hand-written kernel skips at run time)
        if args.terms:  # 0.2 N m of Coulomb friction (v_c 0.01 rad/s), 0.5 N m at 2 Hz on every joint
            on = dict(Fc=0.2, v_coulomb=0.01, tau_sin=0.5, f_sin=2.0)
            plants = plants._replace(params=plants.params._replace(**{
                k: np.full(np.shape(getattr(plants.params, k)), v, X0s.dtype) for k, v in on.items()}))  # fmt: skip
        plants = without_idle_terms(plants)
        ctrl = fj.FOSMC(ctrl) if isinstance(ctrl, fj.FOSMCParams) else ctrl  # the ideal cells' default law
        dtype = X0s.dtype
        keys = dynamic.get("keys", jax.random.PRNGKey(0)[None])
        bound = np.asarray(dynamic.get("divergence_bound", 1e6), dtype)
        cutoff = np.asarray(dynamic.get("chattering_cutoff", 10.0), dtype)
        opts = dict(n_steps=static["n_steps"], integrator=static["integrator"])

        def hand(plants, X0s):
            return rollout.simulate_batch(plants, ctrl, ref, X0s, dt, **dynamic, **static).metrics.rms_error

        def gen(plants, X0s):
            a = (plants, ctrl, ref, X0s, np.asarray(dt, dtype), keys, bound, cutoff)
            return generated.simulate_batch(a, paired=False, **opts).metrics.rms_error

        runs, out = {}, {}
        paths = [("hand", hand), ("generated", gen)] + ([("flags", lambda p, x: gen(p, x))] if args.flags else [])
        for name, fn in paths:
            if name == "flags":  # white-box: the printed model forgotten, so that it is built again
                generated._MODELS.clear()
                os.environ["FOSMC_JAX_GENERATED_FLAGS"] = args.flags
            t0 = time.perf_counter()
            run = jax.jit(fn).lower(plants, X0s).compile()
            out[name] = np.asarray(jax.block_until_ready(run(plants, X0s)))
            runs[name] = [run, time.perf_counter() - t0, []]
            os.environ.pop("FOSMC_JAX_GENERATED_FLAGS", None)
        for _ in range(args.rounds):
            for r in runs.values():
                t0, calls = time.perf_counter(), 0
                while time.perf_counter() - t0 < args.round_s or calls == 0:
                    jax.block_until_ready(r[0](plants, X0s))
                    calls += 1
                r[2].append((time.perf_counter() - t0) / calls)
        ratios = [g / h for g, h in zip(runs["generated"][2], runs["hand"][2])]
        hand_s = statistics.median(runs["hand"][2])
        row = dict(cell, case=None, hand_s=hand_s, generated_s=statistics.median(runs["generated"][2]),
                   ratio=statistics.median(ratios), ratios=ratios, hand_compile_s=runs["hand"][1],
                   generated_build_and_compile_s=runs["generated"][1],
                   rms_rel_diff=float(np.nanmax(np.abs(out["generated"] - out["hand"]) / np.abs(out["hand"]))),
                   rollout_steps_per_s=cell["batch"] * cell["steps"] / hand_s, load=os.getloadavg()[0])  # fmt: skip
        if args.flags:
            flagged = [f / g for f, g in zip(runs["flags"][2], runs["generated"][2])]
            row.update(flags=args.flags, flags_s=statistics.median(runs["flags"][2]), flags_over_generated=
                       statistics.median(flagged), flags_ratios=flagged, flags_build_and_compile_s=runs["flags"][1],
                       flags_bitwise=bool(np.array_equal(out["flags"], out["generated"], equal_nan=True)))  # fmt: skip
            print(f"  with {args.flags}: {1e3 * row['flags_s']:.1f} ms = {row['flags_over_generated']:.3f}x the "
                  f"generated (rounds {min(flagged):.3f}-{max(flagged):.3f}); build + compile "
                  f"{row['flags_build_and_compile_s']:.1f} s; bitwise {row['flags_bitwise']}", flush=True)  # fmt: skip
        rows.append(row)
        print(f"{cell['loop']:7s} {cell['integrator']:5s} {cell['dtype']:7s} {cell['batch']:5d} x {cell['steps']}: "
              f"hand {1e3 * row['hand_s']:.1f} ms, generated {1e3 * row['generated_s']:.1f} ms = {row['ratio']:.2f}x "
              f"(rounds {min(ratios):.2f}-{max(ratios):.2f}); generated build + compile {row['generated_build_and_compile_s']:.1f} s, "
              f"hand compile {row['hand_compile_s']:.1f} s; rms diff {row['rms_rel_diff']:.1e}; load {row['load']:.2f}",
              flush=True)  # fmt: skip
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
