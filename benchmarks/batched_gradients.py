"""Value and gradient of a batch of candidate controllers (``jax.vmap`` of ``fosmc tune``'s
training loss) against one candidate's, on the generated adjoint kernel: per candidate, what a
batch of C costs once the kernels fold the candidates into their SIMD lanes
(``fosmc_jax._simulator.generated._folded_call``). The tuning configs train on 2-3 rollouts, a
quarter of one float64 block of lanes: alone, a candidate's gradient leaves most lanes and the
second core idle.

For each config: the training problem, objective and parameters of ``fosmc tune``
(``tuning_problems``, the objective's scales at the config's parameters); C candidates around
them (each parameter scaled by 1 + 0.01 k); every program compiled first; then ``--rounds``
rounds, each timing one call of every batch size in turn (interleaved, so that the machine's load
reaches them alike); the minimum per size. Prints a Markdown table with the load.

    PYTHONPATH=. .venv/bin/python benchmarks/batched_gradients.py            # arm_set2, arm_ideal_set2
    PYTHONPATH=. .venv/bin/python benchmarks/batched_gradients.py --configs realistic_arm --sizes 1,8
"""

from __future__ import annotations

import argparse
import os
import time

from fosmc_jax import use_all_cores

use_all_cores()  # as the command line does

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

jax.config.update("jax_enable_x64", True)

import fosmc_jax.config as fc  # noqa: E402
import fosmc_jax.search as fs  # noqa: E402


def loss_of(name: str):
    """``fosmc tune``'s training loss of ``tuning/configs/<name>.toml`` and its start u0."""
    cfg = fc.load(f"tuning/configs/{name}.toml")
    plain, train, p0 = fc.tuning_problems(cfg)
    obj = fs.objective_of(cfg.tune, fs.evaluate(train, p0)["metrics"])
    loss = fs.make_loss(train, obj, None)
    return (lambda u: loss(u)[0]), fs.to_internal(p0, plain.base), train


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--configs", default="arm_set2,arm_ideal_set2", help="config names of tuning/configs")
    ap.add_argument("--sizes", default="1,4,16", help="batch sizes C (1: the unbatched call)")
    ap.add_argument("--rounds", type=int, default=5)
    args = ap.parse_args()
    sizes = [int(c) for c in args.sizes.split(",")]
    print(f"load at the start: {os.getloadavg()}; {jax.local_device_count()} JAX CPU devices\n")
    print("| config | rollouts x steps | " + " | ".join(f"C = {c}: ms per candidate" for c in sizes) + " | load |")
    print("|---|---|" + "---|" * len(sizes) + "---|")
    for name in args.configs.split(","):
        loss, u0, train = loss_of(name)
        grad = jax.value_and_grad(loss)
        calls = {}
        for c in sizes:
            if c == 1:
                calls[c] = (jax.jit(grad), u0)
            else:
                scale = (1.0 + 0.01 * jnp.arange(c)).astype(jnp.float64)
                batch = jax.tree.map(lambda x, s=scale: x[None] + jnp.log(s).reshape((-1,) + (1,) * x.ndim), u0)
                calls[c] = (jax.jit(jax.vmap(grad)), batch)
            jax.block_until_ready(calls[c][0](calls[c][1]))  # compiled, the kernels built
        best = {c: np.inf for c in sizes}
        for _ in range(args.rounds):
            for c, (f, x) in calls.items():
                t = time.perf_counter()
                jax.block_until_ready(f(x))
                best[c] = min(best[c], time.perf_counter() - t)
        shape = f"{train.rollouts} x {train.options['n_steps']}"
        cells = " | ".join(f"{1e3 * best[c] / c:.1f}" for c in sizes)
        print(f"| {name} | {shape} | {cells} | {os.getloadavg()[0]:.1f} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
