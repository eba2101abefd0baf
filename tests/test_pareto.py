"""The Pareto indicators (fosmc_jax.search) against analytic cases and independent computations:
the hypervolume against an exact cell count on the grid of the points' own coordinates and
against pymoo's, the epsilon indicators
against their definitions written as plain loops."""

import itertools

import numpy as np
import pytest

from fosmc_jax.search import additive_epsilon, dominated_by, epsilon, hypervolume, nondominated


def _cells_hypervolume(e, c, ref):
    """The dominated area as a sum over the cells of the grid of all coordinates: a cell counts
    when some point is below and left of it (a different algorithm from the library's sweep)."""
    x, y = np.log10(c), np.log10(e)
    xs = np.unique(np.concatenate([x[x < ref[0]], [ref[0]]]))
    ys = np.unique(np.concatenate([y[y < ref[1]], [ref[1]]]))
    area = 0.0
    for (x0, x1), (y0, y1) in itertools.product(zip(xs[:-1], xs[1:]), zip(ys[:-1], ys[1:])):
        if np.any((x <= x0) & (y <= y0)):
            area += (x1 - x0) * (y1 - y0)
    return area


def test_hypervolume_of_a_staircase_is_its_area():
    e, c = 10.0 ** np.array([-1, -2, -3, -1]), 10.0 ** np.array([0, 1, 2, 1])  # the last is dominated
    # in (log10 c, log10 e): (0, -1), (1, -2), (2, -3) under the reference (3, 0): 3 + 2 + 1
    assert hypervolume(e, c, (3.0, 0.0)) == pytest.approx(6.0, abs=1e-12)
    assert hypervolume(e[:1], c[:1], (0.0, 0.0)) == 0.0  # on the reference's edge: nothing dominated


def test_hypervolume_agrees_with_an_exact_cell_count():
    rng = np.random.default_rng(0)
    for _ in range(20):
        e, c = 10.0 ** rng.uniform(-4, 0, 30), 10.0 ** rng.uniform(-1, 1, 30)
        ref = (0.8, -0.2)
        assert hypervolume(e, c, ref) == pytest.approx(_cells_hypervolume(e, c, ref), rel=1e-12)


def test_hypervolume_agrees_with_pymoo():
    from pymoo.indicators import hv  # a dependency of fosmc front's search

    rng = np.random.default_rng(1)
    e, c = 10.0 ** rng.uniform(-4, 0, 50), 10.0 ** rng.uniform(-1, 1, 50)
    ref = (0.9, 0.1)
    theirs = hv.HV(ref_point=np.array(ref))(np.stack([np.log10(c), np.log10(e)], 1))
    assert hypervolume(e, c, ref) == pytest.approx(theirs, rel=1e-12)


def test_epsilon_indicators_follow_their_definitions():
    rng = np.random.default_rng(2)
    a = (10.0 ** rng.uniform(-3, 0, 12), 10.0 ** rng.uniform(-1, 1, 12))
    r = (10.0 ** rng.uniform(-3, 0, 9), 10.0 ** rng.uniform(-1, 1, 9))
    loops = max(
        min(max(np.log10(ae / re), np.log10(ac / rc)) for ae, ac in zip(*a)) for re, rc in zip(*r)
    )  # every reference point covered by some front point, after a shift of eps decades
    assert additive_epsilon(a, r) == pytest.approx(loops, abs=1e-12)
    assert additive_epsilon(a, r) == pytest.approx(np.log10(epsilon(a, r)), abs=1e-12)
    assert additive_epsilon(r, r) == 0.0
    assert additive_epsilon((r[0] * 10, r[1]), r) == pytest.approx(1.0)  # ten times the error: one decade
    assert np.isnan(additive_epsilon(a, (np.array([]), np.array([]))))
    point = (a[0][0], a[1][0])
    by = max(min(np.log10(point[0] / re), np.log10(point[1] / rc)) for re, rc in zip(*r))
    assert dominated_by(point, r) == pytest.approx(by, abs=1e-12)


def test_nondominated_keeps_exactly_the_points_no_other_beats():
    rng = np.random.default_rng(3)
    x, y = rng.integers(0, 6, 40).astype(float), rng.integers(0, 6, 40).astype(float)  # many ties
    beaten = [any(x[j] <= x[i] and y[j] <= y[i] and (x[j], y[j]) != (x[i], y[i]) for j in range(40)) for i in range(40)]
    np.testing.assert_array_equal(nondominated(x, y), ~np.array(beaten))
