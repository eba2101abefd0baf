"""The simulator's inputs checked at the API's edge (fosmc_jax._simulator.checks): wrong shapes
refused always (under jit, grad and vmap too), non-finite and out-of-range values where they are
concrete, each in one line naming the field; lists made arrays; a dt above the stable step
warned about; a user's own controller left alone.

Most tests call check_inputs directly; those that simulate share one set of shapes and static
options (n_steps = 5, euler), so that they compile one program each."""

import dataclasses
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_interfaces import StatePD  # a user's law, defined once

import fosmc_jax as fj
from fosmc_jax import paper
from fosmc_jax._controllers import KINDS
from fosmc_jax._simulator.checks import RULES, check_inputs, rules
from fosmc_jax._simulator.rollout import option_names

OPTIONS = {"n_steps": 5, "integrator": "euler"}
DT = 1e-3  # far below the nominal model's euler limit, 0.24 s


def params(dtype=jnp.float64, **changes):
    c = lambda x: jnp.asarray(x, dtype)
    p = fj.FOSMCParams(
        c(paper.C), c(paper.POLES), c(paper.GAMMA), c(paper.DELTA_SETS[0]), c(paper.A_ROWS), c(paper.B_ROWS)
    )
    return p._replace(**changes)


def inputs(dtype=jnp.float64, **changes):
    """(plant, controller, reference, X0, dt) of one rollout of the nominal plant."""
    plant = fj.LinearPlant(jnp.asarray(paper.A_ROWS, dtype), jnp.asarray(paper.B_ROWS, dtype))
    ref = fj.Cycloid(
        jnp.asarray(paper.THETA_START, dtype), jnp.asarray(paper.THETA_END, dtype), jnp.asarray(paper.TAU, dtype)
    )
    X0 = fj.desired_state(ref(jnp.zeros((), dtype)))
    return plant, fj.FOSMC(params(dtype, **changes)), ref, X0, jnp.asarray(DT, dtype)


def check(plant, controller, reference, X0, dt, batch=False, **options):
    return check_inputs(plant, controller, reference, X0, dt, batch, dict(OPTIONS, **options), option_names(batch))


def refused(match: str, *args, batch=False, **options) -> str:
    """The one-line ValueError ``check`` raises, matching ``match`` from its start."""
    with pytest.raises(ValueError, match="^" + match) as e:
        check(*args, batch=batch, **options)
    assert "\n" not in str(e.value)
    return str(e.value)


def raised(fn, *args) -> str:
    """The one-line ValueError ``fn(*args)`` raises (under a transformation JAX adds a note
    of its own to it, about its frames in the traceback: not part of the message)."""
    with pytest.raises(ValueError) as e:
        fn(*args)
    assert "\n" not in str(e.value)
    return str(e.value)


def test_a_nan_in_X0_is_refused_naming_X0():
    plant, ctrl, ref, X0, dt = inputs()
    message = refused(r"X0: ", plant, ctrl, ref, X0.at[0].set(jnp.nan), dt)
    assert message == "X0: expected 9 finite numbers, got nan at index 0"
    # through the public function too, before anything compiles
    with pytest.raises(ValueError, match=r"^X0: expected 9 finite numbers, got inf at index 4$"):
        fj.simulate(plant, ctrl, ref, X0.at[4].set(jnp.inf), dt, **OPTIONS)


@pytest.mark.parametrize("n", [1, 2, 4])
def test_a_delta_of_the_wrong_length_is_refused_naming_the_field(n):
    plant, ctrl, ref, X0, dt = inputs(delta=jnp.full(n, 0.1))
    message = refused(r"controller\.params\.delta: ", plant, ctrl, ref, X0, dt)
    assert message == f"controller.params.delta: expected shape (3,), got ({n},)"


