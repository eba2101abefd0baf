"""Design quantities: alpha, beta (31), K from poles (16)/(33), gamma bounds (24)-(26), checks.

Every number is checked against an independent NumPy/SciPy computation; the paper's printed
values appear only where the point of the test is to compare with them (and it says so).
"""

import functools
import itertools

import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads
from scipy.optimize import linear_sum_assignment

import fosmc_jax as fj
from fosmc_jax import paper
from fosmc_jax._design.gains import _lambda_max_sym3

A_NOM = paper.full_A(paper.A_ROWS)
B_NOM = paper.full_B(paper.B_ROWS)


def match_spectra(computed, wanted):
    """Pair each wanted pole with one computed eigenvalue (optimal assignment); the pairs."""
    computed, wanted = np.asarray(computed, complex), np.asarray(wanted, complex).ravel()
    cost = np.abs(computed[:, None] - wanted[None, :])
    rows, cols = linear_sum_assignment(cost)
    return computed[rows], wanted[cols]


def numpy_gain(a_rows, b_rows, poles):
    """K solved independently: rows 3, 6, 9 of A + BK = block-diag companion rows, whose
    characteristic polynomials come from np.poly."""
    target = np.zeros((3, 9))
    for j in range(3):
        coeffs = np.real(np.poly(poles[j]))  # [1, a2, a1, a0]
        target[j, 3 * j : 3 * j + 3] = -coeffs[::-1][:3]
    return np.linalg.solve(b_rows, target - a_rows)


# ------------------------------------------------------------------ alpha, beta (31)


@pytest.fixture(scope="module")
def alpha_beta():
    alpha = fj.box_norm_bound(paper.A_ROWS, paper.A_LOWER, paper.A_UPPER, paper.B_ROWS)
    beta = fj.box_norm_bound(paper.B_ROWS, paper.B_LOWER, paper.B_UPPER, paper.B_ROWS)
    return alpha, beta


def test_alpha_beta_reproduce_printed_31(alpha_beta):
    # The point of this test is the comparison with the printed (31): 3 significant figures,
    # i.e. relative agreement within 5e-3. (beta = 0.6218 vs 0.6200: 0.3 % off; the box is
    # printed to two decimals, which moves the third digit of beta.)
    alpha, beta = alpha_beta
    assert alpha.value == pytest.approx(paper.ALPHA_PRINTED, rel=5e-3)
    assert beta.value == pytest.approx(paper.BETA_PRINTED, rel=5e-3)
    # 23 free entries in A's box (column 1 and a_31^13 are fixed), 9 in B's.
    assert alpha.vertices_checked == 2**23
    assert beta.vertices_checked == 2**9
    binv = np.linalg.inv(paper.B_ROWS)
    for bound, nominal, lo, hi in (
        (alpha, paper.A_ROWS, paper.A_LOWER, paper.A_UPPER),
        (beta, paper.B_ROWS, paper.B_LOWER, paper.B_UPPER),
    ):
        v = bound.vertex
        assert np.all((v == lo) | (v == hi))
        assert np.linalg.norm(binv @ (v - nominal), 2) == pytest.approx(bound.value, rel=1e-12)


def test_beta_equals_full_enumeration_in_numpy(alpha_beta):
    # B's box has 9 free entries: enumerate all 512 vertices with np.linalg.norm(., 2).
    _, beta = alpha_beta
    binv = np.linalg.inv(paper.B_ROWS)
    best = max(
        np.linalg.norm(
            binv @ (np.where(np.reshape(bits, (3, 3)), paper.B_UPPER, paper.B_LOWER) - paper.B_ROWS),
            2,
        )
        for bits in itertools.product((0, 1), repeat=9)
    )
    assert beta.value == pytest.approx(best, rel=1e-12)


def brute_force(nominal, lower, upper, b_rows):
    binv = np.linalg.inv(b_rows)
    free = np.flatnonzero((upper - lower).ravel() > 0)
    best, best_v = -1.0, None
    for bits in itertools.product((0, 1), repeat=free.size):
        v = lower.copy()
        v.flat[free[np.array(bits, bool)]] = upper.flat[free[np.array(bits, bool)]]
        n = np.linalg.norm(binv @ (v - nominal), 2)
        if n > best:
            best, best_v = n, v
    return best, best_v, free.size


