"""The FOSMC controller: sliding surface (14), control law (23), switching functions (28).

:class:`FOSMC` (the paper's ideal loop) and :class:`DiscreteFOSMC` (a sampled controller)
wrap these functions in the controller interface of :mod:`fosmc_jax._simulator.step`.

:class:`FOSMCParams` holds what may be traced and tuned (C, the poles, gamma, delta) plus the
nominal design model (rows 3, 6, 9 of A and B) used for K, Omega and the integral term.
Everything derived from it (K, (CB)^-1, CA + CBK) is computed once per rollout by
:func:`derive`, so that gradients reach the poles through K.
"""

from __future__ import annotations

import dataclasses
import functools
import warnings
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from jax import Array

from .._design.gains import closed_loop_matrix, gain_from_poles, input_matrix_product
from .._design.linalg import inv3
from .._plants.reference import desired_state, feedforward
from . import rules
from .kind import Kind, Param, Space

#: Switching functions f(s) that replace SGN(s) in (23). ``ratio`` is (28).
SWITCHING = ("sign", "ratio", "sat", "tanh")
#: ``paper``: (23) as printed. ``equivalent``: (23) plus the nominal equivalent-control term KZ.
LAWS = ("paper", "equivalent")


class FOSMCParams(NamedTuple):
    """FOSMC parameters (a pytree; every field may be traced).

    Fields: ``C`` (3, 9) sliding-surface matrix (15); ``poles`` (3, 3) closed-loop poles per
    joint (1/s), from which K is placed; ``gamma`` (3,) gains of (23); ``delta`` (3,)
    boundary-layer constants of (28) (unused by ``sign``); ``a_rows`` (3, 9), ``b_rows``
    (3, 3): rows 3, 6, 9 of the nominal design model A, B of (29).
    """

    C: Array
    poles: Array
    gamma: Array
    delta: Array
    a_rows: Array
    b_rows: Array


class Derived(NamedTuple):
    """Quantities computed once per rollout from a :class:`FOSMCParams`."""

    K: Array  # (3, 9), places the poles: eig(A + BK) = poles, (16)
    CB_inv: Array  # (3, 3)
    S: Array  # (3, 9), CA + CBK, the integrand's matrix in (14)


def derive(ctrl: FOSMCParams) -> Derived:
    """K from the poles, (CB)^-1, and CA + CBK = C (A + BK)."""
    K = gain_from_poles(ctrl.a_rows, ctrl.b_rows, ctrl.poles)
    CB_inv = inv3(input_matrix_product(ctrl.C, ctrl.b_rows))
    S = ctrl.C @ closed_loop_matrix(ctrl.a_rows, ctrl.b_rows, K)
    return Derived(K, CB_inv, S)


def safe_sqrt(sq: Array) -> Array:
    """sqrt(sq) for sq >= 0, with a zero (not NaN) gradient at sq = 0 (the "double where" trick)."""
    nonzero = sq > 0
    return jnp.where(nonzero, jnp.sqrt(jnp.where(nonzero, sq, 1.0)), 0.0)


def safe_norm(x: Array) -> Array:
    """Euclidean norm with a zero (not NaN) gradient at x = 0."""
    return safe_sqrt(jnp.sum(x * x))


def switch(s: Array, delta: Array, switching: str) -> Array:
    """f(s), elementwise: ``sign`` SGN(s); ``ratio`` s / (|s| + delta) (28);
    ``sat`` clip(s / delta, -1, 1); ``tanh`` tanh(s / delta). Gradients are finite at s = 0."""
    if switching == "sign":
        return jnp.sign(s)
    if switching == "ratio":
        return s / (jnp.abs(s) + delta)
    if switching == "sat":
        return jnp.clip(s / delta, -1.0, 1.0)
    if switching == "tanh":
        return jnp.tanh(s / delta)
    raise ValueError(f"switching must be one of {SWITCHING}, got {switching!r}")


def sliding_surface(ctrl: FOSMCParams, Z: Array, w: Array) -> Array:
    """s = C Z - w (14), where w = int_0^t (CA + CBK) Z dtau is the integral state, (3,)."""
    return ctrl.C @ Z - w


