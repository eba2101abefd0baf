"""Controller design: the gain K from pole locations, the uncertainty bounds alpha and beta
(31), the gamma lower bounds (24)-(26), and the structural checks the paper assumes.

Everything that the tuner may differentiate (``gain_from_poles``, ``gamma_bounds``) is pure
JAX; the vertex enumeration of ``box_norm_bound`` is JAX too, vectorised over chunks of
vertices, but is not meant to be differentiated.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from .linalg import solve3
from .paper import ROWS


class DesignError(ValueError):
    """A design input violates an assumption of the paper (one-line message)."""


# ---------------------------------------------------------------------------- K from poles


def input_matrix_product(C, b_rows):
    """CB (3x3) for C (3x9) and B given by its rows 3, 6, 9; NumPy or JAX arrays."""
    return C[:, list(ROWS)] @ b_rows


def characteristic_coefficients(poles: Array) -> Array:
    """Coefficients [a0, a1, a2] of (s - p1)(s - p2)(s - p3) = s^3 + a2 s^2 + a1 s + a0.

    ``poles``: (..., 3), real or complex (complex poles must come in conjugate pairs; the
    imaginary part of the coefficients is dropped). Returns (..., 3), real.
    """
    p1, p2, p3 = poles[..., 0], poles[..., 1], poles[..., 2]
    a2 = -(p1 + p2 + p3)
    a1 = p1 * p2 + p1 * p3 + p2 * p3
    a0 = -p1 * p2 * p3
    return jnp.real(jnp.stack([a0, a1, a2], axis=-1))


def gain_from_poles(a_rows: Array, b_rows: Array, poles: Array) -> Array:
    """Gain K (3x9) such that A + BK (condition (16)) has the requested poles.

    Because rows 3, 6, 9 of B form the invertible B_bar, K is solved exactly: the rows 3, 6,
    9 of A + BK are set to a block-diagonal companion form, joint i's block having the
    characteristic polynomial with roots ``poles[i]``. Repeated poles are fine; the map is
    differentiable in ``poles``, ``a_rows`` and ``b_rows``.

    Args:
      a_rows: (3, 9) rows 3, 6, 9 of A.
      b_rows: (3, 3) rows 3, 6, 9 of B (B_bar).
      poles: (3, 3) poles per joint (1/s), one row per joint.
    """
    coeffs = characteristic_coefficients(poles)  # (3, 3): joint, [a0, a1, a2]
    target = jnp.zeros_like(a_rows)
    for j in range(3):
        target = target.at[j, 3 * j : 3 * j + 3].set(-coeffs[j].astype(a_rows.dtype))
    return solve3(b_rows, target - a_rows)


def closed_loop_matrix(a_rows: Array, b_rows: Array, K: Array) -> Array:
    """The 9x9 matrix A + BK of (16) and (19)."""
    A = jnp.zeros((9, 9), a_rows.dtype)
    for j in range(3):
        A = A.at[3 * j, 3 * j + 1].set(1.0).at[3 * j + 1, 3 * j + 2].set(1.0)
    return A.at[jnp.array(ROWS)].set(a_rows + b_rows @ K)


# ---------------------------------------------------------------------------- checks

#: Extent of the stability region of each fixed-step scheme on the negative real axis.
_STABILITY_EXTENT = {"euler": 2.0, "rk4": 2.785}


def stable_step(a_rows, b_rows, poles, integrator: str) -> float:
    """Largest step (s) at which ``integrator`` is stable on the fastest mode of the nominal
    model: of A (open loop) and of A + BK (the sliding dynamics (19)), by the extent of the
    scheme's stability region on the real axis over the largest |eigenvalue|. A rule of
    thumb for a warning, not a guarantee (the switching term adds its own fast dynamics)."""
    with jax.enable_x64(True):
        a, b, p = (jnp.asarray(np.asarray(x, dtype=np.float64)) for x in (a_rows, b_rows, poles))
        modes = np.asarray(_modes(a, b, p))
    fastest = max(np.abs(np.linalg.eigvals(M)).max() for M in modes)
    return _STABILITY_EXTENT[integrator] / fastest


@jax.jit
def _modes(a_rows: Array, b_rows: Array, poles: Array) -> Array:
    """A and A + BK (2, 9, 9): one compiled program (every simulate checks its step with it;
    run op by op, its few dozen operations compiled a program each, 1 s per process)."""
    K = gain_from_poles(a_rows, b_rows, poles)
    return jnp.stack([closed_loop_matrix(a_rows, b_rows, G) for G in (jnp.zeros_like(K), K)])


def check_design(b_rows, C, poles) -> None:
    """Raise :class:`DesignError` if CB is singular or a pole is not in the open left half-plane.

    ``b_rows`` (3, 3), ``C`` (3, 9), ``poles`` (3, 3). NumPy inputs; called before tracing.
    """
    CB = input_matrix_product(np.asarray(C), np.asarray(b_rows))
    s = np.linalg.svd(CB, compute_uv=False)
    if not np.all(np.isfinite(s)) or s[-1] <= 1e-12 * max(s[0], 1e-300):
        raise DesignError(f"CB = C B is singular (singular values {s.tolist()}); choose another C")
    poles = np.asarray(poles)
    if np.any(np.real(poles) >= 0):
        bad = poles[np.real(poles) >= 0].tolist()
        raise DesignError(f"poles must have negative real parts (condition (16)); got {bad}")


def matching_condition(B: np.ndarray, dA: np.ndarray, dB: np.ndarray, tol: float = 1e-9) -> bool:
    """Rank conditions (11)-(12): rank[B] = rank[B, dA] = rank[B, dB] (full 9-row matrices)."""
    B, dA, dB = (np.asarray(M, dtype=float) for M in (B, dA, dB))
    scale = max(np.abs(B).max(), np.abs(dA).max(), np.abs(dB).max(), 1.0)
    r = lambda M: np.linalg.matrix_rank(M, tol=tol * scale)
    return r(B) == r(np.hstack([B, dA])) == r(np.hstack([B, dB]))


def check_matching(B: np.ndarray, dA: np.ndarray, dB: np.ndarray) -> None:
    """Raise :class:`DesignError` unless the matching condition (11)-(12) holds."""
    if not matching_condition(B, dA, dB):
        raise DesignError("uncertainty is not matched: rank[B] != rank[B, dA] or rank[B, dB] (11)-(12)")


# ---------------------------------------------------------------------------- alpha, beta


def _lambda_max_sym3(G: Array) -> Array:
    """Largest eigenvalue of symmetric 3x3 matrices G (..., 3, 3), in closed form."""
    a00, a11, a22 = G[..., 0, 0], G[..., 1, 1], G[..., 2, 2]
    a01, a02, a12 = G[..., 0, 1], G[..., 0, 2], G[..., 1, 2]
    q = (a00 + a11 + a22) / 3
    p1 = a01**2 + a02**2 + a12**2
    p2 = (a00 - q) ** 2 + (a11 - q) ** 2 + (a22 - q) ** 2 + 2 * p1
    p = jnp.sqrt(p2 / 6)
    safe_p = jnp.where(p > 0, p, 1.0)
    b00, b11, b22 = (a00 - q) / safe_p, (a11 - q) / safe_p, (a22 - q) / safe_p
    b01, b02, b12 = a01 / safe_p, a02 / safe_p, a12 / safe_p
    det = b00 * (b11 * b22 - b12**2) - b01 * (b01 * b22 - b12 * b02) + b02 * (b01 * b12 - b11 * b02)
    phi = jnp.arccos(jnp.clip(det / 2, -1.0, 1.0)) / 3
    return jnp.where(p > 0, q + 2 * p * jnp.cos(phi), q)


@functools.partial(jax.jit, static_argnames="bits")
def _vertex_max(H_lo: Array, steps: Array, bits: int) -> tuple[Array, Array]:
    """max of lambda_max(H H^T) over H = H_lo + sum_j v_j steps[j], v in {0, 1}^m, enumerated in
    chunks of 2^bits vertices; returns the value and the winning vertex's bit code. Compiled
    once per box shape (module level, so repeated calls do not recompile)."""
    m = steps.shape[0]
    shifts = jnp.arange(m, dtype=jnp.int32)
    local = jnp.arange(2**bits, dtype=jnp.int32)

    def chunk(c):
        idx = c * (2**bits) + local
        v = ((idx[:, None] >> shifts) & 1).astype(H_lo.dtype)
        H = H_lo + jnp.einsum("vm,mij->vij", v, steps)
        lam = _lambda_max_sym3(H @ jnp.swapaxes(H, -1, -2))
        k = jnp.argmax(lam)
        return lam[k], idx[k]

    lam, idx = jax.lax.map(chunk, jnp.arange(2 ** (m - bits), dtype=jnp.int32))
    k = jnp.argmax(lam)
    return lam[k], idx[k]


class BoxBound(NamedTuple):
    """Result of :func:`box_norm_bound`: the bound and the box vertex that attains it."""

    value: float
    vertex: np.ndarray
    vertices_checked: int


def box_norm_bound(
    nominal: np.ndarray,
    lower: np.ndarray,
    upper: np.ndarray,
    b_rows: np.ndarray,
    chunk_bits: int = 16,
    max_free: int = 30,
) -> BoxBound:
    """max ||B_bar^-1 (V - nominal)||_2 over the vertices V of the box [lower, upper].

    This is alpha of (31) with ``nominal = A_rows`` (3x9), and beta with ``nominal = B_rows``
    (3x3). The spectral norm is convex, so its maximum over the box is at a vertex and the
    enumeration is exact. Entries with lower == upper are not free. All 2^m vertices of the m
    free entries are enumerated in chunks of 2^chunk_bits, in JAX (2^23 vertices take about a
    second on one CPU core).
    """
    nominal, lower, upper, b_rows = (np.asarray(x, dtype=np.float64) for x in (nominal, lower, upper, b_rows))
    if np.any(lower > upper):
        raise DesignError("box has lower > upper in some entry")
    width = upper - lower
    free = np.flatnonzero(width.ravel() > 0)
    m = free.size
    if m > max_free:
        raise DesignError(f"box has {m} free entries: 2^{m} vertices is too many to enumerate")
    b_inv = np.linalg.inv(b_rows)
    shape = nominal.shape
    H_lo = b_inv @ (lower - nominal)
    steps = np.zeros((m,) + shape)
    for j, flat in enumerate(free):
        e = np.zeros(shape)
        e.flat[flat] = width.flat[flat]
        steps[j] = b_inv @ e
    lam, idx = _vertex_max(jnp.asarray(H_lo), jnp.asarray(steps), bits=min(chunk_bits, m))
    idx = int(idx)
    vertex = lower.copy()
    for j, flat in enumerate(free):
        if (idx >> j) & 1:
            vertex.flat[flat] = upper.flat[flat]
    value = float(np.linalg.norm(b_inv @ (vertex - nominal), 2))  # exact, for the winner
    return BoxBound(value, vertex, 2**m)


# ---------------------------------------------------------------------------- gamma bounds

#: Norm conventions for (24)-(26). ``spectral``: every norm is the 2-norm, as written.
#: ``paper``: ||CB|| read as the smallest singular value of CB (docs/paper.md), which
#: reproduces the paper's gamma_2 and gamma_3 bounds in (35); ||CBK|| stays a 2-norm.
CONVENTIONS = ("spectral", "paper")


def gamma_bounds(alpha, beta, C: Array, b_rows: Array, K: Array, convention: str = "spectral") -> Array:
    """Lower bounds (24)-(26) on gamma = [gamma_1, gamma_2, gamma_3], shape (3,).

    gamma_1 > (alpha ||CB|| + ||CBK||) / (1 + beta), gamma_2 > alpha ||CB|| / (1 + beta),
    gamma_3 > beta ||CB|| / (1 + beta), with the norm convention named (see ``CONVENTIONS``).
    Differentiable in ``K`` (and hence in the poles), for tuning.
    """
    if convention not in CONVENTIONS:
        raise DesignError(f"convention must be one of {CONVENTIONS}, got {convention!r}")
    CB = input_matrix_product(C, b_rows)
    s_cb = jnp.linalg.svd(CB, compute_uv=False)
    n_cb = s_cb[0] if convention == "spectral" else s_cb[-1]
    n_cbk = jnp.linalg.svd(CB @ K, compute_uv=False)[0]
    return jnp.stack([alpha * n_cb + n_cbk, alpha * n_cb, beta * n_cb]) / (1 + beta)


# ---------------------------------------------------------------------------- summary


class DesignSummary(NamedTuple):
    """Everything the paper derives for a design: (31), (32)-(33), CB and (35)."""

    alpha: BoxBound  # max ||H|| over the box of A's rows, (8), (31)
    beta: BoxBound  # max ||E|| over the box of B's rows, (9), (31)
    K: np.ndarray  # (3, 9) from the poles, (16)
    closed_loop_poles: np.ndarray  # (9,) complex, eig(A + BK)
    CB: np.ndarray  # (3, 3)
    gamma_min: dict[str, np.ndarray]  # convention -> (3,) lower bounds (24)-(26)


def summarize(a_rows, b_rows, box, C, poles) -> DesignSummary:
    """Design quantities for the nominal rows ``a_rows`` (3, 9), ``b_rows`` (3, 3), the box
    (A_lower, A_upper, B_lower, B_upper), ``C`` (3, 9) and ``poles`` (3, 3); float64 NumPy."""
    a_rows, b_rows, C, poles = (np.asarray(x, dtype=np.float64) for x in (a_rows, b_rows, C, poles))
    check_design(b_rows, C, poles)
    A_lo, A_hi, B_lo, B_hi = box
    alpha = box_norm_bound(a_rows, A_lo, A_hi, b_rows)
    beta = box_norm_bound(b_rows, B_lo, B_hi, b_rows)
    with jax.enable_x64(True):
        K = np.asarray(gain_from_poles(jnp.asarray(a_rows), jnp.asarray(b_rows), jnp.asarray(poles)))
        gmin = {
            c: np.asarray(gamma_bounds(alpha.value, beta.value, jnp.asarray(C), jnp.asarray(b_rows), jnp.asarray(K), c))
            for c in CONVENTIONS
        }
        A_cl = np.asarray(closed_loop_matrix(jnp.asarray(a_rows), jnp.asarray(b_rows), jnp.asarray(K)))
    eig = np.linalg.eigvals(A_cl)
    eig = eig[np.lexsort((eig.imag, eig.real))]
    return DesignSummary(alpha, beta, K, eig, input_matrix_product(C, b_rows), gmin)
