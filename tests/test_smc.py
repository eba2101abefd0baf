"""The comparison controllers (fosmc_jax._controllers.smc): super-twisting against a hand-integrated
scalar example with finite-time convergence, SMC's boundary layer, and the config's kinds."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fosmc_jax as fj
from fosmc_jax import _problems as _config
from fosmc_jax._app.cli import main

P = fj.paper
REF = fj.Cycloid(jnp.array(P.THETA_START), jnp.array(P.THETA_END), jnp.array(P.TAU))
NOMINAL = fj.LinearPlant(jnp.array(P.A_ROWS), jnp.array(P.B_ROWS))
SURFACE = fj.SurfaceParams(jnp.array(P.C), jnp.array(P.A_ROWS), jnp.array(P.B_ROWS))
K1, K2 = 3.0, 4.0


def st_run(scale, n=4000, dt=1e-3):
    """On the nominal plant, U_eq cancels everything but the switching part, so each joint's s
    follows the unperturbed super-twisting system s' = -k1 |s|^1/2 sign s + v, v' = -k2 sign s."""
    ctrl = fj.ContinuousSuperTwisting(fj.SuperTwisting(SURFACE, jnp.full(3, K1), jnp.full(3, K2), jnp.asarray(0.0)))
    X0 = fj.desired_state(REF(0.0)) + scale * jnp.array([0.0, 0.0, 1.0, 0, 0, 0, 0, 0, 0])
    return fj.simulate(NOMINAL, ctrl, REF, X0, dt, n_steps=n, integrator="rk4", save_every=1)


def numpy_st(s0, t_final, dt=1e-5):
    """The scalar system integrated by hand in continuous time (RK4, dt = 1e-5 s), v(0) = 0."""
    f = lambda y: np.array([-K1 * np.sqrt(abs(y[0])) * np.sign(y[0]) + y[1], -K2 * np.sign(y[0])])
    y, out = np.array([s0, 0.0]), [s0]
    for _ in range(round(t_final / dt)):
        k1 = f(y)
        k2 = f(y + dt / 2 * k1)
        k3 = f(y + dt / 2 * k2)
        k4 = f(y + dt * k3)
        y = y + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        out.append(y[0])
    return np.array(out)


def convergence_time(t, s, s0, tol=1e-2):
    after = np.abs(s) > tol * abs(s0)
    return t[np.flatnonzero(after)[-1] + 1]


@pytest.mark.slow  # 5 s: the default tier keeps to 4 minutes on 2 cores
def test_super_twisting_matches_the_hand_integrated_scalar_system_and_converges_in_finite_time():
    # The simulator holds U (hence U_eq too) over each step: its s follows the scalar system
    # up to a first-order sampling error, which halves with dt.
    # Every run takes 4000 steps (n_steps is static: one compilation for all); the first 1 s of
    # each is compared.
    want = numpy_st(1.0, 1.0)
    dev = []
    for dt in (1e-3, 5e-4):
        r = st_run(1.0, dt=dt)
        s_ = np.asarray(r.trace.s[: round(1.0 / dt) + 1, 0])
        assert s_[0] == pytest.approx(1.0)  # C's theta'' coefficient for joint 1 is 1
        dev.append(np.max(np.abs(s_ - want[:: round(dt / 1e-5)])))
    assert dev[1] < 3e-3 and 1.6 < dev[0] / dev[1] < 2.5, dev
    res = st_run(1.0)
    t, s = np.asarray(res.trace.t), np.asarray(res.trace.s[:, 0])
    s0 = s[0]
    T = convergence_time(t, s, s0)
    assert T < 3.0 and np.all(np.abs(s[t >= T]) <= 1e-2 * abs(s0)) and np.max(np.abs(s[-500:])) < 1e-5
    # finite time, not exponential: the system is homogeneous (s -> l^2 s, t -> l t), so a start
    # 100x smaller converges 10x sooner; an exponential rate would take the same time to 1e-2.
    res_small = st_run(0.01)
    s_small = np.asarray(res_small.trace.s[:, 0])
    T_small = convergence_time(t, s_small, s_small[0])
    assert T_small == pytest.approx(T / 10, rel=0.25)


def test_smc_holds_s_in_the_boundary_layer_on_the_nominal_plant():
    """s' = -k sat(s / phi): outside the layer |s| falls at rate k, inside it decays as e^(-k t / phi)."""
    k, phi = 50.0, 0.5
    ctrl = fj.SMC(SURFACE, jnp.full(3, k), jnp.full(3, phi))
    X0 = fj.desired_state(REF(0.0)) + jnp.array([0.0, 0.0, 10.0, 0, 0, 0, 0, 0, 0])
    res = fj.simulate(NOMINAL, ctrl, REF, X0, 1e-4, n_steps=3000, integrator="rk4", save_every=1)
    t, s = np.asarray(res.trace.t), np.asarray(res.trace.s[:, 0])
    s0 = 10.0
    outside = t <= (s0 - phi) / k
    # (U_eq held over each 1e-4 s step drifts s by a few 1e-3 over the approach)
    np.testing.assert_allclose(s[outside], s0 - k * t[outside], rtol=0, atol=5e-3)
    t_in = (s0 - phi) / k
    assert np.all(np.abs(s[t > t_in + 1e-3]) <= phi * 1.01) and abs(s[-1]) < 0.01 * phi
    tau = phi / k  # inside the layer s decays with this time constant (the held U_eq leaves ~1e-5)
    i1, i2 = np.searchsorted(t, t_in + tau), np.searchsorted(t, t_in + 3 * tau)
    assert s[i2] / s[i1] == pytest.approx(np.exp(-(t[i2] - t[i1]) / tau), rel=0.02)


