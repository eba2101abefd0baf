"""Controllers to compare the FOSMC with, through the same controller interface
(:mod:`fosmc_jax._simulator.rollout`): conventional sliding mode with a boundary layer, and Levant's
super-twisting algorithm, both on the conventional surface s = C Z of the third-order model.

With Z = X - X_d and X' = A X + B U (the nominal rows 3, 6, 9 of (29)), s' = C (A X + B U -
X_d'); both laws cancel the nominal part with the equivalent control

    U_eq = (CB)^-1 (C X_d' - C A X)       (X_d' = [theta_d', theta_d'', theta_d'''] per joint)

and add a switching part:

    SMC:             U = U_eq - (CB)^-1 k sat(s / phi)
    super-twisting:  U = U_eq - (CB)^-1 (k1 |s|^(1/2) sign(s) - v),   v' = -k2 sign(s)

Super-twisting's control is continuous (the discontinuity is integrated into v). In the ideal
loop v is integrated with the plant; as a sampled law (``period`` > 0) it is the sum
v_{j+1} = v_j - T k2 sign(s_j).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import Array

from .._design.gains import input_matrix_product
from .._plants.reference import desired_state
from .fosmc import safe_sqrt


class SurfaceParams(NamedTuple):
    """What both laws share: the surface ``C`` (3, 9) and the nominal rows ``a_rows`` (3, 9),
    ``b_rows`` (3, 3) of (29)."""

    C: Array
    a_rows: Array
    b_rows: Array


def _full(a_rows: Array, X: Array) -> Array:
    """X' of the nominal third-order model without input: chains plus rows 3, 6, 9."""
    jerk = a_rows @ X
    return jnp.stack([X[1::3], X[2::3], jerk], axis=1).reshape(9)


def _surface(p: SurfaceParams, Y: Array, r: Array) -> tuple[Array, Array]:
    """s = C Z and the equivalent control U_eq (3,)."""
    X_d = desired_state(r)
    dX_d = jnp.stack([r[1], r[2], r[3]], axis=1).reshape(9)
    CB = input_matrix_product(p.C, p.b_rows)
    U_eq = jnp.linalg.solve(CB, p.C @ dX_d - p.C @ _full(p.a_rows, Y))
    return p.C @ (Y - X_d), U_eq


class SMCState(NamedTuple):
    s: Array  # (3,) the sliding variable at the last sample (for traces)


@functools.partial(jax.tree_util.register_dataclass, data_fields=["surface", "k", "phi"], meta_fields=[])
@dataclasses.dataclass(frozen=True)
class SMC:
    """Conventional sliding mode with a boundary layer: U = U_eq - (CB)^-1 k sat(s / phi).
    Fields (traced): ``surface`` (:class:`SurfaceParams`), ``k`` (3,) V-scaled gains,
    ``phi`` (3,) boundary-layer widths."""

    surface: SurfaceParams
    k: Array
    phi: Array

    def init(self, X0: Array, r0: Array, key=None) -> SMCState:
        return SMCState(jnp.zeros(3, X0.dtype))

    def update(self, state: SMCState, Y: Array, r: Array, t: Array) -> tuple[Array, SMCState]:
        s, U_eq = _surface(self.surface, Y, r)
        CB = input_matrix_product(self.surface.C, self.surface.b_rows)
        return U_eq - jnp.linalg.solve(CB, self.k * jnp.clip(s / self.phi, -1.0, 1.0)), SMCState(s)

    def sliding_variable(self, state: SMCState) -> Array:
        return state.s


class STState(NamedTuple):
    v: Array  # (3,) the integral term
    s: Array  # (3,) the sliding variable at the last sample


def _signed_sqrt(s: Array) -> Array:
    """|s|^(1/2) sign(s), with a finite (zero) gradient at s = 0."""
    return safe_sqrt(jnp.abs(s)) * jnp.sign(s)


@functools.partial(jax.tree_util.register_dataclass, data_fields=["surface", "k1", "k2", "period"],
                   meta_fields=[])  # fmt: skip
@dataclasses.dataclass(frozen=True)
class SuperTwisting:
    """Levant's super-twisting law on s = C Z (module docstring). Fields (traced):
    ``surface``, ``k1`` (3,), ``k2`` (3,), ``period`` T (s; 0: the ideal loop, v integrated
    with the plant; > 0: v summed at the samples, for :class:`fosmc_jax.DigitalLoop`)."""

    surface: SurfaceParams
    k1: Array
    k2: Array
    period: Array

    def init(self, X0: Array, r0: Array, key=None) -> STState:
        return STState(jnp.zeros(3, X0.dtype), jnp.zeros(3, X0.dtype))

    def update(self, state: STState, Y: Array, r: Array, t: Array) -> tuple[Array, STState]:
        s, U_eq = _surface(self.surface, Y, r)
        CB = input_matrix_product(self.surface.C, self.surface.b_rows)
        U = U_eq - jnp.linalg.solve(CB, self.k1 * _signed_sqrt(s) - state.v)
        v = state.v - self.period * self.k2 * jnp.sign(s)
        return U, STState(v, s)

    def sliding_variable(self, state: STState) -> Array:
        return state.s


@functools.partial(jax.tree_util.register_dataclass, data_fields=["law"], meta_fields=[])
@dataclasses.dataclass(frozen=True)
class ContinuousSuperTwisting:
    """:class:`SuperTwisting` in the ideal loop: v' = -k2 sign(s(t)) integrated with the plant."""

    law: SuperTwisting  # with period = 0

    def init(self, X0: Array, r0: Array, key=None) -> STState:
        return self.law.init(X0, r0, key)

    def update(self, state: STState, Y: Array, r: Array, t: Array) -> tuple[Array, STState]:
        return self.law.update(state, Y, r, t)  # period 0: v is left to derivative

    def derivative(self, state: STState, X: Array, r: Array, t: Array) -> STState:
        s, _ = _surface(self.law.surface, X, r)
        return STState(-self.law.k2 * jnp.sign(s), jnp.zeros_like(s))

    def sliding_variable(self, state: STState) -> Array:
        return state.s
