"""What the arm's optional terms (Coulomb friction, external torques: docs/arm.md) cost the
``vmap`` path when they are zero, and what leaving them out (``without_idle_terms``) saves:
the realistic preset's digital loop, 16 payloads from 0 to 10 kg, 1 s, ``fast=False`` (the
tuner's and the gradients' path), best of 5 calls after the first (BENCHMARKS.md, "Issue 25"):

    python benchmarks/idle_terms_cost.py          # both variants, about 40 s on 2 cores
"""

from __future__ import annotations

import subprocess
import sys
import time

import jax
import numpy as np


def measure(variant: str) -> tuple[float, float]:
    """(seconds of the first call, best of 5 later calls) for ``variant``: "pruned" (as the
    simulator runs) or "evaluated" (every zero term in the program)."""
    jax.config.update("jax_enable_x64", True)
    import fosmc_jax as fj

    if variant == "evaluated":
        import fosmc_jax._simulator.rollout as rollout

        rollout.without_idle_terms = lambda plant: plant
    cfg = fj.config.load(fj.config.PRESETS["realistic_arm"]).as_dict()
    cfg["plant"]["payloads"] = np.linspace(0.0, 10.0, 16).tolist()
    cfg["sim"]["t_final"] = 1.0
    problem = fj.build(cfg)

    def run() -> float:
        t = time.perf_counter()
        jax.block_until_ready(problem.simulate(fast=False).metrics.rms_error)
        return time.perf_counter() - t

    first = run()
    return first, min(run() for _ in range(5))


if __name__ == "__main__":
    if len(sys.argv) > 1:  # one variant, in a process of its own
        first, best = measure(sys.argv[1])
        print(f"{sys.argv[1]:>9}: first call {first:.1f} s, best of 5 {best * 1e3:.0f} ms", flush=True)
    else:
        for variant in ("pruned", "evaluated"):
            subprocess.run([sys.executable, __file__, variant], check=True)
