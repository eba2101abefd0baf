"""Pareto fronts of tracking error against chattering (``fosmc front``).

A front is found within a wall-time budget by a derivative-free search on the training
problem, then (with a training surrogate) rounds on the plain problem, then gradient steps. The
search is pymoo's NSGA-II by default (``Settings.search`` "nsga2", :func:`_nsga2`: generations
of ``population`` over the box below until the search's time is spent), or the staged search
("staged"), in three stages (1-3 below). Given the staged search's time, NSGA-II found the
better front at 60 s on realistic_arm and unseen_arm, three seeds each (docs/tuning.md "The search").

The staged search and the plain rounds, over log10 factors z
that scale the start's parameters per joint (:func:`from_factors`) within the box of the controller
kind's :class:`fosmc_jax._search.tune.Space`: for the FOSMC z (9,) scales delta x 10^[-3, 3],
gamma x 10^[-2.5, 1], poles x 10^[0, 3]; for SMC z (6,) scales k x
10^[-2, 2], phi x 10^[-3, 2]; for super-twisting z (6,) scales k1 x 10^[-2, 2], k2 x 10^[-2, 3].

1. global: the start, a log grid of factors common to the joints (g per axis, g^k points for
   k parameters: the good controllers lie near this k-D family), and per-joint log-uniform
   draws for the rest (:func:`global_factors`);
2. CMA-ES: pycma runs from points along the global stage's front, each on the weighted log
   objective at the front's slope there (:func:`cma_stage`), ``cma_share`` of the search:
   CMA-ES adapts its steps to the problem's scaling and finds per-joint trade-offs that
   random local steps miss (tuning/README.md);
3. local: rounds of one chunk each; a round draws ``points`` parents at random from the
   non-dominated set of everything evaluated so far and perturbs a random subset of their
   factors, per joint or common to the joints, by sigma (hi - lo) N(0, 1), clipped to the box,
   sigma shrinking geometrically over the rounds (:func:`local_factors`);
4. plain (with a training surrogate only): the points non-dominated on the training metrics
   are re-evaluated on the plain problem, then ``polish_share`` of the search goes to local
   rounds on the plain problem from them, with smaller steps (``polish_sigma``): the
   surrogate ranks points like the plain problem but not to the last few percent of the
   trade-off (tuning/README.md).

Every evaluation is a vmapped chunk split over the local devices. The front is the
non-dominated set in (mean ``rms_error``, mean ``chattering_hf``), sorted by chattering, of
plain metrics: without a training surrogate (``[tune] train_t_final``, ``train_dt``) the
training metrics are the plain ones; with one, only the plain metrics of stage 4 count.
With sizes from the budget (``candidates`` or ``steps`` not given) every stage runs until its
share of the search time is spent: one chunk is timed first (compiled, then warm; its
candidates join the global stage), which sizes the global stage; CMA-ES, the local rounds and
the plain rounds then run until their deadlines, and the last stage ends where the final
evaluations of the front it has found (the plain re-evaluation, the caller's held-out
evaluation) still fit before the run's deadline. A local or plain round's step shrinks with
the rounds run, over a horizon of rounds estimated from the timed chunk (not with the clock),
so that the work done is a list of counts: ``stages["replay"]`` records it (:class:`Plan`), and
:func:`replay_settings` turns it into settings that redo it without a clock, bit for bit on the
same machine and device count (``fosmc front --replay``). A budgeted run itself depends on the
machine's speed and load: the same seed gives another front when the stages get more or fewer
chunks done.

The checkpoint is written after every ``checkpoint_every`` units of work (chunks of the global
stage, CMA-ES or NSGA-II generations, whose algorithms' state is pickled whole, local or plain rounds; with a
budget at most every 10 s); a resumed run continues from it, so it ends where an
uninterrupted run of the same recorded work ends. The deadlines are stored as offsets from the
run's start, and a resumed run sets its start back by the time already spent, so it ends when
the uninterrupted run would have. With given sizes (``candidates`` and ``steps``; no CMA-ES or
plain rounds unless ``cma``, ``polish``) nothing depends on time: a resumed run ends where an
uninterrupted one does.
"""

from __future__ import annotations

import pickle
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.sharding import Mesh
from jax.sharding import PartitionSpec as Spec

from .._io import stamped
from .._simulator import sharding
from .._simulator.metrics import METRIC_NAMES, mean_over_survivors
from . import tune as tuner
from .pareto import nondominated

#: The two metrics a front is drawn in (means over rollouts and joints).
AXES = ("rms_error", "chattering_hf")
_FOSMC = tuner.SPACES["fosmc"]
#: Number of the FOSMC's log factors: delta, gamma, poles, one per joint each (a kind's: its Space's dim).
DIM = _FOSMC.dim


#: The derivative-free searches of a front (``Settings.search``).
SEARCHES = ("nsga2", "staged")
#: The problems the gradient steps may descend (``Settings.gradient_on``).
GRADIENT_ON = ("plain", "train")
#: With ``gradient_on = "train"``: the chunks of the steps' points evaluated on the plain problem
#: in a run without a clock (sized steps).
GRADIENT_PLAIN_CHUNKS = 4
#: With ``gradient_on = "train"`` and a clock: the most of the gradient stage's time that the
#: plain evaluation of the steps' points may take (the steps stop that much before the end, or
#: less where fewer points are to evaluate). 4 chunks bound every 300 s run (58-64 of 64 joined,
#: tuning/results/front_300s_gradient_on.md).
GRADIENT_PLAIN_SHARE = 0.5


class Plan(NamedTuple):
    """The work of a front run, all that its sizes from the budget decided (front.json's
    ``stages.replay``, with the seed and sizes): global candidates ``drawn`` (the size
    :func:`global_factors` was called with: its grid follows it) and ``evaluated`` (their
    first ones), whether the ``probe``'s chunk joined them, CMA-ES generations, local and plain
    rounds, the ``horizon`` in rounds over which each stage's sigma shrinks, the gradient steps
    and how many of their points the plain problem evaluated (with ``gradient_on = "train"``)."""

    drawn: int
    evaluated: int
    probe: bool
    cma_generations: int
    local_rounds: int
    local_horizon: int
    plain_rounds: int
    plain_horizon: int
    gradient_steps: int = 0
    nsga2_generations: int = 0
    gradient_plain: int = -1  # points of the steps evaluated on the plain problem; -1: GRADIENT_PLAIN_CHUNKS chunks


class Settings(NamedTuple):
    # the derivative-free search before the plain and gradient stages: "nsga2" (pymoo's NSGA-II,
    # :func:`_nsga2`), or "staged" (global stage, CMA-ES, local rounds: candidates, steps, cma);
    # NSGA-II, given the staged search's time, beat it at 60 s (docs/tuning.md "The search")
    search: str = "nsga2"
    population: int = 256  # NSGA-II's population
    generations: int = 0  # NSGA-II's generations; 0: from the budget
    points: int = 8  # parents per local round, drawn from the current front
    budget: float = 300.0  # s, wall time of the whole run (held-out evaluation and references included)
    candidates: int = 0  # global stage size; 0: from the budget
    steps: int = 0  # local rounds (one chunk each); 0: from the budget
    chunk: int = 16  # candidates per vmapped evaluation
    seed: int = 0
    # share of the search time spent on the global stage (candidates = 0); 0.15 rather than 0.3:
    # the time left to CMA-ES wins more of the front (tuning/README.md)
    global_share: float = 0.15
    grid_share: float = 1.0  # share of the global stage on the grid of common factors
    sigma: tuple[float, float] = (0.3, 0.01)  # local step, first and last round, in shares of each range
    checkpoint_every: int = 5  # local rounds between checkpoints
    # CMA-ES (pycma) after the global stage: cma_starts runs from points along its front, each on
    # the weighted log objective at the front's slope there, one generation of a chunk each;
    # generations (0: from the budget, cma_share of the search time; given sizes: none)
    cma: int = 0
    cma_share: float = 0.4
    cma_starts: int = 4
    cma_sigma: float = 0.1  # the first step, in shares of each range
    # with a training surrogate: rounds on the plain problem after the training's front is
    # re-evaluated (0: from the budget, polish_share of the search time; given sizes: none)
    polish: int = 0
    polish_share: float = 0.25
    polish_sigma: tuple[float, float] = (0.01, 0.003)  # the plain rounds' step, first and last
    # gradient steps at the end: the front's points refined by Adam on the weighted log objective
    # at the front's slope there, on the plain problem, ``chunk`` points at once (:func:`_gradient`);
    # steps (0: from the budget, gradient_share of the search time; given sizes: none); after
    # NSGA-II, 0.25 beat 0 at 300 s and lost to it at 60 s (docs/tuning.md "The search")
    gradient: int = 0
    gradient_share: float = 0.25
    gradient_rate: float = 0.01  # Adam's rate in log coordinates (fosmc tune's on a rough loop)
    # the problem the gradient steps descend: "plain", or "train" (with a training surrogate:
    # its cheaper gradient, the points the steps reach that are non-dominated among themselves
    # then evaluated on the plain problem; without one the two are the same); "train" lowered the
    # median gap 1.4-3.6x and raised the HV on three configs at 300 s, three seeds each
    # (tuning/results/front_300s_plain_share.md; docs/tuning.md "Gradients in the front")
    gradient_on: str = "train"
    plan: Plan | None = None  # the work to redo (a replay, replay_settings): no clock, sizes and rounds as recorded


