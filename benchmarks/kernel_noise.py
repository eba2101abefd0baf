"""A noisy digital loop on the generated kernel against the ``vmap`` path (issue 32, item 6):

    python benchmarks/kernel_noise.py                       # the two shapes below
    python benchmarks/kernel_noise.py --steps 500 --rounds 1   # a short trial
    python benchmarks/kernel_noise.py --kernel-only            # the kernel's rows alone (minutes less)

The ``realistic_arm`` preset's 1 kHz digital loop (dt 0.1 ms, m = 10, encoders, differenced
rates, delay, voltage limit) with Gaussian noise of ``--std`` rad on the encoders' angles, RK4
float64, 64 rollouts either way: ``one_key``, 8 payloads x 8 initial offsets with one noise key;
``realizations``, 8 payloads x 1 offset x 8 noise realizations (``sensors.realizations``). For
each, after compilation (its time recorded), in ``--rounds`` rounds timing each function in turn
(interleaved, so that the machine's load reaches all alike):
- ``forward``: ``problem.simulate(p)``, the default path (the generated kernel), jitted;
- ``value_and_grad``: ``jax.value_and_grad`` of mean(rms_error) + 1e-3 mean(chattering) over it
  in the FOSMC's 15 parameters and in ``noise_std`` (the reparameterised draws);
- ``vmap_forward``, ``vmap_value_and_grad``: the same with ``fast=False`` (the ``vmap`` path);
- ``per_key_forward``, ``per_key_value_and_grad`` (``realizations``): the kernel called once per
  key (``generated.TABLE_BYTES`` set below one table) instead of once for all keys, each key's
  rollouts reading its own table.
Printed: seconds per call (the rounds' median), rollouts per second, the kernel's speed-up, the
largest relative difference of the two paths' gradients, and the 1-minute load average.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time

SHAPES = {"one_key": (8, 8, 1), "realizations": (8, 1, 8)}  # payloads, offsets, realizations


def load() -> float:
    return round(os.getloadavg()[0], 2)


def problem_of(shape: str, steps: int, std: float):
    import numpy as np

    import fosmc_jax as fj
    from fosmc_jax import config as _config

    payloads, offsets, realizations = SHAPES[shape]
    cfg = _config.load("realistic_arm").as_dict()
    lo, hi = cfg["plant"].get("payload_range", [0.0, 10.0])
    cfg["plant"]["payloads"] = np.linspace(lo, hi, payloads).tolist()
    cfg["plant"].pop("uncertainty", None)
    cfg["sensors"].update(noise_std=[std, 0.0, 0.0] * 3, realizations=realizations)
    cfg["sim"].update(t_final=steps * cfg["sim"]["dt"],
                      initial_offset=np.random.default_rng(1).uniform(-0.05, 0.05, (offsets, 9)).tolist())  # fmt: skip
    problem = fj.build(cfg)
    assert problem.rollouts == payloads * offsets * realizations, problem.rollouts
    return problem


def functions(problem, vmap: bool = True) -> tuple[dict, tuple]:
    """The four functions of (controller parameters, noise_std) and their arguments."""
    import dataclasses

    import jax
    import jax.numpy as jnp

    def run(p, std, fast):
        loop = problem.controller(p)
        loop = dataclasses.replace(loop, sensors=dataclasses.replace(loop.sensors, noise_std=std))
        from fosmc_jax._simulator import rollout

        return rollout.simulate_batch(problem.plants, loop, problem.reference, problem.X0s, problem.dt,
                                      keys=problem.keys, fast=fast, **problem.options)  # fmt: skip

    def loss(p, std, fast):
        m = run(p, std, fast).mean()
        return jnp.mean(m.rms_error) + 1e-3 * jnp.mean(m.chattering)

    fns = {
        "forward": lambda p, std: run(p, std, True).metrics,
        "value_and_grad": jax.value_and_grad(lambda p, std: loss(p, std, True), argnums=(0, 1)),
    }
    if vmap:
        fns["vmap_forward"] = lambda p, std: run(p, std, False).metrics
        fns["vmap_value_and_grad"] = jax.value_and_grad(lambda p, std: loss(p, std, False), argnums=(0, 1))
    return fns, (problem.params(), problem.controller().sensors.noise_std)


def measure(shape: str, steps: int, std: float, rounds: int, round_s: float, vmap: bool = True) -> dict:
    import jax
    import numpy as np

    problem = problem_of(shape, steps, std)
    fns, args = functions(problem, vmap)
    runs = {}
    from fosmc_jax._simulator import generated

    if SHAPES[shape][2] > 1:
        fns["per_key_forward"], fns["per_key_value_and_grad"] = fns["forward"], fns["value_and_grad"]
    table_bytes = generated.TABLE_BYTES
    for name, fn in fns.items():
        generated.TABLE_BYTES = 1 if name.startswith("per_key") else table_bytes  # read when traced
        t0 = time.perf_counter()
        compiled = jax.jit(fn).lower(*args).compile()
        compile_s = time.perf_counter() - t0
        generated.TABLE_BYTES = table_bytes
        t0 = time.perf_counter()
        out = jax.block_until_ready(compiled(*args))
        runs[name] = (compiled, compile_s, time.perf_counter() - t0, out)
    times = {name: [] for name in runs}
    loads = []
    for _ in range(rounds):
        for name, (compiled, _, warm, _) in runs.items():
            calls = max(1, int(round_s / max(warm, 1e-6)))
            t0 = time.perf_counter()
            for _ in range(calls):
                jax.block_until_ready(compiled(*args))
            times[name].append((time.perf_counter() - t0) / calls)
        loads.append(load())
    rel = float("nan")
    if vmap:
        grads = [jax.tree.leaves(runs[name][3][1]) for name in ("value_and_grad", "vmap_value_and_grad")]
        rel = max(float(np.max(np.abs(a - b) / np.maximum(np.abs(b), 1e-300))) for a, b in zip(*grads))
    out = {"shape": shape, "rollouts": problem.rollouts, "steps": steps, "grad_rel_diff": rel, "loads": loads}
    for name, (_, compile_s, _, _) in runs.items():
        s = statistics.median(times[name])
        out[name] = {"s": s, "rollouts_per_s": problem.rollouts / s, "compile_s": compile_s, "all_s": times[name]}
    return out


def main() -> None:
    import jax

    jax.config.update("jax_enable_x64", True)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=4000)
    parser.add_argument("--std", type=float, default=1e-4, help="the angles' noise (rad)")
    parser.add_argument("--only", choices=sorted(SHAPES))
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--round-s", type=float, default=2.0)
    parser.add_argument("--kernel-only", action="store_true", help="leave the vmap path's rows out")
    parser.add_argument("--out", help="a JSON file for every figure")
    args = parser.parse_args()
    results = []
    for shape in [args.only] if args.only else list(SHAPES):
        r = measure(shape, args.steps, args.std, args.rounds, args.round_s, not args.kernel_only)
        results.append(r)
        print(f"{shape}: {r['rollouts']} rollouts x {r['steps']} RK4 float64 steps, load {r['loads']}")
        for kind in ("forward", "value_and_grad"):
            k = r[kind]
            line = f"  {kind:15s} kernel {k['s']:.4f} s ({k['rollouts_per_s']:.0f} rollouts/s)"
            if "vmap_" + kind in r:
                v = r["vmap_" + kind]
                line += (f"   vmap path {v['s']:.4f} s ({v['rollouts_per_s']:.0f} rollouts/s)   {v['s'] / k['s']:.1f}x"
                         f"   compile {k['compile_s']:.1f} s / {v['compile_s']:.1f} s")  # fmt: skip
            print(line)
            if "per_key_" + kind in r:
                v = r["per_key_" + kind]
                print(f"  {'':15s} a kernel call per key {v['s']:.4f} s ({v['rollouts_per_s']:.0f} rollouts/s)")
        print(f"  value_and_grad / forward: kernel {r['value_and_grad']['s'] / r['forward']['s']:.2f}, "
              f"gradients' largest relative difference {r['grad_rel_diff']:.1e}")  # fmt: skip
    if args.out:
        with open(args.out, "w") as f:
            json.dump(results, f, indent=1)


if __name__ == "__main__":
    main()
