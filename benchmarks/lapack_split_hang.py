"""The jaxlib deadlock behind the arm's gradient hang, in plain JAX (no code of the package):

    python benchmarks/lapack_split_hang.py              # N = 2,048 and 3,072, 60 s each
    python benchmarks/lapack_split_hang.py --n 3072 --xla-flags=--xla_cpu_multi_thread_eigen=false

Each N runs in a child process: ``jit(vmap)`` of four 3x3 solves with 9 right-hand sides (as the
arm's per-rollout lane values hold), called 300 times. jaxlib's CPU LAPACK kernels split a batch
whose work (their estimate: 81 flops per 3x3 solve with 9 right-hand sides) reaches 200,000 over
XLA's intra-op threads and wait on the calling thread: with two such solves ready at once on a
2-core machine every thread waits and the child hangs. Prints per N: ``ran`` (300 calls, with the
time) or ``hung`` (no end within ``--timeout`` seconds; the child is killed).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time

CHILD = """
import sys
import jax, jax.numpy as jnp
import numpy as np
jax.config.update("jax_enable_x64", True)
N = int(sys.argv[1])
x = jnp.asarray(np.random.default_rng(0).normal(size=(N, 12)))
def one(v):
    M = jnp.diag(3 + jnp.cos(v[:3])) + 0.1 * jnp.outer(jnp.sin(v[3:6]), jnp.cos(v[6:9]))
    b = jnp.outer(jnp.tanh(v[9:12]), jnp.ones(9)) * jnp.arange(1.0, 10.0)
    return [jnp.linalg.solve(M + 0.01 * j, b * (j + 1)) for j in range(4)]
f = jax.jit(jax.vmap(one))
for i in range(300):
    jax.block_until_ready(f(x + i))
"""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, nargs="+", default=[2048, 3072], help="batch sizes")
    parser.add_argument("--timeout", type=float, default=60.0, help="seconds before a child counts as hung")
    parser.add_argument("--xla-flags", default=None, help="XLA_FLAGS for the children")
    args = parser.parse_args()
    env = dict(os.environ)
    if args.xla_flags is not None:
        env["XLA_FLAGS"] = args.xla_flags
    print(f"cores {os.cpu_count()}, load {os.getloadavg()[0]:.2f}, XLA_FLAGS={env.get('XLA_FLAGS', '')!r}")
    for n in args.n:
        t = time.perf_counter()
        try:
            subprocess.run([sys.executable, "-c", CHILD, str(n)], env=env, check=True, timeout=args.timeout)
            print(f"N = {n}: ran 300 calls in {time.perf_counter() - t:.1f} s", flush=True)
        except subprocess.TimeoutExpired:
            print(f"N = {n}: hung (no end within {args.timeout:g} s; killed)", flush=True)


if __name__ == "__main__":
    main()
