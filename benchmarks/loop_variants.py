"""Variants of the linear batch fast path (``_simulator._linear_batch``) timed back to back,
interleaved, best of N, in one process on one device (issue 13, item 1):

    python benchmarks/loop_variants.py [--batch 1024] [--steps 2000] [--reps 5] [--dtype float32]

- ``baseline``: the fast path as it is (tuple-of-(P, O) carry, every stage under an
  always-true ``cond`` so that XLA materialises it once per step, the time ``scan`` unrolled
  twice since issue 13);
- ``unroll=k``: the time ``scan`` unrolled k times (``unroll=1``: the fast path before issue 13);
- ``packed``: the carry packed into one (n, P, O) array per dtype (one buffer in the loop
  instead of ~50 scalar-per-rollout leaves), unpacked at the top of the body;
- ``packed unroll=4``;
- ``no cond``: the stages without the ``cond`` barrier (XLA fuses freely, recomputing shared terms);
- ``chunks=c``: the batch cut into c blocks of plants run one after another (``lax.map``),
  each block small enough for the cache.

Every variant's metrics are checked against the baseline (max relative difference printed).
Prints one table row per variant: best wall seconds, rollout-steps/s, ratio to baseline, and
the load average. The SIMD anchor (``../shared/anchors/simd_kernel/run.sh``) runs in the same
process when gcc is present.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fosmc_jax._simulator import linear_path  # noqa: E402

_ORIGINAL_SCAN = linear_path._scan_steps


def scan_unrolled(unroll):
    def scan_steps(body, carry, steps, **_):
        return carry if steps == 0 else jax.lax.scan(body, carry, None, length=steps, unroll=unroll)[0]

    return scan_steps


def scan_packed(unroll=1):
    """The carry's leaves grouped by (shape, dtype) and stacked into one array per group."""

    def scan_steps(body, carry, steps, **_):
        if steps == 0:
            return carry
        leaves, tree = jax.tree.flatten(carry)
        groups: dict = {}
        for i, x in enumerate(leaves):
            groups.setdefault((x.shape, x.dtype), []).append(i)
        keys = list(groups)

        def pack(leaves):
            return tuple(jnp.stack([leaves[i] for i in groups[k]]) for k in keys)

        def unpack(packed):
            out = [None] * len(leaves)
            for k, arr in zip(keys, packed):
                for j, i in enumerate(groups[k]):
                    out[i] = arr[j]
            return jax.tree.unflatten(tree, out)

        def packed_body(p, _):
            c, y = body(unpack(p), None)
            return pack(jax.tree.leaves(c)), y

        p = jax.lax.scan(packed_body, pack(leaves), None, length=steps, unroll=unroll)[0]
        return unpack(p)

    return scan_steps


def make(variant, args, opts):
    """A compiled callable for ``variant``."""
    plants, ctrl, ref, X0s, dt = args
    linear_path._scan_steps = _ORIGINAL_SCAN
    cond = jax.lax.cond
    try:
        if variant.startswith("unroll="):
            linear_path._scan_steps = scan_unrolled(int(variant.split("=")[1]))
        elif variant.startswith("packed"):
            linear_path._scan_steps = scan_packed(int(variant.split("=")[1]) if "=" in variant else 1)
        elif variant == "no cond":
            jax.lax.cond = lambda p, f, g, *a: f(*a)
        if variant.startswith("chunks="):
            c = int(variant.split("=")[1])
            P = plants.a_rows.shape[0]

            def fn(plants, ctrl, ref, X0s, dt):
                blocks = jax.tree.map(lambda x: x.reshape((c, P // c) + x.shape[1:]), plants)
                res = jax.lax.map(lambda p: linear_path._linear_batch(p, ctrl, ref, X0s, dt, **opts), blocks)
                return jax.tree.map(lambda x: x.reshape((-1,) + x.shape[2:]), res)
        else:
            fn = lambda plants, ctrl, ref, X0s, dt: linear_path._linear_batch(plants, ctrl, ref, X0s, dt, **opts)  # noqa: E731
        compiled = jax.jit(fn).lower(plants, ctrl, ref, X0s, dt).compile()
    finally:
        linear_path._scan_steps = _ORIGINAL_SCAN
        jax.lax.cond = cond
    return lambda: compiled(plants, ctrl, ref, X0s, dt)


def anchor(batch, steps):
    run = Path(__file__).resolve().parents[2] / "shared" / "anchors" / "simd_kernel" / "run.sh"
    if not run.exists():
        return None
    import re
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        out = subprocess.run(["bash", str(run), str(batch), str(steps)], capture_output=True, text=True, cwd=tmp)
    vals = [float(v) for v in re.findall(r"threads=1 .*?: ([0-9.e+]+) rollout-steps/s", out.stdout)]
    return max(vals) if vals else None


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--batch", type=int, default=1024)
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--dtype", default="float32")
    ap.add_argument("--integrator", default="euler")
    ap.add_argument("--variants", default="baseline,unroll=1,unroll=4,unroll=8,packed,packed unroll=4,no cond,chunks=4")
    a = ap.parse_args(argv)
    import bench

    dtype = np.dtype(a.dtype)
    if dtype == np.float64:
        jax.config.update("jax_enable_x64", True)
    args = bench.problem(a.batch, dtype)
    opts = dict(n_steps=a.steps, integrator=a.integrator)
    variants = a.variants.split(",")
    fns, comp = {}, {}
    for v in variants:
        t0 = time.perf_counter()
        fns[v] = make(v, args, opts)
        jax.block_until_ready(fns[v]())
        comp[v] = time.perf_counter() - t0
    ref = jax.tree.map(np.asarray, fns[variants[0]]().metrics)
    diff = {}
    for v in variants:
        out = jax.tree.map(np.asarray, fns[v]().metrics)
        diff[v] = max(float(np.nanmax(np.abs(x - y) / (np.abs(y) + 1e-30))) for x, y in zip(out, ref))
    times = {v: [] for v in variants}
    loads = []
    for _ in range(a.reps):  # interleaved repetitions
        for v in variants:
            t0 = time.perf_counter()
            jax.block_until_ready(fns[v]())
            times[v].append(time.perf_counter() - t0)
        loads.append(os.getloadavg()[0])
    roof = anchor(a.batch, a.steps)
    base = min(times[variants[0]])
    work = a.batch * a.steps
    print(f"batch {a.batch}, {a.steps} steps, {a.integrator}, {a.dtype}, 1 device, best of {a.reps} interleaved; "
          f"load during timing {min(loads):.2f}-{max(loads):.2f}")  # fmt: skip
    print(
        "| variant | best s | rollout-steps/s | vs baseline | of anchor (1 thread) | compile+first s | max rel diff |"
    )
    print("|---|---|---|---|---|---|---|")
    for v in variants:
        t = min(times[v])
        frac = f"{work / t / roof:.1%}" if roof else ""
        print(f"| {v} | {t:.4f} | {work / t:.3g} | {base / t:.2f}x | {frac} | {comp[v]:.1f} | {diff[v]:.1e} |")
    if roof:
        print(
            f"| SIMD anchor, 1 thread (best of 3) | {work / roof:.4f} | {roof:.3g} | {roof / (work / base):.1f}x | 100% | | |"
        )
    print(f"load after: {os.getloadavg()}")


if __name__ == "__main__":
    main()