@pytest.mark.parametrize("chunk_bits", [16, 3])
@pytest.mark.parametrize("seed", [0, 1])
def test_box_norm_bound_equals_brute_force(seed, chunk_bits):
    # A 3x5 box with 10 free entries and 5 fixed ones (lower == upper, not at the nominal).
    # chunk_bits = 3 forces 2^7 chunks, exercising the chunked enumeration.
    rng = np.random.default_rng(seed)
    nominal = rng.normal(size=(3, 5))
    lower = nominal - rng.uniform(0.1, 2.0, size=(3, 5))
    upper = nominal + rng.uniform(0.1, 2.0, size=(3, 5))
    fixed = rng.permutation(15)[:5]
    lower.flat[fixed] = upper.flat[fixed] = nominal.flat[fixed] + rng.normal(size=5)
    b_rows = rng.normal(size=(3, 3)) + 3 * np.eye(3)

    value, _, m = brute_force(nominal, lower, upper, b_rows)
    got = fj.box_norm_bound(nominal, lower, upper, b_rows, chunk_bits=chunk_bits)
    assert m == 10 and got.vertices_checked == 2**10
    assert got.value == pytest.approx(value, rel=1e-10)
    # The returned vertex is a vertex and attains the value.
    assert np.all((got.vertex == lower) | (got.vertex == upper))
    attained = np.linalg.norm(np.linalg.inv(b_rows) @ (got.vertex - nominal), 2)
    assert attained == pytest.approx(value, rel=1e-10)


def test_box_norm_bound_rejects_bad_boxes():
    z = np.zeros((3, 3))
    with pytest.raises(fj.DesignError):
        fj.box_norm_bound(z, z + 1, z, np.eye(3))  # lower > upper
    with pytest.raises(fj.DesignError):
        fj.box_norm_bound(np.zeros((3, 11)), np.zeros((3, 11)), np.ones((3, 11)), np.eye(3), max_free=30)


# ------------------------------------------------------------------ closed-form lambda_max


def special_symmetric():
    rng = np.random.default_rng(3)
    Q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    rot = lambda d: Q @ np.diag(d) @ Q.T
    x = rng.normal(size=3)
    return np.stack(
        [
            np.zeros((3, 3)),
            2.5 * np.eye(3),
            -np.eye(3),
            np.diag([2.0, 2.0, 1.0]),
            np.diag([1.0, 2.0, 2.0]),
            rot([3.0, 3.0, -1.0]),  # repeated largest
            rot([3.0, -1.0, -1.0]),  # repeated smallest
            np.outer(x, x),  # rank one
            rot([1e-3, 0.0, 0.0]),
            rot([1e6, 1.0, -1e6]),
        ]
    )


def test_lambda_max_sym3_matches_eigvalsh():
    rng = np.random.default_rng(0)
    M = rng.normal(size=(2000, 3, 3)) * rng.lognormal(0, 2, size=(2000, 1, 1))
    G = np.concatenate([M + np.swapaxes(M, 1, 2), M @ np.swapaxes(M, 1, 2), special_symmetric()])
    got = np.asarray(_lambda_max_sym3(jnp.asarray(G)))
    want = np.linalg.eigvalsh(G)[:, -1]
    scale = np.abs(np.linalg.eigvalsh(G)).max(axis=1)
    # The trigonometric formula loses up to sqrt(eps) relative accuracy when the two smallest
    # eigenvalues coincide (arccos near -1); 1e-7 of the matrix's scale covers it.
    assert np.all(np.abs(got - want) <= 1e-7 * np.maximum(scale, 1e-300))
    assert got[-10] == 0.0  # zero matrix, exactly


# ------------------------------------------------------------------ K from poles


POLE_CASES = {
    "paper_33": paper.POLES,
    "repeated_within_joint": np.array([[-1.0, -1.0, -2.0], [-2.0, -2.0, -2.0], [-0.5, -0.5, -0.05]]),
    "complex_pair": np.array([[-1 + 2j, -1 - 2j, -4], [-0.3, -0.31, -3.0], [-0.2 + 0.05j, -0.2 - 0.05j, -0.03]]),
}