def switching_gain(gamma: Array, norm_Z: Array, norm_X_d: Array, norm_Omega: Array) -> Array:
    """The switching gain of (23), rho = gamma_1 ||Z|| + gamma_2 ||X_d|| + gamma_3 ||Omega||, from
    the three norms (a batched path passes a reference part computed once per time step with
    ``norm_Z = 0``)."""
    return gamma[0] * norm_Z + gamma[1] * norm_X_d + gamma[2] * norm_Omega


def control_law(
    ctrl: FOSMCParams,
    derived: Derived,
    Z: Array,
    X_d: Array,
    Omega: Array,
    s: Array,
    switching: str = "ratio",
    law: str = "paper",
) -> Array:
    """The control U (3,), volts.

    ``paper``:      U = -(CB)^-1 rho f(s) + Omega                      (23)
    ``equivalent``: U = -(CB)^-1 rho f(s) + Omega + K Z
    with rho = gamma_1 ||Z|| + gamma_2 ||X_d|| + gamma_3 ||Omega||. The ``equivalent`` law adds
    the nominal equivalent control (18) with H = E = 0, which (23) leaves to the switching term.
    """
    rho = switching_gain(ctrl.gamma, safe_norm(Z), safe_norm(X_d), safe_norm(Omega))
    U = Omega - derived.CB_inv @ (rho * switch(s, ctrl.delta, switching))
    if law == "equivalent":
        return U + derived.K @ Z
    if law != "paper":
        raise ValueError(f"law must be one of {LAWS}, got {law!r}")
    return U


# ---------------------------------------------------------------------------- controllers
#
# A controller is a pytree with the shape optax gives optimizers (see fosmc_jax._simulator.step):
#   init(X0, r0, key) -> state
#   update(state, Y, r, t) -> (U, state)     at each controller sample, from the measurement Y
# and optionally derivative(state, X, r, t) -> state', the continuous-time part of its state,
# integrated with the plant between samples (the ideal loop's integral of (14)).


class FOSMCState(NamedTuple):
    """State of :class:`FOSMC` and :class:`DiscreteFOSMC`."""

    w: Array  # (3,) integral state of (14)
    s: Array  # (3,) the sliding variable at the last sample (kept for traces)


def _fosmc_sample(ctrl: FOSMCParams, state: FOSMCState, Y: Array, r: Array, switching: str, law: str):
    X_d = desired_state(r)
    Omega = feedforward(ctrl.a_rows, ctrl.b_rows, r)
    Z = Y - X_d
    s = sliding_surface(ctrl, Z, state.w)
    return control_law(ctrl, derive(ctrl), Z, X_d, Omega, s, switching, law), s, Z


def _fosmc_init(ctrl: FOSMCParams, X0: Array, r0: Array) -> FOSMCState:
    return FOSMCState(jnp.zeros(3, X0.dtype), ctrl.C @ (X0 - desired_state(r0)))


@functools.partial(jax.tree_util.register_dataclass, data_fields=["params"], meta_fields=["switching", "law"])
@dataclasses.dataclass(frozen=True)
class FOSMC:
    """The FOSMC in the paper's ideal loop: U from the exact state at every simulation step,
    and the integral w = int_0^t (CA + CBK) Z dtau of (14) integrated with the plant.

    Fields: ``params`` (:class:`FOSMCParams`, traced); ``switching`` and ``law`` (static).
    """

    params: FOSMCParams
    switching: str = "ratio"
    law: str = "paper"

    def init(self, X0: Array, r0: Array, key=None) -> FOSMCState:
        return _fosmc_init(self.params, X0, r0)

    def update(self, state: FOSMCState, Y: Array, r: Array, t: Array) -> tuple[Array, FOSMCState]:
        U, s, _ = _fosmc_sample(self.params, state, Y, r, self.switching, self.law)
        return U, state._replace(s=s)

    def derivative(self, state: FOSMCState, X: Array, r: Array, t: Array) -> FOSMCState:
        return FOSMCState(derive(self.params).S @ (X - desired_state(r)), jnp.zeros_like(state.s))

    def sliding_variable(self, state: FOSMCState) -> Array:
        return state.s