def bounds(space: tuner.Space = _FOSMC) -> tuple[np.ndarray, np.ndarray]:
    """The search box of the log factors z (space.dim,): each parameter's range, three joints
    each (the FOSMC's: delta, gamma, poles)."""
    return space.bounds()


def from_factors(p0: tuner.Params, z: np.ndarray) -> tuner.Params:
    """Parameter sets (n,) of p0's kind from log10 factors z (n, 3 k): parameter i of joint j
    scaled by 10^z[:, 3 i + j] (the FOSMC's delta, gamma, poles: i = 0, 1, 2)."""
    z = np.atleast_2d(z)
    scale = lambda x, f: jnp.asarray(np.asarray(x)[None] * (10.0 ** f).reshape(f.shape + (1,) * (np.ndim(x) - 1)),
                                     jnp.asarray(x).dtype)  # fmt: skip
    return type(p0)(*(scale(x, z[:, 3 * i : 3 * i + 3]) for i, x in enumerate(p0)))


def to_factors(p0: tuner.Params, params: tuner.Params) -> np.ndarray:
    """The log10 factors z (n, 3 k) of parameter sets ``params`` (leading axis n) of p0's kind
    relative to p0: :func:`from_factors`' inverse (a parameter with several entries per joint,
    the FOSMC's poles, is read from its first)."""
    first = lambda x, n: np.asarray(x, float).reshape(n, 3, -1)[:, :, 0]
    n = len(np.asarray(params[0]))
    return np.concatenate([np.log10(first(x, n) / first(x0, 1)) for x, x0 in zip(params, p0)], axis=1)


def grid_factors(g: int, space: tuner.Space = _FOSMC) -> np.ndarray:
    """The g^k log factors (g^k, 3 k) of a grid of common factors (the same for every joint)
    over the k parameters of ``space``: g values per parameter, evenly spaced over its range,
    ends included."""
    k = len(space.params)
    ticks = [np.linspace(*p.box, g) for p in space.params]
    return np.repeat(np.stack(np.meshgrid(*ticks, indexing="ij"), -1).reshape(-1, k), 3, axis=1)


def global_factors(n: int, seed: int, grid_share: float = 0.5, space: tuner.Space = _FOSMC) -> np.ndarray:
    """``n`` log factors (n, space.dim): 0 (the start itself), then :func:`grid_factors` with
    g = floor((grid_share n)^(1/k)) for k parameters (no grid below n = 16), then per-joint
    log-uniform draws."""
    g = grid_size(n, grid_share, len(space.params))
    lo, hi = space.bounds()
    grid = grid_factors(g, space) if g else np.zeros((0, space.dim))
    draws = np.random.default_rng(seed).uniform(lo, hi, size=(n - 1 - len(grid), space.dim))
    return np.concatenate([np.zeros((1, space.dim)), grid, draws])


def grid_size(n: int, grid_share: float, k: int = 3) -> int:
    """Values per axis of the grid over k parameters in :func:`global_factors` of size n (0
    below n = 16)."""
    g = int((grid_share * n) ** (1 / k) + 1e-9) if n >= 16 else 0
    return g if 1 + g**k <= n or not g else g - 1


def local_factors(z: np.ndarray, m: dict, n: int, points: int, sigma: float, seed: int,
                  space: tuner.Space = _FOSMC) -> np.ndarray:  # fmt: skip
    """``n`` children (n, space.dim) of the front of the evaluated factors z with metrics m:
    up to ``points`` parents drawn without replacement from its non-dominated set, children in
    turn per parent, each its parent + a step sigma (hi - lo) N(0, 1), clipped to the box: for
    every other child per joint on every coordinate; for the others common to the joints, on
    a random subset of the parameters (each with probability 1/2, one at least), the same step
    for the three joints: these keep children in the family of common factors and on the
    faces of the box, where the grid of the global stage finds the ends of the front."""
    e, c = axes(m)
    idx = np.flatnonzero(nondominated(e, c))
    rng = np.random.default_rng(seed)
    parents = rng.choice(idx, size=min(points, len(idx)), replace=False)
    lo, hi = space.bounds()
    k = len(space.params)
    zp = z[parents[np.arange(n) % len(parents)]]
    joint = rng.standard_normal((n, space.dim))
    common = np.repeat(rng.standard_normal((n, k)) * _subset(rng, n, k, 1 / 2), 3, axis=1)
    step = np.where((np.arange(n) % 2 == 0)[:, None], joint, common)
    return np.clip(zp + sigma * (hi - lo) * step, lo, hi)


def _subset(rng: np.random.Generator, n: int, k: int, p: float) -> np.ndarray:
    """n random masks over k items, each item in with probability p, and one at least."""
    mask = rng.random((n, k)) < p
    mask[np.arange(n), rng.integers(0, k, n)] = True
    return mask


def sample_candidates(p0: tuner.Params, n: int, seed: int) -> tuner.Params:
    """``n`` parameter sets of p0's kind around p0 (:func:`global_factors` with a grid of about
    half). Leading axis n."""
    return from_factors(p0, global_factors(n, seed, 0.5, space=tuner.space_of(p0)))


