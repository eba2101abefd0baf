"""Which lever bought what for the arm's closed loop, measured one at a time, one command:

    python benchmarks/arm_levers.py                       # full: 1,000 steps, 5 rounds of >= 0.3 s
    python benchmarks/arm_levers.py --quick               # a trial: 200 steps, 3 rounds of >= 0.1 s
    python benchmarks/arm_levers.py --out /tmp/arm_levers.json

The case: ``benchmarks/bench.py``'s ``problem(1024, dtype, arm=True)`` (32 payloads in [0, 10] kg
x 32 initial offsets, the ideal-loop FOSMC, ratio switching, Table 1 set 1, dt = 1e-4), 1,000
steps, in two cells: Euler float32 and RK4 float64. The variants, each in a fresh process:

- (a) the ``vmap`` path: ``FOSMC_JAX_NATIVE=0`` (``vmap`` of ``simulate``, a ``lax.scan``);
- (b) the kernel (``fosmc_jax/_simulator/arm_kernel.cc``), as built by default;
- (c) the kernel built with ``-DFOSMC_NO_REUSE``: the accelerations recomputed at the start of
  each step instead of reusing those computed when the state was observed;
- (d) the kernel built with ``-DFOSMC_LIBM_SINCOS``: libm's sin and cos lane by lane instead of
  the vectorised branch-free sincos;
- (e) the kernel built with ``-DFOSMC_SIMD_BYTES=64``: blocks of 64 bytes (the width before
  issue 32) where the CPU's register is narrower (AVX2: 32; on AVX-512 (e) is (b)).

(c), (d) and (e) pass their macro through ``FOSMC_JAX_KERNEL_FLAGS`` (part of the kernel's build
cache key: each variant is built once, under ``FOSMC_JAX_CACHE``); each kernel process checks
that ``simulate_batch`` takes the kernel on this batch and records which library it loaded,
(a) that it does not. Each variant runs twice: unpinned (both cores) and in a process pinned to
CPU 0 before JAX is imported (one core really: no thread of it, XLA's pools included, can run
on another); the two share a persistent compilation cache (one per variant), so the pinned
process loads the unpinned one's programs. Per cell: compile (timed, apart), a warm call, then
``rounds`` timed rounds of as many calls as last ``round_s`` at least; the figure is the median
round's rollout-steps/s (rollouts x steps / seconds). The 1-minute load average and the
process's CPU seconds per wall second (every thread: 2 = both cores its own) are recorded with
every round: the machine may be shared, and the both-cores column is the one other work takes
from.

The variants must compute the same thing: per cell, the mean rms error of joint 1 over the batch
and its per-rollout values are compared with (b)'s; a relative difference beyond 1e-4 (float32)
or 1e-9 (float64), ``bench.py``'s tolerances against the arm anchor, or a different number of
diverged rollouts, is flagged MISMATCH in the table and the command exits with status 1 (after
writing ``--out``). Pinned and unpinned runs of one variant must agree exactly.

Prints a Markdown table: rollout-steps/s per variant, cell and core count, each as a ratio to (b).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

if __name__ == "__main__" and "--pin" in sys.argv[1:]:
    # the one-core column: this process on CPU 0 before JAX (and its thread pools) starts
    os.sched_setaffinity(0, {0})

HERE = Path(__file__).resolve().parent
VARIANTS = (
    ("a", "vmap path (FOSMC_JAX_NATIVE=0)", {"FOSMC_JAX_NATIVE": "0"}),
    ("b", "kernel", {}),
    ("c", "kernel -DFOSMC_NO_REUSE", {"FOSMC_JAX_KERNEL_FLAGS": "-DFOSMC_NO_REUSE"}),
    ("d", "kernel -DFOSMC_LIBM_SINCOS", {"FOSMC_JAX_KERNEL_FLAGS": "-DFOSMC_LIBM_SINCOS"}),
    ("e", "kernel -DFOSMC_SIMD_BYTES=64", {"FOSMC_JAX_KERNEL_FLAGS": "-DFOSMC_SIMD_BYTES=64"}),
)
CELLS = (("euler", "float32"), ("rk4", "float64"))
BATCH = 1024
#: Largest relative difference of a variant's rms error of joint 1 from (b)'s (bench.ARM_RMS_TOL).
RMS_TOL = {"float32": 1e-4, "float64": 1e-9}
#: What a child's environment must not inherit: the variant sets these itself.
CLEARED = ("FOSMC_JAX_NATIVE", "FOSMC_JAX_KERNEL_FLAGS", "XLA_FLAGS", "JAX_NUM_CPU_DEVICES")


def load() -> float:
    return round(os.getloadavg()[0], 2)


def cpu_s() -> float:
    """CPU seconds of this process so far, every thread (user + system)."""
    t = os.times()
    return t.user + t.system


def child(spec_path: str) -> None:
    """One variant in this fresh process (pinned or not by ``--pin`` at the top of the file): both
    cells timed; the rows (and each cell's per-rollout rms error of joint 1) go to ``spec["out"]``."""
    import numpy as np

    spec = json.loads(Path(spec_path).read_text())
    sys.path.insert(0, str(HERE))
    import bench  # noqa: F401  (problem(); sets up JAX as bench.py does: 2 CPU devices, x64 on)
    import jax

    import fosmc_jax as fj
    from fosmc_jax._simulator import arm_native as _arm_native
    from fosmc_jax._simulator import native as _native
    from fosmc_jax._simulator import rollout as _simulator

    jax.config.update("jax_compilation_cache_dir", spec["cache"])
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    t0 = time.perf_counter()
    native = _native.available()  # builds this variant's kernel the first time (cached after)
    build_s = time.perf_counter() - t0
    library = str(_native._build()) if native else None
    cpus = sorted(os.sched_getaffinity(0))
    rows = []
    for integrator, dtype in CELLS:
        args = bench.problem(BATCH, np.dtype(dtype).type, arm=True)
        kernel = _arm_native.supports(args[0], _simulator.as_controller(args[1]), integrator)
        if kernel != spec["kernel"]:
            raise SystemExit(f"variant {spec['variant']}: the kernel {'runs' if kernel else 'does not run'} "
                             f"({integrator}, {dtype}); expected the opposite")  # fmt: skip
        opts = dict(n_steps=spec["steps"], integrator=integrator)
        t0 = time.perf_counter()
        compiled = fj.simulate_batch.lower(*args, **opts).compile()
        compile_s = time.perf_counter() - t0
        call = lambda: jax.block_until_ready(compiled(*args))
        t0 = time.perf_counter()
        call()  # warm; its time sets the calls per round
        warm_s = time.perf_counter() - t0
        calls = max(1, int(np.ceil(spec["round_s"] / warm_s)))
        rates, loads, busy = [], [], []
        for _ in range(spec["rounds"]):
            c0, t0 = cpu_s(), time.perf_counter()
            for _ in range(calls):
                r = call()
            wall = time.perf_counter() - t0
            rates.append(calls * BATCH * spec["steps"] / wall)
            busy.append(round((cpu_s() - c0) / wall, 2))
            loads.append(load())
        rms = np.asarray(r.metrics.rms_error, np.float64)[:, 0]
        rows.append({"integrator": integrator, "dtype": dtype, "batch": BATCH, "steps": spec["steps"],
                     "kernel": kernel, "rollout_steps_per_s": statistics.median(rates), "min": min(rates),
                     "max": max(rates), "samples": rates, "calls_per_round": calls, "compile_s": compile_s,
                     "warm_call_s": warm_s, "loads": loads, "cpu_per_wall": busy, "rms_error_joint1": float(np.mean(rms)),
                     "rms_joint1": rms.tolist(), "diverged": int(np.sum(np.asarray(r.diverged)))})  # fmt: skip
        print(f"  ({spec['variant']}) {integrator:5s} {dtype:7s} CPUs {cpus}: {rows[-1]['rollout_steps_per_s']:.3e} "
              f"rollout-steps/s ({calls} calls/round, compile {compile_s:.1f} s, CPU s per s {statistics.median(busy)})  "
              f"load {min(loads)}-{max(loads)}",
              flush=True)  # fmt: skip
    Path(spec["out"]).write_text(json.dumps({"rows": rows, "cpus": cpus, "native": native, "build_s": build_s,
                                             "library": library, "devices": jax.device_count(),
                                             "jax": jax.__version__}))  # fmt: skip


def run_variant(key: str, label: str, env_add: dict, pinned: bool, spec: dict, tmp: str) -> dict:
    """One variant in a fresh process of this script, unpinned or pinned to CPU 0."""
    name = f"{key}-{'pinned' if pinned else 'unpinned'}"
    path, out = Path(tmp) / f"{name}.json", Path(tmp) / f"{name}-rows.json"
    path.write_text(json.dumps(dict(spec, variant=key, kernel=key != "a", out=str(out),
                                    cache=str(Path(tmp) / f"xla-cache-{key}"))))  # fmt: skip
    env = {k: v for k, v in os.environ.items() if k not in CLEARED}
    env.update(env_add)
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", str(path)] + (["--pin"] if pinned else [])
    print(f"({key}) {label}, {'one core (pinned to CPU 0)' if pinned else 'both cores (unpinned)'}: "
          f"{' '.join(f'{k}={v}' for k, v in env_add.items()) or 'default environment'}, load {load()}", flush=True)  # fmt: skip
    t0 = time.perf_counter()
    subprocess.run(cmd, env=env, check=True)
    return dict(json.loads(out.read_text()), process_s=time.perf_counter() - t0, env=env_add, label=label)


def compare(results: dict) -> list[str]:
    """Each variant's rms errors of joint 1 against (b)'s, per cell (recorded in the rows);
    returns the mismatches, described."""
    import numpy as np

    bad = []
    for key, per in results.items():
        for where in ("both", "one"):
            for row, ref in zip(per[where]["rows"], results["b"]["both"]["rows"]):
                x, y = np.asarray(row["rms_joint1"]), np.asarray(ref["rms_joint1"])
                mean_rel = abs(row["rms_error_joint1"] - ref["rms_error_joint1"]) / abs(ref["rms_error_joint1"])
                per_rollout = float(np.max(np.abs(x - y) / np.abs(y)))
                ok = mean_rel <= RMS_TOL[row["dtype"]] and row["diverged"] == ref["diverged"]
                row.update(rms_rel_diff_to_b=mean_rel, rms_rel_diff_to_b_per_rollout_max=per_rollout,
                           rms_bitwise_equal_to_b=bool(np.array_equal(x, y)), rms_match=bool(ok))  # fmt: skip
                if where == "one":
                    both = next(r for r in per["both"]["rows"] if r["integrator"] == row["integrator"])
                    row["same_as_unpinned"] = both["rms_joint1"] == row["rms_joint1"]
                    if not row["same_as_unpinned"]:
                        bad.append(f"({key}) {row['integrator']} {row['dtype']}: pinned and unpinned results differ")
                if not ok:
                    bad.append(f"({key}) {row['integrator']} {row['dtype']} ({where}): rms joint 1 "
                               f"{row['rms_error_joint1']:.10g} vs (b) {ref['rms_error_joint1']:.10g} (rel "
                               f"{mean_rel:.1e} > {RMS_TOL[row['dtype']]:.0e}), diverged {row['diverged']} vs "
                               f"{ref['diverged']}")  # fmt: skip
    return bad


def table(info: dict) -> str:
    res = info["results"]
    variants = [v for v in VARIANTS if v[0] in res]
    head = "| variant |"
    for integrator, dtype in CELLS:
        cell = f"{integrator} {dtype}"
        head += f" {cell}: both cores | x (b) | {cell}: 1 core | x (b) | {cell}: rms joint 1 (rel. to (b)) |"
    lines = [head, "|---|" + "---|" * 5 * len(CELLS)]
    for key, label, _ in variants:
        line = f"| ({key}) {label} |"
        for i in range(len(CELLS)):
            for where in ("both", "one"):
                r, b = res[key][where]["rows"][i], res["b"][where]["rows"][i]
                rate = r["rollout_steps_per_s"]
                line += f" {rate:.3g} ({r['min']:.3g}-{r['max']:.3g}) | {rate / b['rollout_steps_per_s']:.3f} |"
            r = res[key]["both"]["rows"][i]
            same = "bitwise" if r["rms_bitwise_equal_to_b"] else f"{r['rms_rel_diff_to_b']:.1e}"
            line += f" {r['rms_error_joint1']:.10g} ({same}{'' if r['rms_match'] else ', **MISMATCH**'}) |"
        lines.append(line)
    loads = [x for per in res.values() for w in per.values() for r in w["rows"] for x in r["loads"]]
    lines += ["", f"Median (min-max) of {info['rounds']} rounds of >= {info['round_s']} s; batch {BATCH} "
              f"(problem({BATCH}, dtype, arm=True)), {info['steps']} steps; x (b): the ratio to the default kernel's "
              f"rate in the same column. Load average during the rounds: {min(loads)}-{max(loads)}."]  # fmt: skip
    busy = [f"({key}) " + ", ".join(f"{r['integrator']} {r['dtype']} {statistics.median(r['cpu_per_wall'])}"
                                    for r in res[key]["both"]["rows"]) for key, _, _ in variants]  # fmt: skip
    lines.append("CPU seconds per wall second of the both-cores process during its rounds (median; 2 = both "
                 "cores its own, less = a core shared with other work or idle): " + "; ".join(busy) + ".")  # fmt: skip
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="a trial: 200 steps, 3 rounds of >= 0.1 s")
    ap.add_argument("--out", help="write everything as JSON")
    ap.add_argument("--variants", default="abcde", help="a subset of abcde; (b) is always run (default abcde)")
    ap.add_argument("--child", help=argparse.SUPPRESS)  # a variant's process: its spec file
    ap.add_argument("--pin", action="store_true", help=argparse.SUPPRESS)  # that process on CPU 0 (top of file)
    args = ap.parse_args(argv)
    if args.child:
        return child(args.child)
    steps, rounds, round_s = (200, 3, 0.1) if args.quick else (1000, 5, 0.3)
    keys = sorted(set(args.variants) | {"b"})
    uptime = lambda: subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    info = {"command": "python benchmarks/arm_levers.py " + " ".join(sys.argv[1:] if argv is None else argv),
            "steps": steps, "rounds": rounds, "round_s": round_s, "batch": BATCH, "cells": CELLS,
            "cores": os.cpu_count(), "uptime_start": uptime(), "results": {}}  # fmt: skip
    print(f"start: {info['uptime_start']}", flush=True)
    t_start = time.perf_counter()
    spec = {"steps": steps, "rounds": rounds, "round_s": round_s}
    with tempfile.TemporaryDirectory() as tmp:
        for key, label, env_add in VARIANTS:
            if key in keys:  # unpinned first: it compiles (and builds the kernel) for the pinned one
                info["results"][key] = {pinned: run_variant(key, label, env_add, pinned == "one", spec, tmp)
                                        for pinned in ("both", "one")}  # fmt: skip
    libraries = {k: v["both"]["library"] for k, v in info["results"].items() if k != "a"}
    if len(set(libraries.values())) != len(libraries):
        raise SystemExit(f"two kernel variants loaded the same library: {libraries}")
    bad = compare(info["results"])
    for per in info["results"].values():  # the per-rollout values were for the comparison only
        for where in per.values():
            for row in where["rows"]:
                del row["rms_joint1"]
    info.update(mismatches=bad, total_s=time.perf_counter() - t_start, uptime_end=uptime())
    info["table"] = table(info)
    print(f"end: {info['uptime_end']}\n\n{info['table']}")
    for line in bad:
        print("MISMATCH:", line)
    if args.out:
        Path(args.out).write_text(json.dumps(info, indent=1))
        print(f"wrote {args.out}")
    if bad:
        sys.exit(1)


if __name__ == "__main__":
    main()
