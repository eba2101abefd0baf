"""The linear plant's fast path: the closed loop of :func:`fosmc_jax._simulator.step.closed_loop_step`
for a batch of :class:`LinearPlant` under the ideal-loop FOSMC, written structure-of-arrays.

The batch is the trailing (minor) axis of every array, and each matrix-vector product is
written out row by row on (batch,) vectors with the matrix entries as scalars (or, for the
plants, as (batch,) vectors). A step is then a few fused elementwise loops over the batch;
``vmap`` of :func:`fosmc_jax.simulate` instead makes (batch, 3, 9) x (batch, 9) dot_generals,
one small kernel each. The reference, X_d, Omega and everything derived from the controller
depend on t only: computed once per step for the whole batch. Only rows 3, 6, 9 of the plant
carry dynamics. Same operations as :func:`fosmc_jax.simulate`, so the same results to rounding
(tests/test_performance_paths.py). Where the host has a C++ compiler the time loop runs in
fosmc_jax/_simulator/kernel.cc instead (:func:`_kernel_advance`), the same operations again;
the scan stays for derivatives and for hosts without a compiler.
"""

from __future__ import annotations

import functools
import operator
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from jax import Array

from .._controllers.fosmc import FOSMCParams, derive, is_ideal_fosmc, reference_terms, safe_sqrt, switch, switching_gain
from .._plants.linear import LinearPlant
from .._plants.reference import desired_state
from . import metrics as _metrics
from . import native as _native
from .step import _STEPPERS, INTEGRATORS, Result, _guard, _in_blocks, _scan_steps


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
    """:func:`fosmc_jax.simulate_batch` without a trace for plants (P,) of :class:`LinearPlant` and
    X0s (O, 9); results with a leading axis P * O, plant-major. With ``native`` the time loop
    runs in the compiled kernel of :mod:`fosmc_jax._simulator.native` (forward only), else in
    ``lax.scan``. Its length: the step's stages (``sample``, ``field``, ``body``) are closures
    over the batch's rows of A, B, C, S, K, gamma and delta, unpacked once here."""
    if integrator not in _STEPPERS:
        raise ValueError(f"integrator must be one of {INTEGRATORS}, got {integrator!r}")
    dtype = X0s.dtype
    dt = jnp.asarray(dt, dtype)
    P, O = plants.a_rows.shape[0], X0s.shape[0]
    gain = _metrics.lowpass(dt, jnp.asarray(chattering_cutoff, dtype))
    derived = derive(controller)
    C, S, CB_inv, K = (_rows(m, 2) for m in (controller.C, derived.S, derived.CB_inv, derived.K))
    # Every batch vector has the shape ``lanes``, (P, O), or (P,) when O = 1: a trailing axis
    # of length 1 leaves XLA:CPU a loop it does not vectorise (BENCHMARKS.md, "Figures behind
    # the code").
    lanes = (P, O) if O > 1 else (P,)
    col = (lambda a: a[..., None]) if O > 1 else (lambda a: a)
    A = _rows(col(jnp.moveaxis(plants.a_rows, 0, -1)), 2)  # entries (P, 1), or (P,)
    B = _rows(col(jnp.moveaxis(plants.b_rows, 0, -1)), 2)
    gamma, delta = _rows(controller.gamma), _rows(controller.delta)
    # XLA:CPU fuses each output separately and would recompute shared terms in each; an
    # optimization_barrier does not survive its pipeline, but a conditional's outputs are
    # always materialised: ``materialised`` runs ``fn`` under an always-true cond, so that every
    # stage's result is a (P, O) vector computed once per step.
    always = jnp.isfinite(dt)

    def materialised(fn):
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

        return materialised(f)

    def ok_of(x, w, U, s):
        finite = functools.reduce(operator.and_, (jnp.isfinite(v) for v in x + w + U + s))
        return functools.reduce(operator.and_, (jnp.abs(v) <= divergence_bound for v in x), finite)

    step = _STEPPERS[integrator]

    def body(c: _Batch, _) -> tuple[_Batch, None]:
        t = c.k.astype(dtype) * dt
        x, w = materialised(lambda y: step(field(c.U), t, y, dt))((c.x, c.w))
        k = c.k + 1
        U, s, e = materialised(sample)(x, w, k.astype(dtype) * dt)
        ok = ok_of(x, w, U, s)
        acc = tuple(_metrics.add(a, ej, uj, pj, gain) for a, ej, uj, pj in zip(c.acc, e, U, c.U))
        kept, diverged, diverged_at = _guard(
            c.diverged, c.diverged_at, ok, k.astype(dtype) * dt, (c.x, c.w, c.U, c.acc), (x, w, U, acc)
        )
        return _Batch(k, *kept, diverged, diverged_at), None

    # Two steps per loop trip: a little faster than one (benchmarks/loop_variants.py); a packed
    # carry, more unrolling, no ``materialised`` or blocks of the batch were slower or no faster.
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


