"""The closed-loop simulator: one rollout, a ``lax.scan`` in time; ``vmap`` outside.

Time stepping. Samples are t_k = k dt, k = 0..n. At each t_k the controller reads the plant's
X(t_k) and computes U_k, which is held over [t_k, t_{k+1}] (zero-order hold, as a digital
controller does). The plant state and the sliding surface's integral state
w = int_0^t (CA + CBK) Z dtau of (14) are integrated together over the step with a fixed-step
``euler`` or ``rk4`` scheme; the reference is evaluated at the scheme's stage times.

A plant is any pytree with methods ``init(X0) -> state``, ``observe(state) -> X (9,)`` and
``derivative(state, U) -> state'`` (see :class:`fosmc_jax.LinearPlant`). A reference is any
pytree callable ``ref(t) -> (4, 3)`` (see :class:`fosmc_jax.Cycloid`; wrap a plain function in
``jax.tree_util.Partial``).

Rollouts that blow up (a non-finite value, or |X| beyond ``divergence_bound``) are frozen at
their last finite state and flagged, so one bad rollout never spoils a batch.
"""

from __future__ import annotations

import functools
import operator
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from jax import Array

from . import _metrics
from ._controller import Controller, control_law, derive, safe_norm, safe_sqrt, sliding_surface, switch
from ._linear_plant import LinearPlant
from ._reference import desired_state, feedforward

INTEGRATORS = ("euler", "rk4")


class Trace(NamedTuple):
    """Decimated samples of a rollout, each with a leading time axis of length m."""

    t: Array  # (m,) s
    X: Array  # (m, 9) plant state [theta, theta', theta''] per joint
    X_d: Array  # (m, 9) desired state
    U: Array  # (m, 3) control, V
    s: Array  # (m, 3) sliding variable (14)


class Result(NamedTuple):
    """One rollout's outcome (leading batch axes when vmapped)."""

    metrics: _metrics.Metrics
    diverged: Array  # bool
    diverged_at: Array  # time (s) of the first bad step, +inf if none
    trace: Trace | None


class _Sample(NamedTuple):
    X: Array
    X_d: Array
    U: Array
    s: Array


class _Carry(NamedTuple):
    k: Array
    plant_state: Any
    w: Array
    sample: _Sample
    acc: _metrics.Accumulator
    diverged: Array
    diverged_at: Array


def _euler(f, t, y, dt):
    return jax.tree.map(lambda a, da: a + dt * da, y, f(t, y))


def _rk4(f, t, y, dt):
    axpy = lambda a, x, y: jax.tree.map(lambda xi, yi: yi + a * xi, x, y)
    k1 = f(t, y)
    k2 = f(t + dt / 2, axpy(dt / 2, k1, y))
    k3 = f(t + dt / 2, axpy(dt / 2, k2, y))
    k4 = f(t + dt, axpy(dt, k3, y))
    incr = jax.tree.map(lambda a, b, c, d: (a + 2 * b + 2 * c + d) / 6, k1, k2, k3, k4)
    return axpy(dt, incr, y)


_STEPPERS = {"euler": _euler, "rk4": _rk4}


def _guard(diverged, diverged_at, ok, t, old, fresh):
    """Freeze rollouts that have diverged or fail ``ok`` now: keep ``old`` there, ``fresh``
    elsewhere; returns (kept, diverged, time of the first failure)."""
    keep = diverged | ~ok
    kept = jax.tree.map(lambda a, b: jnp.where(keep, a, b), old, fresh)
    return kept, keep, jnp.where(~diverged & ~ok, t, diverged_at)


def _scan_steps(body, carry, steps: int):
    """``steps`` iterations of the scan ``body`` (none when 0)."""
    return carry if steps == 0 else jax.lax.scan(body, carry, None, length=steps)[0]


def _finite_and_bounded(tree, X, bound) -> Array:
    finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in jax.tree.leaves(tree)]))
    return finite & jnp.all(jnp.abs(X) <= bound)


_STATIC = ("n_steps", "integrator", "switching", "law", "save_every", "checkpoint_every")


