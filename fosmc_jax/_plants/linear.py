"""The linear uncertain plant (3): X' = (A + dA) X + (B + dB) U, and its uncertainty draws.

A plant, for the simulator, is any pytree with three methods (see :mod:`fosmc_jax._simulator.step`):
``init(X0) -> state``, ``observe(state) -> X (9,)`` and ``derivative(state, U) -> state'``.
For this plant the internal state is X itself. Only rows 3, 6, 9 carry dynamics (and all the
uncertainty: the matching condition (11)-(12)); the others are integrator chains.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
from jax import Array

from .._design.box import vertex_codes, vertices_from_codes

#: How the uncertainty dA, dB of (3) is realised.
UNCERTAINTY = ("none", "fixed", "sample", "vertices")


class LinearPlant(NamedTuple):
    """Plant (3) with rows 3, 6, 9 ``a_rows`` (3, 9) = A_r + dA_r, ``b_rows`` (3, 3) = B_bar + dB_r.

    Batched plants carry a leading axis on both fields.
    """

    a_rows: Array
    b_rows: Array

    def init(self, X0: Array) -> Array:
        return X0

    def observe(self, state: Array) -> Array:
        return state

    def derivative(self, state: Array, U: Array) -> Array:
        chains = state.reshape(3, 3)[:, 1:]  # theta', theta'' of each joint
        jerk = self.a_rows @ state + self.b_rows @ U  # rows 3, 6, 9
        return jnp.concatenate([chains, jerk[:, None]], axis=1).reshape(9)


def _box_vertices(rng: np.random.Generator, lower: np.ndarray, upper: np.ndarray, n: int) -> np.ndarray:
    """n distinct vertices of the box (all of them if it has no more than n), shape (n', *shape)."""
    m = int(np.count_nonzero((upper - lower).ravel() > 0))
    return vertices_from_codes(vertex_codes(m, n, rng), lower, upper)


def uncertain_plants(
    a_rows: np.ndarray,
    b_rows: np.ndarray,
    uncertainty: str = "none",
    *,
    box: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None,
    dA_rows: np.ndarray | None = None,
    dB_rows: np.ndarray | None = None,
    samples: int = 1,
    seed: int = 0,
) -> LinearPlant:
    """A batch of plants (3) around the nominal rows ``a_rows`` (3, 9), ``b_rows`` (3, 3).

    ``uncertainty``:
      - ``none``: one plant, the nominal;
      - ``fixed``: one plant, nominal + ``dA_rows`` (3, 9), ``dB_rows`` (3, 3);
      - ``sample``: ``samples`` plants with rows drawn uniformly in ``box``, seeded;
      - ``vertices``: ``samples`` distinct box vertices drawn with ``seed`` (all of them if
        the box has fewer).
    ``box`` is (A_lower, A_upper, B_lower, B_upper). Returns a :class:`LinearPlant` with a
    leading batch axis (NumPy float64 arrays; cast them to the dtype in use).
    """
    a_rows, b_rows = np.asarray(a_rows, float), np.asarray(b_rows, float)
    if uncertainty == "none":
        return LinearPlant(a_rows[None], b_rows[None])
    if uncertainty == "fixed":
        dA = np.zeros_like(a_rows) if dA_rows is None else np.asarray(dA_rows, float)
        dB = np.zeros_like(b_rows) if dB_rows is None else np.asarray(dB_rows, float)
        return LinearPlant((a_rows + dA)[None], (b_rows + dB)[None])
    if uncertainty not in UNCERTAINTY:
        raise ValueError(f"uncertainty must be one of {UNCERTAINTY}, got {uncertainty!r}")
    if box is None:
        raise ValueError(f"uncertainty = {uncertainty!r} needs a box")
    A_lo, A_hi, B_lo, B_hi = (np.asarray(x, float) for x in box)
    rng = np.random.default_rng(seed)
    if uncertainty == "sample":
        return LinearPlant(rng.uniform(A_lo, A_hi, (samples, 3, 9)), rng.uniform(B_lo, B_hi, (samples, 3, 3)))
    lo = np.concatenate([A_lo, B_lo], axis=1)
    hi = np.concatenate([A_hi, B_hi], axis=1)
    v = _box_vertices(rng, lo, hi, samples)
    return LinearPlant(v[:, :, :9], v[:, :, 9:])
