"""One closed-loop rollout: the step, written once, and its ``lax.scan`` in time (batches:
:mod:`fosmc_jax._simulator.rollout`).

Time stepping. Samples are t_k = k dt, k = 0..n. The controller runs at every m-th sample
(m = ``controller.sample_steps``, 1 by default): at t_k it reads the plant's X(t_k) and
returns the control applied over [t_k, t_{k+m}) (zero-order hold). Between its samples the
plant is integrated with a fixed-step ``euler`` or ``rk4`` scheme, together with the
controller's continuous-time state if it has one (the ideal FOSMC's integral of (14)); the
reference is evaluated at the scheme's stage times.

A controller is any pytree with the shape optax gives optimizers:
``init(X0, r0, key) -> state`` and ``update(state, Y, r, t) -> (U, state)``, called at each
controller sample with the measurement Y (9,), the reference sample r = reference(t) (4, 3)
and t; optionally ``derivative(state, X, r, t) -> state'`` (continuous-time state), and the
attributes ``sample_steps`` (static int m) and ``u_max`` ((3,) actuator limit, for the
``saturation_fraction`` metric). See :class:`fosmc_jax.FOSMC`, :class:`fosmc_jax.DiscreteFOSMC`
and :class:`fosmc_jax.DigitalLoop`. The FOSMC parameters :class:`fosmc_jax.FOSMCParams` alone
run as the paper's ideal loop.

A plant is any pytree with methods ``init(X0) -> state``, ``observe(state) -> X (9,)`` and
``derivative(state, U) -> state'`` (see :class:`fosmc_jax.LinearPlant`); a time-varying plant
(``time_varying = True``, :class:`fosmc_jax.Arm`) gets the time too: ``observe(state, t)``,
``derivative(state, U, t)`` at the samples' and the stages' times (:mod:`fosmc_jax._plants.base`). A reference is any
pytree callable ``ref(t) -> (4, 3)`` (see :class:`fosmc_jax.Cycloid`; wrap a plain function in
``jax.tree_util.Partial``).

Rollouts that blow up (a non-finite value, or |X| beyond ``divergence_bound``) are frozen at
their last finite state and flagged, so one bad rollout never spoils a batch.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from jax import Array

from .._controllers.base import ContinuousLaw, HasSlidingVariable, SampledLoop, check_controller
from .._controllers.fosmc import as_controller
from .._plants.base import check_plant, derivative_at, derivative_observed_at, observe_at, reuses_observation
from .._plants.reference import desired_state
from . import metrics as _metrics

INTEGRATORS = ("euler", "rk4")


class Trace(NamedTuple):
    """Decimated samples of a rollout, each with a leading time axis of length m."""

    t: Array  # (m,) s
    X: Array  # (m, 9) plant state [theta, theta', theta''] per joint
    X_d: Array  # (m, 9) desired state
    U: Array  # (m, 3) applied control, V
    s: Array  # (m, 3) sliding variable (14) at the last controller sample (NaN if the controller has none)


class Result(NamedTuple):
    """One rollout's outcome (a leading batch axis from :func:`simulate_batch`). A diverged
    rollout's ``metrics`` are NaN (its ``diverged`` flag and ``diverged_at`` say when); means
    over a batch leave it out: :meth:`mean`, :meth:`summary`."""

    metrics: _metrics.Metrics
    diverged: Array  # bool
    diverged_at: Array  # time (s) of the first bad step, +inf if none
    trace: Trace | None

    def mean(self) -> _metrics.Metrics:
        """Each metric's mean over the rollouts that did not diverge, per joint ((3,) each;
        NaN where all diverged); traceable, for losses: ``res.mean().rms_error.mean()``.
        ``res.survivors`` counts the rollouts it averages."""
        diverged = jnp.reshape(self.diverged, (-1,))
        return _metrics.Metrics(*(_metrics.mean_over_survivors(jnp.reshape(m, (-1, 3)), diverged)
                                  for m in self.metrics))  # fmt: skip

    @property
    def survivors(self) -> Array:
        """The number of rollouts that did not diverge."""
        return jnp.sum(~jnp.asarray(self.diverged, bool))

    def summary(self) -> dict:
        """Over the rollouts that did not diverge, per metric and joint: the mean, the max and
        the 5th, 50th and 95th percentiles, with the number left out (NumPy, for reports; what
        ``fosmc simulate`` prints)."""
        return _metrics.batch_summary(self.metrics, jnp.reshape(self.diverged, (-1,)))


#: The carries' fields through which a state's derivative flows to the next step (``truncate_every``).
_DYNAMIC = ("plant_state", "ctrl_state", "U", "X")


class _Carry(NamedTuple):
    k: Array
    plant_state: Any
    ctrl_state: Any
    U: Array  # the applied control held over the coming step
    X: Array | None  # the plant's observation now, for the coming step's first stage (None: not reused)
    acc: _metrics.Accumulator
    diverged: Array
    diverged_at: Array


def _euler(f, t, y, dt, k1=None):
    """y + dt f(t, y); ``k1``: f(t, y) where the caller has it (:func:`_rk4` the same)."""
    return jax.tree.map(lambda a, da: a + dt * da, y, f(t, y) if k1 is None else k1)


def _rk4(f, t, y, dt, k1=None):
    axpy = lambda a, x, y: jax.tree.map(lambda xi, yi: yi + a * xi, x, y)
    k1 = f(t, y) if k1 is None else k1
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


def _scan_steps(body, carry, steps: int, unroll: int = 1):
    """``steps`` iterations of the scan ``body`` (none when 0), ``unroll`` per loop trip."""
    return carry if steps == 0 else jax.lax.scan(body, carry, None, length=steps, unroll=min(unroll, steps))[0]


def _in_blocks(advance, carry, n_steps: int, detach, checkpoint_every: int = 0, truncate_every: int = 0):
    """``advance(carry, steps)`` over ``n_steps``, in blocks where the options ask for them.

    ``truncate_every``: blocks of that many steps, the dynamic state ``detach``-ed (its
    gradient stopped, the metric sums kept) at each block's start: the gradient flows
    through the closed loop over at most one block (truncated backpropagation through time;
    values unchanged). ``checkpoint_every``: blocks of that many steps (or the truncation's
    blocks) rematerialised with ``jax.checkpoint``."""
    block = truncate_every or checkpoint_every
    if not block or block >= n_steps:
        return advance(carry, n_steps)
    cut = detach if truncate_every else (lambda c: c)
    run = lambda c, _: (advance(cut(c), block), None)
    blocks, rest = divmod(n_steps, block)
    carry = jax.lax.scan(jax.checkpoint(run) if checkpoint_every else run, carry, None, length=blocks)[0]
    return advance(cut(carry), rest)


def _finite_and_bounded(tree, X, bound) -> Array:
    leaves = [x for x in jax.tree.leaves(tree) if jnp.issubdtype(x.dtype, jnp.inexact)]
    finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in leaves]))
    return finite & jnp.all(jnp.abs(X) <= bound)


def _sliding_variable(ctrl, state, dtype) -> Array:
    """The controller's sliding variable (:class:`HasSlidingVariable`), else NaN."""
    return ctrl.sliding_variable(state) if isinstance(ctrl, HasSlidingVariable) else jnp.full(3, jnp.nan, dtype)