@functools.partial(jax.jit, static_argnames=_STATIC)
def simulate(
    plant,
    controller: Controller,
    reference,
    X0: Array,
    dt: Array,
    *,
    n_steps: int,
    integrator: str = "rk4",
    switching: str = "ratio",
    law: str = "paper",
    save_every: int = 0,
    checkpoint_every: int = 0,
    divergence_bound: float = 1e6,
) -> Result:
    """Simulate one closed-loop rollout of the FOSMC (14), (23) on ``plant`` from X(0) = ``X0``.

    Args:
      plant: plant pytree (see module docstring), e.g. ``LinearPlant`` or ``Arm``.
      controller: :class:`Controller`.
      reference: pytree callable t -> (4, 3) desired angles and derivatives.
      X0: (9,) initial state [theta, theta', theta''] per joint.
      dt: step (s). The dtype of ``X0`` sets the precision of the run.
      n_steps: number of steps n; t_final = n dt. Static.
      integrator: ``euler`` or ``rk4``. Static.
      switching: ``sign``, ``ratio`` (28), ``sat`` or ``tanh``. Static.
      law: ``paper`` (23) or ``equivalent``. Static.
      save_every: keep every ``save_every``-th sample (and the last) in ``Result.trace``;
        0 keeps none. Static.
      checkpoint_every: for reverse-mode gradients, rematerialise blocks of this many steps
        (``jax.checkpoint``), so memory grows with n / checkpoint_every + checkpoint_every
        instead of n; 0 stores every step. Ignored when ``save_every`` is set. Static.
      divergence_bound: a rollout with some |X_i| above it is frozen and flagged.

    Returns:
      :class:`Result` with the metrics of :mod:`fosmc_jax._metrics`.
    """
    if integrator not in _STEPPERS:
        raise ValueError(f"integrator must be one of {INTEGRATORS}, got {integrator!r}")
    dtype = X0.dtype
    dt = jnp.asarray(dt, dtype)
    derived = derive(controller)
    theta = slice(0, 9, 3)

    def sample(plant_state, w, t) -> _Sample:
        ref = reference(t)
        X_d = desired_state(ref)
        Omega = feedforward(controller.a_rows, controller.b_rows, ref)
        X = plant.observe(plant_state)
        Z = X - X_d
        s = sliding_surface(controller, Z, w)
        U = control_law(controller, derived, Z, X_d, Omega, s, switching, law)
        return _Sample(X, X_d, U, s)

    def field(U):
        def f(t, y):
            plant_state, _ = y
            Z = plant.observe(plant_state) - desired_state(reference(t))
            return plant.derivative(plant_state, U), derived.S @ Z

        return f

    step = _STEPPERS[integrator]

    def body(c: _Carry, _) -> tuple[_Carry, None]:
        t = c.k.astype(dtype) * dt
        plant_state, w = step(field(c.sample.U), t, (c.plant_state, c.w), dt)
        k = c.k + 1
        new = sample(plant_state, w, k.astype(dtype) * dt)
        ok = _finite_and_bounded((plant_state, w, new), new.X, divergence_bound)
        acc = _metrics.add(c.acc, new.X[theta] - new.X_d[theta], new.U, c.sample.U)
        kept, diverged, diverged_at = _guard(
            c.diverged, c.diverged_at, ok, k.astype(dtype) * dt, (c.plant_state, c.w, c.sample, c.acc),
            (plant_state, w, new, acc),
        )  # fmt: skip
        return _Carry(k, *kept, diverged, diverged_at), None

    advance = functools.partial(_scan_steps, body)

    plant_state = plant.init(X0)
    w = jnp.zeros(3, dtype)
    first = sample(plant_state, w, jnp.zeros((), dtype))
    carry = _Carry(
        jnp.zeros((), jnp.int32),
        plant_state,
        w,
        first,
        _metrics.start(first.X[theta] - first.X_d[theta], first.U),
        ~_finite_and_bounded(first, first.X, divergence_bound),
        jnp.asarray(jnp.inf, dtype),
    )
    carry = carry._replace(diverged_at=jnp.where(carry.diverged, jnp.zeros((), dtype), carry.diverged_at))

    trace = None
    if save_every:
        blocks, rest = divmod(n_steps, save_every)

        def block(c, _):
            c = advance(c, save_every)
            return c, (c.k, c.sample)

        carry, (ks, samples) = jax.lax.scan(block, carry, None, length=blocks)
        carry = advance(carry, rest)
        stack = lambda head, body, tail: jnp.concatenate([head[None], body] + ([tail[None]] if rest else []))
        ks = stack(jnp.zeros((), jnp.int32), ks, carry.k)
        samples = jax.tree.map(stack, first, samples, carry.sample)
        trace = Trace(ks.astype(dtype) * dt, *samples)
    elif checkpoint_every:
        blocks, rest = divmod(n_steps, checkpoint_every)
        remat = jax.checkpoint(lambda c, _: (advance(c, checkpoint_every), None))
        carry = jax.lax.scan(remat, carry, None, length=blocks)[0]
        carry = advance(carry, rest)
    else:
        carry = advance(carry, n_steps)

    metrics = _metrics.finish(carry.acc, n_steps * dt)
    return Result(metrics, carry.diverged, carry.diverged_at, trace)


