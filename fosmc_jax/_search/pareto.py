"""Pareto utilities for fronts of (tracking error, chattering), both minimised: the
non-dominated filter and the standard indicators a front is judged by, the epsilon indicators
(Zitzler et al., "Performance assessment of multiobjective optimizers", IEEE TEC 2003) and the
hypervolume in log10 of both axes. NumPy; written here because in two dimensions each is a sort
and a reduction (tests/test_pareto.py checks them against analytic cases and pymoo's)."""

from __future__ import annotations

import numpy as np


def nondominated(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Mask of the points not dominated in (x, y), both minimised (NaN points never kept;
    equal points kept together). One sort, no Python loop: in (x, y) order a point is
    dominated exactly when some earlier point that differs from it has y <= its y, i.e. the
    first of each run of equal points is kept when its y is below every earlier y, and the
    rest of the run with it."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    keep = np.zeros(x.shape, bool)
    idx = np.flatnonzero(np.isfinite(x) & np.isfinite(y))
    if not idx.size:
        return keep
    idx = idx[np.lexsort((y[idx], x[idx]))]
    xs, ys = x[idx], y[idx]
    first = np.concatenate([[True], (xs[1:] != xs[:-1]) | (ys[1:] != ys[:-1])])  # a run of equal points starts
    earlier = np.concatenate([[np.inf], np.minimum.accumulate(ys)[:-1]])  # lowest y before each point
    run = np.cumsum(first) - 1
    keep[idx] = (ys < earlier)[first][run]
    return keep


def epsilon(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]) -> float:
    """The multiplicative epsilon indicator I(A, B) of point sets a = (errors, chatterings) and
    b (Zitzler et al., "Performance assessment of multiobjective optimizers", IEEE TEC 2003):
    the smallest factor by which every point of A would have to be divided, in both metrics,
    for A to weakly dominate every point of B. I(A, B) <= 1: no point of B is better than A
    anywhere; 1.06: some point of B beats A by 6% somewhere, and none by more."""
    (ae, ac), (be, bc) = (np.asarray(x, float) for x in a), (np.asarray(x, float) for x in b)
    ratio = np.maximum(ae[:, None] / be[None, :], ac[:, None] / bc[None, :])  # (A, B)
    return float(np.max(np.min(ratio, axis=0)))


def additive_epsilon(front: tuple[np.ndarray, np.ndarray], ref: tuple[np.ndarray, np.ndarray]) -> float:
    """The additive epsilon indicator in log10 of both axes of a front a = (errors,
    chatterings) against reference points r: the smallest eps such that every r has some a
    with log10 a_err <= log10 r_err + eps and log10 a_chat <= log10 r_chat + eps, i.e.
    max_r min_a max(log10 a_err - log10 r_err, log10 a_chat - log10 r_chat). <= 0: the front
    weakly dominates every reference point; NaN with no reference point, inf with no front
    point. It is log10 of the multiplicative :func:`epsilon` (front, ref), restricted to the
    reference points given."""
    (ae, ac), (re, rc) = (tuple(np.log10(np.asarray(x, float)) for x in s) for s in (front, ref))
    if not len(re):
        return float("nan")
    if not len(ae):
        return float("inf")
    gap = np.maximum(ae[:, None] - re[None, :], ac[:, None] - rc[None, :])  # (A, R)
    return float(np.max(np.min(gap, axis=0)))


def dominated_by(point: tuple[float, float], ref: tuple[np.ndarray, np.ndarray]) -> float:
    """By how much, at most, some reference point beats one point in both axes at once, in log10:
    max_r min(log10 e - log10 r_e, log10 c - log10 r_c) (<= 0: no reference point dominates it;
    0.05: one beats it by 12% in both). The score of ``fosmc tune``'s single point."""
    (e, c), (re, rc) = np.log10(point), (np.log10(np.asarray(x, float)) for x in ref)
    return float(np.max(np.minimum(e - re, c - rc)))


def hypervolume(e: np.ndarray, c: np.ndarray, ref: tuple[float, float]) -> float:
    """Area dominated by the points (errors ``e``, chatterings ``c``) in (log10 c, log10 e) and
    bounded by ``ref`` = (log10 c, log10 e): the points' non-dominated set swept in order of
    chattering, each adding the rectangle between it, the reference point and the error of
    the point before it."""
    e, c = np.asarray(e, float), np.asarray(c, float)
    keep = nondominated(e, c)
    x, y = np.log10(c[keep]), np.log10(e[keep])
    order = np.argsort(x)
    area, y_prev = 0.0, ref[1]
    for xi, yi in zip(x[order], y[order]):
        if xi < ref[0] and yi < y_prev:
            area += (ref[0] - xi) * (y_prev - yi)
            y_prev = yi
    return float(area)