def _u_max(ctrl) -> Array | None:
    """A sampled loop's actuator limit (:class:`SampledLoop`); None in the ideal loop."""
    return ctrl.u_max if isinstance(ctrl, SampledLoop) else None


def sample_steps(ctrl) -> int:
    """m: the simulation steps per controller sample (1 in the ideal loop)."""
    return ctrl.sample_steps if isinstance(ctrl, SampledLoop) else 1


def closed_loop_step(plant, ctrl, reference, dt: Array, integrator: str, divergence_bound, chattering_cutoff):
    """The closed loop's step, ``step(carry, sample) -> carry``: one step of ``integrator``
    over [t_k, t_k + dt) with the control held, then at t_{k+1} the observation, a controller
    sample when ``sample`` (static), the divergence guard and the metrics' update. The one
    source of the loop: :func:`simulate` scans it, and the generated kernels
    (:mod:`fosmc_jax._simulator.generated`) are printed from it."""
    u_max = _u_max(ctrl)
    flows = isinstance(ctrl, ContinuousLaw)
    dtype = dt.dtype
    a = _metrics.lowpass(dt, jnp.asarray(chattering_cutoff, dtype))
    theta = slice(0, 9, 3)
    stepper = _STEPPERS[integrator]
    reuse = reuses_observation(plant)

    def integrate(plant_state, ctrl_state, U, t, X):
        # the first stage from the carried observation X of (plant_state, t), where the plant
        # can use it (the arm: its closed-form accelerations once per step instead of twice)
        first = None if X is None else derivative_observed_at(plant, plant_state, X, U, t)
        if not flows:
            return stepper(lambda t, y: derivative_at(plant, y, U, t), t, plant_state, dt, first), ctrl_state

        def f(t, y):
            ps, cs = y
            X = observe_at(plant, ps, t)
            dps = derivative_observed_at(plant, ps, X, U, t) if reuse else derivative_at(plant, ps, U, t)
            return dps, ctrl.derivative(cs, X, reference(t), t)

        k1 = None if X is None else (first, ctrl.derivative(ctrl_state, X, reference(t), t))
        return stepper(f, t, (plant_state, ctrl_state), dt, k1)

    def step(c: _Carry, sample: bool) -> _Carry:
        plant_state, ctrl_state = integrate(c.plant_state, c.ctrl_state, c.U, c.k.astype(dtype) * dt, c.X)
        k = c.k + 1
        t = k.astype(dtype) * dt
        X = observe_at(plant, plant_state, t)
        r = reference(t)
        U = c.U
        if sample:
            U, ctrl_state = ctrl.update(ctrl_state, X, r, t)
        ok = _finite_and_bounded((plant_state, ctrl_state, X, U), X, divergence_bound)
        acc = _metrics.add(c.acc, X[theta] - r[0], U, c.U, a, u_max)
        (plant_state, ctrl_state, U, X, acc), diverged, diverged_at = _guard(
            c.diverged, c.diverged_at, ok, t, (c.plant_state, c.ctrl_state, c.U, c.X, c.acc),
            (plant_state, ctrl_state, U, X if reuse else None, acc),
        )  # fmt: skip
        return _Carry(k, plant_state, ctrl_state, U, X, acc, diverged, diverged_at)

    return step


