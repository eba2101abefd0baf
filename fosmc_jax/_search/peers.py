"""Derivative-free baselines for the front, at a wall-time budget: a log grid, random search,
CMA-ES (pycma, the reference implementation) and NSGA-II, pymoo's (:func:`nsga2`) and
optuna's (:func:`optuna_nsga2`; optional: ``pip install fosmc_jax[peers]``).

They search the same space as :mod:`fosmc_jax._search.front` (the parameters of p0's controller kind,
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

from .._simulator import sharding
from . import tune as tuner
from .front import (
    DIM,
    bounds,
    evaluate_many,
    evaluator,
    from_factors,
    grid_factors,
    nondominated,
    nsga2_algorithm,
    nsga2_tell,
    objectives,
)

__all__ = ["DIM", "bounds", "cma_es", "cma_front", "from_factors", "log_grid", "nsga2", "optuna_nsga2", "random_search"]


def _joined(zs: list[np.ndarray], ms: list[dict]) -> dict[str, Any]:
    """Chunks of evaluated factors and their metrics as one ``{"z", "metrics"}``."""
    return {"z": np.concatenate(zs), "metrics": {k: np.concatenate([m[k] for m in ms]) for k in ms[0]}}


def _collect(problem, p0, zs: list[np.ndarray], chunk: int, log, what) -> dict[str, Any]:
    z = np.concatenate(zs)
    m = evaluate_many(problem, from_factors(p0, z), chunk, log=log, what=what)
    return {"z": z, "metrics": m}


def log_grid(problem: tuner.Problem, p0: tuner.Params, per_axis: int, chunk: int = 16, log=print) -> dict[str, Any]:
    """A grid over the common factors of p0's parameters (the FOSMC's delta, gamma, poles; the
    same for every joint), ``per_axis`` log-spaced values each over the search box."""
    return _collect(problem, p0, [grid_factors(per_axis, tuner.space_of(p0))], chunk, log, "log grid")


def random_search(problem: tuner.Problem, p0: tuner.Params, budget: float, chunk: int = 16, seed: int = 0,
                  log=print) -> dict[str, Any]:  # fmt: skip
    """Uniform draws of the log factors over the search box, a chunk at a time (at least one),
    until the wall-time ``budget`` (s) is spent."""
    problem = evaluator(problem)  # compiled once for every chunk
    space = tuner.space_of(p0)
    lo, hi = space.bounds()
    rng = np.random.default_rng(seed)
    start, zs, ms = time.perf_counter(), [], []
    while not zs or time.perf_counter() - start < budget:
        z = rng.uniform(lo, hi, size=(chunk, space.dim))
        zs.append(z)
        ms.append(evaluate_many(problem, from_factors(p0, z), chunk, log=lambda _: None))
        log(f"random search: {len(zs) * chunk} evaluations  {time.perf_counter() - start:7.1f} s")
    return _joined(zs, ms)


def cma_es(objective: Callable[[np.ndarray], np.ndarray], x0: np.ndarray, sigma0: float, budget: float,
           popsize: int = 16, seed: int = 0, lower=None, upper=None, log=print,
           generations: int | None = None):  # fmt: skip
    """Minimise ``objective`` (a batch (n, d) -> (n,), one vmapped call per generation) with
    pycma's CMA-ES from ``x0`` (one generation at least) until the wall-time ``budget`` (s) is
    spent, pycma's own criteria stop it or ``generations`` (None: no limit) are run; returns
    (best x, best value, every x evaluated, their values)."""
    import cma  # here, not at the top: importing pycma takes 1-2 s

    # a stream of its own: pycma's default (its seed into NumPy's global stream) would reset the
    # caller's np.random and share a stream with anything else drawing from it (the same draws as
    # that default where nothing does)
    opts = {"popsize": popsize, "randn": np.random.RandomState(seed + 1).randn, "verbose": -9}
    if lower is not None:
        opts["bounds"] = [list(lower), list(upper)]
    es = cma.CMAEvolutionStrategy(np.asarray(x0, float), sigma0, opts)
    start, xs, fs = time.perf_counter(), [], []
    # one generation at least; process 0's clock (sharding.first): in a run across processes
    # (fosmc tune's CMA-ES stage) every process runs the same generations
    while ((not xs or sharding.first(time.perf_counter() - start < budget)) and not es.stop()
           and (generations is None or len(xs) < generations)):  # fmt: skip
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


def cma_front(problem: tuner.Problem, p0: tuner.Params, weights, budget: float, popsize: int = 16, seed: int = 0,
              log=print) -> dict[str, Any]:  # fmt: skip
    """CMA-ES on the weighted log objective log E + w log C (:mod:`fosmc_jax._search.tune`) for
    each weight in turn, the budget split evenly; every evaluation is kept."""
    problem = evaluator(problem)  # compiled once for every chunk
    space = tuner.space_of(p0)
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
    return _joined(zs, ms)


def _archive(front: np.ndarray, m: dict[str, np.ndarray]) -> np.ndarray:
    """The non-dominated (mean rms_error, mean chattering_hf) pairs (k, 2) of ``front`` and the
    candidates of metrics m without a diverged rollout: the progress line's count, kept
    without sweeping every evaluation again each generation."""
    e, c = (np.mean(m[k], axis=-1) for k in ("rms_error", "chattering_hf"))
    pts = np.concatenate([front, np.stack([e, c], -1)[m["diverged"] == 0]])
    return pts[nondominated(pts[:, 0], pts[:, 1])]


def _generations(problem: tuner.Problem, p0: tuner.Params, budget: float, popsize: int, ask, tell, name: str,
                 log) -> dict[str, Any]:  # fmt: skip
    """A peer's generations (one at least) until the wall-time ``budget`` (s) is spent:
    ``ask() -> (z (popsize, dim), handle)``, the generation evaluated in one
    :func:`evaluate_many` call, ``tell(handle, metrics)``. Returns every candidate evaluated
    and their metrics."""
    problem = evaluator(problem)  # compiled once for every chunk
    start, zs, ms, front = time.perf_counter(), [], [], np.zeros((0, 2))
    while not zs or time.perf_counter() - start < budget:
        z, handle = ask()
        m = evaluate_many(problem, from_factors(p0, z), popsize, log=lambda _: None)
        tell(handle, m)
        zs.append(z)
        ms.append(m)
        front = _archive(front, m)
        log(f"{name}: generation {len(zs)}  {sum(map(len, zs))} evaluations  {len(front)} non-dominated  "
            f"{time.perf_counter() - start:7.1f} s")  # fmt: skip
    return _joined(zs, ms)


def nsga2(problem: tuner.Problem, p0: tuner.Params, budget: float, popsize: int = 64, seed: int = 0,
          log=print) -> dict[str, Any]:  # fmt: skip
    """pymoo's NSGA-II (its defaults: uniform initial population, SBX crossover, polynomial
    mutation, rank and crowding survival) on :func:`objectives` over the search box of p0's
    kind, through pymoo's ask/tell interface: each generation of ``popsize`` evaluated in one
    :func:`evaluate_many` call, generations (one at least) until the wall-time ``budget`` (s)
    is spent. Returns every candidate evaluated and their metrics."""
    space = tuner.space_of(p0)
    lo, hi = space.bounds()
    algorithm = nsga2_algorithm(space, popsize, seed)

    def ask():
        pop = algorithm.ask()
        return np.clip(pop.get("X"), lo, hi), pop

    tell = lambda pop, m: nsga2_tell(algorithm, pop, m)
    return _generations(problem, p0, budget, popsize, ask, tell, "nsga2 (pymoo)", log)


def optuna_nsga2(problem: tuner.Problem, p0: tuner.Params, budget: float, popsize: int = 64, seed: int = 0,
                 log=print) -> dict[str, Any]:  # fmt: skip
    """optuna's NSGA-II (``NSGAIISampler(population_size=popsize, seed=seed)``, its defaults
    otherwise) on :func:`objectives` over the search box of p0's kind, through optuna's ask/tell
    interface: a whole generation of ``popsize`` trials asked (optuna puts a trial in the next
    generation once the current one has ``popsize`` complete trials, so all of them land in the
    same one), evaluated in one :func:`evaluate_many` call, then told; generations (one at
    least) until the wall-time ``budget`` (s) is spent. optuna's logging is silenced. Returns
    every candidate evaluated and their metrics."""
    import optuna  # optional (fosmc_jax[peers]), imported here

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    space = tuner.space_of(p0)
    lo, hi = space.bounds()
    dists = {f"z{i:02d}": optuna.distributions.FloatDistribution(a, b) for i, (a, b) in enumerate(zip(lo, hi))}
    sampler = optuna.samplers.NSGAIISampler(population_size=popsize, seed=seed)
    study = optuna.create_study(directions=["minimize", "minimize"], sampler=sampler)

    def ask():
        trials = [study.ask(dists) for _ in range(popsize)]
        return np.array([[t.params[k] for k in dists] for t in trials]), trials

    def tell(trials, m):
        for t, f in zip(trials, objectives(m)):
            study.tell(t, f.tolist())

    return _generations(problem, p0, budget, popsize, ask, tell, "nsga2 (optuna)", log)
