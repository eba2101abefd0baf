"""The closed-loop simulator's batches: :func:`simulate` (one rollout, :mod:`fosmc_jax._simulator.step`)
and :func:`simulate_batch`, which picks once the path that runs a batch (the kernel generated from
the step, else ``vmap`` of the one rollout), every input checked first
(:mod:`fosmc_jax._simulator.checks`).
"""

from __future__ import annotations

import functools
import inspect

import jax
import jax.numpy as jnp
from jax import Array

from .._plants.arm import without_idle_terms
from . import codegen as _codegen
from . import generated as _generated
from . import metrics as _metrics
from .checks import check_inputs
from .step import _STATIC, INTEGRATORS, Result, Trace, _simulate, as_controller, check_save_every, sample_steps

__all__ = ["INTEGRATORS", "PAIRINGS", "Result", "Trace", "simulate", "simulate_batch"]


#: How :func:`simulate_batch` combines plants and initial states: every plant with every
#: initial state, or the i-th plant with the i-th initial state (a Monte-Carlo sample).
PAIRINGS = ("cross", "paired")


@functools.partial(jax.jit, static_argnames=_STATIC + ("fast", "native", "pairing"))
def _simulate_batch(
    plants,
    controller,
    reference,
    X0s: Array,
    dt: Array,
    *,
    keys: Array | None = None,
    pairing: str = "cross",
    fast: bool = True,
    native: bool = True,
    **options,
) -> Result:
    """Every plant in ``plants`` (leading axis P) crossed with every initial state in ``X0s``
    (O, 9), and with every key in ``keys`` (R keys, e.g. ``jax.random.split(key, R)``; one
    noise realization each): P x O (x R) rollouts of :func:`simulate`, returned flattened in
    plant, offset, realization order, shape (P*O*R, ...). With ``pairing = "paired"``
    (static), the i-th plant runs from the i-th initial state only (P = O): P (x R) rollouts,
    a Monte-Carlo sample's. ``options`` are :func:`simulate`'s keyword arguments (``key`` too,
    when ``keys`` is None).

    With ``fast`` (static), batches run the kernel generated from their step wherever it prints
    (every plant and law of the package, a user's law or plant, the ideal loop or a
    :class:`fosmc_jax.DigitalLoop` with or without sensor noise, one key or R: the same draws as
    the ``vmap`` path's), forward and adjoint
    (:mod:`fosmc_jax._simulator.generated`, equal to the ``vmap`` path's to rounding, built on
    first use; a trace's samples taken between blocks of ``save_every`` steps); anything else
    runs ``vmap`` of :func:`simulate`, with one warning naming what kept it there.
    ``native=False`` (static) keeps the compiled kernels out: the ``vmap`` path (the benchmarks'
    baseline; ``FOSMC_JAX_GENERATED=0`` or ``FOSMC_JAX_NATIVE=0`` does the same for a whole
    process)."""
    ctrl = as_controller(controller, options.get("switching", "ratio"), options.get("law", "paper"))
    paired = pairing == "paired"
    if pairing not in PAIRINGS:
        raise ValueError(f"pairing: expected one of {', '.join(PAIRINGS)}, got {pairing!r}")
    if paired and jax.tree.leaves(plants)[0].shape[0] != X0s.shape[0]:
        raise ValueError(f"pairing = 'paired': expected as many initial states as plants "
                         f"({jax.tree.leaves(plants)[0].shape[0]}), got {X0s.shape[0]}")  # fmt: skip
    key = options.pop("key", None)
    if keys is None:
        keys = (jax.random.PRNGKey(0) if key is None else key)[None]
    # traced options are the paths' arguments: closed over, they would leak from the custom_jvp rules
    traced = (options.pop("divergence_bound", 1e6), options.pop("chattering_cutoff", _metrics.CHATTERING_CUTOFF))
    options.setdefault("integrator", "rk4")
    args = (plants, ctrl, reference, X0s, dt, keys, *(jnp.asarray(x, X0s.dtype) for x in traced))
    vmap = functools.partial(_vmap_batch, paired=paired, **options)
    if not (fast and native):
        return vmap(*args)
    return _generated_or(vmap, *args, paired=paired, **options)