class Evaluator:
    """Mean metrics of many parameter sets of one problem, in jitted, vmapped chunks split over
    every local device (on CPU one per core after :func:`fosmc_jax.use_all_cores`: the CLI's
    default), and over every process's devices in a run across processes
    (``jax.distributed``: each process holds every chunk, runs its devices' slice, and gets
    all the metrics back); candidates are independent, so the split changes no result. The
    object owns its compilation (one per chunk size): a second call reuses it; a fresh
    evaluator of the same problem pays it again (the studies' equal-cost comparisons)."""

    def __init__(self, problem: tuner.Problem):
        self.problem = problem
        self.devices = jax.device_count()  # every process's, in a run across processes
        self._run: Callable | None = None
        self._mesh: Mesh | None = None

    def compiled(self) -> Callable:
        """The jitted evaluation of a chunk (built on first use)."""
        if self._run is not None:
            return self._run
        mesh = self._mesh = Mesh(np.asarray(jax.devices()), ("candidates",))

        def one(p):
            r = self.problem.simulate(p, checkpoint_every=0)
            out = {name: mean_over_survivors(getattr(r.metrics, name), r.diverged) for name in METRIC_NAMES}
            return dict(out, diverged=jnp.sum(r.diverged))

        # shard_map, not sharded jit: XLA's partitioner would run the native kernel's custom call
        # (the linear plant's fast path) on every candidate on every device
        split = Spec("candidates")
        self._run = jax.jit(jax.shard_map(jax.vmap(one), mesh=mesh, in_specs=split, out_specs=split, check_vma=False))
        return self._run

    def __call__(self, params: tuner.Params, chunk: int, log: Callable[[str], None] = print, what: str = "evaluating",
                 deadline: float | None = None, command: str = "front",
                 each: Callable[[int, dict], None] | None = None) -> dict[str, np.ndarray]:  # fmt: skip
        """Mean metrics (over non-diverged rollouts) of every parameter set (leading axis n):
        {metric: (n, 3)} and ``diverged`` (n,) counts, in chunks of ``chunk``; with a
        ``deadline`` (a ``time.perf_counter()`` value) only the first chunks evaluated before it
        passes (one at least). Progress lines ``{command}: {what} i/n`` go to ``log``; after each
        chunk ``each(k, metrics of the first k)`` (a checkpoint's hook)."""
        n = jax.tree.leaves(params)[0].shape[0]
        run, devices = self.compiled(), self.devices
        padded = -(-chunk // devices) * devices  # the compiled size: a multiple of the devices
        parts, start, shown = [], time.perf_counter(), -np.inf
        for i in range(0, n, chunk):
            if parts and deadline is not None and sharding.first(time.perf_counter() > deadline):
                break
            part = jax.tree.map(lambda x, i=i: x[i : i + chunk], params)
            size = jax.tree.leaves(part)[0].shape[0]
            if size < padded:  # pad to the compiled size
                part = jax.tree.map(lambda x, pad=padded - size: jnp.concatenate([x, jnp.repeat(x[-1:], pad, 0)]), part)
            if sharding.across_processes():  # every process holds the chunk; each runs its devices' slice
                part = sharding.spread(part, self._mesh, Spec("candidates"))
            parts.append(jax.tree.map(lambda x, size=size: x[:size], sharding.gathered(run(part))))
            if each is not None:
                each(min(i + chunk, n), {k: np.concatenate([p[k] for p in parts]) for k in parts[0]})
            now = time.perf_counter()
            if now - shown > 1.0 or i + chunk >= n:  # progress about once a second
                log(f"{command}: {what} {min(i + chunk, n)}/{n}  {now - start:7.1f} s")
                shown = now
        return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def evaluator(problem: tuner.Problem | Evaluator) -> Evaluator:
    """``problem``'s :class:`Evaluator` (an evaluator is returned as it is)."""
    return problem if isinstance(problem, Evaluator) else Evaluator(problem)


def evaluate_many(problem: tuner.Problem | Evaluator, params: tuner.Params, chunk: int,
                  log: Callable[[str], None] = print, what: str = "evaluating", deadline: float | None = None,
                  command: str = "front", each: Callable[[int, dict], None] | None = None
                  ) -> dict[str, np.ndarray]:  # fmt: skip
    """:class:`Evaluator`'s call: a problem is compiled afresh for this call, an evaluator reuses
    its compilation."""
    return evaluator(problem)(params, chunk, log=log, what=what, deadline=deadline, command=command, each=each)


def global_starts(problem: tuner.Problem, obj: tuner.Objective, p0: tuner.Params, n: int, k: int, *,
                  free: tuple[str, ...] | None = None, seed: int = 0, chunk: int = 16,
                  log: Callable[[str], None] = print, command: str = "tune",
                  deadline: float | None = None) -> tuple[tuner.Params, np.ndarray]:  # fmt: skip
    """The coarse global stage of ``fosmc tune``: ``n`` candidates of :func:`sample_candidates`
    (the parameters not in ``free`` kept at p0, None: all free; p0 itself among them) scored
    by ``obj`` on their batch-mean metrics; returns the best ``k`` (a leading axis, best first:
    the starts of :func:`fosmc_jax._search.tune.run_starts`) and their scores. Its progress lines
    start with ``command``. With a ``deadline`` (a ``time.perf_counter()`` value), only the
    candidates evaluated before it (one chunk at least)."""
    cands = sample_candidates(p0, n, seed)
    free = p0._fields if free is None else free
    cands = type(p0)(*(c if q in free else jnp.broadcast_to(x, c.shape) for q, c, x in zip(p0._fields, cands, p0)))
    m = evaluate_many(problem, cands, chunk, log=log, what="global stage", command=command, deadline=deadline)
    means = type("Means", (), {q: jnp.asarray(v) for q, v in m.items()})
    J = np.asarray(tuner.rollout_costs(means, jnp.asarray(m["diverged"] > 0), obj)[0])
    order = np.argsort(np.where(np.isnan(J), np.inf, J), kind="stable")[:k]  # NaN last, as nanargmin
    return jax.tree.map(lambda x: x[order], cands), J[order]


def global_stage(problem: tuner.Problem, obj: tuner.Objective, p0: tuner.Params, n: int,
                 **options) -> tuple[tuner.Params, float]:  # fmt: skip
    """The best of :func:`global_starts` (its ``options``) and its score."""
    best, scores = global_starts(problem, obj, p0, n, 1, **options)
    return jax.tree.map(lambda x: x[0], best), float(scores[0])


def axes(m: dict) -> tuple[np.ndarray, np.ndarray]:
    """The two axes of evaluated points, NaN (never non-dominated) where some rollout diverged:
    such a point's metrics are means over the rollouts that survived (unless every point has a
    diverged rollout)."""
    e, c = np.mean(m[AXES[0]], axis=-1), np.mean(m[AXES[1]], axis=-1)
    bad = np.asarray(m.get("diverged", np.zeros(e.shape))) > 0
    return (e, c) if bad.all() else (np.where(bad, np.nan, e), np.where(bad, np.nan, c))


def front_size(m: dict) -> int:
    """The number of non-dominated points among evaluated metrics m."""
    return int(nondominated(*axes(m)).sum())


def pick_starts(m: dict, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Up to ``k`` non-dominated points spread evenly by rank along the front, and the
    front's slope -d log E / d log C at each (weights of the log objective there)."""
    e, c = axes(m)
    idx = np.flatnonzero(nondominated(e, c))
    idx = idx[np.argsort(c[idx])]
    if len(idx) > k:
        idx = idx[np.unique(np.round(np.linspace(0, len(idx) - 1, k)).astype(int))]
    le, lc = np.log(e[idx]), np.log(c[idx])
    if len(idx) > 1:
        slope = -np.gradient(le, lc) if np.all(np.diff(lc) > 0) else np.ones(len(idx))
    else:
        slope = np.ones(1)
    return idx, np.clip(np.nan_to_num(slope, nan=1.0), 0.05, 20.0)


def cma_stage(problem: tuner.Problem | Evaluator, p0: tuner.Params, z: np.ndarray, m: dict, settings: Settings,
              generations: int, deadline: float | None, log: Callable[[str], None], *, resumed: bytes | None = None,
              start: int = 0, save: Callable[[int, np.ndarray, dict, bytes], None] | None = None
              ) -> tuple[np.ndarray, dict, int]:  # fmt: skip
    """``settings.cma_starts`` runs of pycma's CMA-ES (the reference implementation) from points
    spread along the front of the evaluated (z, m) (:func:`pick_starts`), run k minimising
    log E + w_k log C at the front's slope w_k there (the objective of the CMA-ES baseline,
    :func:`fosmc_jax._search.peers.cma_front`), steps ``cma_sigma`` of each range, within the box;
    each generation of every run is one vmapped evaluation. The runs draw from one random stream
    of their own (not NumPy's global one), so that their state is whole in a pickle: every
    ``settings.checkpoint_every`` generations (with a ``deadline``, at most every 10 s)
    ``save(g, z, m, state)`` gets the generations run, the evaluations so far and that pickle,
    and ``resumed`` (such a state, with ``start`` = its g and (z, m) as saved) continues from it
    as if never stopped. Returns (z, m) with every point evaluated appended and the generations
    run (fewer than ``generations`` when the ``deadline`` passes or every run has stopped)."""
    problem = evaluator(problem)  # compiled once for every generation
    import cma  # here, not at the top: importing pycma takes 1-2 s

    space = tuner.space_of(p0)
    lo, hi = space.bounds()
    if resumed is not None:
        runs, slopes = pickle.loads(resumed)
    else:
        starts, slopes = pick_starts(m, settings.cma_starts)
        rng = np.random.RandomState(settings.seed * 1_000_003 + 700_000)
        opts = lambda k: {"popsize": settings.chunk, "seed": settings.seed * 1_000_003 + 700_000 + k + 1,
                          "verbose": -9, "bounds": [list(lo), list(hi)], "CMA_stds": list(hi - lo),
                          "randn": rng.randn}  # fmt: skip
        runs = [cma.CMAEvolutionStrategy(z[i], settings.cma_sigma, opts(k)) for k, i in enumerate(starts)]
    t0 = shown = saved = time.perf_counter()
    for g in range(start, generations):
        live = [k for k, es in enumerate(runs) if not es.stop()]
        if not live or (deadline is not None and sharding.first(time.perf_counter() > deadline)):
            why = "every run met pycma's stop criteria" if not live else "the stage's time is spent"
            log(f"front: CMA-ES stopped after {g} generations: {why}")
            return z, m, g
        X = [np.asarray(runs[k].ask()) for k in live]
        mr = evaluate_many(problem, from_factors(p0, np.concatenate(X)), settings.chunk, log=lambda _: None)
        e, c = axes(mr)
        f = np.log(e) + np.repeat(slopes[live], settings.chunk) * np.log(c) + np.where(mr["diverged"] > 0, 1e3, 0.0)
        f = np.where(np.isfinite(f), f, 1e30).reshape(len(live), -1)
        for k, x, fk in zip(live, X, f):
            runs[k].tell(list(x), list(fk))
        z, m = np.concatenate([z, *X]), {k: np.concatenate([m[k], mr[k]]) for k in m}
        if deadline is None or time.perf_counter() - shown > 1.0:  # with a deadline, about once a second
            shown = time.perf_counter()
            total = f"/{generations}" if deadline is None else f" ({max(0.0, deadline - shown):.1f} s left)"
            log(f"front: CMA-ES generation {g + 1}{total}  best {np.round(f.min(axis=1), 3).tolist()}  "
                f"{int(nondominated(*axes(m)).sum())} non-dominated  {time.perf_counter() - t0:7.1f} s")  # fmt: skip
        every = settings.checkpoint_every
        due = save is not None and every and (g + 1) % every == 0
        if due and (deadline is None or time.perf_counter() - saved > 10):
            save(g + 1, z, m, pickle.dumps((runs, slopes)))
            saved = time.perf_counter()
    return z, m, generations


#: Added to both objectives of a candidate with a diverged rollout (NSGA-II), as the weighted
#: objectives of the CMA-ES stage and baseline add 1e3; a candidate whose every rollout
#: diverged (NaN metrics) scores this alone.
PENALTY = 1e3


def objectives(m: dict[str, np.ndarray]) -> np.ndarray:
    """The two objectives (n, 2) of NSGA-II from the metrics of :func:`evaluate_many`: log10 of
    mean ``rms_error`` and mean ``chattering_hf``, + :data:`PENALTY` for a candidate with a
    diverged rollout, :data:`PENALTY` where not finite."""
    f = np.log10(np.stack([np.mean(m[k], axis=-1) for k in AXES], -1))
    f = f + np.where(m["diverged"] > 0, PENALTY, 0.0)[:, None]
    return np.where(np.isfinite(f), f, PENALTY)


def nsga2_algorithm(space: tuner.Space, population: int, seed: int):
    """pymoo's NSGA-II with its defaults (uniform initial population, SBX crossover, polynomial
    mutation, rank and crowding survival) over the box of ``space``, set up for its ask/tell
    interface (:func:`nsga2_tell`); its random stream is its own (a pickle holds its whole
    state)."""
    from pymoo.algorithms.moo.nsga2 import NSGA2  # here, not at the top: importing pymoo takes about 1 s
    from pymoo.core.problem import Problem
    from pymoo.core.termination import NoTermination

    lo, hi = space.bounds()
    algorithm = NSGA2(pop_size=population)
    box = Problem(n_var=space.dim, n_obj=2, xl=lo, xu=hi)
    algorithm.setup(box, termination=NoTermination(), seed=seed, verbose=False)
    return algorithm


def nsga2_tell(algorithm, population, m: dict[str, np.ndarray]) -> None:
    """Tell pymoo's ``algorithm`` the metrics m of the ``population`` it asked for (their
    :func:`objectives`)."""
    from pymoo.core.evaluator import Evaluator as Told
    from pymoo.problems.static import StaticProblem

    Told().eval(StaticProblem(algorithm.problem, F=objectives(m)), population)
    algorithm.tell(infills=population)


class _Clock:
    """Stage deadlines of a run whose sizes come from the budget, as offsets (s) from its start
    (so that a resumed run keeps them: its start is set back by the time already spent); with
    given sizes, no deadlines."""

    def __init__(self, start: float, ends: dict[str, float] | None):
        self.start, self.ends = start, ends

    def end(self, stage: str) -> float | None:
        return None if self.ends is None else self.start + self.ends[stage]

    def elapsed(self) -> float:
        return time.perf_counter() - self.start


#: Seconds of search below which :func:`front_search` says that its budget is short (and names one that gives them).
MIN_SEARCH_S = 30.0


def _join(a: dict, b: dict) -> dict:
    """The evaluations ``b`` after ``a`` (``a`` empty: ``b``'s)."""
    return {k: np.concatenate([a[k], b[k]]) for k in b} if a else dict(b)


class _Run:
    """One front search as its stages see it (:func:`front_search`): the problems, the sizes
    (given, planned from the budget, or resumed from a checkpoint), the clock, and the
    evaluations so far (``z``, ``m``: log factors and metrics, with the counts that mark each
    stage's share), which each stage advances in turn."""

    def __init__(self, train, plain, p0, settings: Settings, checkpoint, resume, reserve_per_point, log, t0):
        self.settings, self.p0, self.log, self.t0 = settings, p0, log, t0
        self.checkpoint, self.reserve_per_point = checkpoint, reserve_per_point
        self.space = tuner.space_of(p0)
        state: dict[str, Any] = {}
        ckpt: dict[str, np.ndarray] = {}
        if resume and checkpoint is not None and checkpoint.exists():
            state, ckpt = tuner._load(checkpoint)
            if state.get("search", "staged") != settings.search:  # the other search's stages and state
                raise ValueError(f"the checkpoint {checkpoint} is of the {state.get('search', 'staged')} search, "
                                 f"not of {settings.search}: resume with that search, or start afresh")  # fmt: skip
            where = {
                "global": f"{len(ckpt['z'])} global candidates",
                "cma": f"CMA-ES generation {state.get('cma_round')}",
                "local": f"local round {state.get('round')}",
                "polish": f"plain round {state.get('polish_round')}",
                "gradient": "the start of the gradient steps",
                "nsga2": f"NSGA-II generation {state.get('nsga2_round')}",
            }
            log(f"front: resumed from {checkpoint} at {where[state['stage']]}")  # fmt: skip
        self.state, self.ckpt = state, ckpt
        self.gradient_program: tuple | None = None  # _gradient_program's, built on first use
        self.train, self.plain = evaluator(train), evaluator(plain)  # each compiled once for the whole run
        self.surrogate = not _same_simulation(self.train.problem, self.plain.problem)
        plan = self.plan = settings.plan
        sized = settings.generations if settings.search == "nsga2" else settings.candidates and settings.steps
        self.timed = plan is None and not sized
        self.n_cand = state.get("candidates", plan.drawn if plan else settings.candidates)
        self.rounds = state.get("steps", plan.local_rounds if plan else settings.steps)
        self.polish = state.get("polish", plan.plain_rounds if plan else settings.polish if self.surrogate else 0)
        self.generations = state.get("cma_generations", plan.cma_generations if plan else settings.cma)
        self.gradient_steps = state.get("gradient_steps", plan.gradient_steps if plan else settings.gradient)
        self.gradient_plain = plan.gradient_plain if plan else -1
        self.nsga2_generations = state.get("nsga2_generations",
                                           plan.nsga2_generations if plan else settings.generations)  # fmt: skip
        self.horizon = state.get("horizon", {"local": plan.local_horizon, "plain": plan.plain_horizon} if plan else {})
        self.probe = state.get("probe", plan.probe if plan else self.timed)
        self.costs = state.get("costs", {})  # s per chunk of the training and plain evaluations (the budget's plan)
        self.clock = _Clock(t0 - state.get("elapsed", 0.0), state.get("ends"))
        self.stage = state.get("stage", "global")
        self.keys = state.get("keys", ())
        self.z0 = ckpt.get("probe.z", np.zeros((0, self.space.dim)))
        self.m0 = {k: ckpt[f"probe.m.{k}"] for k in self.keys if "probe.z" in ckpt}
        self.n_global = state.get("global_end", 0)  # the global stage's evaluations (the probe's among them)
        self.n_cma = state.get("cma_end", 0)  # evaluations up to the end of the CMA-ES stage
        self.z = ckpt.get("z", np.zeros((0, self.space.dim)))
        self.m = {k: ckpt[f"m.{k}"] for k in self.keys}
        self.evaluated = state.get("global_evaluated", 0)  # the global stage's own candidates (not the probe's)

    def evaluate(self, problem, z: np.ndarray, chunk: int | None = None, **kw) -> dict:
        return evaluate_many(problem, from_factors(self.p0, z), chunk or self.settings.chunk, **kw)

    def save(self, stage: str, z: np.ndarray, m: dict, extra: dict | None = None, arrays: dict | None = None) -> None:
        if self.checkpoint is not None:
            header = {"stage": stage, "search": self.settings.search, "elapsed": self.clock.elapsed(),
                      "ends": self.clock.ends,
                      "candidates": self.n_cand, "global_end": self.n_global, "cma_end": self.n_cma,
                      "steps": self.rounds, "polish": self.polish, "keys": list(m),
                      "cma_generations": self.generations, "horizon": self.horizon, "probe": self.probe,
                      "costs": self.costs, "gradient_steps": self.gradient_steps,
                      "nsga2_generations": self.nsga2_generations, **(extra or {})}  # fmt: skip
            stored = {"z": z, **{f"m.{k}": v for k, v in m.items()}, **(arrays or {})}  # the evaluations so far
            if stage == "global" and self.m0:  # the probe's, which join the global stage at its end
                stored.update({"probe.z": self.z0, **{f"probe.m.{k}": v for k, v in self.m0.items()}})
            tuner._save(self.checkpoint, header, stored)

    def search_end(self) -> Callable[[int], float] | None:
        """The training search's deadline (local rounds or NSGA-II) for a front of n points: the
        local stage's end where plain rounds or gradient steps follow, else the run's end less
        the final evaluations (None: no clock)."""
        if self.clock.ends is None:
            return None
        if self.surrogate or self.gradient_steps:
            return lambda n: self.clock.end("local")
        return lambda n: self.finish_by("end", n)

    def finish_by(self, stage: str, n_points: int) -> float | None:
        """The deadline of the last stage: the run's end less the final evaluations of its front."""
        end = self.clock.end(stage)
        return None if end is None else end - n_points * self.reserve_per_point

    def rounds_horizon(self, which: str, n: int, end: float | None) -> int:
        """The rounds over which a stage's sigma shrinks: its rounds less one with given sizes;
        with a budget, the rounds its time holds at the probe's cost per chunk (a count, not
        the clock, so that a replay or a resumed run steps as the first run did)."""
        if which not in self.horizon:
            cost = self.costs.get("train" if which == "local" else "plain", 0.0)
            guess = sharding.first((end - time.perf_counter()) / cost) if end is not None and cost > 0 else n - 1
            self.horizon[which] = int(max(1, min(guess, n - 1)))
        return self.horizon[which]


def front_search(
    train: tuner.Problem | Evaluator,
    plain: tuner.Problem | Evaluator,
    p0: tuner.Params,
    settings: Settings,
    *,
    checkpoint: Path | None = None,
    resume: bool = False,
    deadline: float | None = None,
    reserve_per_point: float = 0.0,
    log: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Find the front (see module docstring). With sizes from the budget (``settings.candidates``
    or ``settings.steps`` 0, no ``settings.plan``) the run returns by ``deadline`` (a
    ``time.perf_counter()`` value; None: ``settings.budget`` from now), leaving
    ``reserve_per_point`` seconds per front point for what follows (the caller's held-out
    evaluation). Returns {"fosmc_jax": versions, "axes", "points": [...], "stages": {...}}
    (``fosmc_jax._io.stamped``: front.json's head) with every point's parameters, plain mean
    metrics and diverged count; non-dominated only, sorted by chattering; ``stages["replay"]``
    holds the work done (:func:`replay_settings` makes the settings that redo it, bit for bit).
    The search space is that of ``p0``'s controller kind (:func:`fosmc_jax._search.tune.space_of`).

    ``checkpoint``: written after every ``settings.checkpoint_every`` units of work (chunks of
    the global stage, CMA-ES generations, local or plain rounds; with a budget, at most every
    10 s); ``resume`` continues from it where it was written (a fresh run otherwise).

    The stages, each over the run's state (:class:`_Run`): :func:`_probe_and_plan`,
    :func:`_global`, :func:`_cma`, :func:`_local` (``settings.search`` "staged") or :func:`_nsga2`
    ("nsga2"), :func:`_plain`, :func:`_gradient`, :func:`_result`."""
    if settings.search not in SEARCHES:
        raise ValueError(f"search: expected one of {', '.join(SEARCHES)}, got {settings.search!r}")
    if settings.gradient_on not in GRADIENT_ON:
        raise ValueError(f"gradient_on: expected one of {', '.join(GRADIENT_ON)}, got {settings.gradient_on!r}")
    staged_sizes = [k for k in ("candidates", "steps", "cma") if getattr(settings, k)]
    if settings.search == "nsga2" and staged_sizes:
        raise ValueError(f"{', '.join(staged_sizes)}: sizes of the staged search (search='staged'); NSGA-II's is "
                         "generations")  # fmt: skip
    run = _Run(train, plain, p0, settings, checkpoint, resume, reserve_per_point, log, time.perf_counter())
    _probe_and_plan(run, deadline)
    if settings.search == "nsga2":
        if run.stage in ("global", "nsga2"):
            _nsga2(run)
    else:
        if run.stage == "global":
            _global(run)
        if run.stage == "cma":
            _cma(run)
        if run.stage == "local":
            _local(run)
    n_train = len(run.z)
    # the points of (zp, mp) among the training evaluations (-1: a plain round's, -2: a gradient step's)
    idx, zp, mp = np.arange(n_train), run.z, run.m
    if run.stage == "gradient":  # resumed in the gradient stage: the front it started from
        idx, zp = run.ckpt["gradient.idx"], run.ckpt["gradient.z"]
        mp = {k: run.ckpt[f"gradient.m.{k}"] for k in run.keys}
    elif run.surrogate:  # plain metrics of the points non-dominated on the training metrics, then plain rounds
        idx, zp, mp = _plain(run)
    if run.gradient_steps:
        idx, zp, mp = _gradient(run, idx, zp, mp)
    return _result(run, zp, mp, idx, n_train)


def _probe_and_plan(run: _Run, deadline: float | None) -> None:
    """A fresh run's probe, one chunk of the training evaluation kept as candidates (timed with
    a budget: compiled, then warm); with a budget, the stages' deadlines and the sizes they
    hold planned from its cost."""
    settings, state = run.settings, run.state
    if run.probe and not state:
        run.z0 = global_factors(settings.chunk, settings.seed + 1, space=run.space)
        t = time.perf_counter()
        run.m0 = run.evaluate(run.train, run.z0, log=lambda _: None)
    if not (run.timed and not state):
        return
    compile_s = time.perf_counter() - t
    t = time.perf_counter()
    run.m0 = run.evaluate(run.train, run.z0, log=lambda _: None)
    costs = run.costs
    costs["train"] = sharding.first(time.perf_counter() - t)  # process 0's clock: the plan is the same everywhere
    plain_point_s = 0.0  # a plain evaluation's cost per point (the surrogate's front is re-evaluated)
    if run.surrogate:  # the plain evaluator compiled now (its cost known before the search is planned)
        for _ in range(2):
            t = time.perf_counter()
            run.evaluate(run.plain, run.z0, log=lambda _: None)
        costs["plain"] = sharding.first(time.perf_counter() - t)
        plain_point_s = costs["plain"] / settings.chunk
    if settings.gradient_share and not settings.gradient:  # the gradient steps compiled now, and a step timed
        step, update, init = _gradient_program(run)
        Y, W = jnp.asarray(np.log(10.0) * run.z0), jnp.ones(len(run.z0))
        for _ in range(2):
            t = time.perf_counter()
            (_, _), g = jax.block_until_ready(step(Y, W))
            jax.block_until_ready(update(Y, init(Y), g))
        costs["gradient"] = sharding.first(time.perf_counter() - t)
    end = settings.budget if deadline is None else deadline - run.t0
    # the search's time, less the final evaluations of a front of a few hundred points
    # once, and at most the end: the stages' ends must not pass the run's (local = now + search <= end),
    # also where compiling took the whole budget (a loaded machine)
    elapsed, end = sharding.first(run.clock.elapsed()), sharding.first(float(end))
    now = min(elapsed, end)
    final = 300 * (run.reserve_per_point + plain_point_s)
    search = max(0.0, end - now - final)
    staged = settings.search == "staged"  # NSGA-II has the global and CMA-ES stages' time too
    shares = (settings.global_share, settings.cma_share) if staged else (0.0, 0.0)
    ends = {"global": now + shares[0] * search}
    ends["cma"] = ends["global"] + (shares[1] * search if not settings.cma else 0.0)
    ends["local"] = now + (1 - (settings.polish_share if run.surrogate else 0.0)) * search
    ends["plain"] = ends["end"] = end  # less the final evaluations of the front found (see finish_by)
    if settings.gradient_share and not settings.gradient:
        # the gradient steps take the search's last share from the local and plain rounds' time
        rest = max(1e-9, 1 - sum(shares))
        tail = min(settings.gradient_share, rest) * search
        ends["local"] = ends["cma"] + (ends["local"] - ends["cma"]) * (1 - tail / (rest * search + 1e-12))
        ends["plain"] = now + search - tail
        ends["gradient"] = end
        run.gradient_steps = 10**9
    run.clock = _Clock(run.clock.start, ends)
    if staged:
        run.n_cand = run.n_cand or max(1, int(settings.global_share * search / costs["train"])) * settings.chunk
        run.generations = run.generations or 10**9
        run.rounds = run.rounds or 10**9
        stages = f"{run.n_cand} global candidates, then CMA-ES, local rounds"
    else:
        run.nsga2_generations = run.nsga2_generations or 10**9
        stages = f"NSGA-II generations of {settings.population}"
    run.polish = run.polish or (10**9 if run.surrogate and settings.polish_share else 0)
    run.log(f"front: one chunk of {settings.chunk} costs {costs['train']:.3f} s (compilation "
            f"{compile_s - costs['train']:.1f} s): {search:.0f} s of search: {stages}"
            f"{' and plain rounds' if run.surrogate else ''}"
            + (f", gradient steps ({costs['gradient']:.3f} s each)" if "gradient" in costs else "")
            + " until their shares of it are spent")  # fmt: skip
    if search < MIN_SEARCH_S:  # the budget before the search (the caller's share too) and after it
        serve = settings.budget - end + elapsed + final + MIN_SEARCH_S
        run.log(f"front: warning: --budget {settings.budget:g} s leaves {search:.1f} s of search after "
                f"{settings.budget - end + elapsed:.1f} s of set-up (compilation, timing) and {final:.1f} s kept for "
                f"the final evaluations: each stage runs one chunk at least, so the run may end late; a budget of "
                f"{np.ceil(serve):.0f} s or more leaves {MIN_SEARCH_S:.0f} s")  # fmt: skip


def _global(run: _Run) -> None:
    """The global stage: candidates drawn over the box (the grid of common factors first),
    evaluated in chunks until they are done or the stage's time is spent; the probe's join them."""
    settings, z, m = run.settings, run.z, run.m
    zg = global_factors(run.n_cand, settings.seed, settings.grid_share, run.space)
    limit, done = (run.plan.evaluated if run.plan else run.n_cand), len(z)
    end = None if run.plan or settings.candidates else run.clock.end("global")
    saved = [time.perf_counter(), 0]

    def partial(k: int, mk: dict) -> None:  # a checkpoint every checkpoint_every chunks (timed: 10 s at least)
        chunks = -(-k // settings.chunk)
        every = settings.checkpoint_every
        if every and chunks - saved[1] >= every and (end is None or time.perf_counter() - saved[0] > 10):
            run.save("global", np.concatenate([z, zg[done : done + k]]), _join(m, mk))
            saved[:] = [time.perf_counter(), chunks]

    if done < limit and not (done and end is not None and sharding.first(time.perf_counter() > end)):
        mg = run.evaluate(run.train, zg[done:limit], log=run.log, what="global stage", deadline=end, each=partial)
        z, m = np.concatenate([z, zg[done : done + len(mg["diverged"])]]), _join(m, mg)
    run.evaluated = len(z)
    run.z, run.m = np.concatenate([z, run.z0]), _join(m, run.m0) if run.m0 else m
    run.n_global = len(run.z)
    run.stage = "cma"
    run.save("cma", run.z, run.m, {"cma_round": 0, "global_evaluated": run.evaluated})
    run.log(f"front: global stage done, {int(nondominated(*axes(run.m)).sum())} non-dominated of {len(run.z)}")


def _cma(run: _Run) -> None:
    """The CMA-ES stage (:func:`cma_stage`), where it has generations to run."""
    g0 = run.state.get("cma_round", 0) if run.state.get("stage") == "cma" else 0
    blob = bytes(run.ckpt["cma.state"]) if g0 and "cma.state" in run.ckpt else None
    if run.generations:
        save_cma = lambda g, z, m, b: run.save("cma", z, m, {"cma_round": g, "global_evaluated": run.evaluated},
                                               {"cma.state": np.frombuffer(b, np.uint8)})  # fmt: skip
        run.z, run.m, run.generations = cma_stage(run.train, run.p0, run.z, run.m, run.settings, run.generations,
                                                  run.clock.end("cma"), run.log, resumed=blob, start=g0,
                                                  save=save_cma)  # fmt: skip
    run.n_cma, run.stage = len(run.z), "local"
    run.save("local", run.z, run.m, {"round": 0, "global_evaluated": run.evaluated})


def _local(run: _Run) -> None:
    """The local rounds on the training problem, around its front."""
    r0 = run.state.get("round", 0) if run.state.get("stage") == "local" else 0
    local_end = run.search_end()
    h = run.rounds_horizon("local", run.rounds, None if local_end is None else local_end(front_size(run.m)))
    at = {"global_evaluated": run.evaluated}
    save_local = lambda r, z_, m_: run.save("local", z_, m_, {"round": r, **at})
    run.z, run.m, run.rounds = _rounds_on(run, run.train, run.z, run.m, r0, run.rounds, run.settings.sigma,
                                          run.settings.seed * 1_000_003, local_end, "local", save_local, h)  # fmt: skip


def _nsga2(run: _Run) -> None:
    """The NSGA-II stage (``settings.search`` "nsga2", in place of the global, CMA-ES and local
    stages): pymoo's NSGA-II (:func:`nsga2_algorithm`, population ``settings.population``, the
    run's seed) on :func:`objectives` of the training metrics, one generation evaluated per
    ask in one call (one compilation of the population's size), generations until the stage's
    time is spent (or as many as given or recorded); the probe's chunk and every candidate join
    the evaluations. The algorithm's state is pickled
    into the checkpoint every ``checkpoint_every`` generations (with a budget, at most every
    10 s) and at the stage's end: a resumed run asks for the same generations as an
    uninterrupted one."""
    settings, log = run.settings, run.log
    lo, hi = run.space.bounds()
    if run.stage == "nsga2" and "nsga2.state" in run.ckpt:
        g0, algorithm = run.state["nsga2_round"], pickle.loads(bytes(run.ckpt["nsga2.state"]))
    else:
        g0, algorithm = 0, nsga2_algorithm(run.space, settings.population, settings.seed)
        run.z, run.m = run.z0, dict(run.m0)  # the probe's chunk
        run.n_global = run.n_cma = len(run.z)
    run.stage = "nsga2"
    n = run.nsga2_generations
    end = run.search_end()
    save = lambda g: run.save("nsga2", run.z, run.m, {"nsga2_round": g},
                              {"nsga2.state": np.frombuffer(pickle.dumps(algorithm), np.uint8)})  # fmt: skip
    t0 = shown = saved = time.perf_counter()
    front_n, saved_at = front_size(run.m) if run.m else 0, g0
    for g in range(g0, n):
        if g and end is not None and sharding.first(time.perf_counter() > end(front_n)):
            log(f"front: NSGA-II stopped after {g} generations: the stage's time is spent")
            n = g
            break
        asked = algorithm.ask()
        X = np.clip(asked.get("X"), lo, hi)
        # the whole generation in one call, as the NSGA-II peers evaluate theirs (fosmc_jax._search.peers):
        # on realistic_arm 1.5x fewer seconds a candidate than chunks of 16, the same metrics to the bit
        mg = run.evaluate(run.train, X, chunk=settings.population, log=lambda _: None)
        nsga2_tell(algorithm, asked, mg)
        run.z, run.m = np.concatenate([run.z, X]), _join(run.m, mg)
        if end is None or time.perf_counter() - shown > 1.0:
            shown, front_n = time.perf_counter(), front_size(run.m)
            total = f"/{n}" if end is None else f" ({max(0.0, end(front_n) - shown):.1f} s left)"
            log(f"front: NSGA-II generation {g + 1}{total}  {len(run.z)} evaluations  {front_n} non-dominated  "
                f"{time.perf_counter() - t0:7.1f} s")  # fmt: skip
        every = settings.checkpoint_every
        if every and (g + 1) % every == 0 and (end is None or time.perf_counter() - saved > 10):
            save(g + 1)
            saved, saved_at = time.perf_counter(), g + 1
    run.nsga2_generations = n
    if saved_at != n:
        save(n)
    run.stage = "searched"


def _plain(run: _Run) -> tuple[np.ndarray, np.ndarray, dict]:
    """With a training surrogate: the plain metrics of the points non-dominated on the training
    metrics, then plain rounds around their front. Returns (each point's index among the
    training evaluations, -1 for a plain round's; their log factors; their plain metrics)."""
    z, m, at = run.z, run.m, {"global_evaluated": run.evaluated}
    idx = np.flatnonzero(nondominated(*axes(m)))
    plain_state = lambda r, z_, m_: ({"polish_round": r, **at},
                                     {"plain.z": z_, **{f"plain.m.{k}": v for k, v in m_.items()}})  # fmt: skip
    if run.stage == "polish":
        p_run, zp = run.state["polish_round"], run.ckpt["plain.z"]
        mp = {k: run.ckpt[f"plain.m.{k}"] for k in run.keys}
    else:
        p_run, zp = 0, z[idx]
        mp = run.evaluate(run.plain, zp, log=run.log, what="plain evaluation")
        run.save("polish", z, m, *plain_state(0, zp, mp))
    plain_end = (
        None
        if run.clock.ends is None
        else ((lambda n: run.clock.end("plain")) if run.gradient_steps else (lambda n: run.finish_by("plain", n)))
    )
    h = run.rounds_horizon("plain", run.polish, None if plain_end is None else plain_end(front_size(mp)))
    save_plain = lambda r, z_, m_: run.save("polish", z, m, *plain_state(r, z_, m_))
    zp, mp, run.polish = _rounds_on(run, run.plain, zp, mp, p_run, run.polish, run.settings.polish_sigma,
                                    run.settings.seed * 1_000_003 + 500_000, plain_end, "plain", save_plain,
                                    h)  # fmt: skip
    return np.concatenate([idx, np.full(len(zp) - len(idx), -1)]), zp, mp


def scalarized(problem: tuner.Problem, p0: tuner.Params) -> Callable:
    """f(y, w) -> (log E + w log C, (E, C, diverged)) of one candidate: p0 scaled by the log
    factors z = y / ln 10 (:func:`from_factors`), E and C its means over rollouts and joints of
    :data:`AXES` on ``problem``; 1e3 with no gradient where a rollout diverged."""
    p0 = jax.tree.map(jnp.asarray, p0)

    def f(y, w):
        z = y / np.log(10.0)
        scale = lambda x, f: x * 10.0 ** f.reshape(f.shape + (1,) * (x.ndim - 1))
        p = type(p0)(*(scale(x, z[3 * i : 3 * i + 3]) for i, x in enumerate(p0)))
        r = problem.simulate(p, split=True)
        E, C = (jnp.mean(getattr(r.metrics, a)) for a in AXES)
        bad = jnp.any(r.diverged) | ~jnp.isfinite(E + C)
        return jnp.where(bad, jax.lax.stop_gradient(1e3), jnp.log(E) + w * jnp.log(C)), (E, C, bad)

    return f


def _gradient_program(run: _Run) -> tuple[Callable, Callable, Callable]:
    """The gradient stage's compiled functions, built once per run: ``step(Y, W)`` (the values,
    means and gradients of :func:`scalarized` on the problem of ``settings.gradient_on`` for a
    batch of candidates), ``update(Y, state,
    g)`` (Adam's step; a non-finite gradient's entries make no step) and ``init(Y)`` (Adam's
    states). The steps are not kept in the box the derivative-free stages sample: it is where
    they look, not a limit on the controller (the log factors keep every parameter's sign), and
    on the realistic preset the front's ends lie on its faces."""
    if run.gradient_program is None:
        opt = optax.chain(optax.clip_by_global_norm(1.0), optax.adam(run.settings.gradient_rate))

        @jax.jit
        def update(Y, state, g):
            g = jax.tree.map(lambda x: jnp.where(jnp.isfinite(x), x, 0.0), g)
            d, state = jax.vmap(opt.update)(g, state, Y)
            return Y + d, state

        problem = run.train.problem if run.settings.gradient_on == "train" else run.plain.problem
        step = jax.jit(jax.vmap(jax.value_and_grad(scalarized(problem, run.p0), has_aux=True)))
        run.gradient_program = step, update, jax.jit(jax.vmap(opt.init))
    return run.gradient_program


def _gradient(run: _Run, idx: np.ndarray, zp: np.ndarray, mp: dict) -> tuple[np.ndarray, np.ndarray, dict]:
    """Gradient steps on the plain front (``run.gradient_steps`` of them, or until the stage's
    time is spent): ``chunk`` points spread along it (:func:`pick_starts`), each minimising
    log E + w log C at the front's slope w there (:func:`scalarized`) by Adam in y = z ln 10
    (leaving the box where the descent leads), all at once: one ``vmap`` of the value and
    gradient per step (the generated adjoint folds the candidates into its lanes). The points
    the steps reach that join the front (by the steps' own means) are evaluated by the plain
    evaluator and added (index -2). With ``gradient_on = "train"`` and a training surrogate the
    steps descend the training problem, and the points they reach that are non-dominated among
    themselves (spread by chattering: as many as :data:`GRADIENT_PLAIN_SHARE` of the stage's time
    holds, or :data:`GRADIENT_PLAIN_CHUNKS` chunks without a clock) are evaluated on the plain
    problem and join by those metrics. A run killed during the stage
    resumes at its start."""
    settings, log = run.settings, run.log
    step, update, init = _gradient_program(run)
    if run.stage != "gradient":
        run.stage = "gradient"
        at = {"global_evaluated": run.evaluated}
        run.save("gradient", run.z, run.m, at, {"gradient.idx": idx, "gradient.z": zp,
                                                **{f"gradient.m.{k}": v for k, v in mp.items()}})  # fmt: skip
    sel, w = pick_starts(mp, settings.chunk)
    Y, W = jnp.asarray(np.log(10.0) * zp[sel]), jnp.asarray(w)
    state = init(Y)
    on_train = settings.gradient_on == "train" and run.surrogate
    end = None if run.clock.ends is None else run.finish_by("gradient", front_size(mp))
    # on the training problem with a clock, the steps stop where the plain evaluation of their
    # non-dominated points (at most GRADIENT_PLAIN_SHARE of the stage) would pass the end
    per_point = run.costs.get("plain", 0.0) / settings.chunk if on_train and end is not None else 0.0
    most = GRADIENT_PLAIN_SHARE * (end - time.perf_counter()) if per_point else 0.0
    ys, es, cs, shown, n = [], [], [], -np.inf, run.gradient_steps
    reached = (np.zeros(0), np.zeros(0))  # the steps' non-dominated (E, C) so far (a dominated point stays so)
    for k in range(n + 1):  # call k evaluates the points of step k (call 0: the starts)
        (_, (E, C, bad)), g = step(Y, W)
        if k:
            ys.append(np.asarray(Y)), es.append(np.where(bad, np.nan, E)), cs.append(np.asarray(C))
            if per_point:
                reached = tuple(np.concatenate([a, b]) for a, b in zip(reached, (es[-1], cs[-1])))
                reached = tuple(a[nondominated(*reached)] for a in reached)
        stop = end is not None and time.perf_counter() > end - min(most, len(reached[0]) * per_point)
        if k == n or (k and sharding.first(stop)):
            n = k
            break
        Y, state = update(Y, state, g)
        if time.perf_counter() - shown > 1.0:
            shown = time.perf_counter()
            log(f"front: gradient step {k + 1}  {len(sel)} points  "
                f"{time.perf_counter() - run.t0:7.1f} s")  # fmt: skip
    run.gradient_steps = n
    if not ys:
        return idx, zp, mp
    zg, eg, cg = np.concatenate(ys) / np.log(10.0), np.concatenate(es), np.concatenate(cs)
    if on_train:  # the steps' own non-dominated points, evaluated on the plain problem
        own = np.flatnonzero(nondominated(eg, cg))
        own = own[np.argsort(cg[own], kind="stable")]
        if per_point:  # as many as the time left holds, a chunk at least (as evaluate_many's deadline)
            cap = max(settings.chunk, int(sharding.first(max(0.0, end - time.perf_counter()) / per_point)))
        else:
            cap = run.gradient_plain if run.gradient_plain >= 0 else GRADIENT_PLAIN_CHUNKS * settings.chunk
        if len(own) > cap:
            own = own[np.round(np.linspace(0, len(own) - 1, cap)).astype(int)]
        run.gradient_plain = len(own)
        zg, mg = zg[own], run.evaluate(run.plain, zg[own], log=lambda _: None)
        bad = np.asarray(mg["diverged"]) > 0  # never joins, even where every one of them diverged
        eg, cg = (np.where(bad, np.nan, x) for x in axes(mg))
    e, c = axes(mp)
    joins = np.flatnonzero(nondominated(np.concatenate([e, eg]), np.concatenate([c, cg]))[len(e) :])
    log(f"front: gradient steps: {n} of {len(sel)} points, {len(joins)} of their {len(zg)} points join the front")
    if not len(joins):
        return idx, zp, mp
    if on_train:
        mg = {k: v[joins] for k, v in mg.items()}
    else:
        mg = run.evaluate(run.plain, zg[joins], log=lambda _: None)
    return np.concatenate([idx, np.full(len(joins), -2)]), np.concatenate([zp, zg[joins]]), _join(mp, mg)


def _rounds_on(run: _Run, problem, z, m, r0, n, sigma, seed, deadline, what, save_at, horizon):
    """Local rounds r0..n-1 on ``problem`` from the evaluated (z, m), until ``deadline()``
    (None: no deadline) passes, sigma from sigma[0] at round 0 to sigma[1] at round
    ``horizon`` and after; returns (z, m, rounds run). Parents are drawn from the
    front, kept as the rounds go (the non-dominated set of the old front and the round's
    children: a dominated point stays dominated). With a deadline, checkpoints are written
    at most every 10 s (a round can cost less than writing the archive)."""
    settings, log = run.settings, run.log
    (s0, s1), shown, saved = sigma, -np.inf, time.perf_counter()
    keep = nondominated(*axes(m))
    fz, fm = z[keep], {k: v[keep] for k, v in m.items()}
    zs, ms = [z], [m]
    for r in range(r0, n):
        now, end = time.perf_counter(), None if deadline is None else deadline(len(fz))
        if end is not None and sharding.first(now > end):
            log(f"front: {what} rounds: {r} run, the stage's time is spent")
            n = r
            break
        sig = s0 * (s1 / s0) ** min(r / horizon, 1.0)
        zr = local_factors(fz, fm, settings.chunk, settings.points, sig, seed + r, run.space)
        mr = run.evaluate(problem, zr, log=lambda _: None)
        zs.append(zr)
        ms.append(mr)
        fz, fm = np.concatenate([fz, zr]), _join(fm, mr)
        keep = nondominated(*axes(fm))
        fz, fm = fz[keep], {k: v[keep] for k, v in fm.items()}
        if end is None or time.perf_counter() - shown > 1.0:
            shown = time.perf_counter()
            total = f"/{n}" if end is None else f" ({max(0.0, end - shown):.1f} s left)"
            log(f"front: {what} round {r + 1}{total}  sigma {sig:.4f}  {len(fz)} non-dominated  "
                f"{time.perf_counter() - run.t0:7.1f} s")  # fmt: skip
        due = settings.checkpoint_every and ((r + 1) % settings.checkpoint_every == 0 or r + 1 == n)
        if due and (end is None or time.perf_counter() - saved > 10.0):
            z, m = np.concatenate(zs), {k: np.concatenate([x[k] for x in ms]) for k in m}
            zs, ms = [z], [m]
            save_at(r + 1, z, m)
            saved = time.perf_counter()
    return np.concatenate(zs), {k: np.concatenate([x[k] for x in ms]) for k in m}, n


def _result(run: _Run, zp: np.ndarray, mp: dict, idx: np.ndarray, n_train: int) -> dict[str, Any]:
    """front.json's head: the front's points (non-dominated, sorted by chattering, no repeats)
    and the stages' counts, with the work done (``stages["replay"]``)."""
    settings, clock = run.settings, run.clock
    if clock.ends is not None:
        left = clock.end("end") - time.perf_counter()
        run.log(f"front: the search ends {left:.1f} s before the run's deadline, kept for the final evaluations "
                f"({run.reserve_per_point * 1e3:.1f} ms per point)" if left >= 0 else
                f"front: the search ends {-left:.1f} s after the run's deadline: "
                + ("the budget is shorter than compilation and one chunk of each stage"
                   if clock.ends["local"] == clock.ends["global"] else "its last round ran past it"))  # fmt: skip
    generations = 0 if run.generations >= 10**9 else run.generations  # 10**9: the CMA-ES stage never started
    e, c = axes(mp)
    keep = np.flatnonzero(nondominated(e, c))
    keep = keep[np.unique(np.stack([c[keep], e[keep]], 1), axis=0, return_index=True)[1]]  # sorted, no repeats
    params = from_factors(run.p0, zp[keep])
    points = [point_of(jax.tree.map(lambda x, i=i: x[i], params), mp, j) for i, j in enumerate(keep)]
    work = Plan(drawn=run.n_cand, evaluated=run.evaluated, probe=bool(run.probe), cma_generations=generations,
                local_rounds=run.rounds, local_horizon=run.horizon.get("local", 1), plain_rounds=run.polish,
                plain_horizon=run.horizon.get("plain", 1), gradient_steps=run.gradient_steps,
                gradient_plain=run.gradient_plain,
                nsga2_generations=run.nsga2_generations if settings.search == "nsga2" else 0)  # fmt: skip
    n_global, n_cma = run.n_global, run.n_cma
    grid = grid_size(run.n_cand, settings.grid_share, len(run.space.params))
    stages = {"candidates": n_global, "grid_per_axis": grid,
              "cma_generations": generations,
              "local_rounds": run.rounds, "plain_rounds": run.polish, "evaluations": n_train,
              "plain_evaluations": len(zp) if run.surrogate else 0, "wall_time_s": time.perf_counter() - run.t0,
              "from_cma": int(np.sum((idx[keep] >= n_global) & (idx[keep] < n_cma))),
              # the points of the last derivative-free stage: the local rounds' or NSGA-II's
              "from_local" if settings.search == "staged" else "from_nsga2": int(np.sum(idx[keep] >= n_cma)),
              "search": settings.search, "nsga2_generations": work.nsga2_generations,
              "from_plain_rounds": int(np.sum(idx[keep] == -1)),
              "gradient_steps": run.gradient_steps, "from_gradient": int(np.sum(idx[keep] == -2)),
              "replay": {"seed": settings.seed, "points": settings.points, "chunk": settings.chunk,
                         "search": settings.search, "population": settings.population,
                         "gradient_rate": settings.gradient_rate, "gradient_on": settings.gradient_on,
                         **work._asdict()}}  # fmt: skip
    return stamped({"axes": list(AXES), "points": points, "stages": stages})


def replay_settings(stages: dict[str, Any]) -> Settings:
    """The settings that redo the work recorded in a front's ``stages`` (front.json's; its
    ``replay``): the same draws, stage sizes, rounds and steps, with no clock, so that
    :func:`run` on the same problems ends at the same front bit for bit (on the same machine
    and device count). A ``ValueError`` names what is missing from a front written before
    the work was recorded."""
    rec = stages.get("replay") if isinstance(stages, dict) else None
    if not isinstance(rec, dict) or set(Plan._fields) - set(Plan._field_defaults) - set(rec):
        raise ValueError("stages.replay: this front.json does not record its work (written by a fosmc_jax before "
                         "--replay existed): it cannot be replayed")  # fmt: skip
    plan = Plan(**{k: bool(rec[k]) if k == "probe" else int(rec[k]) for k in Plan._fields if k in rec})
    # a file without gradient_on was written when the steps descended the plain problem alone
    return Settings(points=int(rec["points"]), chunk=int(rec["chunk"]), seed=int(rec["seed"]),
                    search=str(rec.get("search", "staged")), population=int(rec.get("population", Settings.population)),
                    generations=plan.nsga2_generations,
                    candidates=plan.drawn, steps=plan.local_rounds, cma=plan.cma_generations,
                    polish=plan.plain_rounds, gradient=plan.gradient_steps,
                    gradient_rate=float(rec.get("gradient_rate", Settings.gradient_rate)),
                    gradient_on=str(rec.get("gradient_on", "plain")), plan=plan)  # fmt: skip


def _same_simulation(a: tuner.Problem, b: tuner.Problem) -> bool:
    """Whether two problems simulate the same thing (the training problem is no surrogate):
    rematerialisation and gradient truncation change derivatives, not values."""
    opts = lambda p: {k: v for k, v in p.options.items() if k not in ("checkpoint_every", "truncate_every")}
    return float(a.dt) == float(b.dt) and opts(a) == opts(b) and a.make is b.make and a.keys is b.keys


def point_of(p: tuner.Params, metrics: dict, i: int) -> dict[str, Any]:
    """A front point as JSON: parameters by name, per-joint mean metrics, diverged count."""
    return {"params": {k: np.asarray(v).tolist() for k, v in p._asdict().items()},
            "metrics": {name: np.asarray(metrics[name][i]).tolist() for name in METRIC_NAMES},
            "diverged": int(metrics["diverged"][i])}  # fmt: skip
