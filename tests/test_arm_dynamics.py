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
    gravity,
    gravity_closed,
    kinetic_energy,
    mass_matrix,
    mass_matrix_closed,
    potential_energy,
)
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