@pytest.mark.parametrize("case", sorted(POLE_CASES))
def test_gain_from_poles_places_poles(case):
    poles = POLE_CASES[case]
    K = np.asarray(fj.gain_from_poles(jnp.asarray(paper.A_ROWS), jnp.asarray(paper.B_ROWS), jnp.asarray(poles)))
    assert K.shape == (3, 9) and K.dtype == np.float64
    np.testing.assert_allclose(K, numpy_gain(paper.A_ROWS, paper.B_ROWS, poles), rtol=1e-10, atol=1e-12)

    A_cl_lib = np.asarray(fj.closed_loop_matrix(jnp.asarray(paper.A_ROWS), jnp.asarray(paper.B_ROWS), jnp.asarray(K)))
    A_cl_np = A_NOM + B_NOM @ K  # independent 9x9 construction
    np.testing.assert_allclose(A_cl_lib, A_cl_np, rtol=1e-13, atol=1e-12)

    # det(sI - A_cl) = prod (s - p_i): well conditioned even for repeated poles.
    for s in (0.7, -0.1 + 0.4j, 2.0j, -5.0):
        lhs = np.linalg.det(s * np.eye(9) - A_cl_np)
        rhs = np.prod(s - poles.ravel())
        assert abs(lhs - rhs) <= 1e-9 * abs(rhs)

    # Eigenvalues, relative to each pole's size (poles near -0.03 are small). A pole of
    # multiplicity k is computed to about eps^(1/k) relative accuracy: 1e-3 covers k = 3.
    eig, want = match_spectra(np.linalg.eigvals(A_cl_np), poles)
    mult = np.array([np.sum(np.abs(poles.ravel() - p) < 1e-12) for p in want])
    rtol = np.where(mult == 1, 1e-8, np.where(mult == 2, 1e-6, 1e-3))
    assert np.all(np.abs(eig - want) <= rtol * np.abs(want)), (eig, want)
    assert np.all(np.linalg.eigvals(A_cl_lib).real < 0)


def test_printed_K_is_for_A_minus_BK_and_not_stabilising():
    # NOTES item 3: computed, not copied. The point here is to compare with the printed (32).
    K = numpy_gain(paper.A_ROWS, paper.B_ROWS, paper.POLES)
    # Sign convention: the printed K is -K up to its two-decimal rounding and the paper's
    # own rounding of A, B; it is nowhere near +K.
    assert np.max(np.abs(paper.K_PRINTED + K)) < 0.07
    assert np.max(np.abs(paper.K_PRINTED - K)) > 1.0

    minus = np.linalg.eigvals(A_NOM - B_NOM @ paper.K_PRINTED)
    plus = np.linalg.eigvals(A_NOM + B_NOM @ paper.K_PRINTED)
    poles = paper.POLES.ravel()
    far = lambda ev: np.max(np.min(np.abs(ev[:, None] - poles[None, :]), axis=1))
    # A - B K_printed: every eigenvalue within 1 of a pole of (33) (close-ish); A + B K_printed:
    # some eigenvalue more than 5 away, and a spectral radius over 4 x that of (33).
    assert far(minus) < 1.0
    assert far(plus) > 5.0
    assert np.max(np.abs(plus)) > 4 * np.max(np.abs(poles))
    # ... but the rounded A - B K_printed is unstable (a pair near 0.25 +/- 0.21j).
    assert np.max(minus.real) > 0.1
    unstable = minus[minus.real > 0]
    assert unstable.size == 2 and np.all(np.abs(unstable.imag) > 0.1)
    # So is the exact K rounded to two decimals: the poles near -0.03 are that sensitive.
    assert np.max(np.linalg.eigvals(A_NOM + B_NOM @ np.round(K, 2)).real) > 0


@pytest.mark.slow  # 3 s: the default tier keeps to 4 minutes on 2 cores
def test_gain_from_poles_is_differentiable():
    a, b = jnp.asarray(paper.A_ROWS), jnp.asarray(paper.B_ROWS)
    check_grads(
        lambda p: fj.gain_from_poles(a, b, p),
        (jnp.asarray(paper.POLES),),
        order=1,
        modes=("fwd", "rev"),
    )
    # and in the model rows
    check_grads(lambda a, b: fj.gain_from_poles(a, b, jnp.asarray(paper.POLES)), (a, b), order=1)


# ------------------------------------------------------------------ gamma bounds (24)-(26)


def numpy_gamma_bounds(alpha, beta, C, b_rows, K, n_cb_kind):
    CB = C @ paper.full_B(b_rows)
    sv = np.linalg.svd(CB, compute_uv=False)
    n_cb = sv.max() if n_cb_kind == "max" else sv.min()
    n_cbk = np.linalg.norm(CB @ K, 2)
    return np.array([alpha * n_cb + n_cbk, alpha * n_cb, beta * n_cb]) / (1 + beta)


