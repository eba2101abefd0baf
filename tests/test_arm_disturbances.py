"""Coulomb friction and external torque disturbances on the arm (issue 25, item 5): the joint
torque balance against a NumPy re-implementation, steady speeds against the analytic balance,
the simulator's clock at the integrator's stages against a plain RK4, the kernel against
vmap(simulate), the [arm] keys and [arm.uncertainty] half-widths, gradients against central
differences, and the third-order rows with the Coulomb term."""

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fosmc_jax as fj
from fosmc_jax._plants import arm as arm_model
from fosmc_jax._plants.base import derivative_at
from fosmc_jax._simulator.step import _rk4

#: An arm with every new term on: Coulomb friction, a bias, a step at 50.4 ms (between the
#: samples of dt = 1e-3 s) and a sinusoid per joint.
DIST = dict(
    Fc=np.array([1.5, 0.8, 0.3]),
    v_coulomb=0.02,
    tau_bias=np.array([2.0, -1.5, 0.3]),
    tau_step=np.array([-1.0, 2.0, -0.4]),
    t_step=0.0504,
    tau_sin=np.array([1.2, -0.7, 0.25]),
    f_sin=np.array([7.0, 13.0, 21.0]),
)
PARAMS = arm_model.ARM_PARAMS._replace(**DIST)


def np_external(p, t):
    """tau_bias + tau_step [t >= t_step] + tau_sin sin(2 pi f_sin t), NumPy."""
    return p.tau_bias + p.tau_step * (t >= p.t_step) + p.tau_sin * np.sin(2 * np.pi * p.f_sin * t)


def np_coulomb(p, dq):
    return p.Fc * np.tanh(dq / p.v_coulomb)


def random_states(n, seed):
    rng = np.random.default_rng(seed)
    return [
        arm_model.ArmState(*(tuple(jnp.asarray(x) for x in rng.normal(scale=s, size=3)) for s in (1.0, 0.05, 5.0)))
        for _ in range(n)
    ]  # rates of 0.05 rad/s: the Coulomb term's curved part (v_coulomb = 0.02)


# the autodiff oracle (tests/test_arm.py holds it to the closed form), one compilation
_oracle = jax.jit(
    lambda p, m, q, dq: (
        arm_model.mass_matrix(p, m, q),
        arm_model.coriolis_matrix(p, m, q, dq) @ dq,
        arm_model.gravity(p, m, q),
    )
)


def test_joint_torque_balance_equals_numpy():
    """M q'' + C q' + G + F q' + Fc tanh(q'/v_c) = Kt i + tau_ext(t), q'' what observe and
    derivative give at t, the new terms in NumPy, M, C q', G from the autodiff oracle: at
    random states, before and after the step (t = 0.03, 0.07 s), to 1e-10 of the torques."""
    arm = arm_model.Arm(PARAMS, 4.0)
    observe = jax.jit(lambda s, t: arm.observe(s, t))
    rates = jax.jit(lambda s, t: arm.derivative(s, jnp.zeros(3), t).dtheta)
    for state in random_states(4, seed=1):
        q, dq, i = (np.asarray(x) for x in state)
        M, Cq, G = (np.asarray(x) for x in _oracle(PARAMS, 4.0, jnp.asarray(q), jnp.asarray(dq)))
        for t in (0.03, 0.07):
            ddq = np.asarray(observe(state, t))[2::3]
            lhs = M @ ddq + Cq + G + PARAMS.F * dq + np_coulomb(PARAMS, dq)
            rhs = PARAMS.Kt * i + np_external(PARAMS, t)
            np.testing.assert_allclose(lhs, rhs, rtol=0, atol=1e-10 * np.max(np.abs(rhs)))
            np.testing.assert_allclose(np.stack(rates(state, t)), ddq, rtol=1e-13, atol=1e-12)
    # the external torque differs before and after the step and over time: t is used
    assert not np.allclose(np.asarray(observe(state, 0.03)), np.asarray(observe(state, 0.07)))


def test_init_solves_the_currents_with_the_torques_at_t0():
    """Arm.init(X0) is the state at t = 0: observe(init(X), 0) = X with a bias, a step on from
    t = 0 and Coulomb friction; observe at a later time differs (the sinusoid)."""
    arm = arm_model.Arm(PARAMS._replace(t_step=0.0), 2.0)
    X = jnp.asarray(np.random.default_rng(2).normal(size=9))
    s = arm.init(X)
    np.testing.assert_allclose(arm.observe(s, 0.0), X, atol=1e-10)
    np.testing.assert_allclose(arm.observe(s), X, atol=1e-10)  # t = 0 when left out
    assert not np.allclose(arm.observe(s, 0.01), X, atol=1e-6)


