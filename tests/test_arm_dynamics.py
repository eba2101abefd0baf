"""The arm's closed-form dynamics (the time loop's) against the autodiff formulation (the
oracle), and energy conservation of the whole electromechanical plant."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from fosmc_jax._plants.arm import (
    ARM_PARAMS,
    Arm,
    ArmState,
    coriolis_closed,
    coriolis_matrix,
    coulomb_friction,
    external_torque,
    gravity,
    gravity_closed,
    kinetic_energy,
    mass_matrix,
    mass_matrix_closed,
    potential_energy,
    tracking_voltage,
)
from fosmc_jax._plants.reference import Sinusoid
from fosmc_jax._simulator.step import _rk4


def test_closed_form_equals_the_autodiff_oracle():
    """M, C theta' and G at random states and payloads (0-10 kg), to 1e-10 relative (float64)."""
    rng = np.random.default_rng(7)
    q = jnp.asarray(rng.uniform(-np.pi, np.pi, (64, 3)))
    dq = jnp.asarray(rng.normal(scale=3.0, size=(64, 3)))
    m = jnp.asarray(rng.uniform(0.0, 10.0, 64))
    pairs = [(mass_matrix_closed, mass_matrix), (gravity_closed, gravity)]
    # each side jitted: one compilation instead of the autodiff oracle's many ops one by one
    batched = lambda f, axes: jax.jit(lambda *args: jax.vmap(f, (None, *axes))(ARM_PARAMS, *args))
    for closed, oracle in pairs:
        a = np.asarray(batched(closed, (0, 0))(m, q))
        b = np.asarray(batched(oracle, (0, 0))(m, q))
        assert np.max(np.abs(a - b)) <= 1e-10 * np.max(np.abs(b))
    a = np.asarray(batched(coriolis_closed, (0, 0, 0))(m, q, dq))
    b = np.asarray(jax.jit(jax.vmap(lambda m, q, dq: coriolis_matrix(ARM_PARAMS, m, q, dq) @ dq))(m, q, dq))
    assert np.max(np.abs(a - b)) <= 1e-10 * np.max(np.abs(b))


def _energy(arm: Arm, s: ArmState):
    p, theta, dtheta, current = arm.params, jnp.stack(s.theta), jnp.stack(s.dtheta), jnp.stack(s.current)
    magnetic = 0.5 * jnp.sum(jnp.asarray(p.L) * current**2)
    return kinetic_energy(p, arm.payload, theta, dtheta) + potential_energy(p, arm.payload, theta) + magnetic


@pytest.mark.slow  # RK4 and Euler over several steps, compiled per step size: ~11 s
def test_energy_is_conserved_to_the_integrators_order():
    """No voltage, no friction, no winding resistance and Kb = Kt: the motor converts magnetic
    energy 1/2 L i^2 into work exactly, so T + V + sum 1/2 L i^2 is conserved. RK4's drift over
    a fixed horizon falls about 16x per halving of the step (order 4)."""
    params = ARM_PARAMS._replace(F=np.zeros(3), R=np.zeros(3), Kb=ARM_PARAMS.Kt)
    arm = Arm(jax.tree.map(jnp.asarray, params), jnp.asarray(4.0))
    s0 = jax.tree.map(jnp.asarray, ArmState((0.3, 0.8, -0.6), (1.0, -0.5, 2.0), (3.0, -2.0, 1.0)))
    f = lambda t, s: arm.derivative(s, jnp.zeros(3))
    E0 = float(_energy(arm, s0))

    def drift(dt, t_final=2.0):
        run = jax.jit(lambda s: jax.lax.fori_loop(0, round(t_final / dt), lambda k, s: _rk4(f, 0.0, s, dt), s))
        return abs(float(_energy(arm, run(s0))) - E0)

    d = [drift(dt) for dt in (4e-2, 2e-2, 1e-2)]
    assert d[0] < 1e-3 * abs(E0) and d[2] > 1e3 * 1e-16 * abs(E0)  # truncation, well above rounding
    ratios = [d[0] / d[1], d[1] / d[2]]
    assert all(14 < r < 40 for r in ratios), (d, ratios)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_arm_plant_follows_the_input_dtype(dtype):
    arm = Arm(jax.tree.map(lambda x: jnp.asarray(x, dtype), ARM_PARAMS), jnp.asarray(2.0, dtype))
    X0 = jnp.asarray(np.linspace(-1, 1, 9), dtype)
    s = arm.init(X0)
    assert all(x.dtype == dtype for x in jax.tree.leaves(s)) and arm.observe(s).dtype == dtype
    np.testing.assert_allclose(arm.observe(s), X0, rtol=1e-4 if dtype == jnp.float32 else 1e-10, atol=1e-4)


