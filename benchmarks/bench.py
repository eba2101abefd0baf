"""Throughput of fosmc_jax against baselines and the machine's matmul roof, one command:

    python benchmarks/bench.py            # full: 4,000 steps, batches 1..16,384, one 40,000-step check
    python benchmarks/bench.py --quick    # CI: fewer steps and batches, under 2 minutes on 2 cores
    python benchmarks/bench.py --quick --out /tmp/scratch   # a trial run that leaves results/ alone

With gcc, the SIMD anchor (../shared/anchors/simd_kernel/run.sh, a hand-written C kernel of
the same closed loop) runs in the same process and every linear row is given as a fraction
of its best thread count; ``fosmc simulate --json`` and ``--npz`` run as a user runs them
(1 and 2 devices; steady state from the difference of two horizons).

The arm table (arm_table): the arm's closed loop through simulate_batch in all four integrator x
precision cells (Euler, RK4 x float32, float64; batches 1,024 and 4,096, quick: 1,024; 1,000
steps, the arm anchor's frozen horizon) and the realistic preset's digital loop through the
config path, each on both cores (a process unpinned, 1 device) and on one core (a process pinned
to CPU 0 before JAX is imported), median of several rounds, compilation apart. Where
../shared/anchors/arm_kernel is present (not in a user's clone: then one line says it is
skipped), its kernel.c is built from its frozen/ headers without the package and run in the same
run on the same inputs (1 thread and every core), and its mean rms error of joint 1 is checked
against the package's: equal to 1e-4 (float32) or 1e-9 (float64) relative, or the row says
MISMATCH (not the same work).

Writes benchmarks/results/bench[-quick].json, .md and .png. Figure of merit: rollout-steps per
second (rollouts x steps / wall seconds of a compiled call, best of 3; compile time apart).
The CPU is shown as two devices (``use_host_devices(2)``) for the 1- vs 2-device figures;
single-device runs use device 0.

FLOP count of the minimal algorithm per rollout-step (linear plant, batch-independent work
such as the reference and Omega not counted; comparisons, selects and the divergence check
not counted):
  plant rows 3, 6, 9: a X + b U      3 x (12 mul + 11 add)          =  69
  integrator chains and update       9 x 2                          =  18 (Euler)
  integral state: Z, S Z, w update   9 + 3 x 17 + 3 x 2             =  66
  control: Z, C Z - w, ||Z||, rho, ratio (28), (CB)^-1 f, Omega - . 9 + 54 + 18 + 3 + 9 + 3 + 15 + 3 = 114
  metrics: e, e^2, |e|, |du|, u^2, |u|                              =  36
  Euler total                                                       = 303
  RK4: 4 x (69 + 9 + 51) plant + integral evaluations, 3 x 24 stage states, 12 x 6 combination,
  + control 114 + metrics 36                                         = 810
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
if __name__ == "__main__" and "--pin-child" in sys.argv[1:]:
    # the arm table's one-core column (arm_package): this process on CPU 0 before JAX is
    # imported, so that no thread of it (XLA's pools included) can run on another core
    os.sched_setaffinity(0, {0})
from fosmc_jax import simulate_sharded, use_host_devices  # noqa: E402
from fosmc_jax.io import save_figure, write_text  # noqa: E402

use_host_devices(2)

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

jax.config.update("jax_enable_x64", True)

import baselines  # noqa: E402

import fosmc_jax as fj  # noqa: E402
from fosmc_jax import paper  # noqa: E402
from fosmc_jax import search as fs  # noqa: E402

FLOPS = {"euler": 303, "rk4": 810}
BOX = (paper.A_LOWER, paper.A_UPPER, paper.B_LOWER, paper.B_UPPER)
DT = 1e-4


def load() -> float:
    return round(os.getloadavg()[0], 2)


def best(fn, reps=3):
    out, times = None, []
    for _ in range(reps):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return min(times), out


def problem(batch: int, dtype, arm: bool = False):
    """batch = P plants (box samples, or payloads for the arm) x O initial offsets."""
    P = int(2 ** np.ceil(np.log2(batch) / 2))
    O = batch // P
    c = lambda x: jnp.asarray(np.asarray(x, np.float64), dtype)
    ctrl = fj.FOSMCParams(c(paper.C), c(paper.POLES), c(paper.GAMMA), c(paper.DELTA_SETS[0]),
                         c(paper.A_ROWS), c(paper.B_ROWS))  # fmt: skip
    ref = fj.Cycloid(c(paper.THETA_START), c(paper.THETA_END), c(paper.TAU))
    if arm:
        plants = fj.arm_sweep(c(np.linspace(0.0, 10.0, P)))
    else:
        p = fj.uncertain_plants(paper.A_ROWS, paper.B_ROWS, "sample", box=BOX, samples=P, seed=0)
        plants = fj.LinearPlant(c(p.a_rows), c(p.b_rows))
    X0 = np.asarray(baselines.reference(np.zeros(1))[0, :3].T.reshape(9))
    offsets = np.random.default_rng(1).uniform(-0.05, 0.05, (O, 9)) * (O > 1)
    return plants, ctrl, ref, c(X0 + offsets), c(DT)


def digital(ctrl, m, dtype):
    """The realistic preset's loop around ``ctrl`` at m simulation steps per sample (2,621,440
    counts, differences, one sample of delay, 24 V), or only the sampling when m = 1."""
    T = jnp.asarray(m * DT, dtype)
    if m == 1:
        sensors = fj.Sensors(jnp.zeros(3, dtype), None, "measured")
        return fj.DigitalLoop(fj.DiscreteFOSMC(ctrl, T), sensors, jnp.full(3, jnp.inf, dtype), T, 1, 0)
    sensors = fj.Sensors(jnp.full(3, 2621440.0, dtype), None, "difference")
    return fj.DigitalLoop(fj.DiscreteFOSMC(ctrl, T), sensors, jnp.full(3, 24.0, dtype), T, m, 1)


def time_jax(batch, dtype, integrator, steps, arm=False, devices=0, loop=0, fast=True):
    """``loop`` = m > 0: the digital loop of :func:`digital`; ``fast`` = False: the ideal loop
    through the vmap path (where no compiler is)."""
    args = problem(batch, dtype, arm)
    if loop:
        args = (args[0], digital(args[1], loop, dtype), *args[2:])
    opts = dict(n_steps=steps, integrator=integrator)
    if not fast:
        opts["fast"] = False
    if devices:
        fn = lambda: simulate_sharded(*args, devices=devices, **opts)
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        compile_s = None
        first = time.perf_counter() - t0
    else:
        t0 = time.perf_counter()
        compiled = fj.simulate_batch.lower(*args, **opts).compile()
        compile_s = time.perf_counter() - t0
        fn = lambda: compiled(*args)
        first = None
    reps = 3 if batch * steps <= 4e8 else 1
    wall, r = best(fn, reps)
    rs = batch * steps / wall
    kind = "fosmc_jax" + (f" ({devices} devices)" if devices else "") + (f" digital m={loop}" if loop else "")
    kind += " vmap path" if not fast and not loop and not arm else ""
    return {"kind": kind, "plant": "arm" if arm else "linear",
            "integrator": integrator, "dtype": np.dtype(dtype).name, "batch": batch, "steps": steps,
            "wall_s": wall, "compile_s": compile_s, "first_call_s": first, "rollout_steps_per_s": rs,
            "flop_per_s": None if arm else rs * FLOPS[integrator], "reps": reps, "load": load(),
            "rms_error": float(np.nanmean(np.asarray(r.metrics.rms_error)))}  # fmt: skip


def baseline(kind, batch, dtype, integrator, steps, extrapolated=False):
    plants, *_, X0s, _ = problem(batch, dtype)
    P, O = plants.a_rows.shape[0], X0s.shape[0]
    a = np.repeat(np.asarray(plants.a_rows), O, axis=0)
    b = np.repeat(np.asarray(plants.b_rows), O, axis=0)
    X0 = np.tile(np.asarray(X0s), (P, 1))
    fn = {"numpy_loop": baselines.numpy_loop, "numpy_vectorised": baselines.numpy_vectorised,
          "numba_prange": baselines.numba_prange}.get(kind)  # fmt: skip
    compile_s = None
    if kind == "scipy_ivp":
        run = lambda: baselines.scipy_ivp(a, b, X0, DT, steps * DT)
    else:
        run = lambda: fn(a, b, X0, DT, steps, integrator)
        if kind == "numba_prange":
            t0 = time.perf_counter()
            if run() is None:
                return None
            compile_s = time.perf_counter() - t0
    reps = 1 if kind in ("numpy_loop", "scipy_ivp") else 3
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        rms = run()
        times.append(time.perf_counter() - t0)
    wall = min(times)
    rs = batch * steps / wall
    return {"kind": kind, "plant": "linear", "integrator": integrator if kind != "scipy_ivp" else "RK45 (adaptive, max_step=dt)",
            "dtype": np.dtype(dtype).name, "batch": batch, "steps": steps, "wall_s": wall, "compile_s": compile_s,
            "rollout_steps_per_s": rs, "flop_per_s": rs * FLOPS.get(integrator, 0), "reps": reps,
            "extrapolated": extrapolated, "load": load(), "rms_error": rms}  # fmt: skip


def roof(n):
    out = {}
    for dtype in (np.float32, np.float64):
        x = jnp.asarray(np.random.default_rng(0).standard_normal((n, n)), dtype)
        f = jax.jit(lambda a: a @ a)
        jax.block_until_ready(f(x))
        wall, _ = best(lambda: f(x), 3)
        out[np.dtype(dtype).name] = 2 * n**3 / wall
    out["load"] = load()
    return out


def arm_gradient(batch, steps, big_batch, big_steps):
    """One arm tuning step (value and grad of the tuner's loss) and its ratio to the forward
    evaluation, at (batch, steps) and at (big_batch, big_steps)."""

    def one(b, n):
        plants, ctrl, ref, X0s, dt = problem(b, np.float32, arm=True)
        opts = dict(n_steps=n, integrator="euler", checkpoint_every=100)
        prob = fs.Problem(plants, ctrl, ref, X0s, dt, opts)
        u = fs.to_internal(fs.Tunable(ctrl.delta, ctrl.gamma, ctrl.poles), ctrl)
        loss = fs.make_loss(prob, fs.Objective(), None)
        t0 = time.perf_counter()
        vg = jax.jit(jax.value_and_grad(loss, has_aux=True)).lower(u).compile()
        compile_s = time.perf_counter() - t0
        fwd = jax.jit(loss).lower(u).compile()
        t_vg, _ = best(lambda: vg(u))
        t_f, _ = best(lambda: fwd(u))
        return {"batch": b, "steps": n, "value_and_grad_s": t_vg, "forward_s": t_f, "ratio": t_vg / t_f,
                "compile_s": compile_s}  # fmt: skip

    out = one(batch, steps)
    out["big"] = one(big_batch, big_steps)
    out["load"] = load()
    return out


def gradient(batch, steps, checkpoint_every, horizons, plain_horizons=()):
    """The tuner's path exactly: fosmc_jax.search.make_loss (simulate_batch fast=False, vmap of simulate),
    Euler float32, reverse mode, scan checkpointed every ``checkpoint_every`` steps (the CLI's
    default remat_steps = 100). One value_and_grad against one forward call of the same loss,
    both compiled; XLA temp memory of the compiled value_and_grad at each horizon (with and,
    for ``plain_horizons``, without checkpointing)."""
    plants, ctrl, ref, X0s, dt = problem(batch, np.float32)
    opts = dict(n_steps=steps, integrator="euler", checkpoint_every=checkpoint_every)
    prob = fs.Problem(plants, ctrl, ref, X0s, dt, opts)
    u = fs.to_internal(fs.Tunable(ctrl.delta, ctrl.gamma, ctrl.poles), ctrl)
    loss_of = lambda **o: fs.make_loss(prob._replace(options=dict(opts, **o)), fs.Objective(), None)
    vg_of = lambda **o: jax.jit(jax.value_and_grad(loss_of(**o), has_aux=True)).lower(u).compile()
    t0 = time.perf_counter()
    vgc = vg_of()
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    fwdc = jax.jit(loss_of()).lower(u).compile()
    fwd_compile_s = time.perf_counter() - t0
    t_vg, _ = best(lambda: vgc(u))
    t_f, _ = best(lambda: fwdc(u))
    mem = lambda c: {"temp": c.memory_analysis().temp_size_in_bytes, "total": c.memory_analysis().temp_size_in_bytes
                     + c.memory_analysis().argument_size_in_bytes + c.memory_analysis().output_size_in_bytes}  # fmt: skip
    temp = {str(n): mem(vgc if n == steps else vg_of(n_steps=n)) for n in horizons}
    plain = {str(n): mem(vg_of(n_steps=n, checkpoint_every=0)) for n in plain_horizons}
    return {"path": "tuner: make_loss, simulate_batch(fast=False), euler, float32, reverse mode",
            "batch": batch, "steps": steps, "checkpoint_every": checkpoint_every, "value_and_grad_s": t_vg,
            "forward_s": t_f, "ratio": t_vg / t_f, "compile_s": compile_s, "forward_compile_s": fwd_compile_s,
            "rollout_steps_per_s": batch * steps / t_vg, "temp_bytes": {k: v["temp"] for k, v in temp.items()},
            "memory_bytes": temp, "memory_bytes_no_checkpoint": plain, "load": load()}  # fmt: skip


def arm_baseline(batch, dtype, steps):
    plants, _, _, X0s, _ = problem(batch, dtype, arm=True)
    P, O = plants.payload.shape[0], X0s.shape[0]
    payloads = np.repeat(np.asarray(plants.payload), O)
    X0 = np.tile(np.asarray(X0s), (P, 1))
    t0 = time.perf_counter()
    rms = baselines.numpy_arm(payloads, X0, DT, steps)
    wall = time.perf_counter() - t0
    return {"kind": "numpy_arm", "plant": "arm", "integrator": "euler", "dtype": np.dtype(dtype).name,
            "batch": batch, "steps": steps, "wall_s": wall, "compile_s": None, "rollout_steps_per_s": batch * steps / wall,
            "flop_per_s": None, "reps": 1, "load": load(), "rms_error": rms}  # fmt: skip


ANCHOR = Path(__file__).resolve().parents[2] / "shared" / "anchors" / "simd_kernel" / "run.sh"


def anchor(batch: int, steps: int) -> list[dict]:
    """The hand-written SIMD kernel of the same closed loop (../shared/anchors/simd_kernel,
    linear plant, Euler, float32), best of its three repetitions per thread count; [] when
    gcc or the anchor is missing."""
    import re
    import shutil

    if not ANCHOR.exists() or shutil.which("gcc") is None:
        print("anchor: ../shared/anchors/simd_kernel or gcc missing, skipped")
        return []
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:  # run.sh writes data.h into its working directory
        out = subprocess.run(["bash", str(ANCHOR), str(batch), str(steps)], capture_output=True, text=True, cwd=tmp)
    if out.returncode:
        print(f"anchor: run.sh failed ({out.returncode}): {out.stderr.strip()[-300:]}")
        return []
    best: dict[int, float] = {}
    for m in re.finditer(r"threads=(\d+) .*?: ([0-9.e+]+) rollout-steps/s", out.stdout):
        best[int(m.group(1))] = max(best.get(int(m.group(1)), 0.0), float(m.group(2)))
    return [{"kind": f"simd anchor ({t} thread{'s' if t > 1 else ''})", "plant": "linear", "integrator": "euler",
             "dtype": "float32", "batch": batch, "steps": steps, "wall_s": batch * steps / v, "compile_s": None,
             "rollout_steps_per_s": v, "flop_per_s": v * FLOPS["euler"], "reps": 3, "load": load()}
            for t, v in sorted(best.items())]  # fmt: skip


SHARED = Path(__file__).resolve().parents[2] / "shared"  # <repo>/../shared: absent from a user's clone
ARM_ANCHOR = SHARED / "anchors" / "arm_kernel"
#: The arm anchor's frozen headers (frozen/<integrator>_<dtype>.h) fix its horizon at 1,000 steps.
ARM_STEPS = 1000
ARM_CFLAGS = ["-O3", "-march=native", "-fno-math-errno", "-fschedule-insns", "-fsched-pressure", "-fopenmp"]
#: Largest relative difference of the package's and the anchor's mean rms error of joint 1.
ARM_RMS_TOL = {"float32": 1e-4, "float64": 1e-9}
#: The realistic preset (the package's own copy, fosmc_jax/_problems/presets/realistic_arm.toml, is the
#: same file: tests/test_digital_loop.py checks it).
PRESET = Path(__file__).resolve().parents[1] / "tuning" / "configs" / "realistic_arm.toml"
#: simulate_batch's static options (compiled in); the others are traced arguments of the compiled call.
STATIC_OPTIONS = (
    "n_steps",
    "integrator",
    "switching",
    "law",
    "save_every",
    "checkpoint_every",
    "truncate_every",
    "pairing",
)


def split(batch: int) -> tuple[int, int]:
    """problem()'s P plants x O initial offsets of a batch."""
    P = int(2 ** np.ceil(np.log2(batch) / 2))
    return P, batch // P


def read_case(path, batch: int, dtype):
    """An arm anchor case file: P payloads, then O initial states of 9 numbers, raw ``dtype``."""
    P, O = split(batch)
    a = np.fromfile(path, np.dtype(dtype))
    if a.size != P + 9 * O:
        raise ValueError(f"{path}: {a.size} numbers, expected {P} payloads + {O} x 9 initial states")
    return a[:P], a[P:].reshape(O, 9)


def realistic(batch: int, dtype, steps: int):
    """The realistic preset (:data:`PRESET`: DigitalLoop around the
    DiscreteFOSMC, 2,621,440-count encoders, differenced rates, one sample of delay, 24 V, RK4,
    dt = 1e-4, a sample every 10 steps) through the config path as ``run_simulate`` takes it
    (``_config.load``, ``resolve``, ``build``), its batch enlarged to P payloads in [0, 10] kg
    x O initial offsets (problem()'s P, O and offsets), ``steps`` steps, in ``dtype``.
    Returns (positional arguments, dynamic keyword arguments, static options) of simulate_batch."""
    from fosmc_jax import config as _config

    P, O = split(batch)
    cfg = _config.load(PRESET).as_dict()
    cfg["plant"]["payloads"] = np.linspace(0.0, 10.0, P).tolist()
    offsets = np.random.default_rng(1).uniform(-0.05, 0.05, (O, 9)) * (O > 1)
    cfg["sim"].update(t_final=steps * DT, precision=np.dtype(dtype).name, initial_offset=offsets.tolist())
    prob = _config.build(_config.resolve(cfg))
    assert prob.options["n_steps"] == steps and prob.X0s.shape[0] * P == batch
    static = {k: v for k, v in prob.options.items() if k in STATIC_OPTIONS}
    dynamic = {k: v for k, v in prob.options.items() if k not in static}
    return prob.args, dict(dynamic, keys=prob.keys), static


def arm_cell_inputs(cell: dict):
    """(positional arguments, dynamic keyword arguments, static options) of simulate_batch for
    one cell of the arm table: the ideal loop on problem(batch, dtype, arm=True), or on the
    anchor's case file where ``cell["case"]`` names one; or the realistic preset's digital loop.
    The arm's zero friction and disturbance terms are left out as a call of simulate_batch
    leaves them out (its ``lower``, which the table times, compiles the inputs as given)."""
    dtype = np.dtype(cell["dtype"]).type
    if cell["loop"] == "digital":
        (plants, *rest), dynamic, static = realistic(cell["batch"], dtype, cell["steps"])
        return (fj.without_idle_terms(plants), *rest), dynamic, static
    plants, ctrl, ref, X0s, dt = problem(cell["batch"], dtype, arm=True)
    if cell.get("case"):
        payloads, x0 = read_case(cell["case"], cell["batch"], dtype)
        plants, X0s = fj.arm_sweep(jnp.asarray(payloads)), jnp.asarray(x0)
    return (
        (fj.without_idle_terms(plants), ctrl, ref, X0s, dt),
        {},
        dict(n_steps=cell["steps"], integrator=cell["integrator"]),
    )


def arm_child(spec_path: str) -> None:
    """The package's side of the arm table, in a child process of arm_package (pinned to CPU 0
    by ``--pin-child`` before JAX was imported, or not): per cell, compile (timed), a warm call,
    then ``rounds`` timed rounds of as many calls as last ``round_s``; the rows go to
    ``spec["out"]`` as JSON."""
    import statistics

    spec = json.loads(Path(spec_path).read_text())
    # the pinned child loads the unpinned child's compilations: the same programs, compiled once
    jax.config.update("jax_compilation_cache_dir", spec["cache"])
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    cpus = sorted(os.sched_getaffinity(0))
    rows = []
    for cell in spec["cells"]:
        args, dynamic, static = arm_cell_inputs(cell)
        t0 = time.perf_counter()
        compiled = fj.simulate_batch.lower(*args, **dynamic, **static).compile()
        compile_s = time.perf_counter() - t0
        call = lambda: jax.block_until_ready(compiled(*args, **dynamic))  # noqa: B023
        t0 = time.perf_counter()
        call()  # warm, and the number of calls per round: a round lasts spec["round_s"] at least
        calls = max(1, int(np.ceil(spec["round_s"] / (time.perf_counter() - t0))))
        rates, loads = [], []
        for _ in range(spec["rounds"]):
            t0 = time.perf_counter()
            for _ in range(calls):
                r = call()
            rates.append(calls * cell["batch"] * cell["steps"] / (time.perf_counter() - t0))
            loads.append(load())
        rms = np.asarray(r.metrics.rms_error, np.float64)
        rows.append({"rollout_steps_per_s": statistics.median(rates), "min": min(rates), "max": max(rates),
                     "samples": rates, "calls_per_round": calls, "compile_s": compile_s, "load": [min(loads), max(loads)],
                     "cpus": cpus,
                     "rms_error_joint1": float(np.mean(rms[:, 0])), "diverged": int(np.sum(np.asarray(r.diverged)))})  # fmt: skip
        print(f"  arm {cell['loop']:7s} {cell['integrator']:5s} {cell['dtype']:7s} batch {cell['batch']:5d} "
              f"{cell['steps']} steps, CPUs {cpus}: {rows[-1]['rollout_steps_per_s']:.3e} rollout-steps/s "
              f"(compile {compile_s:.1f} s)  load {loads[0]}-{loads[-1]}", flush=True)  # fmt: skip
    Path(spec["out"]).write_text(json.dumps(rows))


def arm_package(cells: list[dict], pinned: bool, rounds: int, round_s: float, tmp: str) -> list[dict]:
    """Time ``cells`` in a fresh process of this script: unpinned (both cores, 1 device), or
    pinned to CPU 0 before JAX is imported (one core really: XLA's thread pool cannot use the
    second). The two share a persistent compilation cache in ``tmp``: run unpinned first."""
    name = "pinned" if pinned else "unpinned"
    spec = Path(tmp) / f"arm-{name}.json"
    out = Path(tmp) / f"arm-{name}-rows.json"
    spec.write_text(json.dumps({"cells": cells, "rounds": rounds, "round_s": round_s, "cache": str(Path(tmp) / "xla-cache"),
                                "out": str(out)}))  # fmt: skip
    cmd = [sys.executable, str(Path(__file__).resolve()), "--arm-child", str(spec)] + (
        ["--pin-child"] if pinned else []
    )
    print(f"arm table: package, {'one core (child pinned to CPU 0)' if pinned else 'both cores (unpinned child)'}",
          flush=True)  # fmt: skip
    subprocess.run(cmd, check=True)
    return json.loads(out.read_text())


def build_arm_anchor(tmp: str) -> tuple[dict, str]:
    """The arm anchor (../shared/anchors/arm_kernel/kernel.c) built from its frozen headers, no
    package involved: {(integrator, dtype): executable}, and what was done (or why not)."""
    import shutil

    if not (ARM_ANCHOR / "kernel.c").exists():
        return {}, f"skipped: {ARM_ANCHOR} not found (it lives in ../shared beside the repository; a clone has none)"
    if shutil.which("gcc") is None:
        return {}, "skipped: gcc not found"
    exes = {}
    for integrator in ("euler", "rk4"):
        for dtype in ("float32", "float64"):
            d = Path(tmp) / f"arm-{integrator}-{dtype}"
            d.mkdir()
            shutil.copy(ARM_ANCHOR / "frozen" / f"{integrator}_{dtype}.h", d / "data.h")
            exe = d / "kernel"
            cmd = ["gcc", *ARM_CFLAGS, f"-I{d}", str(ARM_ANCHOR / "kernel.c"), "-o", str(exe), "-lm"]
            out = subprocess.run(cmd, capture_output=True, text=True)
            if out.returncode:
                return {}, f"skipped: {' '.join(cmd)} failed: {out.stderr.strip()[-300:]}"
            exes[(integrator, dtype)] = exe
    gcc = subprocess.run(["gcc", "--version"], capture_output=True, text=True).stdout.split("\n")[0]
    return exes, f"built from {ARM_ANCHOR}/frozen/ with gcc {' '.join(ARM_CFLAGS)} ({gcc})"


def arm_anchor_case(batch: int, dtype: str, tmp: str) -> tuple[str, str]:
    """(case file, where it comes from): frozen/case_<batch>_<dtype>.bin where it exists (1,024),
    else written here from problem(batch, dtype, arm=True): its payloads and initial states, the
    layout gen_data.py's ``case`` writes."""
    frozen = ARM_ANCHOR / "frozen" / f"case_{batch}_{dtype}.bin"
    if frozen.exists():
        return str(frozen), f"frozen/{frozen.name}"
    plants, _, _, X0s, _ = problem(batch, np.dtype(dtype).type, arm=True)
    path = Path(tmp) / f"case_{batch}_{dtype}.bin"
    np.concatenate([np.asarray(plants.payload), np.asarray(X0s).ravel()]).astype(dtype).tofile(path)
    return str(path), f"problem({batch}) written as a case file"


def arm_anchor_run(exe: Path, batch: int, dtype: str, case: str, threads: int, tmp: str) -> tuple[float, float]:
    """One run of the anchor (its 3 in-process repetitions): (the best rollout-steps/s, the mean
    rms error of joint 1 over the batch from its full-precision output file; the line it prints
    has 6 digits)."""
    import re

    P, O = split(batch)
    out_bin = Path(tmp) / "arm-out.bin"
    env = dict(os.environ, OMP_NUM_THREADS=str(threads), OMP_PROC_BIND="close")
    out = subprocess.run([str(exe), str(P), str(O), case, "3", str(out_bin)], capture_output=True, text=True,
                         env=env, check=True).stdout  # fmt: skip
    rate = max(float(m) for m in re.findall(r": ([0-9.e+]+) rollout-steps/s", out))
    printed = float(re.findall(r"mean rms error joint 1 ([0-9.e+-]+) rad", out)[-1])
    rms = float(np.mean(np.fromfile(out_bin, np.dtype(dtype)).reshape(batch, 41)[:, 15].astype(np.float64)))
    assert abs(rms - printed) <= 1e-5 * abs(printed), (rms, printed)  # column 15: rms_error of joint 1
    return rate, rms


def arm_table(quick: bool) -> dict:
    """The arm's closed loop in all four integrator x precision cells (batches 1,024 and 4,096;
    quick: 1,024) and the realistic preset's digital loop (RK4, both precisions, 1,024), each
    on both cores and on one core really pinned; beside it the arm anchor in the same run where
    ../shared is present, with its mean rms error of joint 1 against the package's."""
    import statistics
    import tempfile

    from fosmc_jax import config as _config

    preset_integrator = _config.load(PRESET)["sim"]["integrator"]
    batches = (1024,) if quick else (1024, 4096)
    rounds, round_s = (3, 0.2) if quick else (5, 0.5)
    n = os.cpu_count()
    with tempfile.TemporaryDirectory() as tmp:
        exes, anchor_status = build_arm_anchor(tmp)
        print(f"arm anchor: {anchor_status}", flush=True)
        cells, sources = [], []
        for integrator in ("euler", "rk4"):
            for dtype in ("float32", "float64"):
                for batch in batches:
                    case, source = arm_anchor_case(batch, dtype, tmp) if exes else (None, f"problem({batch})")
                    cells.append({"loop": "ideal", "integrator": integrator, "dtype": dtype, "batch": batch,
                                  "steps": ARM_STEPS, "case": case})  # fmt: skip
                    sources.append(source)
        for dtype in ("float64", "float32"):
            cells.append({"loop": "digital", "integrator": preset_integrator, "dtype": dtype, "batch": 1024,
                          "steps": 500 if quick else 4000, "case": None})  # fmt: skip
            sources.append(f"{PRESET.name}, {split(1024)[0]} payloads in [0, 10] kg x {split(1024)[1]} offsets")
        both = arm_package(cells, False, rounds, round_s, tmp)
        one = arm_package(cells, True, rounds, round_s, tmp)
        rows = []
        for cell, source, a, b in zip(cells, sources, both, one):
            row = {k: v for k, v in cell.items() if k != "case"}
            row.update(inputs=source, rounds=rounds, calls_per_round=[a["calls_per_round"], b["calls_per_round"]],
                       package_all=a["rollout_steps_per_s"], package_all_min=a["min"],
                       package_1core=b["rollout_steps_per_s"], package_1core_min=b["min"], compile_s=a["compile_s"],
                       compile_1core_s=b["compile_s"], load_all=a["load"], load_1core=b["load"],
                       pinned_cpus=b["cpus"], rms_error_joint1=a["rms_error_joint1"], diverged=a["diverged"],
                       same_result_1core=a["rms_error_joint1"] == b["rms_error_joint1"])  # fmt: skip
            exe = exes.get((cell["integrator"], cell["dtype"])) if cell["loop"] == "ideal" else None
            if exe is not None:
                rates = {t: [] for t in sorted({1, n})}
                loads = []
                try:
                    for _ in range(rounds):
                        for t in rates:
                            rate, rms = arm_anchor_run(exe, cell["batch"], cell["dtype"], cell["case"], t, tmp)
                            rates[t].append(rate)
                        loads.append(load())
                except (subprocess.CalledProcessError, ValueError, IndexError, AssertionError) as e:
                    print(f"arm anchor: {cell['integrator']} {cell['dtype']} batch {cell['batch']} failed: {e!r}")
                    exe, row["anchor_failed"] = None, repr(e)
            if exe is not None:
                rel = abs(row["rms_error_joint1"] - rms) / abs(rms)
                row.update(anchor_threads=n, anchor_1=statistics.median(rates[1]), anchor_n=statistics.median(rates[n]),
                           anchor_1_min=min(rates[1]), anchor_n_min=min(rates[n]), anchor_load=[min(loads), max(loads)],
                           anchor_rms_error_joint1=rms, rms_rel_diff=rel,
                           rms_match=bool(rel <= ARM_RMS_TOL[cell["dtype"]]))  # fmt: skip
                row["anchor_n_over_package_all"] = row["anchor_n"] / row["package_all"]
                row["anchor_1_over_package_1core"] = row["anchor_1"] / row["package_1core"]
            rows.append(row)
            line = (
                f"arm {row['loop']:7s} {row['integrator']:5s} {row['dtype']:7s} batch {row['batch']:5d}: package "
                f"{row['package_all']:.3e} (both cores), {row['package_1core']:.3e} (1 core) rollout-steps/s"
            )
            if "anchor_n" in row:
                line += (f"; anchor {row['anchor_n']:.3e} ({n} threads), {row['anchor_1']:.3e} (1 thread): "
                         f"{row['anchor_n_over_package_all']:.1f}x, {row['anchor_1_over_package_1core']:.1f}x; "
                         f"rms joint 1 {row['rms_error_joint1']:.10g} vs anchor {row['anchor_rms_error_joint1']:.10g} "
                         f"(rel {rel:.1e}{'' if row['rms_match'] else ', MISMATCH: not the same work'})")  # fmt: skip
            print(line + f"  load {row['load_all']}/{row['load_1core']}", flush=True)
    return {
        "rows": rows,
        "anchor": anchor_status,
        "rounds": rounds,
        "round_s": round_s,
        "threads": n,
        "FOSMC_JAX_NATIVE": os.environ.get("FOSMC_JAX_NATIVE"),
    }


CLI_CONFIG = """[plant]
uncertainty = "sample"
samples = {samples}
seed = 0

[sim]
t_final = {t_final}
dt = {dt}
integrator = "euler"
precision = "float32"
"""


def cli(samples: int, steps: int, devices: int, output: str = "json", longer: int = 10) -> dict:
    """``fosmc simulate --json`` (``output = "json"``) or ``--npz FILE`` (``"npz"``) as a user
    runs it (a fresh process: start-up, compilation, the run, every rollout's metrics written
    out) on the same work (linear, Euler, float32, set 1, ratio switching; ``uncertainty =
    "sample"``, one offset), ``samples`` rollouts over ``steps`` and ``longer`` x ``steps``
    steps: the steady state is samples x (longer - 1) x steps / (difference of the wall times).
    The start-up, the compilation and the output of each rollout are the same in both runs
    and cancel (a difference of batch sizes, used before, also differed in compilation, and
    a fresh process's start-up varies by more than the simulation between the sizes: steady
    states from 1.4e8 to 4.6e8 rollout-steps/s for the same command at 995ff94, where the
    library runs 3e8; hence the long run);
    the wall times of both are returned, and the output's cost per rollout is the difference
    of the --json and --npz rows' walls."""
    import tempfile

    fosmc = Path(sys.executable).with_name("fosmc")
    exe = [str(fosmc)] if fosmc.exists() else [sys.executable, "-m", "fosmc_jax"]
    walls, loads = {}, []
    with tempfile.TemporaryDirectory() as tmp:
        for n in (steps, longer * steps):
            cfg = Path(tmp) / f"cli{n}.toml"
            cfg.write_text(CLI_CONFIG.format(samples=samples, t_final=round(n * DT, 10), dt=DT))
            out_args = ["--json"] if output == "json" else ["--npz", str(Path(tmp) / "out.npz")]
            cmd = exe + ["simulate", "--config", str(cfg), *out_args, "--devices", str(devices)]
            env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "JAX_NUM_CPU_DEVICES")}
            times = []
            for _ in range(2):
                t0 = time.perf_counter()
                out = subprocess.run(cmd, capture_output=True, text=True, env=env)
                times.append(time.perf_counter() - t0)
                if out.returncode:
                    raise RuntimeError(f"{' '.join(cmd)} failed: {out.stderr[-500:]}")
            walls[n] = min(times)
            loads.append(load())
    dw = walls[longer * steps] - walls[steps]
    rs = samples * (longer - 1) * steps / dw if dw > 0 else float("nan")
    return {"kind": f"fosmc simulate --{output} ({devices} device{'s' if devices > 1 else ''}, steady state)",
            "plant": "linear", "integrator": "euler", "dtype": "float32", "batch": samples, "steps": steps,
            "wall_s": walls[steps], "compile_s": None, "rollout_steps_per_s": rs, "flop_per_s": rs * FLOPS["euler"],
            "reps": 2, "load": max(loads), "cli_wall_s": {str(k): v for k, v in walls.items()},
            "command": " ".join(exe[-1:] + cmd[len(exe):])}  # fmt: skip


