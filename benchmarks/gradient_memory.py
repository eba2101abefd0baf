"""Peak resident memory of a gradient of 4,096 arm rollouts x 40,000 RK4 float64 steps through the
public default path (the generated adjoint kernel), issue 32's memory target (at most 2 GB):

    /usr/bin/time -v python benchmarks/gradient_memory.py            # "Maximum resident set size"
    python benchmarks/gradient_memory.py --steps 2000 --payloads 8   # a short trial

``tuning/configs/arm_ideal_set2.toml`` with ``--payloads`` payloads in [0, 10] kg x 64 initial
offsets (uniform in +-0.05, seed 1): 64 x 64 = 4,096 rollouts by default. Prints the forward's and
the value-and-gradient's times (each with and without compilation) and this process's peak
resident memory (``resource.getrusage``, as ``/usr/bin/time -v`` reports it) after each.
"""

from __future__ import annotations

import argparse
import os
import resource
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def peak_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # Linux: KiB


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=40_000)
    parser.add_argument("--payloads", type=int, default=64)
    args = parser.parse_args()

    import jax
    import jax.numpy as jnp
    import numpy as np

    jax.config.update("jax_enable_x64", True)
    import fosmc_jax as fj
    from fosmc_jax import config as _config

    cfg = _config.load(ROOT / "tuning" / "configs" / "arm_ideal_set2.toml").as_dict()
    cfg["plant"]["payloads"] = np.linspace(0, 10, args.payloads).tolist()
    cfg["sim"].update(integrator="rk4", precision="float64", t_final=args.steps * cfg["sim"]["dt"],
                      initial_offset=np.random.default_rng(1).uniform(-0.05, 0.05, (64, 9)).tolist())  # fmt: skip
    problem = fj.build(cfg)
    p = problem.params()
    print(f"{problem.rollouts} rollouts x {args.steps} RK4 float64 steps; load {os.getloadavg()[0]:.2f}", flush=True)

    def loss(p):
        m = problem.simulate(p).mean()
        return jnp.mean(m.rms_error) + 1e-3 * jnp.mean(m.chattering)

    for name, f in (("forward", jax.jit(loss)), ("value_and_grad", jax.jit(jax.value_and_grad(loss)))):
        for when in ("with compilation", "compiled"):
            t = time.perf_counter()
            jax.block_until_ready(f(p))
            print(f"{name} ({when}): {time.perf_counter() - t:.1f} s; peak resident {peak_mib():.0f} MiB; "
                  f"load {os.getloadavg()[0]:.2f}", flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
