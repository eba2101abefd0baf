"""The vertices of an uncertainty box [lower, upper] (entries with lower == upper are not free),
named by integer codes: bit j of a code sets the j-th free entry (C order) to its upper bound.
The linear plant's ``vertices`` batch and the certificate's vertex checks draw them here."""

from __future__ import annotations

import numpy as np


def vertex_codes(m: int, n: int, rng: np.random.Generator) -> np.ndarray:
    """All 2^m vertex codes if 2^m <= n, else n distinct ones drawn with ``rng`` (int64)."""
    if 2**m <= n:
        return np.arange(2**m, dtype=np.int64)
    codes = np.unique(rng.integers(0, 2**m, size=2 * n, dtype=np.int64))
    while codes.size < n:
        codes = np.unique(np.concatenate([codes, rng.integers(0, 2**m, size=n, dtype=np.int64)]))
    return rng.permutation(codes)[:n]


def vertices_from_codes(codes: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """Box vertices (len(codes), *lower.shape): bit j of a code sets free entry j (the j-th entry,
    in C order, with lower < upper) to its upper bound."""
    free = np.flatnonzero((upper - lower).ravel() > 0)
    bits = (codes[:, None] >> np.arange(free.size)) & 1
    out = np.broadcast_to(lower.ravel(), (codes.size, lower.size)).copy()
    out[:, free] = np.where(bits == 1, upper.ravel()[free], lower.ravel()[free])
    return out.reshape((codes.size,) + lower.shape)


def code_of(vertex: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> int:
    free = np.flatnonzero((upper - lower).ravel() > 0)
    v, hi = vertex.ravel()[free], upper.ravel()[free]
    return int(sum(1 << j for j in range(free.size) if v[j] == hi[j]))
