"""References (30) and the feed-forward Omega of (10), against automatic differentiation of the
position alone and against the full 9x9 model in NumPy."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fosmc_jax as fj
from fosmc_jax import paper

PAPER_CYCLOID = fj.Cycloid(jnp.asarray(paper.THETA_START), jnp.asarray(paper.THETA_END), jnp.asarray(paper.TAU))
OTHER_CYCLOID = fj.Cycloid(jnp.array([0.3, -2.0, 0.0]), jnp.array([-0.4, 1.0, 0.05]), jnp.asarray(0.7))
SINUSOID = fj.Sinusoid(
    jnp.array([0.1, -0.5, 1.0]),
    jnp.array([0.8, 0.2, -0.3]),
    jnp.array([1.5, 4.0, 0.3]),
    jnp.array([0.0, 1.0, -2.0]),
)


@jax.jit  # one compilation per reference type, instead of nested jacfwd op by op at every t
def derivatives_by_autodiff(ref, t):
    """theta_d and its first three derivatives from the position row only, by nested jacfwd."""
    pos = lambda t: ref(t)[0]
    d1 = jax.jacfwd(pos)
    d2 = jax.jacfwd(d1)
    d3 = jax.jacfwd(d2)
    return jnp.stack([pos(t), d1(t), d2(t), d3(t)])


@pytest.mark.parametrize("ref", [PAPER_CYCLOID, OTHER_CYCLOID], ids=["paper", "other"])
def test_cycloid_derivatives_match_autodiff(ref):
    tau = float(ref.duration)
    for frac in (0.013, 0.25, 0.5, 0.61, 0.999, 1.2, 3.0):  # inside (0, tau), then after tau
        t = jnp.asarray(frac * tau)
        got = np.asarray(ref(t))
        assert got.shape == (4, 3)
        np.testing.assert_allclose(got, derivatives_by_autodiff(ref, t), rtol=1e-12, atol=1e-12)
    # after tau: at rest at the end point
    np.testing.assert_allclose(np.asarray(ref(jnp.asarray(1.5 * tau)))[0], np.asarray(ref.end), atol=1e-14)
    np.testing.assert_allclose(np.asarray(ref(jnp.asarray(1.5 * tau)))[1:], 0.0, atol=0)
    # and before 0: at rest at the start point
    np.testing.assert_allclose(np.asarray(ref(jnp.asarray(-0.1)))[0], np.asarray(ref.start), atol=0)


def test_cycloid_position_formula():
    # (30) written out in NumPy at a few t.
    s, e, tau = paper.THETA_START, paper.THETA_END, paper.TAU
    for t in (0.0, 0.3, 1.0, 1.7, 2.0, 2.5):
        want = s + (e - s) / (2 * np.pi) * (2 * np.pi * t / tau - np.sin(2 * np.pi * t / tau)) if t < tau else e
        np.testing.assert_allclose(np.asarray(PAPER_CYCLOID(jnp.asarray(t)))[0], want, rtol=0, atol=1e-14)


@pytest.mark.parametrize("ref", [PAPER_CYCLOID, OTHER_CYCLOID], ids=["paper", "other"])
def test_cycloid_continuity_and_jerk_jump(ref):
    # theta, theta', theta'' are continuous at t = 0 and tau (differences O(h)); theta''' jumps
    # by Delta (2 pi)^2 / tau^3 (NOTES item 7): up at 0, down at tau.
    start, end, tau = (np.asarray(x) for x in ref)
    jump = (end - start) * (2 * np.pi) ** 2 / tau**3
    h = 1e-7
    for t0, sign in ((0.0, +1.0), (float(tau), -1.0)):
        before = np.asarray(ref(jnp.asarray(t0 - h)))
        after = np.asarray(ref(jnp.asarray(t0 + h)))
        at = np.asarray(ref(jnp.asarray(t0)))
        assert np.all(np.abs(after[:3] - before[:3]) <= 1e3 * h)
        assert np.all(np.abs(at[:3] - before[:3]) <= 1e3 * h)
        np.testing.assert_allclose(after[3] - before[3], sign * jump, rtol=1e-9, atol=1e-12)


def test_sinusoid_derivatives_match_autodiff():
    for t in (0.0, 0.37, 2.0, 11.3):
        t = jnp.asarray(t)
        np.testing.assert_allclose(
            np.asarray(SINUSOID(t)), derivatives_by_autodiff(SINUSOID, t), rtol=1e-12, atol=1e-12
        )


def test_desired_state_layout():
    d = jnp.arange(12.0).reshape(4, 3)  # rows: theta, theta', theta'', theta''' ; columns: joints
    want = np.array([0, 3, 6, 1, 4, 7, 2, 5, 8], float)  # joint by joint [theta, theta', theta'']
    np.testing.assert_array_equal(np.asarray(fj.desired_state(d)), want)


@pytest.mark.parametrize("ref", [PAPER_CYCLOID, SINUSOID], ids=["cycloid", "sinusoid"])
@pytest.mark.parametrize("model", ["nominal", "perturbed"])
def test_feedforward_satisfies_10(ref, model):
    a_rows, b_rows = paper.A_ROWS, paper.B_ROWS
    if model == "perturbed":
        plant = fj.uncertain_plants(
            a_rows,
            b_rows,
            "sample",
            box=(paper.A_LOWER, paper.A_UPPER, paper.B_LOWER, paper.B_UPPER),
            seed=5,
        )
        a_rows, b_rows = plant.a_rows[0], plant.b_rows[0]
    A, B = paper.full_A(a_rows), paper.full_B(b_rows)
    for t in (0.05, 0.5, 1.3, 1.99, 2.7):
        d = np.asarray(ref(jnp.asarray(t)))
        X_d = np.concatenate([d[:3, j] for j in range(3)])  # independent of desired_state
        X_d_dot = np.concatenate([d[1:, j] for j in range(3)])  # from the reference rows
        Omega = np.asarray(fj.feedforward(jnp.asarray(a_rows), jnp.asarray(b_rows), jnp.asarray(d)))
        assert Omega.shape == (3,)
        np.testing.assert_allclose(A @ X_d + B @ Omega, X_d_dot, rtol=1e-11, atol=1e-11)
        # ... and dX_d/dt by autodiff of X_d(t)
        X_d_dot_ad = jax.jacfwd(lambda t: fj.desired_state(ref(t)))(jnp.asarray(t))
        np.testing.assert_allclose(np.asarray(X_d_dot_ad), X_d_dot, rtol=1e-12, atol=1e-12)


def test_reference_fields_can_be_traced():
    # The reference is a pytree: jit/vmap over its fields (e.g. a batch of end points).
    ends = jnp.stack([PAPER_CYCLOID.end, PAPER_CYCLOID.end + 0.1])
    f = jax.jit(jax.vmap(lambda e: fj.Cycloid(PAPER_CYCLOID.start, e, PAPER_CYCLOID.duration)(jnp.asarray(0.9))))
    got = np.asarray(f(ends))
    for i in range(2):
        np.testing.assert_allclose(
            got[i],
            np.asarray(fj.Cycloid(PAPER_CYCLOID.start, ends[i], PAPER_CYCLOID.duration)(jnp.asarray(0.9))),
            rtol=1e-14,
        )
