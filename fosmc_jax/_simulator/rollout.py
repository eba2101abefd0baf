"""The closed-loop simulator: one rollout, a ``lax.scan`` in time; ``vmap`` outside.

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
import operator
import warnings
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from jax import Array

from .._controllers.base import ContinuousLaw, HasSlidingVariable, SampledLoop, check_controller
from .._controllers.fosmc import FOSMC, FOSMCParams, derive, reference_terms, safe_sqrt, switch, switching_gain
from .._plants.arm import without_idle_terms
from .._plants.base import check_plant, derivative_at, observe_at
from .._plants.linear import LinearPlant
from .._plants.reference import desired_state
from . import arm_native as _arm_native
from . import codegen as _codegen
from . import generated as _generated
from . import metrics as _metrics
from . import native as _native
from .checks import check_inputs

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
_DYNAMIC = ("plant_state", "ctrl_state", "U")


class _Carry(NamedTuple):
    k: Array
    plant_state: Any
    ctrl_state: Any
    U: Array  # the applied control held over the coming step
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


def as_controller(controller, switching: str = "ratio", law: str = "paper"):
    """A :class:`FOSMCParams` (FOSMC parameters) as the ideal-loop :class:`FOSMC`, with a
    DeprecationWarning (the simulator takes controllers: ``FOSMC(params, switching, law)``);
    any other controller as it is."""
    if not isinstance(controller, FOSMCParams):
        return controller
    warnings.warn("simulate: bare FOSMC parameters with switching= and law= are deprecated; pass the controller "
                  "fosmc_jax.FOSMC(params, switching, law)", DeprecationWarning, stacklevel=3)  # fmt: skip
    return FOSMC(controller, switching, law)


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

    def integrate(plant_state, ctrl_state, U, t):
        if not flows:
            return stepper(lambda t, y: derivative_at(plant, y, U, t), t, plant_state, dt), ctrl_state

        def f(t, y):
            ps, cs = y
            return derivative_at(plant, ps, U, t), ctrl.derivative(cs, observe_at(plant, ps, t), reference(t), t)

        return stepper(f, t, (plant_state, ctrl_state), dt)

    def step(c: _Carry, sample: bool) -> _Carry:
        plant_state, ctrl_state = integrate(c.plant_state, c.ctrl_state, c.U, c.k.astype(dtype) * dt)
        k = c.k + 1
        t = k.astype(dtype) * dt
        X = observe_at(plant, plant_state, t)
        r = reference(t)
        U = c.U
        if sample:
            U, ctrl_state = ctrl.update(ctrl_state, X, r, t)
        ok = _finite_and_bounded((plant_state, ctrl_state, X, U), X, divergence_bound)
        acc = _metrics.add(c.acc, X[theta] - r[0], U, c.U, a, u_max)
        kept, diverged, diverged_at = _guard(
            c.diverged, c.diverged_at, ok, t, (c.plant_state, c.ctrl_state, c.U, c.acc),
            (plant_state, ctrl_state, U, acc),
        )  # fmt: skip
        return _Carry(k, *kept, diverged, diverged_at)

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
    """
    if integrator not in _STEPPERS:
        raise ValueError(f"integrator must be one of {INTEGRATORS}, got {integrator!r}")
    ctrl = as_controller(controller, switching, law)
    check_plant(plant)
    check_controller(ctrl)
    m = sample_steps(ctrl)
    if save_every % m:
        raise ValueError(f"save_every = {save_every} must be a multiple of the controller's sample_steps = {m}")
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

    def snapshot(c: _Carry):
        return (
            c.k,
            observe_at(plant, c.plant_state, c.k.astype(dtype) * dt),
            c.U,
            _sliding_variable(ctrl, c.ctrl_state, dtype),
        )

    trace = None
    if save_every:
        blocks, rest = divmod(n_steps, save_every)

        def block(c, _):
            c = advance(c, save_every)
            return c, snapshot(c)

        first = snapshot(carry)
        carry, samples = jax.lax.scan(block, carry, None, length=blocks)
        carry = advance(carry, rest)
        stack = lambda head, body, tail: jnp.concatenate([head[None], body] + ([tail[None]] if rest else []))
        ks, Xs, Us, ss = jax.tree.map(stack, first, samples, snapshot(carry))
        ts = ks.astype(dtype) * dt
        X_ds = jax.vmap(lambda t: desired_state(reference(t)))(ts)
        trace = Trace(ts, Xs, X_ds, Us, ss)
    else:
        whole = lambda steps: -(-steps // m) * m
        detach = lambda c: c._replace(**{f: jax.lax.stop_gradient(getattr(c, f)) for f in _DYNAMIC})
        carry = _in_blocks(advance, carry, n_steps, detach, whole(checkpoint_every), whole(truncate_every))

    metrics = _metrics.masked(_metrics.finish(carry.acc, n_steps * dt), carry.diverged)
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
# (tests/test_performance_paths.py). Where the host has a C++ compiler the time loop runs in
# fosmc_jax/_simulator/kernel.cc instead (:func:`_kernel_advance`), the same operations again; the
# scan stays for derivatives and for hosts without a compiler.


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


def _time_terms(controller: FOSMCParams, reference, t: Array) -> tuple[Array, Array, Array]:
    """X_d (9,), Omega (3,) and the reference part of rho (19), gamma_2 ||X_d|| + gamma_3 ||Omega||."""
    X_d, Omega, norm_X_d, norm_Omega = reference_terms(controller.a_rows, controller.b_rows, reference(t))
    return X_d, Omega, switching_gain(controller.gamma, 0.0, norm_X_d, norm_Omega)


def _linear_batch(
    plants: LinearPlant,
    controller: FOSMCParams,
    reference,
    X0s: Array,
    dt: Array,
    *,
    n_steps: int,
    integrator: str = "rk4",
    switching: str = "ratio",
    law: str = "paper",
    checkpoint_every: int = 0,
    truncate_every: int = 0,
    divergence_bound: float = 1e6,
    chattering_cutoff: float = _metrics.CHATTERING_CUTOFF,
    native: bool = False,
) -> Result:
    """:func:`simulate_batch` without a trace for plants (P,) of :class:`LinearPlant` and
    X0s (O, 9); results with a leading axis P * O, plant-major. With ``native`` the time loop
    runs in the compiled kernel of :mod:`fosmc_jax._simulator.native` (forward only), else in
    ``lax.scan``."""
    if integrator not in _STEPPERS:
        raise ValueError(f"integrator must be one of {INTEGRATORS}, got {integrator!r}")
    dtype = X0s.dtype
    dt = jnp.asarray(dt, dtype)
    P, O = plants.a_rows.shape[0], X0s.shape[0]
    gain = _metrics.lowpass(dt, jnp.asarray(chattering_cutoff, dtype))
    derived = derive(controller)
    C, S, CB_inv, K = (_rows(m, 2) for m in (controller.C, derived.S, derived.CB_inv, derived.K))
    # Every batch vector has the shape ``lanes``, (P, O), or (P,) when O = 1: a trailing axis
    # of length 1 leaves XLA:CPU a loop it does not vectorise (2.7x slower at P = 4,096,
    # O = 1, the CLI's ``uncertainty = "sample"`` batch).
    lanes = (P, O) if O > 1 else (P,)
    col = (lambda a: a[..., None]) if O > 1 else (lambda a: a)
    A = _rows(col(jnp.moveaxis(plants.a_rows, 0, -1)), 2)  # entries (P, 1), or (P,)
    B = _rows(col(jnp.moveaxis(plants.b_rows, 0, -1)), 2)
    gamma, delta = _rows(controller.gamma), _rows(controller.delta)
    # XLA:CPU fuses each output separately and would recompute shared terms in each; an
    # optimization_barrier does not survive its pipeline, but a conditional's outputs are
    # always materialised: ``once`` runs ``fn`` under an always-true cond, so that every
    # stage's result is a (P, O) vector computed once per step.
    always = jnp.isfinite(dt)

    def once(fn):
        return lambda *args: jax.lax.cond(always, fn, fn, *args)

    def sample(x, w, t):
        X_d, Omega, rho_ref = _time_terms(controller, reference, t)
        Z = _sub(x, _rows(X_d))
        s = _sub(_mv(C, Z), w)
        # switching_gain's Z part; its reference part is rho_ref
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
        acc = tuple(_metrics.add(a, ej, uj, pj, gain) for a, ej, uj, pj in zip(c.acc, e, U, c.U))
        kept, diverged, diverged_at = _guard(
            c.diverged, c.diverged_at, ok, k.astype(dtype) * dt, (c.x, c.w, c.U, c.acc), (x, w, U, acc)
        )
        return _Batch(k, *kept, diverged, diverged_at), None

    # Two steps per loop trip: a little faster than one (benchmarks/loop_variants.py); a packed
    # carry, more unrolling, no ``once`` or blocks of the batch were slower or no faster.
    advance = functools.partial(_scan_steps, body, unroll=2)

    x = tuple(jnp.broadcast_to(X0s[:, i], lanes) for i in range(9))
    w = (jnp.zeros(lanes, dtype),) * 3
    U, s, e = sample(x, w, jnp.zeros((), dtype))
    bad = ~ok_of(x, w, U, s)
    acc = tuple(_metrics.start(ej, uj) for ej, uj in zip(e, U))
    acc = tuple(a._replace(count=jnp.ones(lanes, dtype)) for a in acc)
    carry = _Batch(
        jnp.zeros((), jnp.int32),
        x,
        w,
        U,
        acc,
        bad,
        jnp.where(bad, jnp.zeros((), dtype), jnp.asarray(jnp.inf, dtype)),
    )
    if native:
        carry = _kernel_advance(carry, n_steps, A, B, controller, derived, reference, dt, gain, divergence_bound,
                                rk4=integrator == "rk4", switching=switching, law=law)  # fmt: skip
    else:
        detach = lambda c: c._replace(**{f: jax.lax.stop_gradient(getattr(c, f)) for f in ("x", "w", "U")})
        carry = _in_blocks(advance, carry, n_steps, detach, checkpoint_every, truncate_every)

    acc = jax.tree.map(lambda *joints: jnp.stack(joints, axis=-1), *carry.acc)
    acc = acc._replace(count=carry.acc[0].count[..., None])
    metrics = _metrics.finish(acc, n_steps * dt)
    flat = lambda a: a.reshape((P * O,) + a.shape[len(lanes) :])
    diverged = flat(carry.diverged)
    return Result(_metrics.masked(jax.tree.map(flat, metrics), diverged), diverged, flat(carry.diverged_at), None)


def _kernel_advance(c: _Batch, n_steps, A, B, controller, derived, reference, dt, gain, bound, **how) -> _Batch:
    """``n_steps`` of ``body`` in :mod:`fosmc_jax._simulator.native`'s kernel: the carry packed into
    rows of lanes (padded to a multiple of its block), the time-only terms in a table; every
    input in the carry's dtype (the widest of the inputs', as the scan promotes them)."""
    lanes = c.diverged.shape
    n = c.diverged.size
    pad = (-n) % _native.LANES

    def rows(entries, dtype=None):
        flat = [jnp.broadcast_to(e, lanes).reshape(n) for e in entries]
        flat = flat if dtype is None else [e.astype(dtype) for e in flat]
        return jnp.pad(jnp.stack(flat), ((0, 0), (0, pad)), mode="edge")

    acc = [field for fields in zip(*c.acc) for field in fields]  # field-major, joint-minor
    carry = rows([*c.x, *c.w, *c.U, *acc, c.diverged_at])
    dtype = carry.dtype
    carry = jnp.concatenate([carry[: _native.LIN_DIV], rows([c.diverged], dtype), carry[_native.LIN_DIV :]])
    ab = rows([e for row in A + B for e in row], dtype)
    bound = jnp.minimum(jnp.asarray(bound, dtype), jnp.finfo(dtype).max)  # |x| <= bound also means finite
    consts = jnp.concatenate([jnp.ravel(m).astype(dtype) for m in (controller.C, derived.S, derived.CB_inv, derived.K,
                              controller.gamma, controller.delta, dt, *gain, bound)])  # fmt: skip
    X_d_at = jax.vmap(lambda t: desired_state(reference(t)))

    def table(k):
        t = k.astype(dt.dtype) * dt
        stages = [X_d_at(t)] if not how["rk4"] else [X_d_at(t), X_d_at(t + dt / 2), X_d_at(t + dt)]
        t1 = (k + 1).astype(dt.dtype) * dt
        X_d, Omega, rho_ref = jax.vmap(functools.partial(_time_terms, controller, reference))(t1)
        return jnp.concatenate([*stages, X_d, Omega, rho_ref[:, None], t1[:, None]], axis=1).astype(dtype)

    out = _native.advance(carry, ab, consts, table, c.k, n_steps, **how)[:, :n].reshape((-1, *lanes))
    div = _native.LIN_DIV
    x, w, U, acc = out[:9], out[9:12], out[12 : _native.LIN_ACC], out[_native.LIN_ACC : div]
    div, div_at = out[div], out[div + 1]
    acc = tuple(_metrics.Accumulator(*acc[j::3]) for j in range(3))
    return _Batch(c.k + n_steps, tuple(x), tuple(w), tuple(U), acc, div != 0, div_at)


def _fast_batch(plants, controller, reference, X0s, dt, *, native: bool = True, **options) -> Result:
    """:func:`_linear_batch` with its time loop in the native kernel where that is built (the
    kernel is the CPU's: on a GPU, or with ``native=False``, the ``lax.scan`` loop runs).
    Derivatives (``custom_jvp``: forward mode, and reverse mode by its transpose) are those of
    ``vmap`` of :func:`simulate`, equal to the scan's to rounding: in forward mode they ran
    3.5x faster than the scan's and compiled 6x sooner (benchmarks/results/linear_paths.md)."""
    kernel = native and jax.default_backend() == "cpu" and _native.available()
    switching, law = options["switching"], options["law"]
    # the traced options are arguments: closed over, they would leak from the custom_jvp rule
    names = [k for k in ("divergence_bound", "chattering_cutoff") if k in options]
    static = {k: v for k, v in options.items() if k not in names}
    rest = {k: v for k, v in static.items() if k not in ("switching", "law")}

    def vmap_path(plants, params, reference, X0s, dt, *traced):  # simulate_batch's own, one realization
        return _simulate_batch(plants, FOSMC(params, switching, law), reference, X0s, dt, fast=False, **rest,
                              **dict(zip(names, traced)))  # fmt: skip

    def scan_path(plants, params, reference, X0s, dt, *traced):
        return _linear_batch(plants, params, reference, X0s, dt, native=kernel, **static, **dict(zip(names, traced)))

    run = jax.custom_jvp(scan_path)
    run.defjvp(lambda primals, tangents: jax.jvp(vmap_path, primals, tangents))
    return run(plants, controller, reference, X0s, dt, *(jnp.asarray(options[k], X0s.dtype) for k in names))


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

    With ``fast`` (static), two batches without a trace (``save_every`` = 0) run a fast path
    with the same results to rounding: :class:`LinearPlant` under the ideal-loop FOSMC (its
    time loop one compiled kernel on every core, :mod:`fosmc_jax._simulator.native`, or, where that
    cannot be built, a structure-of-arrays ``lax.scan``), and :class:`fosmc_jax.Arm` under the
    FOSMC, SMC or super-twisting in the ideal loop or a noise-free :class:`fosmc_jax.DigitalLoop`
    (:mod:`fosmc_jax._simulator.arm_native`, where the kernel is built); anything else runs ``vmap`` of
    :func:`simulate`. Derivatives of the linear fast path are the ``vmap`` path's (its
    ``custom_jvp``); the arm's come from the generated adjoint kernel
    (:mod:`fosmc_jax._simulator.generated`, equal to the ``vmap`` path's to rounding), where
    ``FOSMC_JAX_GENERATED`` allows it (``all``: every printable model runs there, forward too).
    ``native=False`` (static) keeps the compiled kernels out: the linear fast path runs its
    ``lax.scan``, the arm the ``vmap`` path (the benchmarks' scan-only timings;
    ``FOSMC_JAX_NATIVE=0`` does the same for a whole process)."""
    ctrl = as_controller(controller, options.get("switching", "ratio"), options.get("law", "paper"))
    paired = pairing == "paired"
    if pairing not in PAIRINGS:
        raise ValueError(f"pairing: expected one of {', '.join(PAIRINGS)}, got {pairing!r}")
    if paired and jax.tree.leaves(plants)[0].shape[0] != X0s.shape[0]:
        raise ValueError(f"pairing = 'paired': expected as many initial states as plants "
                         f"({jax.tree.leaves(plants)[0].shape[0]}), got {X0s.shape[0]}")  # fmt: skip
    one_key = keys is None or keys.shape[0] == 1  # the ideal FOSMC draws no noise
    linear = isinstance(plants, LinearPlant) and type(ctrl) is FOSMC
    if fast and linear and not paired and one_key and not options.get("save_every"):  # paired: the vmap path
        options = {k: v for k, v in options.items() if k not in ("save_every", "key")}
        options.update(switching=ctrl.switching, law=ctrl.law)
        return _fast_batch(plants, ctrl.params, reference, X0s, dt, native=native, **options)
    key = options.pop("key", None)
    if keys is None:
        keys = (jax.random.PRNGKey(0) if key is None else key)[None]
    # traced options are vmap_path's arguments: closed over, they would leak from the custom_jvp rules
    traced = (options.pop("divergence_bound", 1e6), options.pop("chattering_cutoff", _metrics.CHATTERING_CUTOFF))

    def vmap_path(plants, ctrl, reference, X0s, dt, keys, bound, cutoff):
        one = lambda plant, X0, key: _simulate(plant, ctrl, reference, X0, dt, key=key, divergence_bound=bound,
                                              chattering_cutoff=cutoff, **options)  # fmt: skip
        if paired:
            result = jax.vmap(jax.vmap(one, (None, None, 0)), (0, 0, None))(plants, X0s, keys)
        else:
            result = jax.vmap(jax.vmap(jax.vmap(one, (None, None, 0)), (None, 0, None)), (0, None, None))(
                plants, X0s, keys
            )
        lead = 2 if paired else 3
        return jax.tree.map(lambda x: x.reshape((-1,) + x.shape[lead:]), result)

    options.setdefault("integrator", "rk4")
    args = (plants, ctrl, reference, X0s, dt, keys, *(jnp.asarray(x, X0s.dtype) for x in traced))
    if not (fast and native and keys.shape[0] == 1 and not options.get("save_every")):
        return vmap_path(*args)
    n_steps, integrator = options["n_steps"], options["integrator"]
    generated = _generated.mode()

    def kernel_path(*args):
        """The generated kernel (forward and adjoint), else, where the model cannot be printed, the vmap path."""
        if generated == "0":
            return vmap_path(*args)
        try:
            return _generated.simulate_batch(args, n_steps=n_steps, integrator=integrator, paired=paired,
                                             truncate_every=-(-options.get("truncate_every", 0) // m) * m)  # fmt: skip
        except (_codegen.Unsupported, OSError) as e:  # not printable, or its C++ did not build
            _generated.warn_unsupported(e)
            return vmap_path(*args)

    m = sample_steps(ctrl)
    if _arm_native.supports(plants, ctrl, integrator):  # the hand-written forward, the generated derivatives
        return _arm_native.simulate_batch(args, kernel_path, n_steps=n_steps, integrator=integrator, paired=paired)
    return kernel_path(*args) if generated == "all" else vmap_path(*args)


def _checked(jitted, batch: bool):
    """``jitted`` behind :func:`fosmc_jax._simulator.checks.check_inputs`: its inputs refused
    with a one-line error naming the field where wrong (shapes always, values where concrete),
    lists turned into arrays; the jitted function's ``lower`` and ``_cache_size`` kept."""

    @functools.wraps(jitted)
    def run(plant, controller, reference, X0, dt, **options):
        plant, controller, reference, X0, dt = check_inputs(plant, controller, reference, X0, dt, batch, options)
        plant = without_idle_terms(plant)  # the arm's zero friction and disturbance terms left out of the program
        return jitted(plant, controller, reference, X0, dt, **options)

    run.__name__ = run.__qualname__ = jitted.__name__.lstrip("_")
    run.lower, run._cache_size = jitted.lower, jitted._cache_size
    return run


simulate = _checked(_simulate, batch=False)
simulate_batch = _checked(_simulate_batch, batch=True)