def start(plant, ctrl, reference, X0: Array, key, divergence_bound) -> _Carry:
    """The carry at t = 0: the plant's state from X0, the controller's first sample, the
    metrics' first sample; flagged diverged (at 0) where any of it is not finite."""
    dtype = X0.dtype
    plant_state = plant.init(X0)
    X = observe_at(plant, plant_state, jnp.zeros((), dtype))
    r = reference(jnp.zeros((), dtype))
    ctrl_state = ctrl.init(X, r, key)
    U, ctrl_state = ctrl.update(ctrl_state, X, r, jnp.zeros((), dtype))
    bad = ~_finite_and_bounded((plant_state, ctrl_state, X, U), X, divergence_bound)
    return _Carry(
        jnp.zeros((), jnp.int32),
        plant_state,
        ctrl_state,
        U,
        X if reuses_observation(plant) else None,
        _metrics.start(X[0::3] - r[0], U, _u_max(ctrl)),
        bad,
        jnp.where(bad, jnp.zeros((), dtype), jnp.asarray(jnp.inf, dtype)),
    )


def start_batch(plants, ctrl, reference, X0s: Array, key, divergence_bound, paired: bool) -> _Carry:
    """:func:`start` of every plant (leading axis P) with every initial state (O, 9), plant-major,
    or (``paired``) of the i-th plant with the i-th state: a carry with a leading axis P O (or P)."""
    one = lambda plant, X0: start(plant, ctrl, reference, X0, key, divergence_bound)
    if paired:
        return jax.vmap(one)(plants, X0s)
    carry = jax.vmap(jax.vmap(one, (None, 0)), (0, None))(plants, X0s)
    return jax.tree.map(lambda x: x.reshape((x.shape[0] * x.shape[1],) + x.shape[2:]), carry)  # -1 fails on size 0