def machine():
    cpu = next(
        (line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name")),
        platform.processor(),
    )
    try:
        mem = subprocess.run(["free", "-g"], capture_output=True, text=True).stdout.split("\n")[1].split()[1] + " GiB"
    except Exception:
        mem = "?"
    return {"cpu": cpu, "cores": os.cpu_count(), "memory": mem, "python": platform.python_version(),
            "jax": jax.__version__, "numpy": np.__version__, "platform": platform.platform()}  # fmt: skip


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="CI mode: under 2 minutes on 2 cores")
    ap.add_argument("--out", default=str(Path(__file__).resolve().parent / "results"))
    ap.add_argument("--steps", type=int, help="steps per rollout (default 2,000 quick, 4,000 full)")
    ap.add_argument("--batches", type=lambda s: tuple(int(x) for x in s.split(",")), help="e.g. 1,64,1024")
    ap.add_argument("--arm-only", action="store_true", help="only the arm at batches 64 and 1,024, the linear "
                    "plant at the same batches, the NumPy arm and the arm's gradient (benchmarks/results/bench-arm.*)")  # fmt: skip
    ap.add_argument("--long-steps", type=int, help="one extra Euler float32 point at the head batch "
                    "with this many steps, to confirm the per-step throughput (default 40,000 full, none quick)")  # fmt: skip
    ap.add_argument("--arm-child", help=argparse.SUPPRESS)  # arm_package's child process: a spec file
    ap.add_argument("--pin-child", action="store_true", help=argparse.SUPPRESS)  # that child pinned (top of file)
    args = ap.parse_args(argv)
    if args.arm_child:
        return arm_child(args.arm_child)
    q = args.quick
    steps = args.steps or (2000 if q else 4000)
    batches = args.batches or ((1, 64, 1024) if q else (1, 64, 1024, 4096, 16384))
    head = 1024 if q else 4096
    long_steps = args.long_steps if args.long_steps is not None else (0 if q else 40000)
    t_start = time.perf_counter()
    rows = []
    say = lambda r: print(f"{r['kind']:22s} {r['plant']:6s} {r['integrator'][:5]:5s} {r['dtype']:7s} batch {r['batch']:6d} "
                          f"{r['rollout_steps_per_s']:.3e} rollout-steps/s  load {r['load']}", flush=True)  # fmt: skip
    uptime = lambda: subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    info = {"machine": machine(), "quick": q, "steps": steps, "dt": DT, "load_start": load(), "uptime_start": uptime(),
            "command": "python benchmarks/bench.py " + " ".join(sys.argv[1:] if argv is None else argv)}  # fmt: skip
    info["roof_flop_per_s"] = roof(1024 if q else 2048)
    print("roof", info["roof_flop_per_s"], flush=True)
    if args.arm_only:
        for batch in (64, 1024):
            for arm in (True, False):
                rows.append(time_jax(batch, np.float32, "euler", steps, arm=arm)), say(rows[-1])
        rows.append(arm_baseline(64, np.float32, 1000)), say(rows[-1])
        info["arm_gradient"] = arm_gradient(2, 2000, 64, steps)
        print("arm gradient", info["arm_gradient"], flush=True)
        info["arm_table"] = arm_table(q)
        info["rows"], info["gradient"], info["diffrax"] = rows, None, "not benchmarked (--arm-only)"
        return finish(info, Path(args.out) / "bench-arm", 1024, t_start, uptime)
    for dtype in (np.float32, np.float64):
        for integrator in ("euler", "rk4"):
            for batch in batches:
                rows.append(time_jax(batch, dtype, integrator, steps)), say(rows[-1])
    if long_steps:
        rows.append(time_jax(head, np.float32, "euler", long_steps)), say(rows[-1])
    loop_batch = 1024
    rows.append(time_jax(loop_batch, np.float32, "euler", steps, fast=False)), say(rows[-1])
    for m in (1, 10):
        rows.append(time_jax(loop_batch, np.float32, "euler", steps, loop=m)), say(rows[-1])
    for r in anchor(head, steps):
        rows.append(r), say(r)
    rows.append(time_jax(head, np.float32, "euler", steps, devices=1)), say(rows[-1])
    rows.append(time_jax(head, np.float32, "euler", steps, devices=2)), say(rows[-1])
    for output in ("json", "npz"):
        for d in (1, 2):
            rows.append(cli(4 * head, steps, d, output)), say(rows[-1])
    arm_steps = 1000 if q else steps
    for batch in (1, 64) if q else (1, 64, 1024):
        rows.append(time_jax(batch, np.float32, "euler", arm_steps, arm=True)), say(rows[-1])
    rows.append(arm_baseline(64, np.float32, 100 if q else 1000)), say(rows[-1])
    info["arm_table"] = arm_table(q)
    base_steps = 100 if q else 1000
    for integrator in ("euler", "rk4"):
        rows.append(baseline("numpy_vectorised", head, np.float32, integrator, base_steps)), say(rows[-1])
    rows.append(baseline("numpy_loop", 4, np.float64, "euler", base_steps, extrapolated=True)), say(rows[-1])
    rows.append(baseline("scipy_ivp", 1, np.float64, "rk4", base_steps, extrapolated=True)), say(rows[-1])
    for batch in (head,) if q else (1024, head):
        nb = baseline("numba_prange", batch, np.float32, "euler", steps)
        if nb is None:
            print("numba: not installed, skipped")
            break
        rows.append(nb), say(nb)
    try:
        import diffrax  # noqa: F401

        info["diffrax"] = "installed but not benchmarked"
    except ImportError:
        info["diffrax"] = "not installed"
    info["gradient"] = (gradient(64, 1000, 100, (500, 1000, 2000)) if q else
                        gradient(256, 4000, 100, (1000, 2000, 4000, 8000), (1000, 2000, 4000)))  # fmt: skip
    print("gradient", info["gradient"], flush=True)
    info["arm_gradient"] = arm_gradient(2, 2000, 16 if q else 64, 1000 if q else 4000)
    print("arm gradient", info["arm_gradient"], flush=True)
    info["rows"] = rows
    finish(info, Path(args.out) / ("bench-quick" if q else "bench"), head, t_start, uptime)