# slow: 4 compilations per kind (~12 CPU s for both); in the default tier test_tuning_kinds.py runs
# each kind from its config through the command line and holds its loss's reverse-mode gradient
# (in the log gains) to central differences
@pytest.mark.slow
@pytest.mark.parametrize("kind", ["smc", "super_twisting"])
def test_each_kind_runs_from_the_config_alone_and_is_differentiable(kind, capsys, tmp_path):
    path = tmp_path / "c.toml"
    path.write_text(f'[controller]\nkind = "{kind}"\n[sim]\nt_final = 0.2\ndt = 1e-3\nintegrator = "euler"\n')
    assert main(["simulate", "--config", str(path)]) == 0
    cfg = _config.load(path)
    pr = _config.build(cfg)
    gain = "k" if kind == "smc" else "k1"

    def loss(g):
        law = pr.controller() if kind == "smc" else pr.controller().law
        law = law.__class__(**{**law.__dict__, gain: g})
        ctrl = law if kind == "smc" else pr.controller().__class__(law)
        return jnp.sum(fj.simulate(jax.tree.map(lambda x: x[0], pr.plants), ctrl, pr.reference, pr.X0s[0], pr.dt,
                                   n_steps=200, integrator="euler").metrics.rms_error)  # fmt: skip

    g0 = jnp.asarray(cfg["controller"]["smc_k" if kind == "smc" else "st_k1"])
    grad = np.asarray(jax.grad(loss)(g0))
    e = np.eye(3)[0] * 1e-3 * float(g0[0])
    fd = (float(loss(g0 + e)) - float(loss(g0 - e))) / (2 * e[0])
    assert np.isfinite(grad).all() and grad[0] == pytest.approx(fd, rel=1e-3, abs=1e-12)


def test_certify_refuses_other_kinds(capsys, tmp_path):
    """The hitting condition (20) is the FOSMC's; tuning every kind is tests/test_tuning_kinds.py's."""
    path = tmp_path / "c.toml"
    path.write_text('[controller]\nkind = "smc"\n')
    assert main(["certify", "--config", str(path)]) == 2
    assert capsys.readouterr()[1].count("controller.kind") == 1
