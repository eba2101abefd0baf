"""A digital loop's sensor noise on the generated kernel (fosmc_jax._simulator.generated): the
draws, functions of the batch's key and the sample index alone, computed by JAX in the kernel's
table of time values; values, traces and gradients (in the law's gains and in ``noise_std``: the
reparameterised draws) equal to the ``vmap`` path's, with one key and with R keys (noise
realizations). One small model (two linear plants, two initial offsets, Euler, a few hundred
steps): its C++ is built once for the file; the encoders' counts are a value, not a structure,
so the quantized loop runs the same kernel."""

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fosmc_jax as fj
from fosmc_jax import paper
from fosmc_jax._simulator import generated, native, rollout

N_STEPS = 200
KEYS = jax.random.split(jax.random.PRNGKey(7), 3)
K0 = jnp.array([20.0, 25.0, 30.0])
STD0 = jnp.tile(jnp.array([2e-4, 1e-3, 1e-2]), 3)
COUNTS = jnp.full(3, 2.0**14)


@pytest.fixture(autouse=True, scope="module")
def _kernels():
    """Skip where there are no generated kernels (no C++ compiler, or not the CPU backend)."""
    if not native.available() or jax.default_backend() != "cpu":
        pytest.skip("no C++ compiler or not the CPU backend: no generated kernels")


def _linear():
    plants = fj.LinearPlant(jnp.asarray(paper.A_ROWS)[None] * jnp.array([[1.0], [1.1]])[..., None],
                            jnp.asarray(paper.B_ROWS)[None].repeat(2, 0))  # fmt: skip
    ref = fj.Cycloid(jnp.asarray(paper.THETA_START), jnp.asarray(paper.THETA_END), jnp.asarray(paper.TAU))
    X0s = fj.desired_state(ref(jnp.zeros(()))) + jnp.array([[0.0], [0.02]])
    return plants, ref, X0s, jnp.asarray(1e-3)


def _loop(k, noise_std, counts):
    """SMC sampled every 2 steps, the angles' noise and (``counts`` > 0) encoders, differenced
    rates, a delay of one sample, a limit of 24 V."""
    surface = fj.SurfaceParams(jnp.asarray(paper.C), jnp.asarray(paper.A_ROWS), jnp.asarray(paper.B_ROWS))
    law = fj.SMC(surface, k, jnp.full(3, 0.05))
    return fj.DigitalLoop(law, fj.Sensors(counts, noise_std, "difference"), jnp.full(3, 24.0), jnp.asarray(2e-3), 2, 1)


def _run(k, noise_std, counts, fast, keys=None, save_every=0):
    plants, ref, X0s, dt = _linear()
    options = {"keys": keys} if keys is not None else {"key": KEYS[0]}
    return rollout.simulate_batch(plants, _loop(k, noise_std, counts), ref, X0s, dt, n_steps=N_STEPS,
                                  integrator="euler", fast=fast, save_every=save_every, **options)  # fmt: skip


def _loss(res):
    return jnp.mean(res.metrics.rms_error) + 1e-3 * jnp.mean(res.metrics.chattering)


def _rel(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return float(np.max(np.abs(a - b) / np.maximum(np.abs(b), 1e-300)))


def test_a_noisy_loop_runs_on_the_kernel_with_the_vmap_paths_metrics_and_traces():
    run = jax.jit(lambda std, fast: _run(K0, std, COUNTS, fast, save_every=20), static_argnums=1)
    text = str(jax.make_jaxpr(lambda std: _run(K0, std, COUNTS, True, save_every=20))(STD0))
    assert "fosmc_gen_" in text  # the generated kernel's call, not the vmap path's scan
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no fallback warning
        gen = run(STD0, True)
    vm = run(STD0, False)
    quiet = run(jnp.zeros(9), True)
    assert not np.any(gen.diverged)
    for a, b in zip(gen.metrics, vm.metrics):
        assert _rel(a, b) < 1e-9
    for a, b in zip(gen.trace, vm.trace):
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12)
    # the noise is there: a noise-free run of the same kernel differs
    assert _rel(quiet.metrics.rms_error, gen.metrics.rms_error) > 1e-3


@pytest.mark.parametrize("counts, tol", [(jnp.zeros(3), 1e-9), (COUNTS, 1e-6)])
def test_gradients_in_the_gains_and_the_noise_std_equal_the_vmap_paths(counts, tol):
    grad = lambda fast: jax.jit(jax.value_and_grad(lambda k, std: _loss(_run(k, std, counts, fast)), argnums=(0, 1)))
    (v, g), (w, h) = grad(True)(K0, STD0), grad(False)(K0, STD0)
    assert _rel(v, w) < 1e-12
    for a, b in zip(g, h):
        assert _rel(a, b) < tol and np.any(np.asarray(b) != 0)


