"""Conventional sliding mode with a boundary layer, to compare the FOSMC with, on the
conventional surface s = C Z (:mod:`.surface`):

    U = U_eq - (CB)^-1 k sat(s / phi)
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
from .kind import Kind, Param, Space
from .surface import SurfaceParams, surface_of, surface_terms


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
        s, U_eq = surface_terms(self.surface, Y, r)
        CB = input_matrix_product(self.surface.C, self.surface.b_rows)
        return U_eq - solve3(CB, self.k * jnp.clip(s / self.phi, -1.0, 1.0)), SMCState(s)

    def sliding_variable(self, state: SMCState) -> Array:
        return state.s


class SMCGains(NamedTuple):
    """Conventional SMC's tunable parameters (:class:`SMC`): switching gains ``k`` (3,) and
    boundary-layer widths ``phi`` (3,)."""

    k: Any
    phi: Any


KIND = Kind(
    Space("smc", SMCGains, (Param("k", "smc_k", 1, (-2.0, 2.0)), Param("phi", "smc_phi", 1, (-3.0, 2.0)))),
    {"smc_k": (1000.0, 1000.0, 1000.0), "smc_phi": (10.0, 10.0, 10.0)},
    lambda params, controller, T: SMC(surface_of(params), controller.gains["smc_k"], controller.gains["smc_phi"]),
    rules={
        **surface.RULES,
        SMC: {
            "surface": rules.NESTED_FIELD,
            "k": rules.GAINS,
            "phi": rules.Field((3,), rules.positive, "3 positive boundary-layer widths"),
        },
    },
)