# ---------------------------------------------------------------------------- fast path
#
# The same closed loop for a batch of LinearPlants, written structure-of-arrays: the batch
# is the trailing (minor) axis of every array, and each matrix-vector product is written out
# row by row on (batch,) vectors with the matrix entries as scalars (or, for the plants, as
# (batch,) vectors). A step is then a few fused elementwise loops over the batch; ``vmap`` of
# :func:`simulate` instead makes (batch, 3, 9) x (batch, 9) dot_generals, one small kernel
# each. The reference, X_d, Omega and everything derived from the controller depend on t
# only: computed once per step for the whole batch. Only rows 3, 6, 9 of the plant carry
# dynamics. Same operations as :func:`simulate`, so the same results to rounding
# (tests/test_performance_paths.py).


def _rows(a: Array, lead: int = 1) -> Any:
    """The first ``lead`` axes of ``a`` unpacked into nested tuples."""
    if lead == 0:
        return a
    return tuple(_rows(a[i], lead - 1) for i in range(a.shape[0]))


def _mv(M: tuple, v: tuple) -> tuple:
    """M @ v for M given as rows of entries and v as a tuple of entries."""
    return tuple(functools.reduce(operator.add, (m * x for m, x in zip(row, v))) for row in M)


def _add(*vectors: tuple) -> tuple:
    return tuple(functools.reduce(operator.add, entries) for entries in zip(*vectors))


def _sub(a: tuple, b: tuple) -> tuple:
    return tuple(x - y for x, y in zip(a, b))


class _Batch(NamedTuple):
    k: Array
    x: tuple  # 9 entries (P, O): the plant state X
    w: tuple  # 3 entries (P, O): the integral state of (14)
    U: tuple  # 3 entries (P, O): the control held over the coming step
    acc: tuple  # per joint, an Accumulator with entries (P, O)
    diverged: Array  # (P, O)
    diverged_at: Array  # (P, O)