@functools.partial(jax.jit, static_argnames="n")
def _hold(arm, U, n, dt=1e-3):
    """n RK4 steps of the plant alone under constant voltages U from rest at q = 0."""
    s = arm.init(jnp.zeros(9))
    f = lambda t, y: derivative_at(arm, y, U, t)
    return jax.lax.fori_loop(0, n, lambda k, y: _rk4(f, k * dt, y, dt), s)


@pytest.mark.parametrize(
    "u1, bias1",  # in the slow tier (~4 s each): the default tier keeps to 4 minutes on 2 cores
    [
        pytest.param(4.0, 0.0, marks=pytest.mark.slow),
        pytest.param(-4.0, 1.0, marks=pytest.mark.slow),
        pytest.param(0.0, 3.2, marks=pytest.mark.slow),
    ],
)
def test_zero_gravity_steady_speed_of_the_base(u1, bias1):
    """No gravity, no offsets (d2 = d3 = 0: M12 = M13 = 0), links hanging (q2 = q3 = 0), a
    constant voltage u1 on the base (and none on the others): the base spins up to the speed w
    where Kt i = F w + Fc tanh(w/v_c) - tau_bias and u1 = R i + Kb w,
    the only root of R (F w + Fc tanh(w/v_c) - tau_bias)/Kt + Kb w = u1
    (bisection in NumPy), to 1e-9; joints 2 and 3 stay at rest (no centrifugal torque hanging
    straight). Driven by the voltage, w lies on the friction's flat part; driven by a bias just
    above Fc with the windings shorted (u1 = 0), within the smoothing scale. 4 s of RK4 at
    1 ms: over 20 time constants of the base (M11 / (F + Kt Kb/R) = 0.17 s)."""
    p = arm_model.ARM_PARAMS._replace(
        g=0.0, d2=0.0, d3=0.0, Fc=np.array([3.0, 1.0, 1.0]), v_coulomb=0.05, tau_bias=np.array([bias1, 0, 0])
    )
    s = _hold(arm_model.Arm(jax.tree.map(jnp.asarray, p), jnp.asarray(3.0)), jnp.array([u1, 0.0, 0.0]), 4000)
    R, F, Fc, v, Kt, Kb = p.R[0], p.F[0], p.Fc[0], p.v_coulomb, p.Kt[0], p.Kb[0]
    g = lambda w: R * (F * w + Fc * np.tanh(w / v) - bias1) / Kt + Kb * w - u1  # increasing in w
    lo, hi = -10.0, 10.0
    for _ in range(200):
        lo, hi = (lo, (lo + hi) / 2) if g((lo + hi) / 2) > 0 else ((lo + hi) / 2, hi)
    w = (lo + hi) / 2
    assert (abs(w) > 5 * v) == (u1 != 0)  # the flat part, or the smoothing scale
    np.testing.assert_allclose(float(s.dtheta[0]), w, rtol=1e-9)
    np.testing.assert_allclose(float(s.current[0]), (F * w + Fc * np.tanh(w / v) - bias1) / Kt, rtol=1e-8)
    assert max(abs(float(x)) for x in (*s.theta[1:], *s.dtheta[1:])) < 1e-12


@functools.partial(jax.tree_util.register_dataclass, data_fields=["U"], meta_fields=[])
@dataclasses.dataclass(frozen=True)
class Constant:
    """A controller that holds the voltages U."""

    U: jax.Array

    def init(self, X0, r0, key=None):
        return ()

    def update(self, state, Y, r, t):
        return self.U, state