def test_noise_realizations_run_on_the_kernel_with_the_vmap_paths_values_and_gradients():
    def loss(k, std, fast):
        res = _run(k, std, COUNTS, fast, keys=KEYS)
        return _loss(res), res

    text = str(jax.make_jaxpr(lambda k: loss(k, STD0, True)[0])(K0))
    assert "fosmc_gen_" in text
    grad = lambda fast: jax.jit(jax.value_and_grad(lambda k, std: loss(k, std, fast), argnums=(0, 1), has_aux=True))
    ((v, gen), g), ((w, vm), h) = grad(True)(K0, STD0), grad(False)(K0, STD0)
    assert gen.metrics.rms_error.shape == (4 * len(KEYS), 3)
    for a, b in zip(gen.metrics, vm.metrics):
        assert _rel(a, b) < 1e-9
    # each realization differs: the keys' draws, in the vmap path's order (rollout-major)
    assert np.all(np.asarray(vm.metrics.rms_error[0]) != np.asarray(vm.metrics.rms_error[1]))
    assert _rel(v, w) < 1e-12
    for a, b in zip(g, h):
        assert _rel(a, b) < 1e-6


# two tables a group in the slow tier (16 s in the default one's fresh-clone run): one a group runs the same loop
@pytest.mark.parametrize("tables", [1, pytest.param(2, marks=pytest.mark.slow)])
def test_realizations_beyond_the_tables_memory_run_in_groups_with_the_same_values(monkeypatch, tables):
    """Where the R keys' tables exceed generated.TABLE_BYTES, the kernel runs them in groups of
    ``tables`` keys (one: a call per key; two: a group and the rest): the same values. White-box
    (generated.simulate_batch, not jitted: the limit is read when traced)."""
    want = _run(K0, STD0, COUNTS, True, keys=KEYS)
    plants, ref, X0s, dt = _linear()
    full = lambda k: (plants, _loop(k, STD0, COUNTS), ref, X0s, dt, KEYS, jnp.asarray(1e6), jnp.asarray(10.0))
    run = lambda k: generated.simulate_batch(full(k), n_steps=N_STEPS, integrator="euler", paired=False)
    model = list(generated._MODELS.values())[-1]  # the model just built
    table_bytes = N_STEPS * 8 * sum(generated._size(s.time_avals) for s in (model.held, model.sampled))
    monkeypatch.setattr(generated, "TABLE_BYTES", tables * table_bytes)
    text = str(jax.make_jaxpr(jax.value_and_grad(lambda k: _loss(run(k))))(K0))
    assert "fosmc_gen_" in text and "scan" in text  # the groups' loop
    got = run(K0)
    for a, b in zip(got.metrics, want.metrics):
        assert _rel(a, b) < 1e-12


@pytest.mark.slow
def test_the_realistic_arms_noisy_loop_on_the_default_path_equals_the_vmap_paths():
    """The arm in the realistic_arm preset's loop (encoders, differenced rates, delay, limit) with
    noise on the angles and 2 realizations, through ``problem.simulate``: metrics and gradients
    in every controller parameter (1e-6: the quantized loop)."""
    cfg = fj.config.load("realistic_arm").as_dict()
    cfg["sensors"].update(noise_std=[1e-4, 0.0, 0.0] * 3, realizations=2)
    cfg["sim"]["t_final"] = 300 * cfg["sim"]["dt"]
    problem = fj.build(cfg)
    p0 = problem.params()

    def loss(p, fast):
        res = problem.simulate(p, fast=fast)
        m = res.mean()
        return jnp.mean(m.rms_error) + 1e-3 * jnp.mean(m.chattering), res.metrics

    assert "fosmc_gen_" in str(jax.make_jaxpr(lambda p: loss(p, True))(p0))
    (v, gen), g = jax.jit(jax.value_and_grad(lambda p: loss(p, True), has_aux=True))(p0)
    (w, vm), h = jax.jit(jax.value_and_grad(lambda p: loss(p, False), has_aux=True))(p0)
    for a, b in zip(gen, vm):
        assert _rel(a, b) < 1e-9
    assert _rel(v, w) < 1e-12
    for name in p0:
        assert _rel(g[name], h[name]) < 1e-6, name


def test_realizations_of_a_noise_free_loop_share_one_table_and_one_kernel_call():
    """R keys whose draws nothing takes (no ``noise_std``): one table for all, the R batches'
    rollouts folded into one call's lanes; the vmap path's values, R copies of each rollout's."""
    plants, ref, X0s, dt = _linear()
    loop = _loop(K0, None, COUNTS)
    run = lambda fast: rollout.simulate_batch(plants, loop, ref, X0s, dt, n_steps=N_STEPS, integrator="euler",
                                              keys=KEYS, fast=fast)  # fmt: skip
    text = str(jax.make_jaxpr(lambda: run(True))())
    assert text.count("fosmc_gen_") == 1 and "while" not in text and "scan" not in text
    gen, vm = run(True), run(False)
    for a, b in zip(gen.metrics, vm.metrics):
        assert _rel(a, b) < 1e-9
    np.testing.assert_array_equal(vm.metrics.rms_error[0], vm.metrics.rms_error[1])
