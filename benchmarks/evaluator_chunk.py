"""What the chunk size costs ``fosmc front``'s evaluator: seconds per candidate of the training
problem of each config, the same candidates in chunks of 16 (the rounds' and the probe's), 64 and
256 (an NSGA-II generation of the default population, one call since 93d7a5a):

    .venv/bin/python benchmarks/evaluator_chunk.py
    .venv/bin/python benchmarks/evaluator_chunk.py --configs realistic_arm --rounds 6

Each chunk size compiled apart first; then ``--rounds`` rounds, each evaluating the 256 candidates
(``fosmc_jax.search.global_factors``) once at every chunk size in turn, so that load drift reaches
every size alike; median and best per candidate. The metrics are the same to the bit at every size
(``tests/test_front.py::test_the_evaluators_metrics_do_not_depend_on_its_chunk``). Prints one line per
config and size with the 1-minute load.
"""

from __future__ import annotations

import argparse
import time

import fosmc_jax

fosmc_jax.use_all_cores()

import jax  # noqa: E402
import numpy as np  # noqa: E402

jax.config.update("jax_enable_x64", True)

from fosmc_jax import config as _config  # noqa: E402
from fosmc_jax import search as fs  # noqa: E402

CHUNKS = (16, 64, 256)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--configs", nargs="+", default=["realistic_arm", "unseen_arm", "realistic_arm_robust"])
    ap.add_argument("--rounds", type=int, default=4)
    args = ap.parse_args()
    print(f"devices: {jax.local_device_count()}", flush=True)
    for name in args.configs:
        _, train, p0 = _config.tuning_problems(_config.load(f"tuning/configs/{name}.toml"))
        cands = fs.from_factors(p0, fs.global_factors(max(CHUNKS), seed=1))
        ev, quiet = fs.Evaluator(train), (lambda _: None)
        for chunk in CHUNKS:  # compile each size
            ev(jax.tree.map(lambda x, chunk=chunk: x[:chunk], cands), chunk, log=quiet)
        times = {chunk: [] for chunk in CHUNKS}
        for _ in range(args.rounds):
            for chunk in CHUNKS:
                t = time.perf_counter()
                ev(cands, chunk, log=quiet)
                times[chunk].append((time.perf_counter() - t) / max(CHUNKS))
        load = open("/proc/loadavg").read().split()[0]
        for chunk, ts in times.items():
            print(f"{name}: chunk {chunk:3d}: {np.median(ts) * 1e3:.3f} ms a candidate (median of {args.rounds}), "
                  f"best {min(ts) * 1e3:.3f}; 1-min load {load}", flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