# Every term of the dynamics on: Coulomb friction (smoothed over 0.1 rad/s rather than the default
# 0.01, so that RK4 and the central difference below resolve its turns), constant and sinusoidal
# external torques.
_LOADED = ARM_PARAMS._replace(Fc=np.array([2.0, 1.5, 0.5]), v_coulomb=0.1, tau_bias=np.array([0.5, -1.0, 0.2]),
                              tau_sin=np.array([1.0, 2.0, 0.3]), f_sin=np.array([1.5, 0.7, 2.0]))  # fmt: skip
_SMOOTH = Sinusoid(*(jnp.asarray(x) for x in ([0.2, -0.4, 0.6], [0.5, 0.4, 0.3], [3.0, 4.0, 5.0], [0.1, 0.2, 0.3])))


def test_tracking_voltage_against_the_autodiff_dynamics():
    """U = L i' + R i + Kb theta_d' with i = tau / Kt from the autodiff M, C and G
    (:func:`mass_matrix`, ...) and i' a central difference in time (h = 1e-5 s: error ~1e-10
    relative), against the closed form differentiated by jvp, to 1e-7 relative."""
    arm = Arm(jax.tree.map(jnp.asarray, _LOADED), jnp.asarray(4.0))

    @jax.jit  # one compilation, not the autodiff oracle's many ops one by one
    def current(t):
        q, dq, ddq, _ = _SMOOTH(t)
        tau = (mass_matrix(_LOADED, arm.payload, q) @ ddq + coriolis_matrix(_LOADED, arm.payload, q, dq) @ dq
               + gravity(_LOADED, arm.payload, q) + _LOADED.F * dq + coulomb_friction(_LOADED, dq)
               - external_torque(_LOADED, t))  # fmt: skip
        return tau / _LOADED.Kt

    voltage = jax.jit(lambda t: tracking_voltage(arm, _SMOOTH(t), t))
    h = 1e-5
    for t in np.linspace(0.0, 1.5, 7):
        oracle = (
            _LOADED.L * (current(t + h) - current(t - h)) / (2 * h)
            + _LOADED.R * current(t)
            + _LOADED.Kb * _SMOOTH(t)[1]
        )
        got = voltage(jnp.asarray(t))
        np.testing.assert_allclose(got, oracle, rtol=1e-7, atol=1e-9 * np.max(np.abs(oracle)))


@pytest.mark.slow  # RK4 over 0.5 s compiled at three step sizes: ~12 s
def test_tracking_voltage_drives_the_arm_along_its_reference():
    """Open loop: the arm started on the reference (:meth:`Arm.init`) and driven by the tracking
    voltage, integrated by RK4 with the closed-form forward dynamics, follows the reference for
    0.5 s; the deviation is RK4's truncation error: under 1e-8 rad and falling about 16x per
    halving of the step."""
    arm = Arm(jax.tree.map(jnp.asarray, _LOADED), jnp.asarray(4.0))
    f = lambda t, s: arm.derivative(s, tracking_voltage(arm, _SMOOTH(t), t), t)

    def deviation(dt, t_final=0.5):
        n = round(t_final / dt)
        run = jax.jit(lambda s: jax.lax.fori_loop(0, n, lambda k, s: _rk4(f, k * dt, s, dt), s))
        return float(np.max(np.abs(np.stack(run(arm.init(_SMOOTH(0.0)[:3].T.reshape(9))).theta) - _SMOOTH(n * dt)[0])))

    d = [deviation(dt) for dt in (4e-3, 2e-3, 1e-3)]
    assert d[0] < 1e-8 and d[2] > 1e-13, d  # truncation, well above rounding
    ratios = [d[0] / d[1], d[1] / d[2]]
    assert all(10 < r < 24 for r in ratios), (d, ratios)