def _kernel_advance(c: _Batch, n_steps, A, B, controller, derived, reference, dt, gain, bound, **kernel_opts) -> _Batch:
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
        stages = [X_d_at(t)] if not kernel_opts["rk4"] else [X_d_at(t), X_d_at(t + dt / 2), X_d_at(t + dt)]
        t1 = (k + 1).astype(dt.dtype) * dt
        X_d, Omega, rho_ref = jax.vmap(functools.partial(_time_terms, controller, reference))(t1)
        return jnp.concatenate([*stages, X_d, Omega, rho_ref[:, None], t1[:, None]], axis=1).astype(dtype)

    out = _native.advance(carry, ab, consts, table, c.k, n_steps, **kernel_opts)[:, :n].reshape((-1, *lanes))
    div = _native.LIN_DIV
    x, w, U, acc = out[:9], out[9:12], out[12 : _native.LIN_ACC], out[_native.LIN_ACC : div]
    div, div_at = out[div], out[div + 1]
    acc = tuple(_metrics.Accumulator(*acc[j::3]) for j in range(3))
    return _Batch(c.k + n_steps, tuple(x), tuple(w), tuple(U), acc, div != 0, div_at)


def supports(plants, ctrl, paired: bool) -> bool:
    """Whether this path runs the batch: plants of the linear model (3) under the ideal-loop
    FOSMC (:func:`fosmc_jax._controllers.fosmc.is_ideal_fosmc`), every plant with every initial state."""
    return isinstance(plants, LinearPlant) and is_ideal_fosmc(ctrl) and not paired


def simulate_batch(args: tuple, derivative, *, native: bool, n_steps: int, integrator: str,
                   checkpoint_every: int = 0, truncate_every: int = 0, **_) -> Result:  # fmt: skip
    """:func:`fosmc_jax.simulate_batch` of ``args`` = (plants, ctrl, reference, X0s, dt, keys,
    divergence_bound, chattering_cutoff) (:func:`supports` must hold; the loop draws no noise)
    by :func:`_linear_batch`, its time loop in the native kernel where that is built (the
    kernel is the CPU's: on a GPU, or with ``native=False``, the ``lax.scan`` loop runs).
    Derivatives (``custom_jvp``: forward mode, and reverse mode by its transpose) are those of
    ``derivative(*args)``, the ``vmap`` path's, equal to the scan's to rounding and faster to
    compile and run (BENCHMARKS.md, benchmarks/linear_paths.py)."""
    kernel = native and jax.default_backend() == "cpu" and _native.available()

    def scan_path(plants, ctrl, reference, X0s, dt, keys, bound, cutoff):
        return _linear_batch(plants, ctrl.params, reference, X0s, dt, n_steps=n_steps, integrator=integrator,
                             switching=ctrl.switching, law=ctrl.law, checkpoint_every=checkpoint_every,
                             truncate_every=truncate_every, divergence_bound=bound, chattering_cutoff=cutoff,
                             native=kernel)  # fmt: skip

    run = jax.custom_jvp(scan_path)
    run.defjvp(lambda primals, tangents: jax.jvp(derivative, primals, tangents))
    return run(*args)
