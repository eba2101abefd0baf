"""What every core buys the tuners: the cost of their two kinds of work on the devices the
process shows (run it once as is, one device per core, and once with ``JAX_NUM_CPU_DEVICES=1``):

    .venv/bin/python benchmarks/tuner_devices.py
    JAX_NUM_CPU_DEVICES=1 .venv/bin/python benchmarks/tuner_devices.py

- ``fosmc front``'s chunks: 64 evaluations (4 chunks of 16, split over the devices) of the
  realistic preset's 2 s training problem (tuning/configs/realistic_arm_short_training.toml);
- ``fosmc tune``'s step: one value-and-gradient of the default loss on the ideal arm
  (tuning/configs/arm_ideal_set2.toml: 2 payloads, 40,000 Euler steps), its two rollouts
  split over the devices (``fosmc_jax._simulator.sharding.simulate_split``).

Each timed after a warm-up call (compilation apart), best of 3. Prints one line per figure.
"""

from __future__ import annotations

import time

import fosmc_jax

fosmc_jax.use_all_cores()

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

from fosmc_jax import config as _config  # noqa: E402
from fosmc_jax import search as fs  # noqa: E402


def best_of(fn, n: int = 3) -> float:
    fn()  # compile
    times = []
    for _ in range(n):
        t = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t)
    return min(times)


def main() -> None:
    print(f"devices: {jax.local_device_count()}", flush=True)
    _, train, p0 = _config.tuning_problems(_config.load("tuning/configs/realistic_arm_short_training.toml"))
    cands = fs.from_factors(p0, fs.global_factors(64, seed=1))
    train = fs.Evaluator(train)
    s = best_of(lambda: train(cands, 16, log=lambda _: None))
    print(f"front: 64 evaluations of the 2 s realistic problem: {s:.2f} s", flush=True)

    cfg = _config.load("tuning/configs/arm_ideal_set2.toml")
    plain, problem, p0 = _config.tuning_problems(cfg)
    obj = fs.objective_of(cfg["tune"], fs.evaluate(problem, p0)["metrics"])
    step = jax.jit(jax.value_and_grad(fs.make_loss(problem, obj, None), has_aux=True))
    u0 = fs.to_internal(p0, plain.base, None)
    s = best_of(lambda: step(u0))
    print(f"tune: one value-and-gradient, arm, 2 payloads x {problem.options['n_steps']} steps: {s:.2f} s")


if __name__ == "__main__":
    main()
