"""The simulator's declared interfaces (fosmc_jax.Plant, ControlLaw and the protocols that
extend it): a controller written outside the package runs through them, anything else is
refused at the edge in one line, and the deprecated bare-parameter path still runs."""

import dataclasses
import functools
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fosmc_jax as fj
from fosmc_jax import paper

STEPS = 400  # 0.4 s at dt = 1e-3


@functools.partial(jax.tree_util.register_dataclass, data_fields=["K", "a_rows", "b_rows"], meta_fields=[])
@dataclasses.dataclass(frozen=True)
class StatePD:
    """A user's law: U = Omega + K (X - X_d), feedforward (10) plus pole placement (16), no
    state of its own, no sliding variable."""

    K: jax.Array
    a_rows: jax.Array
    b_rows: jax.Array

    def init(self, X0, r0, key=None):
        return ()

    def update(self, state, Y, r, t):
        return fj.feedforward(self.a_rows, self.b_rows, r) + self.K @ (Y - fj.desired_state(r)), state


def _args(dtype=jnp.float64):
    plant = fj.LinearPlant(jnp.asarray(paper.A_ROWS, dtype), jnp.asarray(paper.B_ROWS, dtype))
    ref = fj.Cycloid(
        jnp.asarray(paper.THETA_START, dtype), jnp.asarray(paper.THETA_END, dtype), jnp.asarray(paper.TAU, dtype)
    )
    X0 = fj.desired_state(ref(jnp.zeros((), dtype)))
    return plant, ref, X0, jnp.asarray(1e-3, dtype)


def _fosmc_params(dtype=jnp.float64):
    c = lambda x: jnp.asarray(x, dtype)
    return fj.FOSMCParams(
        c(paper.C), c(paper.POLES), c(paper.GAMMA), c(paper.DELTA_SETS[0]), c(paper.A_ROWS), c(paper.B_ROWS)
    )


def test_the_built_in_controllers_declare_what_they_offer():
    p = _fosmc_params()
    ideal = fj.FOSMC(p)
    loop = fj.DigitalLoop(
        fj.DiscreteFOSMC(p, jnp.asarray(1e-3)),
        fj.Sensors(jnp.zeros(3), None, "measured"),
        jnp.full(3, 24.0),
        jnp.asarray(1e-3),
    )
    assert isinstance(ideal, fj.ContinuousLaw) and isinstance(ideal, fj.HasSlidingVariable)
    assert not isinstance(ideal, fj.SampledLoop)
    assert isinstance(loop, fj.SampledLoop) and not isinstance(loop, fj.ContinuousLaw)
    assert isinstance(StatePD(jnp.zeros((3, 9)), jnp.zeros((3, 9)), jnp.eye(3)), fj.ControlLaw)
    assert not isinstance(StatePD(jnp.zeros((3, 9)), jnp.zeros((3, 9)), jnp.eye(3)), fj.HasSlidingVariable)
    plant, *_ = _args()
    assert isinstance(plant, fj.Plant) and isinstance(fj.arm_sweep(jnp.zeros(1)), fj.Plant)


def test_a_users_controller_runs_and_its_trace_has_no_sliding_variable():
    plant, ref, X0, dt = _args()
    K = fj.gain_from_poles(plant.a_rows, plant.b_rows, jnp.asarray(paper.POLES))
    res = fj.simulate(plant, StatePD(K, plant.a_rows, plant.b_rows), ref, X0, dt, n_steps=STEPS, save_every=100)
    # the nominal plant from X_d(0): it tracks but for the feedforward held over each step (1.4e-4 rad)
    assert not bool(res.diverged) and float(jnp.max(res.metrics.rms_error)) < 1e-3
    assert res.trace.s.shape == (5, 3) and bool(jnp.all(jnp.isnan(res.trace.s)))


def test_what_is_not_a_plant_or_a_controller_is_refused_in_one_line():
    plant, ref, X0, dt = _args()
    with pytest.raises(TypeError, match=r"^controller: dict is not a controller \(needs init"):
        fj.simulate(plant, {"K": 1.0}, ref, X0, dt, n_steps=10)
    with pytest.raises(TypeError, match=r"^plant: tuple is not a plant \(needs init"):
        fj.simulate((1, 2), fj.FOSMC(_fosmc_params()), ref, X0, dt, n_steps=10)
    with pytest.raises(TypeError, match="the law must be a sampled controller"):
        fj.DigitalLoop(
            fj.FOSMC(_fosmc_params()), fj.Sensors(jnp.zeros(3), None, "measured"), jnp.full(3, 24.0), jnp.asarray(1e-3)
        )


def test_bare_parameters_still_run_as_the_ideal_fosmc_with_a_deprecation_warning():
    plant, ref, X0, dt = _args()
    p = _fosmc_params()
    # STEPS + 1: a trace of its own (the warning is given when simulate traces)
    with pytest.warns(DeprecationWarning, match=r"fosmc_jax.FOSMC\(params, switching, law\)"):
        old = fj.simulate(plant, p, ref, X0, dt, n_steps=STEPS + 1, switching="sat", law="equivalent")
    newer = fj.simulate(plant, fj.FOSMC(p, "sat", "equivalent"), ref, X0, dt, n_steps=STEPS + 1)
    np.testing.assert_array_equal(np.asarray(old.metrics.rms_error), np.asarray(newer.metrics.rms_error))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert fj.Controller is fj.FOSMCParams
    assert any(issubclass(w.category, DeprecationWarning) for w in caught)