def finish(info, stem, head, t_start, uptime):
    info["total_s"] = time.perf_counter() - t_start
    info["load_end"] = load()
    info["uptime_end"] = uptime()
    stem.parent.mkdir(parents=True, exist_ok=True)
    write_text(stem.with_suffix(".json"), json.dumps(info, indent=1))
    write_text(stem.with_suffix(".md"), markdown(info, head))
    plot(info, stem.with_suffix(".png"))
    print(f"wrote {stem}.json/.md/.png in {info['total_s']:.0f} s")


def pick(rows, **kw):
    return [r for r in rows if all(r.get(k) == v for k, v in kw.items())]


def markdown(info, head):
    rows, roof_ = info["rows"], info["roof_flop_per_s"]
    m = info["machine"]
    lines = [f"Machine: {m['cpu']}, {m['cores']} cores, {m['memory']}; Python {m['python']}, JAX {m['jax']}, "
             f"NumPy {m['numpy']}. Steps per rollout: {info['steps']} (dt = {info['dt']}). "
             f"Load average at start/end: {info['load_start']}/{info['load_end']}. "
             f"Matmul roof: float32 {roof_['float32']:.3g} FLOP/s, float64 {roof_['float64']:.3g} FLOP/s.", "",
             "| implementation | plant | integrator | dtype | batch | steps | rollout-steps/s | FLOP/s | of roof | "
             "of SIMD anchor | compile s | load |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
    anchors = [r for r in rows if r["kind"].startswith("simd anchor")]
    top = max(anchors, key=lambda r: r["rollout_steps_per_s"]) if anchors else None
    for r in rows:
        flop = r.get("flop_per_s")
        frac = f"{flop / roof_[r['dtype']]:.1%}" if flop else ""
        kind = r["kind"] + (" (extrapolated)" if r.get("extrapolated") else "")
        comp = f"{r['compile_s']:.1f}" if r.get("compile_s") is not None else ""
        of_anchor = (
            f"{r['rollout_steps_per_s'] / top['rollout_steps_per_s']:.1%}" if top and r["plant"] == "linear" else ""
        )
        lines.append(f"| {kind} | {r['plant']} | {r['integrator']} | {r['dtype']} | {r['batch']} | {r['steps']} | "
                     f"{r['rollout_steps_per_s']:.3g} | {flop or 0:.3g} | {frac} | {of_anchor} | {comp} | {r['load']} |")  # fmt: skip
    ours = pick(rows, kind="fosmc_jax", plant="linear", integrator="euler", dtype="float32", batch=head,
                steps=info["steps"])  # fmt: skip
    npv = pick(rows, kind="numpy_vectorised", integrator="euler")
    nb = pick(rows, kind="numba_prange", batch=head)
    lines.append("")
    if ours and npv:
        lines.append(f"Batch {head}, linear, Euler, float32: {ours[0]['rollout_steps_per_s']:.3g} rollout-steps/s = "
                     f"{ours[0]['rollout_steps_per_s'] / npv[0]['rollout_steps_per_s']:.1f}x NumPy-vectorised"
                     + (f", {ours[0]['rollout_steps_per_s'] / nb[0]['rollout_steps_per_s']:.2f}x Numba" if nb else ", Numba not installed")
                     + f"; {ours[0]['flop_per_s'] / roof_['float32']:.1%} of the float32 matmul roof.")  # fmt: skip
    arm, narm = pick(rows, kind="fosmc_jax", plant="arm", batch=64), pick(rows, kind="numpy_arm")
    if arm and narm:
        lines.append(f"Arm, batch 64, Euler, float32: {arm[0]['rollout_steps_per_s']:.3g} rollout-steps/s = "
                     f"{arm[0]['rollout_steps_per_s'] / narm[0]['rollout_steps_per_s']:.1f}x the NumPy arm "
                     f"({narm[0]['rollout_steps_per_s']:.3g}).")  # fmt: skip
    if anchors:
        ours_all = [r for r in rows if r["kind"].startswith("fosmc") and r["plant"] == "linear"]
        lines.append(f"SIMD anchor (same run, {top['kind']}, batch {top['batch']}): "
                     f"{top['rollout_steps_per_s']:.3g} rollout-steps/s. Each linear fosmc_jax row as a fraction "
                     "of it: " + ", ".join(f"{r['kind']} {r['integrator']} {r['dtype']} batch {r['batch']}: "
                                           f"{r['rollout_steps_per_s'] / top['rollout_steps_per_s']:.1%}"
                                           for r in ours_all) + ".")  # fmt: skip
    arm_big, lin_big = (
        pick(rows, kind="fosmc_jax", plant="arm", batch=1024),
        pick(
            rows, kind="fosmc_jax", plant="linear", integrator="euler", dtype="float32", batch=1024, steps=info["steps"]
        ),
    )
    if arm_big and lin_big:
        lines.append(f"Arm, batch 1,024: {arm_big[0]['rollout_steps_per_s']:.3g} rollout-steps/s = 1/"
                     f"{lin_big[0]['rollout_steps_per_s'] / arm_big[0]['rollout_steps_per_s']:.1f} of the linear plant "
                     f"({lin_big[0]['rollout_steps_per_s']:.3g}, fast path) in the same run.")  # fmt: skip
    for m in (1, 10):
        d = pick(rows, kind=f"fosmc_jax digital m={m}", batch=1024)
        if d and lin_big:
            lines.append(f"Digital loop, m = {m}, batch 1,024, linear, Euler, float32: "
                         f"{lin_big[0]['rollout_steps_per_s'] / d[0]['rollout_steps_per_s']:.2f}x "
                         f"the ideal loop's time per simulation step (both on the generated kernel).")  # fmt: skip
    if info.get("arm_table"):
        lines += arm_markdown(info["arm_table"])
    if info.get("arm_gradient"):
        a = info["arm_gradient"]
        lines.append(f"Arm tuning step: value-and-grad, {a['batch']} payloads x {a['steps']} steps, Euler, float32: "
                     f"{a['value_and_grad_s']:.3f} s ({a['ratio']:.2f}x its forward, compile {a['compile_s']:.1f} s); "
                     f"batch {a['big']['batch']} x {a['big']['steps']} steps: {a['big']['ratio']:.2f}x the forward.")  # fmt: skip
    g = info["gradient"]
    if g is None:
        return "\n".join(lines) + "\n"
    lines.append(f"Gradient: value-and-grad of the tuning objective, {g['batch']} rollouts x {g['steps']} steps "
                 f"(checkpoint every {g['checkpoint_every']}): {g['value_and_grad_s']:.3f} s = {g['ratio']:.2f}x the "
                 f"forward {g['forward_s']:.3f} s; compile {g['compile_s']:.1f} s; XLA temp memory by horizon "
                 + ", ".join(f"{k} steps: {v / 2**20:.1f} MiB" for k, v in g["temp_bytes"].items())
                 + ("; without checkpointing " + ", ".join(f"{k} steps: {v['temp'] / 2**20:.1f} MiB"
                    for k, v in g["memory_bytes_no_checkpoint"].items()) if g.get("memory_bytes_no_checkpoint") else "")
                 + ".")  # fmt: skip
    lines.append(f"diffrax: {info['diffrax']}.")
    return "\n".join(lines) + "\n"


def arm_markdown(t: dict) -> list[str]:
    """The arm table (arm_table's result) as Markdown lines."""
    n = t["threads"]
    lines = ["", f"Arm closed loop, simulate_batch: median (min) rollout-steps/s over {t['rounds']} rounds of "
             f"{t['round_s']} s or more (as many compiled calls as that takes) after a warm call, compilation apart"
             + ("" if t.get("FOSMC_JAX_NATIVE") is None else f" (FOSMC_JAX_NATIVE={t['FOSMC_JAX_NATIVE']})")
             + ". Ideal loop: the FOSMC with "
             "ratio switching, Table 1 set 1, dt = 1e-4, problem(batch, dtype, arm=True); digital: the realistic "
             "preset through the config path. Both cores: one process, unpinned, 1 device; 1 core: a process "
             "pinned to CPU 0 before JAX is imported (it loads the first's compilations from a shared cache). "
             f"Arm anchor (../shared/anchors/arm_kernel/kernel.c, {n} threads and 1, best of its 3 repetitions per "
             f"round): {t['anchor']}. rms: the mean rms error of joint 1 over the batch, package / anchor "
             "(relative difference; a mismatch beyond 1e-4 in float32 or 1e-9 in float64 means not the same work).",
             "",
             f"| loop | integrator | dtype | batch | steps | inputs | package both cores | package 1 core | compile s | "
             f"anchor {n} threads | anchor 1 thread | anchor {n} thr / package both cores | anchor 1 thr / package "
             "1 core | rms joint 1 (package / anchor) | load (both cores, 1 core, anchor) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for r in t["rows"]:
        cell = lambda k: f"{r[k]:.3g} ({r[k + '_min']:.3g})" if k in r else "n/a"  # noqa: B023
        if "anchor_n" in r:
            ratios = f"{r['anchor_n_over_package_all']:.1f}x | {r['anchor_1_over_package_1core']:.1f}x"
            rms = (f"{r['rms_error_joint1']:.8g} / {r['anchor_rms_error_joint1']:.8g} ({r['rms_rel_diff']:.1e}"
                   + ("" if r["rms_match"] else ", **MISMATCH**") + ")")  # fmt: skip
        else:
            ratios, rms = "n/a | n/a", f"{r['rms_error_joint1']:.8g} / n/a"
        loads = ", ".join(f"{r[k][0]}-{r[k][1]}" for k in ("load_all", "load_1core", "anchor_load") if k in r)
        lines.append(f"| {r['loop']} | {r['integrator']} | {r['dtype']} | {r['batch']} | {r['steps']} | {r['inputs']} | "
                     f"{cell('package_all')} | {cell('package_1core')} | {r['compile_s']:.1f} | {cell('anchor_n')} | "
                     f"{cell('anchor_1')} | {ratios} | {rms} | {loads} |")  # fmt: skip
    lines.append("")
    return lines


def plot(info, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    rows = info["rows"]
    for dtype in ("float32", "float64"):
        for integ in ("euler", "rk4"):
            r = pick(rows, kind="fosmc_jax", plant="linear", dtype=dtype, integrator=integ, steps=info["steps"])
            if r:
                ax.plot(
                    [x["batch"] for x in r],
                    [x["rollout_steps_per_s"] for x in r],
                    "o-",
                    label=f"fosmc_jax {integ} {dtype}",
                )
    r = pick(rows, kind="fosmc_jax", plant="arm")
    if r:
        ax.plot(
            [x["batch"] for x in r], [x["rollout_steps_per_s"] for x in r], "s--", label="fosmc_jax arm euler float32"
        )
    for r in rows:
        if r["kind"] != "fosmc_jax" or r["steps"] != info["steps"]:
            ax.plot(
                [r["batch"]],
                [r["rollout_steps_per_s"]],
                "x",
                ms=9,
                label=f"{r['kind']} {r['plant']} {r['integrator'][:5]} {r['dtype']} {r['steps']} steps",
            )
    ax.set_xscale("log"), ax.set_yscale("log")
    ax.set_xlabel("batch (rollouts)"), ax.set_ylabel("rollout-steps / s")
    ax.set_title(f"{info['machine']['cpu']} ({info['machine']['cores']} cores), {info['steps']} steps")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, path)


if __name__ == "__main__":
    main()