@pytest.mark.slow  # 6 s: the default tier keeps to 4 minutes on 2 cores
def test_the_simulator_passes_the_stage_times():
    """fj.simulate's rollout equals a plain RK4 of the same arm written here (the external torque
    and Coulomb friction in NumPy at t_k, t_k + dt/2, t_k + dt, the mechanics from the autodiff
    oracle) over 0.1 s through the step at 50.4 ms: to 1e-9 of each quantity's scale. The same
    RK4 with the torque frozen at t_k over each step is 1e-6 or more away: the check sees the
    clock."""
    dt, n, payload = 1e-3, 100, 3.0
    U = np.array([3.0, -2.0, 0.5])
    X0 = np.array([0.2, 0.5, 0.0, -0.4, -0.3, 0.0, 0.6, 0.2, 0.0])
    arm = arm_model.Arm(jax.tree.map(jnp.asarray, PARAMS), jnp.asarray(payload))
    ref = fj.Cycloid(*(jnp.asarray(x) for x in (fj.paper.THETA_START, fj.paper.THETA_END, fj.paper.TAU)))
    res = fj.simulate(arm, Constant(jnp.asarray(U)), ref, jnp.asarray(X0), dt, n_steps=n, save_every=1)
    X = np.asarray(res.trace.X)
    no_coulomb = PARAMS._replace(Fc=np.zeros(3))
    i0 = np.stack(arm.init(jnp.asarray(X0)).current)

    def acc(q, dq, i, t):
        M, Cq, G = (np.asarray(x) for x in _oracle(no_coulomb, payload, jnp.asarray(q), jnp.asarray(dq)))
        tau = PARAMS.Kt * i + np_external(PARAMS, t) - np_coulomb(PARAMS, dq) - PARAMS.F * dq
        return np.linalg.solve(M, tau - Cq - G)

    def f(t, y):
        q, dq, i = y
        return np.stack([dq, acc(q, dq, i, t), (U - PARAMS.R * i - PARAMS.Kb * dq) / PARAMS.L])

    def run(frozen):
        y, out = np.stack([X0[0::3], X0[1::3], i0]), []
        for k in range(n):
            t = k * dt
            ts = (t, t, t) if frozen else (t + dt / 2, t + dt / 2, t + dt)
            k1 = f(t, y)
            k2 = f(ts[0], y + dt / 2 * k1)
            k3 = f(ts[1], y + dt / 2 * k2)
            k4 = f(ts[2], y + dt * k3)
            y = y + dt * (k1 + 2 * k2 + 2 * k3 + k4) / 6
            out.append(np.stack([y[0], y[1], acc(*y, (k + 1) * dt)], axis=1).ravel())
        return np.asarray(out)

    scale = np.max(np.abs(X[1:]), axis=0)
    mine = run(frozen=False)
    np.testing.assert_allclose(X[1:], mine, rtol=0, atol=1e-9 * np.max(scale))
    assert np.max(np.abs(run(frozen=True) - X[1:])) > 1e-6 * np.max(scale)


# ---------------------------------------------------------------------------- the kernel


def _disturbed(arms, seed=5):
    """``arms`` (P >= 3) with every new term drawn per arm; the first arm without Coulomb friction
    or sinusoid, so that a block mixes lanes with and without them."""
    P = arms.payload.shape[0]
    rng = np.random.default_rng(seed)
    on = np.ones((P, 1))
    on[0] = 0
    new = dict(
        Fc=rng.uniform(0.5, 3.0, (P, 3)) * on,
        v_coulomb=rng.uniform(0.005, 0.05, P),
        tau_bias=rng.uniform(-2, 2, (P, 3)),
        tau_step=rng.uniform(-2, 2, (P, 3)),
        t_step=rng.uniform(0.0, 0.03, P),  # within the 30 steps at 1 ms
        tau_sin=rng.uniform(-2, 2, (P, 3)) * on,
        f_sin=rng.uniform(1.0, 50.0, (P, 3)),
    )
    return arms._replace(params=arms.params._replace(**{k: jnp.asarray(v) for k, v in new.items()}))


def _kernel_helpers():
    tan = pytest.importorskip("test_arm_kernel")
    if tan._native._compiler() is None:
        pytest.skip("no C++ compiler: no kernel")
    return tan


@pytest.mark.slow  # two compilations of a 3 x 2 arm batch: 6-20 s
@pytest.mark.parametrize("integrator", ["euler", "rk4"])
def test_kernel_runs_the_disturbances_as_vmap_of_simulate(integrator):
    """Random arms (every parameter +-30%) with Coulomb friction, a bias, a step inside the
    horizon and a sinusoid of up to 50 Hz per arm (one arm without Coulomb friction and
    sinusoid: a block mixes lanes with and without them), from random offsets, 30 steps: the
    kernel within 1e-10 of each metric's scale of vmap(simulate). (The RK4 case fails, 6e-6
    apart, if the kernel takes the mid-step torque at t_k instead of t_k + dt/2.)"""
    tan = _kernel_helpers()
    arms = _disturbed(tan.random_arms(3))
    fast, slow = tan.both(arms, fj.FOSMC(tan.controller()), tan.cycloid(), tan.offsets(2), 1e-3, n_steps=30,
                          integrator=integrator)  # fmt: skip
    assert not np.asarray(slow.diverged).any()
    tan.assert_close(fast, slow)


