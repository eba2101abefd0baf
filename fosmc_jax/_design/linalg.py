"""3x3 inverse and solve written out (the adjugate over the determinant).

Every per-rollout matrix of the law and the design is 3x3: B_bar of (10) and (16), CB of (23)
and the equivalent controls. ``jnp.linalg`` would solve them with LAPACK, whose CPU kernels
split a large batch of small matrices over XLA's intra-op threads and wait for the pieces on
one of those threads: two such calls ready at once can deadlock a 2-core machine (the batch of
a large gradient, a ``vmap`` of it; docs/troubleshooting.md). Written out, they are a few dozen
multiplications that XLA fuses and the kernel printer turns into straight-line code.
"""

from __future__ import annotations

import jax.numpy as jnp
from jax import Array


def inv3(M: Array) -> Array:
    """The inverse of the 3x3 ``M`` (..., 3, 3): adj(M) / det(M) (inf or NaN where M is singular,
    as a LAPACK solve gives)."""
    m = [[M[..., i, j] for j in range(3)] for i in range(3)]
    cof = lambda i, j: (m[(i + 1) % 3][(j + 1) % 3] * m[(i + 2) % 3][(j + 2) % 3]
                        - m[(i + 1) % 3][(j + 2) % 3] * m[(i + 2) % 3][(j + 1) % 3])  # fmt: skip
    c = [[cof(i, j) for j in range(3)] for i in range(3)]
    det = m[0][0] * c[0][0] + m[0][1] * c[0][1] + m[0][2] * c[0][2]
    return jnp.stack([jnp.stack([c[j][i] for j in range(3)], -1) for i in range(3)], -2) / det[..., None, None]


def solve3(M: Array, b: Array) -> Array:
    """x with M x = b for one 3x3 ``M`` and ``b`` (3,) or (3, k)."""
    return inv3(M) @ b
