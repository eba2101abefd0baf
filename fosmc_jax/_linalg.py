"""Small dense linear algebra written out for 3x3 matrices.

XLA on CPU calls LAPACK for ``jnp.linalg.solve``; for a 3x3 system inside a time loop that
call costs far more than the arithmetic. The adjugate formula below is a handful of fused
multiply-adds, batches under ``vmap`` and differentiates like any other expression.
"""

from __future__ import annotations

import jax.numpy as jnp
from jax import Array


def inv3(M: Array) -> Array:
    """Inverse of a 3x3 matrix (..., 3, 3) by the adjugate: adj(M) / det(M)."""
    a, b, c = M[..., 0, 0], M[..., 0, 1], M[..., 0, 2]
    d, e, f = M[..., 1, 0], M[..., 1, 1], M[..., 1, 2]
    g, h, i = M[..., 2, 0], M[..., 2, 1], M[..., 2, 2]
    A, B, C = e * i - f * h, f * g - d * i, d * h - e * g
    det = a * A + b * B + c * C
    adj = jnp.stack(
        [
            jnp.stack([A, c * h - b * i, b * f - c * e], axis=-1),
            jnp.stack([B, a * i - c * g, c * d - a * f], axis=-1),
            jnp.stack([C, b * g - a * h, a * e - b * d], axis=-1),
        ],
        axis=-2,
    )
    return adj / det[..., None, None]


def solve3(M: Array, b: Array) -> Array:
    """Solution x of M x = b for a 3x3 ``M`` and ``b`` of shape (3,) or (3, k)."""
    return inv3(M) @ b
