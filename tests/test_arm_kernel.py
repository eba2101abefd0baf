"""The arm on the kernel generated from its JAX model (fosmc_jax/_simulator/generated.py, the
default path of every arm batch) against vmap of simulate, the path everything else takes:
the printed closed form (M, C q', G, the solve), the laws, the digital loop's sensors, delay and
limit, and the metrics held to rounding at random states, random arms and random gains, and over
whole rollouts of both loops. (These held the hand-written arm kernel, arm_kernel.cc, to the
same tolerances until the generated one replaced it.)"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fosmc_jax as fj
from fosmc_jax import _problems as _config
from fosmc_jax import paper
from fosmc_jax._plants.arm import ARM_PARAMS, arm_sweep
from fosmc_jax._simulator import native as _native

# the kernels are CPU code: on a GPU backend the default path runs the vmap path (checked there by
# test_simulator, test_api), and these white-box calls of the FFI targets have no handler
pytestmark = pytest.mark.skipif(_native._compiler() is None or jax.default_backend() != "cpu",
                                reason="no C++ compiler or not the CPU backend: no kernel")  # fmt: skip


def controller(dtype=np.float64, delta=paper.DELTA_SETS[0], gamma=paper.GAMMA):
    c = lambda x: jnp.asarray(x, dtype)
    return fj.FOSMCParams(c(paper.C), c(paper.POLES), c(gamma), c(delta), c(paper.A_ROWS), c(paper.B_ROWS))


def cycloid(dtype=np.float64):
    c = lambda x: jnp.asarray(np.asarray(x, np.float64), dtype)
    return fj.Cycloid(c(paper.THETA_START), c(paper.THETA_END), c(paper.TAU))


def offsets(O, dtype=np.float64, scale=0.05, seed=1):
    X0 = np.asarray(fj.desired_state(cycloid()(0.0)))
    return jnp.asarray(X0 + np.random.default_rng(seed).uniform(-scale, scale, (O, 9)), dtype)


def random_arms(P, seed=0, spread=0.3):
    """P arms with every physical parameter drawn within +-``spread`` of the calibrated one
    (payloads in [0, 10] kg): the kernel takes them per rollout."""
    rng = np.random.default_rng(seed)
    draw = lambda v: np.asarray(v, np.float64) * rng.uniform(1 - spread, 1 + spread, (P,) + np.shape(v))
    params = type(ARM_PARAMS)(*(draw(v) for v in ARM_PARAMS))
    return fj.Arm(jax.tree.map(jnp.asarray, params), jnp.asarray(rng.uniform(0.0, 10.0, P)))


def assert_close(fast, slow, rtol=1e-10):
    """Every metric within ``rtol`` of the largest |value| of that metric over the batch, the
    divergence flags and times equal."""
    for name in fast.metrics._fields:
        a, b = np.asarray(getattr(fast.metrics, name)), np.asarray(getattr(slow.metrics, name))
        assert a.shape == b.shape and a.dtype == b.dtype, name
        scale = np.nanmax(np.abs(b)) if np.isfinite(b).any() else 1.0
        np.testing.assert_allclose(a, b, rtol=0, atol=rtol * max(scale, 1e-300), err_msg=name)
    np.testing.assert_array_equal(np.asarray(fast.diverged), np.asarray(slow.diverged))
    np.testing.assert_array_equal(np.asarray(fast.diverged_at), np.asarray(slow.diverged_at))


def on_kernel(*args, **options) -> bool:
    """Whether ``fj.simulate_batch(*args, **options)``'s program calls a generated kernel."""
    return "fosmc_gen_" in str(jax.make_jaxpr(lambda: fj.simulate_batch(*args, **options))())


def both(plants, ctrl, ref, X0s, dt, **options):
    """(the generated kernel, vmap of simulate) for the same batch."""
    assert on_kernel(plants, ctrl, ref, X0s, dt, **options)
    fast = fj.simulate_batch(plants, ctrl, ref, X0s, dt, **options)
    return fast, fj.simulate_batch(plants, ctrl, ref, X0s, dt, fast=False, **options)


# ---------------------------------------------------------------------------- the ideal loop


