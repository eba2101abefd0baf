"""The paper's qualitative results (Figs. 2-5) on the nominal plant, 4 s at dt = 1e-4, from
X(0) = X_d(0) with the gains (36): SGN chatters, Table 1's boundary layers remove the chattering,
and the tracking error grows with delta. Thresholds come from the physics of the problem (the
feed-forward's own variation), not from the paper's figures."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fosmc_jax as fj
from fosmc_jax import paper

DT, N = 1e-4, 40_000  # 4 s, the paper's horizon


def feedforward_variation_rate():
    """Total variation of Omega(t) of (10) per second, sampled like the simulator (t_k = k dt),
    in plain NumPy from (30): the chattering of a control that does nothing but follow the
    reference. Jumps of theta''' at 0 and tau (NOTES item 7) are included."""
    t = np.arange(N + 1) * DT
    s, e, tau = paper.THETA_START, paper.THETA_END, paper.TAU
    w = 2 * np.pi / tau
    inside = (t < tau)[:, None]
    tt = np.minimum(t, tau)[:, None]
    theta = s + (e - s) * (tt / tau - np.sin(w * tt) / (2 * np.pi))
    d1 = np.where(inside, (e - s) / tau * (1 - np.cos(w * tt)), 0.0)
    d2 = np.where(inside, (e - s) / tau * w * np.sin(w * tt), 0.0)
    d3 = np.where(inside, (e - s) / tau * w**2 * np.cos(w * tt), 0.0)
    X_d = np.stack([theta, d1, d2], axis=-1).reshape(-1, 9)  # joint by joint
    Omega = np.linalg.solve(paper.B_ROWS, (d3 - X_d @ paper.A_ROWS.T).T).T
    return np.sum(np.abs(np.diff(Omega, axis=0)), axis=0) / (N * DT)


@pytest.fixture(scope="module")
def runs():
    """{integrator: (SGN metrics, Table 1 metrics with a leading set axis)}, NumPy."""
    plant = fj.LinearPlant(jnp.asarray(paper.A_ROWS), jnp.asarray(paper.B_ROWS))
    ref = fj.Cycloid(jnp.asarray(paper.THETA_START), jnp.asarray(paper.THETA_END), jnp.asarray(paper.TAU))
    ctrl = fj.FOSMCParams(
        *(
            jnp.asarray(x)
            for x in (
                paper.C,
                paper.POLES,
                paper.GAMMA,
                paper.DELTA_SETS[0],
                paper.A_ROWS,
                paper.B_ROWS,
            )
        )
    )
    X0 = fj.desired_state(ref(jnp.asarray(0.0)))

    def run(delta, integrator, switching):
        return fj.simulate(
            plant,
            ctrl._replace(delta=delta),
            ref,
            X0,
            DT,
            n_steps=N,
            integrator=integrator,
            switching=switching,
        )

    out = {}
    for integrator in fj.INTEGRATORS:
        sign = run(ctrl.delta, integrator, "sign")
        sets = jax.vmap(run, in_axes=(0, None, None))(jnp.asarray(paper.DELTA_SETS), integrator, "ratio")
        assert not bool(sign.diverged) and not np.any(np.asarray(sets.diverged))
        out[integrator] = (
            jax.tree.map(np.asarray, sign.metrics),
            jax.tree.map(np.asarray, sets.metrics),
        )
    return out


@pytest.mark.parametrize("integrator", ["euler", "rk4"])
def test_sign_chatters_and_table1_removes_it(runs, integrator):
    sign, sets = runs[integrator]
    omega_rate = feedforward_variation_rate()  # (3,) V/s, a few V/s
    # A boundary layer leaves a control about as smooth as the feed-forward it rides on:
    # within twice the feed-forward's own variation, for every set and joint.
    assert np.all(sets.chattering <= 2 * omega_rate), (sets.chattering, omega_rate)
    # SGN switches sign step after step: its variation exceeds set 1's 1000-fold on every
    # joint (a switch of ~|(CB)^-1 rho| volts every 1e-4 s).
    assert np.all(sign.chattering >= 1e3 * sets.chattering[0]), (
        sign.chattering,
        sets.chattering[0],
    )


@pytest.mark.parametrize("integrator", ["euler", "rk4"])
def test_tracking_error_grows_with_delta(runs, integrator):
    sign, sets = runs[integrator]
    err = sets.max_abs_error  # (set, joint)
    assert np.all(np.diff(err, axis=0) > 0), err  # Fig. 5: set 1 < set 2 < set 3, every joint
    assert np.all(err[0] < 1e-2)  # set 1 tracks within 1e-2 rad
    assert np.all(sign.max_abs_error < 1e-2)  # so does SGN (Fig. 2), at the price of chattering
    # The growth is the boundary layer's, not integrator noise: set 3's is several times set 1's.
    assert np.all(err[2] > 3 * err[0])


def test_rk4_errors_below_euler(runs):
    # NOTES: Euler's own error is visible at dt = 1e-4; RK4's tracking errors are smaller.
    for k in range(3):
        assert np.all(runs["rk4"][1].max_abs_error[k] < runs["euler"][1].max_abs_error[k])
