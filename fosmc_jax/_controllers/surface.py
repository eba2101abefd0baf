"""The conventional sliding surface s = C Z of the third-order model and the equivalent
control that cancels its nominal part, shared by conventional SMC (:mod:`.smc`) and
super-twisting (:mod:`.super_twisting`).

With Z = X - X_d and X' = A X + B U (the nominal rows 3, 6, 9 of (29)), s' = C (A X + B U -
X_d'); both laws cancel the nominal part with the equivalent control

    U_eq = (CB)^-1 (C X_d' - C A X)       (X_d' = [theta_d', theta_d'', theta_d'''] per joint)

and add a switching part of their own.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
from jax import Array

from .._design.gains import input_matrix_product
from .._design.linalg import solve3
from .._plants.reference import desired_state
from . import rules


class SurfaceParams(NamedTuple):
    """What both laws share: the surface ``C`` (3, 9) and the nominal rows ``a_rows`` (3, 9),
    ``b_rows`` (3, 3) of (29)."""

    C: Array
    a_rows: Array
    b_rows: Array


#: The input rules of :class:`SurfaceParams`, part of each of the two kinds' rules.
RULES = {SurfaceParams: {"C": rules.MATRIX_3x9, **rules.ROWS}}


def nominal_rates(a_rows: Array, X: Array) -> Array:
    """X' of the nominal third-order model without input: chains plus rows 3, 6, 9."""
    jerk = a_rows @ X
    return jnp.stack([X[1::3], X[2::3], jerk], axis=1).reshape(9)


def surface_terms(p: SurfaceParams, Y: Array, r: Array) -> tuple[Array, Array]:
    """s = C Z and the equivalent control U_eq (3,)."""
    X_d = desired_state(r)
    dX_d = jnp.stack([r[1], r[2], r[3]], axis=1).reshape(9)
    CB = input_matrix_product(p.C, p.b_rows)
    U_eq = solve3(CB, p.C @ dX_d - p.C @ nominal_rates(p.a_rows, Y))
    return p.C @ (Y - X_d), U_eq


def surface_of(params) -> SurfaceParams:
    """The surface of FOSMC parameters (:class:`fosmc_jax.FOSMCParams`): their C and nominal rows."""
    return SurfaceParams(params.C, params.a_rows, params.b_rows)
