"""Levant's super-twisting algorithm, to compare the FOSMC with, on the conventional surface
s = C Z (:mod:`.surface`):

    U = U_eq - (CB)^-1 (k1 |s|^(1/2) sign(s) - v),   v' = -k2 sign(s)

Its control is continuous (the discontinuity is integrated into v). In the ideal loop v is
integrated with the plant; as a sampled law (``period`` > 0) it is the sum
v_{j+1} = v_j - T k2 sign(s_j).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from jax import Array

from .._design.gains import input_matrix_product
from .._design.linalg import solve3
from . import rules, surface
from .fosmc import safe_sqrt
from .kind import Kind, Param, Space
from .surface import SurfaceParams, surface_of, surface_terms


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
        s, U_eq = surface_terms(self.surface, Y, r)
        CB = input_matrix_product(self.surface.C, self.surface.b_rows)
        U = U_eq - solve3(CB, self.k1 * _signed_sqrt(s) - state.v)
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
        s, _ = surface_terms(self.law.surface, X, r)
        return STState(-self.law.k2 * jnp.sign(s), jnp.zeros_like(s))

    def sliding_variable(self, state: STState) -> Array:
        return state.s


class STGains(NamedTuple):
    """Super-twisting's tunable parameters (:class:`SuperTwisting`): ``k1`` (3,), ``k2`` (3,)."""

    k1: Any
    k2: Any


KIND = Kind(
    Space("super_twisting", STGains, (Param("k1", "st_k1", 1, (-2.0, 2.0)), Param("k2", "st_k2", 1, (-2.0, 3.0)))),
    {"st_k1": (50.0, 50.0, 50.0), "st_k2": (1000.0, 1000.0, 1000.0)},
    lambda params, ctrl, T: SuperTwisting(surface_of(params), ctrl.gains["st_k1"], ctrl.gains["st_k2"], T),
    ideal=ContinuousSuperTwisting,
    rules={
        **surface.RULES,
        SuperTwisting: {
            "surface": rules.NESTED_FIELD,
            "k1": rules.GAINS,
            "k2": rules.GAINS,
            "period": rules.Field((), rules.non_negative, "a non-negative number (s; 0: the ideal loop)"),
        },
        ContinuousSuperTwisting: {"law": rules.NESTED_FIELD},
    },
)
