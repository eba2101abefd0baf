"""Derivative-free baselines for the front, at a wall-time budget: a log grid, random search
and CMA-ES (pycma, the reference implementation).

They search the same space as :mod:`fosmc_jax._front` (the parameters of p0's controller kind,
e.g. the FOSMC's delta, gamma and poles, as per-joint log factors of a start p0 in the kind's
box) and every evaluation runs on the same training problem, a population or grid chunk in one
vmapped call. Each returns every parameter set it evaluated
and their metrics, so that fronts can be compared at equal wall time.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np

from . import _tuning as T
from ._front import DIM, bounds, evaluate_many, from_factors, grid_factors

__all__ = ["DIM", "bounds", "cma_es", "cma_front", "from_factors", "log_grid", "random_search"]


def _collect(problem, p0, zs: list[np.ndarray], chunk: int, log, what) -> dict[str, Any]:
    z = np.concatenate(zs)
    m = evaluate_many(problem, from_factors(p0, z), chunk, log=log, what=what)
    return {"z": z, "metrics": m}


def log_grid(problem: T.Problem, p0: T.Params, per_axis: int, chunk: int = 16, log=print) -> dict[str, Any]:
    """A grid over the common factors of p0's parameters (the FOSMC's delta, gamma, poles; the
    same for every joint), ``per_axis`` log-spaced values each over the search box."""
    return _collect(problem, p0, [grid_factors(per_axis, T.space_of(p0))], chunk, log, "log grid")


def random_search(problem: T.Problem, p0: T.Params, budget: float, chunk: int = 16, seed: int = 0,
                  log=print) -> dict[str, Any]:  # fmt: skip
    """Uniform draws of the log factors over the search box, a chunk at a time (at least one),
    until the wall-time ``budget`` (s) is spent."""
    space = T.space_of(p0)
    lo, hi = space.bounds()
    rng = np.random.default_rng(seed)
    start, zs, ms = time.perf_counter(), [], []
    while not zs or time.perf_counter() - start < budget:
        z = rng.uniform(lo, hi, size=(chunk, space.dim))
        zs.append(z)
        ms.append(evaluate_many(problem, from_factors(p0, z), chunk, log=lambda _: None))
        log(f"random search: {len(zs) * chunk} evaluations  {time.perf_counter() - start:7.1f} s")
    return {"z": np.concatenate(zs), "metrics": {k: np.concatenate([m[k] for m in ms]) for k in ms[0]}}


def cma_es(objective: Callable[[np.ndarray], np.ndarray], x0: np.ndarray, sigma0: float, budget: float,
           popsize: int = 16, seed: int = 0, lower=None, upper=None, log=print):  # fmt: skip
    """Minimise ``objective`` (a batch (n, d) -> (n,), one vmapped call per generation) with
    pycma's CMA-ES from ``x0`` until the wall-time ``budget`` (s) is spent; returns (best x,
    best value, every x evaluated, their values)."""
    import cma  # here, not at the top: importing pycma takes 1-2 s

    opts = {"popsize": popsize, "seed": seed + 1, "verbose": -9}
    if lower is not None:
        opts["bounds"] = [list(lower), list(upper)]
    es = cma.CMAEvolutionStrategy(np.asarray(x0, float), sigma0, opts)
    start, xs, fs = time.perf_counter(), [], []
    while time.perf_counter() - start < budget and not es.stop():
        X = np.asarray(es.ask())
        f = np.asarray(objective(X), float)
        es.tell(list(X), list(np.where(np.isfinite(f), f, 1e30)))
        xs.append(X)
        fs.append(f)
        best = np.nanmin(np.concatenate(fs))
        log(f"cma-es: generation {len(xs)}  best {best:.4g}  {time.perf_counter() - start:7.1f} s")
    X, F = np.concatenate(xs), np.concatenate(fs)
    i = int(np.nanargmin(F))
    return X[i], F[i], X, F


def cma_front(problem: T.Problem, p0: T.Params, weights, budget: float, popsize: int = 16, seed: int = 0,
              log=print) -> dict[str, Any]:  # fmt: skip
    """CMA-ES on the weighted log objective log E + w log C (:mod:`fosmc_jax._tuning`) for
    each weight in turn, the budget split evenly; every evaluation is kept."""
    space = T.space_of(p0)
    lo, hi = space.bounds()
    zs, ms = [], []
    for w in weights:

        def objective(Z, w=w):
            m = evaluate_many(problem, from_factors(p0, Z), len(Z), log=lambda _: None)
            zs.append(Z)
            ms.append(m)
            e, c = (np.mean(m[k], axis=-1) for k in ("rms_error", "chattering_hf"))
            return np.log(e) + w * np.log(c) + np.where(m["diverged"] > 0, 1e3, 0.0)

        cma_es(objective, np.zeros(space.dim), 0.5, budget / len(weights), popsize, seed, lo, hi,
               log=lambda s, w=w: log(f"w = {w:g}: {s}"))  # fmt: skip
    return {"z": np.concatenate(zs), "metrics": {k: np.concatenate([m[k] for m in ms]) for k in ms[0]}}
