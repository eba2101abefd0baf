"""The physical arm plant (fosmc_jax._plants.arm): physics, payload handling, closed loop."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

jax.config.update("jax_enable_x64", True)

import fosmc_jax as fj  # noqa: E402
from fosmc_jax import paper  # noqa: E402
from fosmc_jax._plants.arm import (  # noqa: E402
    ARM_PARAMS,
    PAYLOAD_RANGE,
    Arm,
    ArmParams,
    arm_box,
    arm_sweep,
    box_alpha_beta,
    coriolis_matrix,
    envelope_samples,
    forward_dynamics,
    gravity,
    kinetic_energy,
    mass_matrix,
    potential_energy,
    third_order_rows,
)

P = ARM_PARAMS


def random_states(n, seed=0):
    rng = np.random.default_rng(seed)
    return jnp.asarray(rng.uniform(-2.0, 2.0, (n, 9)))


# ---------------------------------------------------------------------------- physics


@pytest.mark.slow  # moved from the default tier (4-min budget): 4-8 s
def test_energy_conserved_without_motors_friction_gravity():
    params = P._replace(F=np.zeros(3), g=0.0)
    m = 4.0
    acc = lambda q, dq: forward_dynamics(params, m, q, dq, jnp.zeros(3))

    def f(y):
        return jnp.concatenate([y[3:], acc(y[:3], y[3:])])

    def rk4(y, _):
        dt = 1e-3
        k1 = f(y)
        k2 = f(y + dt / 2 * k1)
        k3 = f(y + dt / 2 * k2)
        k4 = f(y + dt * k3)
        return y + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4), None

    y0 = jnp.array([0.3, -1.0, 0.7, 1.5, -2.0, 2.5])
    y1 = jax.jit(lambda y: jax.lax.scan(rk4, y, None, length=1000)[0])(y0)
    e0 = kinetic_energy(params, m, y0[:3], y0[3:])
    e1 = kinetic_energy(params, m, y1[:3], y1[3:])
    assert jnp.abs(y1 - y0).max() > 0.5  # it did move
    assert abs(float(e1 - e0)) < 1e-9 * float(e0)


@pytest.mark.slow  # moved from the default tier (4-min budget): 4-8 s
def test_energy_balance_with_gravity():
    """With gravity on (no friction, no motor torque), kinetic + potential is conserved."""
    params = P._replace(F=np.zeros(3))
    m = 10.0
    y0 = jnp.array([0.1, -0.5, 0.4, 0.5, 0.3, -0.2])

    def rk4(y, _):
        f = lambda y: jnp.concatenate([y[3:], forward_dynamics(params, m, y[:3], y[3:], jnp.zeros(3))])
        dt = 5e-4
        k1 = f(y)
        k2 = f(y + dt / 2 * k1)
        k3 = f(y + dt / 2 * k2)
        k4 = f(y + dt * k3)
        return y + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4), None

    y1 = jax.jit(lambda y: jax.lax.scan(rk4, y, None, length=2000)[0])(y0)
    E = lambda y: kinetic_energy(params, m, y[:3], y[3:]) + potential_energy(params, m, y[:3])
    assert abs(float(E(y1) - E(y0))) < 1e-7 * max(abs(float(E(y0))), 1.0)


@pytest.mark.parametrize("payload", [0.0, 10.0])
def test_mass_matrix_symmetric_positive_definite(payload):
    Ms = jax.vmap(lambda X: mass_matrix(P, payload, X[0::3]))(random_states(200))
    assert np.allclose(Ms, np.swapaxes(Ms, 1, 2), atol=1e-12)
    assert np.linalg.eigvalsh(np.asarray(Ms)).min() > 0


def test_Mdot_minus_2C_is_skew():
    @jax.jit  # one compilation for the 20 states (op by op, each state took 0.4 s)
    def N_of(X):
        q, dq = X[0::3], X[1::3]
        _, Mdot = jax.jvp(lambda q: mass_matrix(P, 3.0, q), (q,), (dq,))
        return Mdot - 2 * coriolis_matrix(P, 3.0, q, dq)

    for X in random_states(20, seed=1):
        N = N_of(X)
        np.testing.assert_allclose(N, -N.T, atol=1e-12)


def test_gravity_independent_of_base_yaw_and_zero_hanging():
    q = jnp.array([0.0, 0.4, -0.3])
    np.testing.assert_allclose(gravity(P, 5.0, q), gravity(P, 5.0, q.at[0].set(1.3)), atol=1e-12)
    np.testing.assert_allclose(gravity(P, 5.0, jnp.zeros(3)), 0.0, atol=1e-12)


def test_joint_1_couples_to_joints_2_and_3():
    M = mass_matrix(P, 5.0, jnp.array([0.0, -0.8, 0.6]))
    assert abs(float(M[0, 1])) > 1e-3 and abs(float(M[0, 2])) > 1e-5


def test_init_observe_roundtrip():
    for X in random_states(5, seed=2):
        arm = Arm(P, 7.0)
        np.testing.assert_allclose(arm.observe(arm.init(X)), X, atol=1e-10)


@pytest.mark.slow  # moved from the default tier (4-min budget): 4-8 s
def test_jerk_is_jvp_of_acceleration_and_matches_third_order_rows():
    rng = np.random.default_rng(3)
    arm = Arm(P, 6.0)

    @jax.jit  # one compilation for the three states instead of op-by-op dispatch
    def jerk_and_rows(X, U):
        state = arm.init(X)
        _, jerk = jax.jvp(arm.accelerations, (state,), (arm.derivative(state, U),))
        return jerk, third_order_rows(arm, X)

    for X in random_states(3, seed=3):
        U = jnp.asarray(rng.normal(scale=5.0, size=3))
        jerk, (a, b) = jerk_and_rows(X, U)
        np.testing.assert_allclose(a @ X + b @ U, jerk, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(a[:, 0], 0.0, atol=1e-12)  # no theta_1 dependence


@pytest.mark.slow  # moved from the default tier (4-min budget): 4-8 s
def test_b_rows_is_Minv_Kt_over_L():
    X = random_states(1, seed=4)[0]
    a, b = jax.jit(third_order_rows)(Arm(P, 2.0), X)  # one compilation, not op by op
    M = mass_matrix(P, 2.0, X[0::3])
    np.testing.assert_allclose(M @ b, np.diag(np.asarray(P.Kt) / np.asarray(P.L)), rtol=1e-10, atol=1e-10)


@pytest.mark.slow  # moved from the default tier (4-min budget): 4-8 s
def test_float32_follows_inputs():
    arm = arm_sweep(jnp.array([0.0, 10.0], jnp.float32))
    one = jax.tree.map(lambda x: x[1], arm)
    X = random_states(1)[0].astype(jnp.float32)

    @jax.jit  # traced once: the same dtype promotion as op by op, one compilation
    def pieces(one, X):
        state = one.init(X)
        d = one.derivative(state, jnp.ones(3, jnp.float32))
        return state, d, one.observe(state), third_order_rows(one, X)

    state, d, observed, rows = pieces(one, X)
    for leaf in jax.tree.leaves((state, d, observed, rows)):
        assert leaf.dtype == jnp.float32
    np.testing.assert_allclose(observed, X, atol=1e-3)


# ---------------------------------------------------------------------------- payload


def test_more_payload_more_inertia():
    dM_of = jax.jit(lambda q: mass_matrix(P, 10.0, q) - mass_matrix(P, 0.0, q))  # one compilation
    for X in random_states(20, seed=5):
        q = X[0::3]
        dM = dM_of(q)
        assert np.linalg.eigvalsh(np.asarray(dM)).min() > -1e-12  # PSD: J^T J
        assert dM[1, 1] > 0 and dM[2, 2] > 0


def _controller(delta=paper.DELTA_SETS[0]):
    c = lambda x: jnp.asarray(x, jnp.float64)
    return fj.FOSMCParams(c(paper.C), c(paper.POLES), c(paper.GAMMA), c(delta), c(paper.A_ROWS), c(paper.B_ROWS))


def _reference():
    return fj.Cycloid(jnp.asarray(paper.THETA_START), jnp.asarray(paper.THETA_END), jnp.asarray(paper.TAU))


def _X0():
    return fj.desired_state(_reference()(jnp.zeros(())))


@pytest.mark.slow  # ~7 s; batches equal to their rollouts one by one: test_simulator.py in the default tier
def test_batched_payload_sweep_equals_one_by_one():
    payloads = jnp.array([0.0, 4.0, 10.0])
    ctrl, ref, X0 = _controller(), _reference(), _X0()
    # Euler: batching does not depend on the integrator, and RK4's four inlined stages cost
    # 14 s of compilation against Euler's 5 s
    opts = dict(n_steps=200, integrator="euler", switching="ratio")
    batch = fj.simulate_batch(arm_sweep(payloads), ctrl, ref, X0[None], 1e-3, **opts)
    for i, m in enumerate(payloads):
        one = fj.simulate(Arm(P, m), ctrl, ref, X0, 1e-3, **opts)
        for a, b in zip(jax.tree.leaves(batch.metrics), jax.tree.leaves(one.metrics)):
            np.testing.assert_allclose(a[i], b, rtol=1e-9, atol=1e-12)


@pytest.mark.slow  # forward-mode compile of the arm rollout (~11 s)
def test_gradient_wrt_payload_matches_finite_differences():
    ctrl, ref, X0 = _controller(), _reference(), _X0()

    def f(m):
        r = fj.simulate(Arm(P, m), ctrl, ref, X0, 1e-3, n_steps=20, integrator="euler", switching="ratio")
        return jnp.sum(r.metrics.rms_error) + 1e-3 * jnp.sum(r.metrics.control_rms)

    check_grads(f, (jnp.asarray(5.0),), order=1, modes=("fwd",), eps=1e-4, atol=1e-6, rtol=1e-4)
    # the open-loop plant too, through the third-order rows (jitted: check_grads evaluates it,
    # its jvp and its vjp several times, each op by op otherwise)
    g = jax.jit(lambda m: jnp.sum(third_order_rows(Arm(P, m), _X0() + 0.1)[1]))
    check_grads(g, (jnp.asarray(3.0),), order=1, modes=("fwd", "rev"), eps=1e-4, atol=1e-6, rtol=1e-4)


# ---------------------------------------------------------------------------- closed loop


@pytest.mark.slow  # 7 s: the default tier keeps to 4 minutes on 2 cores
def test_closed_loop_on_arm_at_0_and_10_kg():
    """The FOSMC designed from (29), poles (33), gains (36), Euler dt = 1e-4 s, 4 s, on the arm.

    SGN (23) tracks: sampling at dt leaves an O(dt) error, which joint 3's slow poles (-0.03,
    -0.031) let drift to about 0.1 rad by t = 4 s (it halves with dt: see REPRODUCTION.md).
    Table 1 set 1 with (28) does not diverge but does not track (errors of order 1 rad): the
    arm's dynamics along the reference differ from (29) by volts, which the boundary-layer law
    rejects only weakly (see the issue's closing note). Both facts are asserted, so a change
    of either is noticed."""
    ref, X0 = _reference(), _X0()
    arms = arm_sweep(jnp.array(PAYLOAD_RANGE))
    run = lambda sw: fj.simulate_batch(arms, _controller(), ref, X0[None], 1e-4, n_steps=40_000,
                                       integrator="euler", switching=sw)  # fmt: skip
    sign, ratio = run("sign"), run("ratio")
    assert not np.any(sign.diverged) and not np.any(ratio.diverged)
    e_sign, e_ratio = np.asarray(sign.metrics.max_abs_error), np.asarray(ratio.metrics.max_abs_error)
    assert np.all(e_sign[:, :2] < 0.01), e_sign
    assert np.all(e_sign[:, 2] < 0.15), e_sign
    assert np.all(e_ratio > 10 * e_sign), (e_ratio, e_sign)
    assert np.all(e_ratio < 3.0), e_ratio


# ---------------------------------------------------------------------------- the arm's box


@pytest.mark.slow  # the arm's box over payloads x reference samples (~10 s)
def test_arm_box_and_alpha_beta():
    box = arm_box(P, jnp.linspace(*PAYLOAD_RANGE, 3), envelope_samples(11))
    assert np.all(box.A_lower <= box.A_nominal) and np.all(box.A_nominal <= box.A_upper)
    assert np.all(box.B_lower <= box.B_nominal) and np.all(box.B_nominal <= box.B_upper)
    assert np.all(box.B_upper - box.B_lower > 0)  # payload and configuration both vary B_bar
    alpha, beta = box_alpha_beta(box)
    assert 0 < beta.value < 1 and alpha.value > 0


def test_params_physically_plausible():
    for name in ("l2", "l3", "m2", "m3", "I1", "I2", "I3", "Jm", "F", "R", "L", "Kt", "Kb", "c2", "c3"):
        assert np.all(np.asarray(getattr(P, name)) > 0), name
    for I in (np.asarray(P.I2), np.asarray(P.I3)):
        assert I[0] + I[1] >= I[2] and I[1] + I[2] >= I[0] and I[0] + I[2] >= I[1]
    assert P.c2 < P.l2 and P.c3 < P.l3
    assert isinstance(P, ArmParams)


def test_the_arms_derivative_from_its_observation_is_its_derivative_and_is_carried():
    """``Arm.derivative_observed`` (theta'' read from the observation) equals ``derivative``
    bit for bit, and the simulator's carry holds the observation for it."""
    from fosmc_jax._simulator import step

    arm, ctrl, ref, X0 = Arm(P, jnp.asarray(3.0)), _controller(), _reference(), _X0()
    state = arm.init(X0 + 0.1)
    U, t = jnp.asarray([1.0, -2.0, 0.5]), jnp.asarray(0.3)
    for a, b in zip(jax.tree.leaves(arm.derivative_observed(state, arm.observe(state, t), U, t)),
                    jax.tree.leaves(arm.derivative(state, U, t))):  # fmt: skip
        np.testing.assert_array_equal(a, b)
    carry = step.start(arm, fj.FOSMC(ctrl), ref, X0, None, 1e6)
    np.testing.assert_array_equal(carry.X, arm.observe(arm.init(X0), jnp.zeros(())))


@pytest.mark.slow  # four arm compilations (~40 s)
@pytest.mark.parametrize("integrator", ["euler", "rk4"])
def test_the_observation_carried_into_the_next_stage_changes_no_value(monkeypatch, integrator):
    """The simulator reuses each step's observation (its theta'') in the next step's first
    stage: the same values as computing it again."""
    from fosmc_jax._simulator import step

    arm, ctrl, ref, X0 = Arm(P, jnp.asarray(3.0)), _controller(), _reference(), _X0()
    run = lambda: fj.simulate(arm, fj.FOSMC(ctrl), ref, X0, 1e-3, n_steps=60, integrator=integrator)
    carries = lambda: step.start(arm, fj.FOSMC(ctrl), ref, X0, None, 1e6).X is not None
    carried, reused = run(), carries()
    jax.clear_caches()
    monkeypatch.setattr(step, "reuses_observation", lambda plant: False)
    again = run()
    assert reused and not carries()  # the two runs differ in what they carry
    for a, b in zip(jax.tree.leaves(carried.metrics), jax.tree.leaves(again.metrics)):
        np.testing.assert_array_equal(a, b)
    assert np.all(np.isfinite(carried.metrics.rms_error))