def test_gamma_bounds_match_numpy_in_both_conventions():
    rng = np.random.default_rng(7)
    for C, b_rows, K, alpha, beta in [
        (paper.C, paper.B_ROWS, numpy_gain(paper.A_ROWS, paper.B_ROWS, paper.POLES), 5.98, 0.62),
        (
            paper.C * rng.uniform(0.5, 2, (3, 9)),
            paper.B_ROWS + rng.normal(size=(3, 3)),
            rng.normal(size=(3, 9)),
            1.3,
            0.2,
        ),
    ]:
        args = (alpha, beta, jnp.asarray(C), jnp.asarray(b_rows), jnp.asarray(K))
        spec = np.asarray(fj.gamma_bounds(*args, convention="spectral"))
        pap = np.asarray(fj.gamma_bounds(*args, convention="paper"))
        np.testing.assert_allclose(spec, numpy_gamma_bounds(alpha, beta, C, b_rows, K, "max"), rtol=1e-12)
        np.testing.assert_allclose(pap, numpy_gamma_bounds(alpha, beta, C, b_rows, K, "min"), rtol=1e-12)
    with pytest.raises(fj.DesignError):
        fj.gamma_bounds(*args, convention="frobenius")


def test_gamma_bounds_paper_convention_reproduces_printed_35():
    # The point of this test is the comparison with the printed (35) (NOTES item 4), fed the
    # printed alpha, beta of (31).
    K = jnp.asarray(numpy_gain(paper.A_ROWS, paper.B_ROWS, paper.POLES))
    args = (
        paper.ALPHA_PRINTED,
        paper.BETA_PRINTED,
        jnp.asarray(paper.C),
        jnp.asarray(paper.B_ROWS),
        K,
    )
    pap = np.asarray(fj.gamma_bounds(*args, convention="paper"))
    spec = np.asarray(fj.gamma_bounds(*args, convention="spectral"))
    np.testing.assert_allclose(pap[1:], paper.GAMMA_MIN_PRINTED[1:], rtol=1e-2)
    # The spectral convention is larger by cond(CB) (independently: NumPy's singular values),
    # about ten times, and misses (35) by far.
    sv = np.linalg.svd(paper.C @ B_NOM, compute_uv=False)
    np.testing.assert_allclose(spec[1:] / pap[1:], sv[0] / sv[-1], rtol=1e-12)
    assert 8 < sv[0] / sv[-1] < 12
    assert np.all(spec[1:] > 5 * paper.GAMMA_MIN_PRINTED[1:])
    # gamma_1 of (35) is reproduced by neither convention (NOTES item 4).
    assert abs(pap[0] / paper.GAMMA_MIN_PRINTED[0] - 1) > 0.5
    assert abs(spec[0] / paper.GAMMA_MIN_PRINTED[0] - 1) > 0.5


def test_gamma_bounds_differentiable_in_K():
    args = (5.98, 0.62, jnp.asarray(paper.C), jnp.asarray(paper.B_ROWS))
    a_rows = jnp.asarray(paper.A_ROWS)
    for conv in fj.CONVENTIONS:
        bounds = functools.partial(
            lambda p, c: fj.gamma_bounds(*args, fj.gain_from_poles(a_rows, args[3], p), c), c=conv
        )
        check_grads(bounds, (jnp.asarray(paper.POLES),), order=1)


# ------------------------------------------------------------------ structural checks


def test_check_design():
    fj.check_design(paper.B_ROWS, paper.C, paper.POLES)  # the paper's design passes
    C0 = paper.C.copy()
    C0[1] = 0.0
    with pytest.raises(fj.DesignError, match="singular"):
        fj.check_design(paper.B_ROWS, C0, paper.POLES)
    for bad in (0.0, 0.1, 1j):
        poles = paper.POLES.astype(complex)
        poles[2, 0] = bad
        with pytest.raises(fj.DesignError, match="negative real"):
            fj.check_design(paper.B_ROWS, paper.C, poles)


def test_check_design_rank_deficient_C_without_zero_row():
    # CB singular with no zero row in C: C = [c1; c2; c1], so CB has two equal rows.
    C = paper.C.copy()
    C[2] = paper.C[0]
    assert np.linalg.matrix_rank(C @ B_NOM) == 2
    with pytest.raises(fj.DesignError):
        fj.check_design(paper.B_ROWS, C, paper.POLES)


def test_matching_condition():
    rng = np.random.default_rng(11)
    rows = list(paper.ROWS)
    dA = np.zeros((9, 9))
    dA[rows] = rng.normal(size=(3, 9))
    dB = np.zeros((9, 3))
    dB[rows] = rng.normal(size=(3, 3))
    assert fj.matching_condition(B_NOM, dA, dB)
    fj.check_matching(B_NOM, dA, dB)

    dA_bad = dA.copy()
    dA_bad[0, 4] = 0.5  # row 1 of dA: not in the range of B
    assert not fj.matching_condition(B_NOM, dA_bad, dB)
    with pytest.raises(fj.DesignError):
        fj.check_matching(B_NOM, dA_bad, dB)
    dB_bad = dB.copy()
    dB_bad[4, 1] = 1e-3
    assert not fj.matching_condition(B_NOM, dA, dB_bad)
