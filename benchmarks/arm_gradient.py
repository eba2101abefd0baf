"""What one gradient of the tuner's loss costs on the arm, against the forward simulation, one command:

    python benchmarks/arm_gradient.py                          # 64 rollouts x 4,000 steps, RK4, float64
    python benchmarks/arm_gradient.py --out /tmp/arm_gradient.json
    python benchmarks/arm_gradient.py --steps 500 --rounds 2   # a short trial

The problem is ``fosmc tune``'s on ``tuning/configs/arm_ideal_set2.toml`` (the ideal loop, the
arm, Table 1 set 2, ratio switching, dt = 1e-4) with ``[sim]`` changed to RK4, float64 and
``t_final = steps x dt`` (the config itself says Euler and 4 s), and the batch enlarged to 64
rollouts: 8 payloads in [0, 10] kg x 8 initial offsets (``bench.problem(64)``'s: uniform in
+-0.05, seed 1). It is built as ``fosmc_jax.run_tune`` builds it:
``fosmc_jax.config.tuning_problems`` (the training problem: the scan rematerialised every
``tune.remat_steps`` steps, default 100), the objective's scales from ``fosmc_jax.search.evaluate`` at the
config's parameters, the loss ``fosmc_jax.search.make_loss`` (``simulate_batch(fast=False)``, the
``vmap`` of ``simulate``, split over the devices) in unconstrained coordinates of delta (3),
gamma (3) and the poles (3 x 3): 15 numbers. The process is set up as the CLI sets itself up
(``use_all_cores()``: one CPU device per core; float64 available).

Timed, each compiled first (``jit(...).lower(u).compile()``, the compile time recorded), then
``--rounds`` rounds of as many calls as last ``--round-s`` at least, the median round's time per
call (the 1-minute load average recorded with every round):

- **reverse**: ``fosmc_jax.search.value_and_grad(loss, "reverse")`` (``jax.value_and_grad``) with the
  scan rematerialised every ``checkpoint_every`` steps, for each of ``--checkpoint-every``
  (default: the tuner's ``remat_steps``, 100, and 1,000);
- **forward**: ``fosmc_jax.search.value_and_grad(loss, "forward")`` (``jax.jacfwd``: one tangent per
  unconstrained parameter, 15);
- **fast forward**: the same loss's value through the native kernel (``fast=True``, as
  ``make_loss`` builds it otherwise: split over the devices), and through one unsplit
  ``simulate_batch`` call (the kernel spreads its blocks over every core itself);
- **vmap forward**: the loss's value as ``make_loss`` computes it (``fast=False``), ``jit`` of the loss.

Each gradient is reported as a ratio to the fast forward (the split one, the loss's own layout)
and to the vmap forward. The loss values of every path must agree (to 1e-9 relative): the
command fails otherwise. ``--out`` writes everything as JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "tuning" / "configs" / "arm_ideal_set2.toml"
PAYLOADS, OFFSETS = 8, 8


def load() -> float:
    return round(os.getloadavg()[0], 2)


def problems(path: Path, steps: int):
    """The config with RK4, float64, ``steps`` steps and 8 payloads x 8 offsets; its
    ``tuning_problems`` (plain, train, p0) and the resolved config."""
    import numpy as np

    from fosmc_jax import config as _config

    cfg = _config.load(path).as_dict()
    offsets = np.random.default_rng(1).uniform(-0.05, 0.05, (OFFSETS, 9))  # bench.problem(64)'s
    cfg["plant"]["payloads"] = np.linspace(0.0, 10.0, PAYLOADS).tolist()
    cfg["sim"].update(integrator="rk4", precision="float64", t_final=steps * cfg["sim"]["dt"],
                      initial_offset=offsets.tolist())  # fmt: skip
    cfg = _config.resolve(cfg)
    plain, train, p0 = _config.tuning_problems(cfg)
    assert train.options["n_steps"] == steps and train.options["integrator"] == "rk4", train.options
    assert str(train.dt.dtype) == "float64" and train.keys is None
    return cfg, plain, train, p0


def timed(fn, u, rounds: int, round_s: float) -> dict:
    """Compile ``fn`` (a ``jax.jit``) for ``u``, one warm call, then ``rounds`` rounds of as many
    calls as last ``round_s``: compile seconds, the median seconds per call and the loads."""
    import jax
    import numpy as np

    t0 = time.perf_counter()
    compiled = fn.lower(u).compile()
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    out = jax.block_until_ready(compiled(u))
    warm = time.perf_counter() - t0
    calls = max(1, int(np.ceil(round_s / warm)))
    per_call, loads = [], []
    for _ in range(rounds):
        t0 = time.perf_counter()
        for _ in range(calls):
            out = jax.block_until_ready(compiled(u))
        per_call.append((time.perf_counter() - t0) / calls)
        loads.append(load())
    mem = compiled.memory_analysis()
    return {"s": statistics.median(per_call), "min_s": min(per_call), "max_s": max(per_call), "all_s": per_call,
            "calls_per_round": calls, "compile_s": compile_s, "warm_call_s": warm, "loads": loads,
            "temp_bytes": None if mem is None else mem.temp_size_in_bytes, "out": out}  # fmt: skip


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--config", default=str(CONFIG), help="TOML config (default: tuning/configs/arm_ideal_set2.toml)")
    ap.add_argument("--steps", type=int, default=4000, help="steps per rollout (default 4,000)")
    ap.add_argument("--checkpoint-every", default="", help="reverse mode's remat blocks, comma-separated (default: "
                    "the config's tune.remat_steps, then 1,000)")  # fmt: skip
    ap.add_argument("--rounds", type=int, default=3, help="timed rounds per measurement (default 3)")
    ap.add_argument("--round-s", type=float, default=0.3, help="a round lasts this long at least (default 0.3)")
    ap.add_argument("--out", help="write the results as JSON")
    args = ap.parse_args(argv)
    t_start = time.perf_counter()
    uptime = lambda: subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    info = {"command": "python benchmarks/arm_gradient.py " + " ".join(sys.argv[1:] if argv is None else argv),
            "uptime_start": uptime()}  # fmt: skip
    print(f"start: {info['uptime_start']}", flush=True)

    from fosmc_jax import use_all_cores

    use_all_cores()  # as the CLI: one CPU device per core
    import jax
    import jax.numpy as jnp
    import numpy as np

    jax.config.update("jax_enable_x64", True)
    from fosmc_jax import kernel_available
    from fosmc_jax import search as fs

    cfg, plain, train, p0 = problems(Path(args.config), args.steps)
    if cfg["tune"]["keep_gamma_bound"]:
        raise SystemExit("arm_gradient.py: tune.keep_gamma_bound is not supported here (no gamma floor)")
    remat = train.options["checkpoint_every"]
    every = [int(x) for x in args.checkpoint_every.split(",") if x] or [remat, 1000]
    obj = fs.objective_of(cfg["tune"], fs.evaluate(plain, p0)["metrics"])  # the objective's scales, as run_tune
    u0 = fs.to_internal(p0, plain.base)
    n_params = sum(int(np.size(x)) for x in u0)
    rollouts = jax.tree.leaves(train.plants)[0].shape[0] * train.X0s.shape[0]
    info.update(config=str(args.config), rollouts=rollouts, payloads=PAYLOADS, offsets=OFFSETS,
                steps=args.steps, dt=float(train.dt), integrator=train.options["integrator"],
                precision=str(train.dt.dtype), remat_steps=remat, params=list(u0._fields), tangents=n_params,
                devices=jax.local_device_count(), cores=os.cpu_count(), native_kernel=kernel_available(),
                objective=obj._asdict(), rounds=args.rounds, round_s=args.round_s, jax=jax.__version__)  # fmt: skip
    print(f"{rollouts} rollouts x {args.steps} steps, RK4, float64, {n_params} parameters, "
          f"{jax.local_device_count()} devices, native kernel {'on' if info['native_kernel'] else 'OFF'}", flush=True)  # fmt: skip

    def value_of(problem, **options):
        """The loss's value as make_loss computes it, with ``options`` to simulate."""

        def value(u):
            r = problem.simulate(fs.to_physical(u, problem.base), **options)
            J, e, c = fs.rollout_costs(r.metrics, r.diverged, obj)
            return fs.aggregate(J, obj), (jnp.mean(e), jnp.mean(c))

        return jax.jit(value)

    loss_of = lambda ce: fs.make_loss(train._replace(options=dict(train.options, checkpoint_every=ce)), obj, None)
    todo = {"fast forward (kernel, split over the devices)": value_of(train, split=True, fast=True),
            "fast forward (kernel, one simulate_batch call)": value_of(train, split=False, fast=True),
            "vmap forward (make_loss: fast=False, split)": jax.jit(fs.make_loss(train, obj, None))}  # fmt: skip
    for ce in every:
        todo[f"reverse, checkpoint every {ce}"] = fs.value_and_grad(loss_of(ce), "reverse")
    todo[f"forward mode ({n_params} tangents)"] = fs.value_and_grad(fs.make_loss(train, obj, None), "forward")
    res = {}
    for name, fn in todo.items():
        res[name] = timed(fn, u0, args.rounds, args.round_s)
        r = res[name]
        print(f"  {name}: {r['s']:.4f} s per call ({r['min_s']:.4f}-{r['max_s']:.4f}), compile {r['compile_s']:.1f} s"
              f"  load {min(r['loads'])}-{max(r['loads'])}", flush=True)  # fmt: skip
    values = {
        k: float(r["out"][0]) if k.startswith(("fast", "vmap")) else float(r["out"][0][0]) for k, r in res.items()
    }
    ref = values["vmap forward (make_loss: fast=False, split)"]
    grads = {k: np.concatenate([np.ravel(x) for x in r["out"][1]]) for k, r in res.items() if "checkpoint" in k or "mode" in k}  # fmt: skip
    g0 = next(iter(grads.values()))
    for r in res.values():
        del r["out"]
    fast, vmap = (
        res["fast forward (kernel, split over the devices)"]["s"],
        res["vmap forward (make_loss: fast=False, split)"]["s"],
    )
    for k, r in res.items():
        r.update(loss=values[k], over_fast_forward=r["s"] / fast, over_vmap_forward=r["s"] / vmap,
                 rollout_steps_per_s=rollouts * args.steps / r["s"])  # fmt: skip
        if k in grads:
            r["grad_rel_diff"] = float(np.max(np.abs(grads[k] - g0)) / np.max(np.abs(g0)))
    info.update(results=res, gradient_norm=float(np.linalg.norm(g0)), total_s=time.perf_counter() - t_start,
                uptime_end=uptime())  # fmt: skip
    lines = ["| measurement | s per call (min-max) | / fast forward | / vmap forward | compile s | loss | load |",
             "|---|---|---|---|---|---|---|"]  # fmt: skip
    for k, r in res.items():
        lines.append(f"| {k} | {r['s']:.4f} ({r['min_s']:.4f}-{r['max_s']:.4f}) | {r['over_fast_forward']:.1f}x | "
                     f"{r['over_vmap_forward']:.2f}x | {r['compile_s']:.1f} | {r['loss']:.12g} | "
                     f"{min(r['loads'])}-{max(r['loads'])} |")  # fmt: skip
    lines += ["", f"{rollouts} rollouts ({PAYLOADS} payloads x {OFFSETS} offsets) x {args.steps} steps, RK4, float64, "
              f"{n_params} parameters, {info['devices']} devices; median of {args.rounds} rounds of >= {args.round_s} s; "
              "/ fast forward: the split kernel forward's time. Gradients agree to "
              + ", ".join(f"{res[k]['grad_rel_diff']:.1e}" for k in grads) + " (max abs difference / max |grad|)."]  # fmt: skip
    info["table"] = "\n".join(lines)
    print(f"end: {info['uptime_end']}\n\n{info['table']}")
    if args.out:
        Path(args.out).write_text(json.dumps(info, indent=1))
        print(f"wrote {args.out}")
    bad = {k: v for k, v in values.items() if abs(v - ref) > 1e-9 * abs(ref)}
    if bad:
        raise SystemExit(f"the loss differs between paths: {bad} vs {ref}")


if __name__ == "__main__":
    main()