def _linear_batch(
    plants: LinearPlant,
    controller: Controller,
    reference,
    X0s: Array,
    dt: Array,
    *,
    n_steps: int,
    integrator: str = "rk4",
    switching: str = "ratio",
    law: str = "paper",
    checkpoint_every: int = 0,
    divergence_bound: float = 1e6,
) -> Result:
    """:func:`simulate_batch` without a trace for plants (P,) of :class:`LinearPlant` and
    X0s (O, 9); results with a leading axis P * O, plant-major."""
    if integrator not in _STEPPERS:
        raise ValueError(f"integrator must be one of {INTEGRATORS}, got {integrator!r}")
    dtype = X0s.dtype
    dt = jnp.asarray(dt, dtype)
    P, O = plants.a_rows.shape[0], X0s.shape[0]
    derived = derive(controller)
    C, S, CB_inv, K = (_rows(m, 2) for m in (controller.C, derived.S, derived.CB_inv, derived.K))
    A = _rows(jnp.moveaxis(plants.a_rows, 0, -1)[..., None], 2)  # entries (P, 1)
    B = _rows(jnp.moveaxis(plants.b_rows, 0, -1)[..., None], 2)
    gamma, delta = _rows(controller.gamma), _rows(controller.delta)
    # XLA:CPU fuses each output separately and would recompute shared terms in each; an
    # optimization_barrier does not survive its pipeline, but a conditional's outputs are
    # always materialised: ``once`` runs ``fn`` under an always-true cond, so that every
    # stage's result is a (P, O) vector computed once per step.
    always = jnp.isfinite(dt)

    def once(fn):
        return lambda *args: jax.lax.cond(always, fn, fn, *args)

    def sample(x, w, t):
        ref = reference(t)
        X_d = desired_state(ref)
        Omega = feedforward(controller.a_rows, controller.b_rows, ref)
        rho_ref = gamma[1] * safe_norm(X_d) + gamma[2] * safe_norm(Omega)
        Z = _sub(x, _rows(X_d))
        s = _sub(_mv(C, Z), w)
        rho = gamma[0] * safe_sqrt(functools.reduce(operator.add, (z * z for z in Z))) + rho_ref
        f = tuple(rho * switch(si, di, switching) for si, di in zip(s, delta))
        U = _sub(_rows(Omega), _mv(CB_inv, f))
        if law == "equivalent":
            U = _add(U, _mv(K, Z))
        return U, s, tuple(x[i] - X_d[i] for i in (0, 3, 6))

    def field(U):
        def f(t, y):
            x, _ = y
            jerk = _add(_mv(A, x), _mv(B, U))
            dx = (x[1], x[2], jerk[0], x[4], x[5], jerk[1], x[7], x[8], jerk[2])
            return dx, _mv(S, _sub(x, _rows(desired_state(reference(t)))))

        return once(f)

    def ok_of(x, w, U, s):
        finite = functools.reduce(operator.and_, (jnp.isfinite(v) for v in x + w + U + s))
        return functools.reduce(operator.and_, (jnp.abs(v) <= divergence_bound for v in x), finite)

    step = _STEPPERS[integrator]

    def body(c: _Batch, _) -> tuple[_Batch, None]:
        t = c.k.astype(dtype) * dt
        x, w = once(lambda y: step(field(c.U), t, y, dt))((c.x, c.w))
        k = c.k + 1
        U, s, e = once(sample)(x, w, k.astype(dtype) * dt)
        ok = ok_of(x, w, U, s)
        acc = tuple(_metrics.add(a, ej, uj, pj) for a, ej, uj, pj in zip(c.acc, e, U, c.U))
        kept, diverged, diverged_at = _guard(
            c.diverged, c.diverged_at, ok, k.astype(dtype) * dt, (c.x, c.w, c.U, c.acc), (x, w, U, acc)
        )
        return _Batch(k, *kept, diverged, diverged_at), None

    advance = functools.partial(_scan_steps, body)

    x = tuple(jnp.broadcast_to(X0s[:, i], (P, O)) for i in range(9))
    w = (jnp.zeros((P, O), dtype),) * 3
    U, s, e = sample(x, w, jnp.zeros((), dtype))
    bad = ~ok_of(x, w, U, s)
    acc = tuple(_metrics.start(ej, uj) for ej, uj in zip(e, U))
    acc = tuple(a._replace(count=jnp.ones((P, O), dtype)) for a in acc)
    carry = _Batch(
        jnp.zeros((), jnp.int32),
        x,
        w,
        U,
        acc,
        bad,
        jnp.where(bad, jnp.zeros((), dtype), jnp.asarray(jnp.inf, dtype)),
    )
    if checkpoint_every:
        blocks, rest = divmod(n_steps, checkpoint_every)
        remat = jax.checkpoint(lambda c, _: (advance(c, checkpoint_every), None))
        carry = jax.lax.scan(remat, carry, None, length=blocks)[0]
        carry = advance(carry, rest)
    else:
        carry = advance(carry, n_steps)

    acc = jax.tree.map(lambda *joints: jnp.stack(joints, axis=-1), *carry.acc)
    acc = acc._replace(count=carry.acc[0].count[..., None])
    metrics = _metrics.finish(acc, n_steps * dt)
    flat = lambda a: a.reshape((P * O,) + a.shape[2:])
    return Result(jax.tree.map(flat, metrics), flat(carry.diverged), flat(carry.diverged_at), None)


@functools.partial(jax.jit, static_argnames=_STATIC + ("fast",))
def simulate_batch(
    plants, controller: Controller, reference, X0s: Array, dt: Array, *, fast: bool = True, **options
) -> Result:
    """Every plant in ``plants`` (leading axis P) crossed with every initial state in ``X0s``
    (O, 9): P x O rollouts of :func:`simulate`, returned flattened plant-major, shape (P*O, ...).
    ``options`` are :func:`simulate`'s keyword arguments.

    With ``fast`` (static), a batch of :class:`LinearPlant` without a trace (``save_every`` =
    0) runs a structure-of-arrays fast path with the same results to rounding; any other plant
    runs ``vmap`` of :func:`simulate`. The fast path speeds up large forward batches; under
    reverse-mode differentiation it compiles several times slower and runs slower than the
    ``vmap`` path, so gradient code (the tuner) passes ``fast=False``."""
    if fast and isinstance(plants, LinearPlant) and not options.get("save_every", 0):
        options = {k: v for k, v in options.items() if k != "save_every"}
        return _linear_batch(plants, controller, reference, X0s, dt, **options)
    one = functools.partial(simulate, **options)
    over_x0 = jax.vmap(one, in_axes=(None, None, None, 0, None))
    over_both = jax.vmap(over_x0, in_axes=(0, None, None, None, None))
    result = over_both(plants, controller, reference, X0s, dt)
    return jax.tree.map(lambda x: x.reshape((-1,) + x.shape[2:]), result)
