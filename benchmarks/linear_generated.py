"""The linear plant's hand-written kernel (kernel.cc, the default path until issue 32 retired it)
against the kernel generated from the same JAX step, forward and value and gradient, one command:

    python benchmarks/linear_generated.py                      # bench.py's cells, 1,024 and 4,096 x 4,000
    python benchmarks/linear_generated.py --batches 1024 --steps 1000 --rounds 3   # a short trial

Runs only at a commit that still has kernel.cc (its last: the commit that adds this file); it
left the repository with kernel.cc. Cells: bench.py's linear problem (Table 1 set 1, sampled
box plants x offsets), Euler and RK4, float32 and float64. Per cell, timed in ``--rounds``
interleaved rounds of at least 0.4 s each after compilation (the generated model's cold build
timed with it, in a fresh kernel cache): the forward through ``fj.simulate_batch`` (kernel.cc)
and through ``generated.simulate_batch``; with ``--grad``, also the value and gradient of
mean(rms_error) + 1e-3 mean(chattering) in delta on both (the default path's derivatives were
the ``vmap`` path's, its ``custom_jvp``). Ratios are medians of the rounds' ratios; the
1-minute load is printed with each cell.
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
    ap.add_argument("--batches", default="1024,4096")
    ap.add_argument("--steps", type=int, default=4000)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--grad", action="store_true", help="value and gradient too (float64 cells)")
    ap.add_argument("--out", help="write the rows as JSON")
    args = ap.parse_args(argv)
    tmp = tempfile.TemporaryDirectory(prefix="fosmc-linear-generated-")
    os.environ["FOSMC_JAX_CACHE"] = tmp.name

    import jax
    import jax.numpy as jnp
    import numpy as np

    jax.config.update("jax_enable_x64", True)
    sys.path.insert(0, str(HERE))
    import bench

    import fosmc_jax as fj
    from fosmc_jax._simulator import generated

    rows, keys = [], jax.random.PRNGKey(0)[None]
    for integrator in ("euler", "rk4"):
        for dtype in (np.float32, np.float64):
            for batch in (int(b) for b in args.batches.split(",")):
                plants, p0, ref, X0s, dt = bench.problem(batch, dtype)
                bound, cutoff = np.asarray(1e6, dtype), np.asarray(10.0, dtype)

                def loss(delta, path, plants=plants, p0=p0, ref=ref, X0s=X0s, dt=dt, dtype=dtype, bound=bound,
                         cutoff=cutoff, integrator=integrator):  # fmt: skip
                    ctrl = fj.FOSMC(p0._replace(delta=delta))
                    opts = dict(n_steps=args.steps, integrator=integrator)
                    if path == "kernel.cc":
                        r = fj.simulate_batch(plants, ctrl, ref, X0s, dt, **opts)
                    else:
                        a = (plants, ctrl, ref, X0s, jnp.asarray(dt, dtype), keys, bound, cutoff)
                        r = generated.simulate_batch(a, paired=False, **opts)
                    return jnp.mean(r.metrics.rms_error) + 1e-3 * jnp.mean(r.metrics.chattering)

                fns = {}
                kinds = ["forward"] + (["value_and_grad"] if args.grad and dtype == np.float64 else [])
                for path in ("kernel.cc", "generated"):
                    for kind in kinds:
                        f = lambda d, path=path: loss(d, path)
                        f = jax.value_and_grad(f) if kind == "value_and_grad" else f
                        t0 = time.perf_counter()
                        c = jax.jit(f).lower(p0.delta).compile()
                        out = jax.block_until_ready(c(p0.delta))
                        fns[path, kind] = dict(call=c, compile_s=time.perf_counter() - t0, out=out, times=[])
                for _ in range(args.rounds):
                    for r in fns.values():
                        t0, n = time.perf_counter(), 0
                        while time.perf_counter() - t0 < 0.4 or n == 0:
                            jax.block_until_ready(r["call"](p0.delta))
                            n += 1
                        r["times"].append((time.perf_counter() - t0) / n)
                for kind in kinds:
                    h, g = fns["kernel.cc", kind], fns["generated", kind]
                    ratios = [x / y for x, y in zip(g["times"], h["times"])]
                    leaves = lambda o: [np.asarray(x) for x in jax.tree.leaves(o)]  # noqa: E731
                    diff = max(float(np.max(np.abs(a - b) / np.maximum(np.abs(b), 1e-300)))
                               for a, b in zip(leaves(g["out"]), leaves(h["out"])))  # fmt: skip
                    row = dict(integrator=integrator, dtype=np.dtype(dtype).name, batch=batch, steps=args.steps,
                               kind=kind, kernel_cc_s=statistics.median(h["times"]),
                               generated_s=statistics.median(g["times"]), ratio=statistics.median(ratios),
                               ratios=ratios, generated_compile_s=g["compile_s"], rel_diff=diff,
                               load=os.getloadavg()[0])  # fmt: skip
                    rows.append(row)
                    print(f"{integrator:5s} {row['dtype']:7s} {batch:5d} x {args.steps} {kind:14s}: default "
                          f"{1e3 * row['kernel_cc_s']:8.1f} ms, generated {1e3 * row['generated_s']:8.1f} ms = "
                          f"{row['ratio']:.2f}x (rounds {min(ratios):.2f}-{max(ratios):.2f}); generated compile "
                          f"{row['generated_compile_s']:.1f} s; rel diff {diff:.1e}; load {row['load']:.2f}",
                          flush=True)  # fmt: skip
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