@pytest.mark.parametrize(
    "integrator, switching, law",
    # RK4 runs in the default tier through the realistic preset's digital loop below; Euler's vmap
    # path compiles in less than half RK4's time
    # (both in the slow tier: the default tier keeps to 4 minutes on 2 cores)
    [
        pytest.param("rk4", "ratio", "paper", marks=pytest.mark.slow),
        pytest.param("euler", "tanh", "equivalent", marks=pytest.mark.slow),
    ],
)
def test_random_states_arms_and_gains(integrator, switching, law):
    """The kernel's copy of the closed form, the law and the metrics, held to the JAX model at
    random states (angles over several turns, rates, accelerations), random arms (every
    parameter +-30%) and random gains, over 30 steps: within 1e-10 of each metric's scale."""
    rng = np.random.default_rng(7)
    X0s = jnp.asarray(rng.uniform(-1, 1, (5, 9)) * np.tile([6.0, 2.0, 20.0], 3))
    delta = paper.DELTA_SETS[1] * rng.uniform(0.1, 10, 3)
    ctrl = controller(delta=delta, gamma=paper.GAMMA * rng.uniform(0.3, 3, 3))
    fast, slow = both(random_arms(3), ctrl, cycloid(), X0s, 1e-3, n_steps=30, integrator=integrator,
                      switching=switching, law=law)  # fmt: skip
    assert not np.asarray(slow.diverged).any()
    assert_close(fast, slow)


@pytest.mark.parametrize(
    "integrator, switching, law",
    [pytest.param("euler", "sign", "paper", marks=pytest.mark.slow),
     pytest.param("rk4", "sat", "equivalent", marks=pytest.mark.slow),
     pytest.param("rk4", "tanh", "paper", marks=pytest.mark.slow),
     pytest.param("euler", "ratio", "equivalent", marks=pytest.mark.slow)],
)  # fmt: skip
def test_ideal_loop_rollouts_equal_vmap_of_simulate(integrator, switching, law):
    """Whole rollouts of the paper's case (payloads 0-10 kg, offsets), float64: within 1e-10."""
    plants = arm_sweep(jnp.linspace(0.0, 10.0, 3))
    fast, slow = both(plants, controller(), cycloid(), offsets(2), 1e-4, n_steps=2000, integrator=integrator,
                      switching=switching, law=law)  # fmt: skip
    assert fast.metrics.rms_error.shape == (6, 3)
    assert_close(fast, slow)


@pytest.mark.slow
@pytest.mark.parametrize("integrator", ["euler", "rk4"])
def test_float32_within_1e_4(integrator):
    dt32 = np.float32
    plants = arm_sweep(jnp.linspace(0.0, 10.0, 2, dtype=dt32))
    fast, slow = both(plants, controller(dt32), cycloid(dt32), offsets(3, dt32), 1e-4, n_steps=1000,
                      integrator=integrator)  # fmt: skip
    assert fast.metrics.rms_error.dtype == jnp.float32
    assert_close(fast, slow, rtol=1e-4)


@pytest.mark.slow  # two programs of a 2 x 3 batch: ~16 s
def test_divergence_and_bad_input_flagged_as_simulate_does():
    """A NaN initial state is flagged at t = 0, a rollout pushed past the divergence bound is
    flagged at the same step as simulate flags it, and neither changes its batch neighbours."""
    X0s = offsets(3)
    X0s = X0s.at[1, 0].set(jnp.nan).at[2, 1].set(500.0)  # NaN; a wild rate that diverges
    plants = arm_sweep(jnp.array([0.0, 10.0]))
    opts = dict(n_steps=150, integrator="euler", divergence_bound=50.0)
    # the jitted function behind the public one, whose input checks refuse a NaN X0 (tests/test_checks.py)
    from fosmc_jax._simulator.rollout import _simulate_batch

    fast = _simulate_batch(plants, controller(), cycloid(), X0s, 1e-3, **opts)
    slow = _simulate_batch(plants, controller(), cycloid(), X0s, 1e-3, fast=False, **opts)
    assert_close(fast, slow)
    flags = np.asarray(fast.diverged).reshape(2, 3)
    assert flags[:, 1].all() and flags[:, 2].all() and not flags[:, 0].any()
    assert (np.asarray(fast.diverged_at).reshape(2, 3)[:, 1] == 0).all()
    alone = fj.simulate_batch(plants, controller(), cycloid(), X0s[:1], 1e-3, **opts)
    # equal to rounding (XLA's code for the first sample differs in the last bit between shapes)
    np.testing.assert_allclose(np.asarray(alone.metrics.rms_error), np.asarray(fast.metrics.rms_error)[[0, 3]],
                               rtol=1e-12)  # fmt: skip


# ---------------------------------------------------------------------------- the digital loop