_STATIC = ("n_steps", "integrator", "switching", "law", "save_every", "checkpoint_every", "truncate_every")


@functools.partial(jax.jit, static_argnames=_STATIC)
def _simulate(
    plant,
    controller,
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
    truncate_every: int = 0,
    divergence_bound: float = 1e6,
    key: Array | None = None,
    chattering_cutoff: float = _metrics.CHATTERING_CUTOFF,
) -> Result:
    """Simulate one closed-loop rollout of ``controller`` on ``plant`` from X(0) = ``X0``.

    The controller runs every m = ``controller.sample_steps`` (default 1) simulation steps:
    at t_k, k a multiple of m, it reads the plant's X(t_k) and returns the applied voltage,
    held until its next sample; between samples the plant (and the controller's
    continuous-time state, if it has a ``derivative``) is integrated with ``integrator``.

    Args:
      plant: plant pytree (see module docstring), e.g. ``LinearPlant`` or ``Arm``.
      controller: a controller (see module docstring): :class:`FOSMC`, :class:`DiscreteFOSMC`,
        :class:`DigitalLoop`, your own; or a :class:`FOSMCParams` (FOSMC parameters), which
        runs as ``FOSMC(controller, switching, law)``, the paper's ideal loop.
      reference: pytree callable t -> (4, 3) desired angles and derivatives.
      X0: (9,) initial state [theta, theta', theta''] per joint.
      dt: step (s). The dtype of ``X0`` sets the precision of the run.
      n_steps: number of steps n; t_final = n dt. Static.
      integrator: ``euler`` or ``rk4``. Static.
      switching: ``sign``, ``ratio`` (28), ``sat`` or ``tanh``, for a :class:`FOSMCParams`. Static.
      law: ``paper`` (23) or ``equivalent``, for a :class:`FOSMCParams`. Static.
      save_every: keep every ``save_every``-th sample (and the last) in ``Result.trace``;
        0 keeps none; a multiple of m. Static.
      checkpoint_every: for reverse-mode gradients, rematerialise blocks of this many steps
        (rounded up to a multiple of m) with ``jax.checkpoint``, so memory grows with
        n / checkpoint_every + checkpoint_every instead of n; 0 stores every step. Ignored
        when ``save_every`` is set. Static.
      truncate_every: truncated backpropagation through time: derivatives follow the closed
        loop over blocks of this many steps (rounded up to a multiple of m) only, the state's
        dependence on earlier blocks cut (the metric sums keep theirs), so that a gradient
        stays finite and informative where the full-horizon one grows exponentially (a
        switching, quantized loop); values are unchanged; 0: the full horizon. Ignored when
        ``save_every`` is set. Static.
      divergence_bound: a rollout with some |X_i| above it is frozen and flagged.
      key: PRNG key handed to ``controller.init`` (sensor noise); default ``PRNGKey(0)``.
      chattering_cutoff: cutoff (Hz) of the ``chattering_hf`` metric's low-pass filter.

    Returns:
      :class:`Result` with the metrics of :mod:`fosmc_jax._simulator.metrics`.

    Its length is this documentation of :func:`fosmc_jax.simulate`'s arguments; the body is
    :func:`closed_loop_step` scanned over sample periods, then the metrics.
    """
    if integrator not in _STEPPERS:
        raise ValueError(f"integrator must be one of {INTEGRATORS}, got {integrator!r}")
    ctrl = as_controller(controller, switching, law)
    check_plant(plant)
    check_controller(ctrl)
    m = sample_steps(ctrl)
    check_save_every(save_every, m)
    dtype = X0.dtype
    dt = jnp.asarray(dt, dtype)
    step = closed_loop_step(plant, ctrl, reference, dt, integrator, divergence_bound, chattering_cutoff)

    def held(c: _Carry, _) -> tuple[_Carry, None]:
        return step(c, sample=False), None

    def period(c: _Carry, _) -> tuple[_Carry, None]:
        """m steps: m - 1 with the control held, then one ending with a controller sample."""
        return step(_scan_steps(held, c, m - 1), sample=True), None

    def advance(c: _Carry, steps: int) -> _Carry:
        """``steps`` simulation steps from a controller sample."""
        periods, rest = divmod(steps, m)
        return _scan_steps(held, _scan_steps(period, c, periods), rest)

    carry = start(plant, ctrl, reference, X0, key, divergence_bound)

    trace = None
    if save_every:
        carry, samples = traced(functools.partial(snapshot, plant, ctrl, dt), advance, carry, n_steps, save_every)
        trace = as_trace(reference, dt, *samples)
    else:
        whole = lambda steps: -(-steps // m) * m
        detach = lambda c: c._replace(**{f: jax.lax.stop_gradient(getattr(c, f)) for f in _DYNAMIC})
        carry = _in_blocks(advance, carry, n_steps, detach, whole(checkpoint_every), whole(truncate_every))

    metrics = _metrics.masked(_metrics.finish(carry.acc, n_steps * dt), carry.diverged)
    return Result(metrics, carry.diverged, carry.diverged_at, trace)


def snapshot(plant, ctrl, dt: Array, c: _Carry) -> tuple[Array, Array, Array, Array]:
    """One sample of the :class:`Trace` from a carry: (k, X, U, s)."""
    t = c.k.astype(dt.dtype) * dt
    return c.k, observe_at(plant, c.plant_state, t), c.U, _sliding_variable(ctrl, c.ctrl_state, dt.dtype)


def traced(snapshot_of: Callable, advance: Callable, carry, n_steps: int, save_every: int):
    """``advance(carry, steps)`` over ``n_steps`` in blocks of ``save_every``, ``snapshot_of(carry)``
    taken at t = 0, after each block and at the end: (the last carry, the samples stacked on a
    leading time axis). One rollout's carry here; the generated kernel's batch of them in
    :func:`fosmc_jax._simulator.generated.simulate_batch`."""

    def block(c, _):
        c = advance(c, save_every)
        return c, snapshot_of(c)

    blocks, rest = divmod(n_steps, save_every)
    first = snapshot_of(carry)
    carry, samples = jax.lax.scan(block, carry, None, length=blocks)
    if rest:
        carry = advance(carry, rest)
    stack = lambda head, body, tail: jnp.concatenate([head[None], body] + ([tail[None]] if rest else []))
    return carry, jax.tree.map(stack, first, samples, snapshot_of(carry))


def as_trace(reference, dt: Array, ks: Array, Xs: Array, Us: Array, ss: Array) -> Trace:
    """The :class:`Trace` of one rollout's samples (their step numbers ``ks``)."""
    ts = ks.astype(dt.dtype) * dt
    return Trace(ts, Xs, jax.vmap(lambda t: desired_state(reference(t)))(ts), Us, ss)


def check_save_every(save_every: int, m: int) -> None:
    if save_every % m:
        raise ValueError(f"save_every = {save_every} must be a multiple of the controller's sample_steps = {m}")
