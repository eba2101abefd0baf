"""chattering_hf is the exact time integral of a held control's high-pass part (issue 22 item 1):
against numerical integration of the low-pass (SciPy), against the closed form of a single jump,
and the same whatever the number of simulation steps per held sample."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

from fosmc_jax._simulator import metrics as _metrics

CUTOFF = 10.0  # Hz
T = 1e-3  # s, the hold period of the sequences below


def held_metrics(u_samples: np.ndarray, m: int) -> _metrics.Metrics:
    """The metrics of a control held at u_samples[j] over [j T, (j + 1) T) (the last sample is
    the final one, never held), simulated with m steps of T / m per sample and zero error."""
    dt = T / m
    lowpass = _metrics.lowpass(jnp.asarray(dt), jnp.asarray(CUTOFF))
    zero = jnp.zeros(u_samples.shape[1])
    acc = _metrics.start(zero, jnp.asarray(u_samples[0]))
    steps = [(u_samples[j], u_samples[j] if i < m - 1 else u_samples[j + 1]) for j in range(len(u_samples) - 1)
             for i in range(m)]  # fmt: skip
    add = jax.jit(lambda acc, held, new: _metrics.add(acc, zero, new, held, lowpass))
    for held, new in steps:
        acc = add(acc, jnp.asarray(held), jnp.asarray(new))
    return _metrics.finish(acc, jnp.asarray(T * (len(u_samples) - 1)))


def scipy_chattering_hf(u_samples: np.ndarray) -> np.ndarray:
    """sqrt(1/t_f int (u - ubar)^2 dt) by solve_ivp on each hold interval (ubar and the integral
    as states), ubar(0) = u_0."""
    w = 2 * np.pi * CUTOFF
    out = []
    for joint in range(u_samples.shape[1]):
        y = np.array([u_samples[0, joint], 0.0])
        for u in u_samples[:-1, joint]:
            f = lambda t, y, u=u: [w * (u - y[0]), (u - y[0]) ** 2]
            y = solve_ivp(f, (0.0, T), y, method="DOP853", rtol=1e-12, atol=1e-14).y[:, -1]
        out.append(np.sqrt(y[1] / (T * (len(u_samples) - 1))))
    return np.array(out)


def test_held_sequence_equals_numerical_integration_at_every_step_count():
    u = np.random.default_rng(0).normal(0.0, 2.0, (60, 3))  # a switching control, V
    want = scipy_chattering_hf(u)
    for m in (1, 3, 10):
        got = np.asarray(held_metrics(u, m).chattering_hf)
        np.testing.assert_allclose(got, want, rtol=1e-9, err_msg=f"{m} steps per sample")
    # the total variation of a held control does not depend on the step either
    np.testing.assert_allclose(held_metrics(u, 1).chattering, held_metrics(u, 10).chattering, rtol=1e-12)


@pytest.mark.parametrize("m", [1, 7])
def test_single_jump_closed_form(m):
    """u = 0 over [0, T), then U for the remaining time: the residual is U e^(-w (t - T)), so
    chattering_hf^2 t_f = U^2 (1 - e^(-2 w (t_f - T))) / (2 w)."""
    U, J = 3.0, 40
    u = np.zeros((J + 1, 1))
    u[1:] = U
    t_f, w = J * T, 2 * np.pi * CUTOFF
    want = np.sqrt(U**2 * (1 - np.exp(-2 * w * (t_f - T))) / (2 * w) / t_f)
    np.testing.assert_allclose(np.asarray(held_metrics(u, m).chattering_hf), [want], rtol=1e-12)


def test_constant_control_has_no_high_frequency_part():
    u = np.full((20, 3), 1.5)
    np.testing.assert_array_equal(np.asarray(held_metrics(u, 4).chattering_hf), np.zeros(3))