def preset(t_final=0.3, **changes):
    """The realistic preset (DigitalLoop around the DiscreteFOSMC: 2.6M-count encoder,
    differenced rates, one-sample delay, 24 V) with two initial offsets and ``changes``
    ({"section.key": value})."""
    cfg = _config.load("fosmc_jax/_problems/presets/realistic_arm.toml").as_dict()
    cfg["sim"]["t_final"] = t_final
    cfg["sim"]["initial_offset"] = [[0.0] * 9, [0.01, 0, 0, -0.02, 0, 0, 0.03, 0, 0]]
    for key, value in changes.items():
        section, name = key.split(".")
        cfg[section][name] = value
        if value is None:
            del cfg[section][name]
    b = _config.build(cfg)
    opts = {k: v for k, v in b.options.items() if k not in ("switching", "law", "save_every")}
    return (b.plants, b.controller(), b.reference, b.X0s, b.dt), opts


@pytest.mark.parametrize(
    "changes",
    # the preset's RK4 in the slow tier (19 s; Euler's vmap path compiles in less than half the time):
    # the default tier keeps to 4 minutes on 2 cores
    [{"sim.integrator": "euler"}, pytest.param({}, marks=pytest.mark.slow),
     pytest.param({"sensors.derivatives": "measured", "controller.delay_samples": 0, "actuator.u_max": [1.5] * 3,
                   "sim.integrator": "euler"}, marks=pytest.mark.slow),
     pytest.param({"controller.delay_samples": 3, "controller.switching": "sat", "controller.law": "equivalent",
                   "controller.sample_period": 5e-4}, marks=pytest.mark.slow)],
)  # fmt: skip
def test_digital_loop_rollouts_equal_vmap_of_simulate(changes):
    """The digital loop (quantization, differenced or measured rates, delay, saturation, sample
    period), float64: within 1e-10."""
    args, opts = preset(**changes)
    assert type(args[1]) is fj.DigitalLoop
    fast, slow = both(*args, **opts)
    assert_close(fast, slow)
    if "actuator.u_max" in changes:  # the limit is reached, so saturation_fraction is tested too
        assert np.asarray(slow.metrics.saturation_fraction).max() > 0.05


@pytest.mark.slow
def test_float32_digital_loop():
    """float32 digital loops. With exact angles and measured rates: within 1e-4 of
    vmap(simulate). With quantized angles or differenced rates two float32 computations of the
    same loop cannot agree: a float32 ulp near 1.5 rad is 0.05 of the preset's 2.6M-count
    encoder, so a reordered sum flips counts, and the differences amplify each flip (or each ulp)
    1e3-1e6-fold; vmap(simulate) in float32 is itself 10-20% from the float64 loop in the
    chattering metrics with the preset's encoder, and 13x with differenced exact angles. There
    the kernel is held to be as close to the float64 loop as vmap(simulate) is (within 3x)."""
    args, opts = preset(**{"sensors.encoder_counts": [0, 0, 0], "sensors.derivatives": "measured",
                           "sim.precision": "float32"})  # fmt: skip
    fast, slow = both(*args, **opts)
    assert_close(fast, slow, rtol=1e-4)
    args64, opts = preset()
    truth = fj.simulate_batch(*args64, **opts).metrics
    args32, _ = preset(**{"sim.precision": "float32"})
    fast, slow = both(*args32, **opts)
    for name in ("rms_error", "chattering", "chattering_hf", "control_rms"):
        t = np.asarray(getattr(truth, name))
        err = lambda m, name=name, t=t: np.max(np.abs(np.asarray(getattr(m, name)) - t))
        assert err(fast.metrics) <= 3 * err(slow.metrics) + 1e-6 * np.max(np.abs(t)), name


IDEAL = {
    "controller.sample_period": 0.0,
    "controller.delay_samples": 0,
    "sensors.encoder_counts": [0, 0, 0],
    "sensors.derivatives": "measured",
    "actuator.u_max": None,
}


@pytest.mark.parametrize(
    "changes, rtol",
    [pytest.param({"controller.kind": "super_twisting"}, 1e-10, marks=pytest.mark.slow),  # ~13 s
     pytest.param({"controller.kind": "smc", "sim.integrator": "euler"}, 1e-10, marks=pytest.mark.slow),
     pytest.param(dict(IDEAL, **{"controller.kind": "smc"}), 1e-10, marks=pytest.mark.slow),
     # v' = -k2 sign(s(t)) at every stage: where s crosses 0 a last-bit difference in s flips
     # the sign for one stage (2 k2 dt in v), so this law is held to 1e-7
     pytest.param(dict(IDEAL, **{"controller.kind": "super_twisting", "sim.integrator": "euler"}), 1e-7,
                  marks=pytest.mark.slow)],
)  # fmt: skip
def test_smc_and_super_twisting_equal_vmap_of_simulate(changes, rtol):
    """SMC and super-twisting, sampled in the digital loop and in the ideal loop, float64."""
    args, opts = preset(**changes)
    fast, slow = both(*args, **opts)
    assert_close(fast, slow, rtol)