def test_out_of_range_parameters_are_refused():
    plant, ctrl, ref, X0, dt = inputs(delta=jnp.array([0.1, -0.1, 0.1]))
    assert (
        refused("", plant, ctrl, ref, X0, dt)
        == "controller.params.delta: expected 3 positive numbers, got -0.1 at index 1"
    )
    plant, ctrl, ref, X0, dt = inputs(poles=jnp.asarray(paper.POLES).at[2, 1].set(3.0))
    refused(r"controller\.params\.poles: expected .* negative real parts .*, got 3\.0 at index \(2, 1\)$",
            plant, ctrl, ref, X0, dt)  # fmt: skip
    plant, ctrl, ref, X0, dt = inputs(gamma=jnp.array([1.0, -1.0, 1.0]))
    refused(r"controller\.params\.gamma: expected 3 non-negative numbers", plant, ctrl, ref, X0, dt)
    plant, ctrl, ref, X0, dt = inputs()
    refused(r"dt: expected a positive finite number \(s\), got -0\.001$", plant, ctrl, ref, X0, -dt)
    refused(r"dt: expected shape \(\), got \(1,\)$", plant, ctrl, ref, X0, jnp.full(1, DT))
    refused(r"reference\.duration: expected a positive number", plant, ctrl, ref._replace(duration=0.0), X0, dt)
    refused(r"plant\.b_rows: expected shape \(3, 3\), got \(3, 9\)$", plant._replace(b_rows=plant.a_rows), ctrl,
            ref, X0, dt)  # fmt: skip


def test_a_negative_payload_is_refused_and_the_range_is_the_configs():
    """The low level refuses a negative payload; the range (the paper's arm: PAYLOAD_RANGE) is
    the configured arm's, [arm] payload_range, checked by the config (an Arm does not carry it)."""
    _, ctrl, ref, X0, dt = inputs()
    message = refused(r"plant\.payload: ", fj.Arm(fj.ARM_PARAMS, -2.0), ctrl, ref, X0, dt)
    assert message == "plant.payload: expected a non-negative payload (kg), got -2.0"
    arms = fj.arm_sweep(jnp.array([0.0, -2.0]))
    message = refused(r"plants\.payload: ", arms, ctrl, ref, X0[None], dt, batch=True)
    assert message.endswith("got -2.0 at index 1")
    check(fj.arm_sweep(jnp.array(fj.PAYLOAD_RANGE)), ctrl, ref, X0[None], dt, batch=True)
    with pytest.raises(
        fj.ConfigError, match=r"^plant.payloads: expected payloads within arm.payload_range = \[0, 10\]"
    ):
        fj.config.resolve({"plant": {"kind": "arm", "payloads": [1.0, 50.0]}})
    fj.config.resolve({"plant": {"kind": "arm", "payloads": [1.0, 50.0]}, "arm": {"payload_range": [0.0, 60.0]}})


@pytest.mark.slow  # 3 s: the default tier keeps to 4 minutes on 2 cores
def test_a_delta_given_as_a_list_runs_as_the_array():
    plant, ctrl, ref, X0, dt = inputs()
    as_list = dataclasses.replace(ctrl, params=ctrl.params._replace(delta=[200.0, 100.0, 60.0]))
    _, checked, *_ = check(plant, as_list, ref, X0, dt)
    assert isinstance(checked.params.delta, jax.Array) and checked.params.delta.dtype == X0.dtype
    a = fj.simulate(plant, ctrl, ref, X0, dt, **OPTIONS)
    b = fj.simulate(plant, as_list, ref, X0, dt, **OPTIONS)
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    # float32 inputs: a list (or tuple) follows X0's dtype; X0 as a list: JAX's default float
    plant32, ctrl32, ref32, X0_32, dt32 = inputs(jnp.float32, delta=(0.1, 0.1, 0.1))
    assert check(plant32, ctrl32, ref32, X0_32, dt32)[1].params.delta.dtype == jnp.float32
    out = check(plant, ctrl, ref, [0.0] * 9, dt)
    assert out[3].dtype == jnp.result_type(float) and out[3].shape == (9,)


def test_a_step_above_the_stable_step_warns_in_one_line():
    plant, ctrl, ref, X0, dt = inputs()
    h = fj.stable_step(paper.A_ROWS, paper.B_ROWS, paper.POLES, "euler")
    with pytest.warns(UserWarning, match=r"^dt = 0\.5 s exceeds the euler stability limit 0\.241 s") as caught:
        check(plant, ctrl, ref, X0, 0.5)
    assert "\n" not in str(caught[0].message) and h < 0.5
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check(plant, ctrl, ref, X0, 0.9 * h)  # below: silent
        check(plant, ctrl, ref, X0, 0.5, integrator="my_own")  # an integrator it does not know: silent
    # the DigitalLoop's law carries the FOSMC parameters too; the warning points at the caller
    loop = fj.DigitalLoop(fj.DiscreteFOSMC(ctrl.params, 0.5), fj.Sensors(jnp.zeros(3)), jnp.full(3, 24.0), 0.5)
    with pytest.warns(UserWarning, match=r"\(controller\.law\.params\): expect divergence$"):
        check(plant, loop, ref, X0, 0.5)
    with pytest.warns(UserWarning, match="stability limit") as caught:
        fj.simulate(plant, ctrl, ref, X0, jnp.asarray(0.5, X0.dtype), **OPTIONS)  # no recompilation
    assert [w.filename for w in caught if "stability limit" in str(w.message)] == [__file__]