@pytest.mark.slow  # the realistic preset's digital loop, kernel and vmap: ~20 s
def test_kernel_digital_loop_with_disturbances_from_the_config():
    """The [arm] keys through build into the digital loop (the realistic preset: quantized
    angles, differenced rates, a delay, 24 V) with Coulomb friction and every disturbance:
    the kernel within 1e-10 of vmap(simulate)."""
    tan = _kernel_helpers()
    changes = {f"arm.{k}": np.asarray(v).tolist() for k, v in DIST.items()}
    args, opts = tan.preset(t_final=0.1, **changes)
    Fc = np.asarray(args[0].params.Fc)
    assert Fc.shape[0] > 1 and np.all(Fc == DIST["Fc"])  # every payload's arm
    fast, slow = tan.both(*args, **opts)
    tan.assert_close(fast, slow)


# ---------------------------------------------------------------------------- the config

ARM = {"plant": {"kind": "arm", "payloads": [0.0, 5.0]}, "sim": {"t_final": 0.1, "dt": 1e-3}}


def test_the_arm_keys_default_to_no_friction_and_no_disturbance_and_build():
    cfg = fj.config.resolve(ARM)
    assert cfg["arm"]["Fc"] == [0.0] * 3 and cfg["arm"]["tau_bias"] == [0.0] * 3 and cfg["arm"]["tau_sin"] == [0.0] * 3
    assert cfg["arm"]["v_coulomb"] == arm_model.V_COULOMB
    mine = fj.build({**ARM, "arm": {k: np.asarray(v).tolist() for k, v in DIST.items()}})
    for k, v in DIST.items():
        expected = np.broadcast_to(v, (2,) + np.shape(v))
        np.testing.assert_array_equal(np.asarray(getattr(mine.plants.params, k)), expected)


@pytest.mark.parametrize(
    "arm, message",
    [({"Fc": [1.0, -0.1, 0.0]}, r"arm.Fc: expected 3 non-negative Coulomb friction levels \(N m\), got \[1.0, -0.1"),
     ({"v_coulomb": 0.0}, r"arm.v_coulomb: expected a positive velocity scale \(rad/s\), got 0.0"),
     ({"tau_bias": [1.0, 2.0]}, r"arm.tau_bias: expected 3 numbers \(N m\), got \[1.0, 2.0\]"),
     ({"tau_step": [1.0, "a", 0.0]}, r"arm.tau_step: expected 3 numbers \(N m\)"),
     ({"t_step": -0.5}, r"arm.t_step: expected a non-negative time \(s\), got -0.5"),
     ({"tau_sin": [np.inf, 0.0, 0.0]}, r"arm.tau_sin: expected 3 numbers \(N m\)"),
     ({"f_sin": [1.0, -2.0, 1.0]}, r"arm.f_sin: expected 3 non-negative frequencies \(Hz\)"),
     ({"uncertainty": {"Fc": 0.3, "samples": 4}}, r"arm.uncertainty.Fc: a relative half-width of arm.Fc = \[0.0, "
      r"0.0, 0.0\] varies nothing where it is zero \(a zero stays zero\); set arm.Fc"),
     ({"Fc": [1.0, 0.0, 0.0], "uncertainty": {"Fc": [0.1, 0.3, 0.0], "samples": 4}},
      r"arm.uncertainty.Fc: a relative half-width of arm.Fc = \[1.0, 0.0, 0.0\] varies nothing where it is zero"),
     ({"uncertainty": {"v_coulomb": 0.3, "samples": 4}},
      r"arm.uncertainty.v_coulomb: varies nothing while arm.Fc is zero; set arm.Fc$"),
     ({"uncertainty": {"f_sin": 0.3, "samples": 4}},
      r"arm.uncertainty.f_sin: varies nothing while arm.tau_sin is zero; set arm.tau_sin$"),
     ({"tau_sin": [0.0, 1.0, 0.0], "f_sin": [1.0, 0.0, 1.0]},
      r"arm.tau_sin: a sinusoid at arm.f_sin = 0 Hz is zero \(joint 2\); set arm.f_sin$"),
     ({"uncertainty": {"tau_sin": [0.5, 0.0, 0.0], "samples": 4}, "tau_sin": [0.0, 1.0, 0.0]},
      r"arm.uncertainty.tau_sin: a relative half-width of arm.tau_sin"),
     ({"uncertainty": {"t_step": 1.0, "samples": 4}},
      r"arm.uncertainty.t_step: expected a relative half-width in \[0, 1\)")],
)  # fmt: skip
def test_bad_disturbance_keys_are_refused_in_one_line(arm, message):
    with pytest.raises(fj.ConfigError, match="^" + message) as e:
        fj.config.resolve({**ARM, "arm": arm})
    assert "\n" not in str(e.value)