def _vmap_batch(plants, ctrl, reference, X0s, dt, keys, bound, cutoff, *, paired: bool, **options) -> Result:
    """``vmap`` of :func:`simulate` over the plants, the initial states (crossed or ``paired``)
    and the keys: every batch runs here, and the fast paths' derivatives come from here where
    the generated kernel does not give them."""
    one = lambda plant, X0, key: _simulate(plant, ctrl, reference, X0, dt, key=key, divergence_bound=bound,
                                          chattering_cutoff=cutoff, **options)  # fmt: skip
    if paired:
        result = jax.vmap(jax.vmap(one, (None, None, 0)), (0, 0, None))(plants, X0s, keys)
    else:
        result = jax.vmap(jax.vmap(jax.vmap(one, (None, None, 0)), (None, 0, None)), (0, None, None))(plants, X0s, keys)
    lead = 2 if paired else 3
    return jax.tree.map(lambda x: x.reshape((-1,) + x.shape[lead:]), result)


def _generated_or(vmap, *args, paired: bool, n_steps: int, integrator: str, truncate_every: int = 0,
                  save_every: int = 0, **_) -> Result:  # fmt: skip
    """The generated kernel (forward and adjoint), else, where the model cannot be printed or
    its C++ not built, ``vmap(*args)`` with a warning naming why."""
    if _generated.mode() == "0":
        return vmap(*args)
    m = sample_steps(args[1])
    check_save_every(save_every, m)
    try:
        return _generated.simulate_batch(args, n_steps=n_steps, integrator=integrator, paired=paired,
                                         truncate_every=-(-truncate_every // m) * m, save_every=save_every)  # fmt: skip
    except (_codegen.Unsupported, OSError) as e:
        _generated.warn_unsupported(e)
        return vmap(*args)


@functools.cache
def option_names(batch: bool) -> tuple[str, ...]:
    """The keyword options :func:`simulate` (``batch`` False) or :func:`simulate_batch` (True)
    take: the keyword-only parameters of their jitted functions (the batch's own and, through
    its ``**options``, the single rollout's)."""
    names = []
    for f in (_simulate_batch, _simulate) if batch else (_simulate,):
        for p in inspect.signature(f).parameters.values():
            if p.kind is inspect.Parameter.KEYWORD_ONLY and p.name not in names:
                names.append(p.name)
    return tuple(names)


def _checked(jitted, batch: bool):
    """``jitted`` behind :func:`fosmc_jax._simulator.checks.check_inputs`: its inputs refused
    with a one-line error naming the field where wrong (shapes always, values where concrete),
    lists turned into arrays, the arm's zero terms left out; the jitted function's ``lower``
    and ``_cache_size`` kept."""

    def checked(plant, controller, reference, X0, dt, options):
        plant, controller, reference, X0, dt = check_inputs(
            plant, controller, reference, X0, dt, batch, options, option_names(batch)
        )
        plant = without_idle_terms(plant)  # the arm's zero friction and disturbance terms left out of the program
        return plant, controller, reference, X0, dt

    @functools.wraps(jitted)
    def run(plant, controller, reference, X0, dt, **options):
        return jitted(*checked(plant, controller, reference, X0, dt, options), **options)

    run.__name__ = run.__qualname__ = jitted.__name__.lstrip("_")
    # lower is the jitted function's own: the inputs as given (a compiled program is then called
    # with them, whose pytree the pruning of the arm's zero terms would change)
    run.lower, run._cache_size = jitted.lower, jitted._cache_size
    return run


simulate = _checked(_simulate, batch=False)
simulate_batch = _checked(_simulate_batch, batch=True)