@pytest.mark.slow  # 5 s: the default tier keeps to 4 minutes on 2 cores
def test_under_jit_and_grad_shapes_are_still_refused_and_traced_values_pass():
    plant, ctrl, ref, X0, dt = inputs()

    def loss(delta, X0=X0):
        c = dataclasses.replace(ctrl, params=ctrl.params._replace(delta=delta))
        return fj.simulate(plant, c, ref, X0, dt, **OPTIONS).metrics.rms_error.sum()

    delta = ctrl.params.delta
    wrong = "controller.params.delta: expected shape (3,), got (2,)"
    assert raised(jax.jit(loss), delta[:2]) == raised(jax.grad(loss), delta[:2]) == wrong
    # a traced negative delta and a traced NaN X0 are not concrete: they pass (values unknown)
    assert np.isfinite(float(jax.jit(loss)(-delta)))
    nan_X0 = jax.jit(lambda X0: fj.simulate(plant, ctrl, ref, X0, dt, **OPTIONS).diverged)(X0.at[0].set(jnp.nan))
    assert bool(nan_X0)
    assert np.all(np.isfinite(np.asarray(jax.grad(loss)(delta))))
    # what is concrete under jit (closed over) is still checked
    bad = X0.at[0].set(jnp.nan)
    message = raised(jax.jit(lambda d: loss(d, bad)), delta)
    assert message == "X0: expected 9 finite numbers, got nan at index 0"
    # vmap: the shapes of one example
    with_delta = lambda d: check(plant, dataclasses.replace(ctrl, params=ctrl.params._replace(delta=d)), ref, X0, dt)
    assert jax.vmap(lambda d: with_delta(d)[1].params.delta)(jnp.ones((4, 3))).shape == (4, 3)
    assert raised(jax.vmap(with_delta), jnp.ones(4)) == "controller.params.delta: expected shape (3,), got ()"


def test_batch_shapes_are_refused_naming_the_argument():
    plant, ctrl, ref, X0, dt = inputs()
    plants = jax.tree.map(lambda x: jnp.stack([x, x]), plant)
    with pytest.raises(ValueError, match=r"^X0s: expected shape \(O, 9\), got \(9,\)$"):
        fj.simulate_batch(plants, ctrl, ref, X0, dt, **OPTIONS)
    refused(r"plants\.a_rows: expected shape \(P, 3, 9\) \(a leading axis of P plants\), got \(3, 9\)$",
            plant, ctrl, ref, X0[None], dt, batch=True)  # fmt: skip
    refused(r"plants\.b_rows: expected shape \(2, 3, 3\) \(P = 2, as plants\.a_rows\), got \(3, 3, 3\)$",
            plants._replace(b_rows=jnp.zeros((3, 3, 3))), ctrl, ref, X0[None], dt, batch=True)  # fmt: skip
    refused(r"X0s: expected initial states of 9 finite numbers each, got nan at index \(1, 2\)$",
            plants, ctrl, ref, jnp.stack([X0, X0.at[2].set(jnp.nan)]), dt, batch=True)  # fmt: skip
    refused(r"keys: expected shape \(R, 2\), got \(2,\)$", plants, ctrl, ref, X0[None], dt, batch=True,
            keys=jax.random.PRNGKey(0))  # fmt: skip
    check(plants, ctrl, ref, X0[None], dt, batch=True, keys=jax.random.split(jax.random.PRNGKey(0), 3))
    check(plants, ctrl, ref, X0[None], dt, batch=True, keys=jax.random.split(jax.random.key(0), 3))  # typed keys