def test_uncertainty_in_the_coulomb_level_gives_distinct_arms():
    """[arm.uncertainty] Fc = 0.3 on arm.Fc = [2, 1, 0.5], 5 arms: each joint's level drawn in
    [0.7, 1.3] x its own, the 5 arms distinct (crossed with 2 payloads), the rest as configured."""
    cfg = {**ARM, "arm": {"Fc": [2.0, 1.0, 0.5], "tau_bias": [1.0, 0.0, 0.0],
                          "uncertainty": {"Fc": 0.3, "tau_bias": 0.5, "samples": 5, "seed": 3}}}  # fmt: skip
    drawn = fj.config.arm_samples(fj.config.resolve(cfg))
    ratio = drawn["Fc"] / np.array([2.0, 1.0, 0.5])
    assert ratio.shape == (5, 3) and np.all((ratio >= 0.7) & (ratio <= 1.3))
    assert len({tuple(r) for r in drawn["Fc"]}) == 5
    bias = drawn["tau_bias"]
    assert np.all((bias[:, 0] >= 0.5) & (bias[:, 0] <= 1.5)) and not bias[:, 1:].any()  # a zero stays zero
    problem = fj.build(cfg)
    Fc = np.asarray(problem.plants.params.Fc)
    assert Fc.shape == (10, 3)
    np.testing.assert_array_equal(Fc[0::2], drawn["Fc"])  # every arm with each payload, the arm first
    np.testing.assert_array_equal(Fc[1::2], drawn["Fc"])
    np.testing.assert_array_equal(np.asarray(problem.plants.params.F), np.broadcast_to(arm_model.ARM_PARAMS.F, (10, 3)))


def test_low_level_checks_name_the_new_fields():
    arms = fj.arm_sweep(jnp.array([1.0]), PARAMS._replace(v_coulomb=-0.01))
    ref = fj.Cycloid(*(jnp.asarray(x) for x in (fj.paper.THETA_START, fj.paper.THETA_END, fj.paper.TAU)))
    X0s = fj.desired_state(ref(0.0))[None]
    with pytest.raises(ValueError, match=r"^plants.params.v_coulomb: expected a positive velocity scale"):
        fj.simulate_batch(arms, Constant(jnp.zeros(3)), ref, X0s, 1e-3, n_steps=1)
    bad = fj.arm_sweep(jnp.array([1.0]), PARAMS._replace(Fc=np.array([1.0, 1.0])))
    with pytest.raises(ValueError, match=r"^plants.params.Fc: expected shape \(1, 3\)"):
        fj.simulate_batch(bad, Constant(jnp.zeros(3)), ref, X0s, 1e-3, n_steps=1)


# ---------------------------------------------------------------------------- derivatives


@pytest.mark.slow  # the arm in reverse mode: ~40 s
def test_gradients_in_coulomb_friction_and_bias_equal_central_differences():
    """d(mean rms_error)/dFc and /dtau_bias through with_arm (one arm, 0.1 s, a step and a
    sinusoid on), against central differences (steps 1e-4 N m): to 1e-5."""
    cfg = {**ARM, "plant": {"kind": "arm", "payloads": [5.0]},
           "arm": {k: np.asarray(v).tolist() for k, v in DIST.items()}}  # fmt: skip
    problem = fj.build(cfg)
    x0 = {name: np.asarray(problem.arm_params()[name]) for name in ("Fc", "tau_bias")}
    loss = jax.jit(lambda x: problem.with_arm(x).simulate(fast=False).mean().rms_error.mean())
    grad = jax.grad(loss)({k: jnp.asarray(v) for k, v in x0.items()})
    for name in x0:
        fd = []
        for e in np.eye(3) * 1e-4:
            up, down = dict(x0, **{name: x0[name] + e}), dict(x0, **{name: x0[name] - e})
            fd.append((float(loss(up)) - float(loss(down))) / 2e-4)
        assert np.max(np.abs(fd)) > 1e-6, name  # the loss depends on them
        np.testing.assert_allclose(np.asarray(grad[name]), fd, rtol=1e-5, atol=1e-5 * np.max(np.abs(fd)), err_msg=name)