# ---------------------------------------------------------------------------- batching and derivatives


@pytest.mark.slow  # the vmapped kernel and the vmap path: ~18 s
def test_vmapped_candidates_fold_into_the_lanes():
    """A vmap over candidate controllers (the front's chunks) runs as one kernel batch and
    equals each candidate's own vmap(simulate); a vmap over references runs one after another."""
    plants, X0s, ref = arm_sweep(jnp.array([0.0, 10.0])), offsets(2), cycloid()
    deltas = jnp.asarray(paper.DELTA_SETS)
    opts = dict(n_steps=50, integrator="euler", divergence_bound=1e6)
    run = lambda d, fast: fj.simulate_batch(plants, controller()._replace(delta=d), ref, X0s, 1e-3, fast=fast, **opts)
    assert_close(jax.vmap(lambda d: run(d, True))(deltas), jax.vmap(lambda d: run(d, False))(deltas))
    ends = jnp.asarray([paper.THETA_END, np.asarray(paper.THETA_END) * 0.5])
    by_ref = jax.vmap(lambda e: fj.simulate_batch(plants, controller(), ref._replace(end=e), X0s, 1e-3, **opts))(ends)
    for i in range(2):
        one = fj.simulate_batch(plants, controller(), ref._replace(end=ends[i]), X0s, 1e-3, fast=False, **opts)
        assert_close(jax.tree.map(lambda x, i=i: x[i], by_ref), one)


@pytest.mark.slow  # three reverse- and forward-mode compilations of the vmap path (~15 s)
@pytest.mark.parametrize("forward", [False, True])
def test_derivatives_are_those_of_the_vmap_path(forward):
    """Forward and reverse mode through the kernel's batch are the vmap path's derivatives."""
    plants, X0s, ref = arm_sweep(jnp.array([0.0, 10.0])), offsets(1), cycloid()

    def loss(delta, fast):
        r = fj.simulate_batch(plants, controller(delta=delta), ref, X0s, 1e-3, n_steps=100, integrator="euler",
                              fast=fast)  # fmt: skip
        return jnp.mean(r.metrics.rms_error) + 0.1 * jnp.mean(r.metrics.chattering_hf)

    delta = jnp.asarray(paper.DELTA_SETS[0], jnp.float64)
    g = jax.grad(loss)(delta, False)
    np.testing.assert_allclose(jax.grad(loss)(delta, True), g, rtol=1e-9)
    if forward:
        np.testing.assert_allclose(jax.jacfwd(loss)(delta, True), g, rtol=1e-9)


def test_what_the_kernel_runs():
    """Every law of the package on the arm, in both loops, any delay and with sensor noise (its
    draws computed by JAX with the table, tests/test_kernel_noise.py), runs on the generated
    kernel."""
    plants, ref, X0s = arm_sweep(jnp.array([0.0])), cycloid(), offsets(1)
    loop = preset()[0][1]
    late = fj.DigitalLoop(loop.law, loop.sensors, loop.u_max, loop.period, 10, 9)
    noisy = fj.DigitalLoop(loop.law, fj.Sensors(loop.sensors.counts, jnp.ones(9)), loop.u_max, loop.period, 10, 1)
    for ctrl in (fj.FOSMC(controller()), loop, late, noisy):
        assert on_kernel(plants, ctrl, ref, X0s, 1e-3, n_steps=20, integrator="euler")


@pytest.mark.parametrize("save_every, n_steps", [(10, 203), (1, 20)])
def test_traces_come_from_the_kernel_as_vmap_of_simulate_samples_them(save_every, n_steps):
    """A trace (every ``save_every``-th step and the last, the horizon not a multiple of it) runs
    the kernel in blocks, its carries sampled between them: the vmap path's trace to rounding."""
    plants, ref, X0s = arm_sweep(jnp.array([0.0, 10.0])), cycloid(), offsets(2)
    opts = dict(n_steps=n_steps, integrator="euler", save_every=save_every)
    fast, slow = both(plants, controller(), ref, X0s, 1e-3, **opts)
    assert_close(fast, slow)
    assert fast.trace.X.shape == (4, -(-n_steps // save_every) + 1, 9)
    for name in fast.trace._fields:
        np.testing.assert_allclose(getattr(fast.trace, name), getattr(slow.trace, name), rtol=1e-10, atol=1e-12,
                                   err_msg=name)  # fmt: skip