def test_nested_objects_are_checked_with_their_path():
    plant, ctrl, ref, X0, dt = inputs()
    bad = ctrl.params._replace(delta=jnp.array([0.1, 0.1, jnp.nan]))
    loop = lambda law, **kw: fj.DigitalLoop(law, fj.Sensors(jnp.zeros(3)), jnp.full(3, jnp.inf), DT, **kw)
    refused(r"controller\.law\.params\.delta: expected 3 positive numbers, got nan at index 2$",
            plant, loop(fj.DiscreteFOSMC(bad, DT)), ref, X0, dt)  # fmt: skip
    refused(r"controller\.sample_steps: expected an integer >= 1, got 0$", plant,
            loop(fj.DiscreteFOSMC(ctrl.params, DT), sample_steps=0), ref, X0, dt)  # fmt: skip
    refused(r"controller\.switching: expected one of sign, ratio, sat, tanh, got 'sgn'$", plant,
            fj.FOSMC(ctrl.params, "sgn"), ref, X0, dt)  # fmt: skip
    surface = fj.SurfaceParams(ctrl.params.C, ctrl.params.a_rows, ctrl.params.b_rows)
    refused(
        r"controller\.law\.k2: expected 3 positive numbers, got -1\.0 at index 0$",
        plant,
        fj.ContinuousSuperTwisting(fj.SuperTwisting(surface, jnp.ones(3), -jnp.ones(3), 0.0)),
        ref,
        X0,
        dt,
    )
    refused(r"controller\.sensors\.noise_std: expected shape \(9,\), got \(3,\)$", plant,
            fj.DigitalLoop(fj.DiscreteFOSMC(ctrl.params, DT), fj.Sensors(jnp.zeros(3), jnp.ones(3)), jnp.ones(3), DT),
            ref, X0, dt)  # fmt: skip
    # lists deep inside become arrays; the objects are rebuilt only where something changed
    listed = loop(fj.DiscreteFOSMC(ctrl.params, DT))
    listed = dataclasses.replace(listed, sensors=fj.Sensors([0, 0, 0]), u_max=[24.0] * 3)
    out = check(plant, listed, ref, X0, dt)[1]
    assert out.sensors.counts.dtype == X0.dtype and out.u_max.shape == (3,) and out.law is listed.law


def test_the_controller_kinds_declare_the_rules_of_their_types():
    """The controllers' rules are their kinds' (``Kind.rules``), not a table of the simulator's."""
    checked = rules()
    for kind in KINDS.values():
        assert kind.rules and all(checked[t] is fields for t, fields in kind.rules.items())
        assert not set(kind.rules) & set(RULES)


def test_a_users_controller_passes_unchecked_and_untouched():
    plant, ctrl, ref, X0, dt = inputs()
    assert StatePD not in rules()
    odd = StatePD([[1.0] * 9] * 3, jnp.full((3, 9), jnp.nan), [1.0])  # lists, NaN, shapes: the user's business
    assert check(plant, odd, ref, X0, dt)[1] is odd
    K = fj.gain_from_poles(plant.a_rows, plant.b_rows, jnp.asarray(paper.POLES))
    res = fj.simulate(plant, StatePD(K, plant.a_rows, plant.b_rows), ref, X0, dt, **OPTIONS)
    assert not bool(res.diverged)
    # as is what is not a controller at all: the simulator's own TypeError names it
    with pytest.raises(TypeError, match=r"^controller: dict is not a controller"):
        fj.simulate(plant, {"K": 1.0}, ref, X0, dt, **OPTIONS)


def test_the_check_computes_the_stable_step_once_per_model(monkeypatch):
    """The default problem's batch (the CLI's), checked as simulate_batch checks it per call:
    its one costly part, the stable step (eigenvalues in JAX), runs once for the same rows and
    poles, then comes from the cache (its cost per call is a benchmark's to measure, not a
    test's: a timed assertion here failed at load 10)."""
    from fosmc_jax._simulator import checks as _checks

    calls = []
    monkeypatch.setattr(_checks, "stable_step", lambda *a: calls.append(a) or 1.0)
    _checks._stable_step.cache_clear()
    p = fj.build(None)
    args = (p.plants, p.controller(), p.reference, p.X0s, p.dt, True, dict(p.options, keys=p.keys), option_names(True))
    for _ in range(3):
        check_inputs(*args)
    assert len(calls) == 1
    _checks._stable_step.cache_clear()  # the stand-in's 1.0 must not outlive this test