@pytest.mark.slow  # third_order_rows and a jvp of the closed form: ~8 s
def test_third_order_rows_hold_the_coulomb_term_and_leave_the_external_torque_outside():
    """theta''' along the dynamics (the jvp of the accelerations in state and time) equals
    a X + b U + M^-1 (diag(R/L) tau_ext(t) + tau_ext'(t)) at random states with Coulomb friction
    (rates around v_c, where its curvature is) and every disturbance on, tau_ext' in NumPy;
    without the exogenous term it does not."""
    arm = arm_model.Arm(jax.tree.map(jnp.asarray, PARAMS), jnp.asarray(6.0))
    rng = np.random.default_rng(3)

    @jax.jit
    def pieces(state, U, t):
        acc = lambda s, t: arm.accelerations(s, t)
        _, jerk = jax.jvp(acc, (state, t), (arm.derivative(state, U, t), jnp.ones(())))
        X = arm.observe(state, t)
        return jerk, X, arm_model.third_order_rows(arm, X), arm_model.mass_matrix(arm.params, arm.payload, X[0::3])

    p = PARAMS
    for state in random_states(3, seed=4):
        U, t = jnp.asarray(rng.normal(scale=5.0, size=3)), 0.08
        jerk, X, (a, b), M = pieces(state, U, jnp.asarray(t))
        jerk, X, a, b, M = (np.asarray(x) for x in (jerk, X, a, b, M))
        w = 2 * np.pi * p.f_sin
        dtau = p.tau_sin * w * np.cos(w * t)  # the step is constant away from t_step
        exo = np.linalg.solve(M, p.R / p.L * np_external(p, t) + dtau)
        model = a @ X + b @ np.asarray(U)
        np.testing.assert_allclose(model + exo, jerk, rtol=1e-9, atol=1e-9 * np.max(np.abs(jerk)))
        assert np.max(np.abs(model - jerk)) > 1e-3 * np.max(np.abs(jerk))


@pytest.mark.slow  # 6 s: the default tier keeps to 4 minutes on 2 cores
def test_zero_terms_are_left_out_before_compiling_with_the_same_results():
    """The simulator drops the optional terms whose amplitudes are concretely zero (None: not
    evaluated, so the vmap path of the calibrated arm costs what it did), keeps the others and
    traced ones, and the dropped terms change no result: 20 Euler steps of the default arm with
    and without them (the jitted function behind simulate_batch, which takes the plants as they
    are) agree to 1e-12."""
    arms = fj.arm_sweep(jnp.array([0.0, 5.0]))
    kept = arm_model.without_idle_terms(arms._replace(params=arms.params._replace(tau_sin=jnp.ones((2, 3)))))
    assert all(getattr(kept.params, k) is None for k in ("Fc", "tau_bias", "tau_step"))
    assert kept.params.tau_sin is not None and kept.params.v_coulomb is not None
    inside = arm_model.without_idle_terms({"user's plant": (arms.params, arms.payload)})  # any pytree holding them
    assert inside["user's plant"][0].Fc is None and inside["user's plant"][0].R is arms.params.R
    seen = []
    jax.jit(
        lambda Fc: seen.append(
            arm_model.without_idle_terms(arms._replace(params=arms.params._replace(Fc=Fc))).params.Fc
        )
    )(jnp.zeros((2, 3)))
    assert isinstance(seen[0], jax.core.Tracer)  # traced: a derivative may follow, the term stays
    from fosmc_jax._simulator.rollout import _simulate_batch

    ref = fj.Cycloid(*(jnp.asarray(x) for x in (fj.paper.THETA_START, fj.paper.THETA_END, fj.paper.TAU)))
    X0s = fj.desired_state(ref(0.0))[None]
    opts = dict(n_steps=20, integrator="euler", fast=False)
    ctrl = Constant(jnp.array([3.0, -2.0, 0.5]))
    lean = fj.simulate_batch(arms, ctrl, ref, X0s, 1e-3, **opts)
    full = _simulate_batch(arms, ctrl, ref, X0s, 1e-3, **opts)
    for a, b in zip(lean.metrics, full.metrics):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-12, atol=1e-15)