@functools.partial(jax.tree_util.register_dataclass, data_fields=["params", "period"], meta_fields=["switching", "law"])
@dataclasses.dataclass(frozen=True)
class DiscreteFOSMC:
    """The FOSMC as a sampled controller with period T: at sample j, from the measurement Y_j,

        Z_j = Y_j - X_d(t_j),  s_j = C Z_j - w_j,  U_j from (23),  w_{j+1} = w_j + T (CA + CBK) Z_j,

    w_0 = 0. It knows only the Y_j: its integral is this sum, not the integral of the true error.

    Fields: ``params`` (:class:`FOSMCParams`), ``period`` T (s, scalar) (traced); ``switching``,
    ``law`` (static).
    """

    params: FOSMCParams
    period: Array
    switching: str = "ratio"
    law: str = "paper"

    def init(self, X0: Array, r0: Array, key=None) -> FOSMCState:
        return _fosmc_init(self.params, X0, r0)

    def update(self, state: FOSMCState, Y: Array, r: Array, t: Array) -> tuple[Array, FOSMCState]:
        U, s, Z = _fosmc_sample(self.params, state, Y, r, self.switching, self.law)
        return U, state._replace(w=state.w + self.period * (derive(self.params).S @ Z), s=s)

    def sliding_variable(self, state: FOSMCState) -> Array:
        return state.s


def as_controller(controller, switching: str = "ratio", law: str = "paper"):
    """A :class:`FOSMCParams` (FOSMC parameters) as the ideal-loop :class:`FOSMC`, with a
    DeprecationWarning (the simulator takes controllers: ``FOSMC(params, switching, law)``);
    any other controller as it is."""
    if not isinstance(controller, FOSMCParams):
        return controller
    warnings.warn("simulate: bare FOSMC parameters with switching= and law= are deprecated; pass the controller "
                  "fosmc_jax.FOSMC(params, switching, law)", DeprecationWarning, stacklevel=3)  # fmt: skip
    return FOSMC(controller, switching, law)


class Tunable(NamedTuple):
    """The FOSMC's tunable parameters: ``delta`` (3,), ``gamma`` (3,), ``poles`` (3, 3) in 1/s."""

    delta: Any
    gamma: Any
    poles: Any


def _law(params: FOSMCParams, controller: Any, T: Array):
    """The FOSMC of the config's loop (``controller``: its typed ``[controller]`` table):
    :class:`FOSMC` in the ideal loop, else :class:`DiscreteFOSMC`."""
    if controller.sample_period:
        return DiscreteFOSMC(params, T, controller.switching, controller.law)
    return FOSMC(params, controller.switching, controller.law)


#: The input rules of the FOSMC's types (from their docstrings and the config's validators,
#: ``fosmc_jax._problems.schema.SCHEMA``).
RULES = {
    FOSMCParams: {
        "C": rules.MATRIX_3x9,
        "poles": rules.Field((3, 3), rules.left_half_plane, "a 3x3 matrix of poles with negative real parts (1/s)"),
        "gamma": rules.Field((3,), rules.non_negative, "3 non-negative numbers"),
        "delta": rules.Field((3,), rules.positive, "3 positive numbers"),
        **rules.ROWS,
    },
    FOSMC: {"params": rules.NESTED_FIELD, "switching": rules.one_of(SWITCHING), "law": rules.one_of(LAWS)},
    DiscreteFOSMC: {
        "params": rules.NESTED_FIELD,
        "period": rules.PERIOD,
        "switching": rules.one_of(SWITCHING),
        "law": rules.one_of(LAWS),
    },
}

#: The front's boxes: delta x 10^[-3, 3], gamma x 10^[-2.5, 1], poles x 10^[0, 3], wide enough for
#: the realistic digital loops' fronts, whose low-chattering ends want a weak switching term
#: (docs/tuning.md "The box"). Its parameters and gains are the core [controller] keys (delta,
#: gamma, poles, switching, law).
KIND = Kind(
    Space("fosmc", Tunable, (Param("delta", "delta", 1, (-3.0, 3.0)), Param("gamma", "gamma", 1, (-2.5, 1.0)),
                             Param("poles", "poles", -1, (0.0, 3.0)))),
    {},
    _law,
    tunes_params=True,
    hitting_condition=True,
    gamma_bounds=True,
    rules=RULES,
)  # fmt: skip
