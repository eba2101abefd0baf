"""The fast path against the reference path: the LinearPlant batch of simulate_batch (the kernel
generated from its step) against vmap of simulate (values, divergence, gradients, float32), the
kernels' build, and the sharded batch against the single-device one (in a subprocess with two
host devices)."""

import os
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fosmc_jax as fj
from fosmc_jax import paper
from fosmc_jax._simulator import native as _native

BOX = (paper.A_LOWER, paper.A_UPPER, paper.B_LOWER, paper.B_UPPER)


def setup(P=3, O=4, dtype=np.float64, gamma=paper.GAMMA):
    c = lambda x: jnp.asarray(np.asarray(x, np.float64), dtype)
    ctrl = fj.FOSMCParams(c(paper.C), c(paper.POLES), c(gamma), c(paper.DELTA_SETS[0]),
                         c(paper.A_ROWS), c(paper.B_ROWS))  # fmt: skip
    ref = fj.Cycloid(c(paper.THETA_START), c(paper.THETA_END), c(paper.TAU))
    p = fj.uncertain_plants(paper.A_ROWS, paper.B_ROWS, "sample", box=BOX, samples=P, seed=3)
    plants = fj.LinearPlant(c(p.a_rows), c(p.b_rows))
    X0 = np.asarray(ref(0.0)[:3].T.reshape(9))
    X0s = c(X0 + np.random.default_rng(1).uniform(-0.05, 0.05, (O, 9)))
    return plants, ctrl, ref, X0s


def reference_path(plants, ctrl, ref, X0s, dt, **options):
    """vmap of simulate, the path every other plant takes."""
    one = lambda p, x: fj.simulate(p, ctrl, ref, x, dt, **options)
    r = jax.vmap(jax.vmap(one, in_axes=(None, 0)), in_axes=(0, None))(plants, X0s)
    return jax.tree.map(lambda x: x.reshape((-1,) + x.shape[2:]), r)


def assert_close(a, b, rtol=1e-10):
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        assert x.shape == y.shape and x.dtype == y.dtype
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=rtol, atol=1e-300)


@pytest.mark.parametrize(
    "integrator, switching, law",
    # every integrator, switching function and law at least once (each case compiles twice,
    # 6-9 s: one case in the default tier, the others in the slow tier)
    [("euler", "sign", "paper"), pytest.param("rk4", "ratio", "paper", marks=pytest.mark.slow),
     pytest.param("euler", "sat", "equivalent", marks=pytest.mark.slow),
     pytest.param("rk4", "tanh", "equivalent", marks=pytest.mark.slow)],
)  # fmt: skip
def test_fast_batch_equals_vmap_of_simulate(integrator, switching, law):
    plants, ctrl, ref, X0s = setup()
    opts = dict(n_steps=400, integrator=integrator, switching=switching, law=law)
    fast = fj.simulate_batch(plants, ctrl, ref, X0s, 1e-3, **opts)
    assert fast.trace is None and fast.metrics.rms_error.shape == (12, 3)
    assert_close(fast, reference_path(plants, ctrl, ref, X0s, 1e-3, **opts))


# (5, 1): the CLI's sampled plants, one initial state; (1, 3); both in the slow tier (~5 s each):
# the default tier keeps to 4 minutes on 2 cores
@pytest.mark.parametrize(
    "P, O", [pytest.param(5, 1, marks=pytest.mark.slow), pytest.param(1, 3, marks=pytest.mark.slow)]
)
def test_fast_batch_one_offset_or_one_plant(P, O):
    # O = 1 runs on (P,) vectors instead of (P, 1) (the CLI's sampled plants)
    plants, ctrl, ref, X0s = setup(P, O)
    # the default bound, passed (an argument, not a constant): the divergence test's programs
    opts = dict(n_steps=300, integrator="euler", divergence_bound=1e6)
    fast = fj.simulate_batch(plants, ctrl, ref, X0s, 1e-3, **opts)
    assert fast.metrics.rms_error.shape == (P * O, 3)
    assert_close(fast, reference_path(plants, ctrl, ref, X0s, 1e-3, **opts))


def test_fast_batch_freezes_diverged_rollouts_like_simulate():
    # far too stiff for dt: blows up. The shapes and options of test_fast_batch_one_offset_or_one_plant's
    # default case (5 plants, 1 initial state): its two programs, compiled once
    plants, ctrl, ref, X0s = setup(5, 1, gamma=[5e4, 5e4, 5e4])
    opts = dict(n_steps=300, integrator="euler", divergence_bound=50.0)
    fast = fj.simulate_batch(plants, ctrl, ref, X0s, 2e-2, **opts)
    slow = reference_path(plants, ctrl, ref, X0s, 2e-2, **opts)
    assert np.asarray(fast.diverged).any()
    assert_close(fast, slow)


@pytest.mark.slow  # a float32 compilation of both paths: ~7 s
def test_fast_batch_float32():
    """The benchmark's precision and integrator (float32, Euler); RK4 in float64 above."""
    plants, ctrl, ref, X0s = setup(dtype=np.float32)
    opts = dict(n_steps=400, integrator="euler")
    fast = fj.simulate_batch(plants, ctrl, ref, X0s, np.float32(1e-3), **opts)
    assert fast.metrics.rms_error.dtype == jnp.float32
    assert_close(fast, reference_path(plants, ctrl, ref, X0s, np.float32(1e-3), **opts), rtol=1e-4)


@pytest.mark.slow  # forward mode through the kernel's custom_jvp: ~17 s
def test_fast_batch_forward_mode_and_mixed_precision():
    """Forward-mode derivatives through the fast path (the kernel's are the scan's), and plants
    in float32 with float64 states (the kernel runs in the promoted dtype, as the scan)."""
    plants, ctrl, ref, X0s = setup(P=2, O=2)
    opts = dict(n_steps=60, integrator="euler")

    def loss(gamma, fast):
        r = fj.simulate_batch(plants, ctrl._replace(gamma=gamma), ref, X0s, 1e-3, fast=fast, **opts)
        return jnp.mean(r.metrics.rms_error)

    np.testing.assert_allclose(jax.jacfwd(loss)(ctrl.gamma, True), jax.grad(loss)(ctrl.gamma, False), rtol=1e-9)
    plants32 = jax.tree.map(lambda a: a.astype(jnp.float32), plants)
    mixed = fj.simulate_batch(plants32, ctrl, ref, X0s, 1e-3, **opts)
    assert mixed.metrics.rms_error.dtype == jnp.float64
    assert_close(mixed, fj.simulate_batch(plants32, ctrl, ref, X0s, 1e-3, fast=False, **opts))


def test_the_linear_batch_runs_the_generated_kernel():
    """The linear plant under the FOSMC prints like any model: its batch calls the generated
    kernel (kernel.cc and the structure-of-arrays scan, its hand-written copies, retired)."""
    if not _native.available():
        pytest.skip("no C++ compiler or not the CPU backend: the vmap path runs")
    plants, ctrl, ref, X0s = setup()
    program = jax.make_jaxpr(lambda: fj.simulate_batch(plants, ctrl, ref, X0s, 1e-3, n_steps=10))()
    assert "fosmc_gen_" in str(program)


def test_failed_kernel_build_is_one_clear_error_and_leaves_no_file(tmp_path, monkeypatch):
    monkeypatch.setenv("FOSMC_JAX_CACHE", str(tmp_path))
    monkeypatch.setenv("CXX", "false")  # a "compiler" that fails at once
    source = '#define FOSMC_T double\n#include "gen_kernel.h"\n'
    with pytest.raises(OSError, match="^false failed"):
        _native.build_generated([source])
    assert list(tmp_path.iterdir()) == []
    monkeypatch.setattr(_native, "_compiler", lambda: None)
    with pytest.raises(OSError, match="no C\\+\\+ compiler found"):
        _native.build_generated([source])


@pytest.mark.slow  # reverse mode through both paths with RK4 (~35 s of compilation on 2 cores)
def test_fast_batch_gradient_with_checkpointing():
    plants, ctrl, ref, X0s = setup(P=2, O=2)

    def loss(delta, batch, checkpoint_every):
        r = batch(plants, ctrl._replace(delta=delta), ref, X0s, 1e-3, n_steps=200,
                  integrator="rk4", checkpoint_every=checkpoint_every)  # fmt: skip
        return jnp.mean(r.metrics.rms_error) + jnp.mean(r.metrics.chattering)

    g = jax.grad(loss)(ctrl.delta, reference_path, 0)
    np.testing.assert_allclose(jax.grad(loss)(ctrl.delta, fj.simulate_batch, 16), g, rtol=1e-9)


@pytest.mark.slow  # five sharded programs in a subprocess (~35 s); the default tier shards once below
def test_sharded_equals_single_device():
    code = textwrap.dedent(
        """
        from fosmc_jax._simulator.sharding import simulate_sharded, use_host_devices
        use_host_devices(2)
        import jax, numpy as np
        jax.config.update("jax_enable_x64", True)
        import fosmc_jax as fj
        sys_path_test = __import__("test_performance_paths")
        assert jax.device_count() == 2
        traced = dict(n_steps=90, save_every=30)
        for P, O, cases in ((3, 4, 2), (2, 3, 1), (3, 5, 1)):  # split X0s; split plants; pad X0s
            args = sys_path_test.setup(P, O)
            for opts in (dict(n_steps=300, integrator="rk4"), traced)[:cases]:
                a = simulate_sharded(*args, 1e-3, devices=2, **opts)
                b = fj.simulate_batch(*args, 1e-3, **opts)
                sys_path_test.assert_close(a, b, rtol=1e-12)
                assert len(a.metrics.rms_error.sharding.device_set) == 2
        print("ok")
        """
    )
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([os.path.dirname(__file__), os.environ.get("PYTHONPATH", "")]))
    env.pop("XLA_FLAGS", None)
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0 and out.stdout.strip().endswith("ok"), out.stderr[-3000:]


@pytest.mark.parametrize(
    "env, expected",
    # the host's cores by default; a count the user set wins (1 turns sharding off)
    # (each a subprocess compiling afresh, ~8-15 s: all three run in the slow tier, which CI runs)
    [pytest.param({}, len(os.sched_getaffinity(0)), marks=pytest.mark.slow),
     pytest.param({"JAX_NUM_CPU_DEVICES": "1"}, 1, marks=pytest.mark.slow),
     pytest.param({"XLA_FLAGS": "--xla_force_host_platform_device_count=3"}, 3, marks=pytest.mark.slow)],
)  # fmt: skip
def test_use_all_cores_default_and_user_count(env, expected):
    code = textwrap.dedent(
        """
        from fosmc_jax._simulator.sharding import simulate_sharded, use_all_cores
        n = use_all_cores()
        import jax, numpy as np
        jax.config.update("jax_enable_x64", True)
        import fosmc_jax as fj
        t = __import__("test_performance_paths")
        assert n == jax.device_count(), (n, jax.devices())
        args = t.setup(3, 4)
        a = simulate_sharded(*args, 1e-3, devices=n, n_steps=200, integrator="euler")
        t.assert_close(a, fj.simulate_batch(*args, 1e-3, n_steps=200, integrator="euler"), rtol=1e-12)
        assert len(a.metrics.rms_error.sharding.device_set) == n
        print("devices", n)
        """
    )
    base = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "JAX_NUM_CPU_DEVICES")}
    env = dict(base, **env, PYTHONPATH=os.pathsep.join([os.path.dirname(__file__), os.environ.get("PYTHONPATH", "")]))
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0 and out.stdout.strip().endswith(f"devices {expected}"), out.stderr[-3000:]


@pytest.mark.slow  # a subprocess compiling a chunk evaluator and two gradients (~25 s)
def test_tuners_split_over_the_devices_as_on_one():
    """The front's chunks split over two devices equal each candidate evaluated alone, and the
    tuner's loss with its rollouts split (simulate_split) has one device's value and gradient."""
    code = textwrap.dedent(
        """
        from fosmc_jax._simulator.sharding import use_host_devices
        use_host_devices(2)
        import jax, numpy as np
        jax.config.update("jax_enable_x64", True)
        assert jax.device_count() == 2
        from fosmc_jax import _problems as _config
        from fosmc_jax._search import front as _front
        from fosmc_jax._search import tune as _tuning
        cfg = _config.resolve({"plant": {"uncertainty": "sample", "samples": 2},
                               "sim": {"t_final": 0.1, "dt": 2e-3, "integrator": "euler"}})
        plain, _, p0 = _config.tuning_problems(cfg)
        ps = _front.sample_candidates(p0, 5, seed=0)  # 5: a chunk padded to the devices
        m = _front.evaluate_many(plain, ps, 3)
        for i in range(5):
            one = _tuning.evaluate(plain, jax.tree.map(lambda x: x[i], ps))
            np.testing.assert_allclose(m["rms_error"][i], one["metrics"]["rms_error"], rtol=1e-12)
            np.testing.assert_allclose(m["chattering_hf"][i], one["metrics"]["chattering_hf"], rtol=1e-12)
        # the tuner's loss with its rollouts split over the devices: the same value and gradient
        def value_and_grad(split):
            def f(p):
                r = plain.simulate(p, split=split, fast=False)
                return jax.numpy.mean(r.metrics.rms_error) + jax.numpy.mean(r.metrics.chattering_hf)
            return jax.jit(jax.value_and_grad(f))(p0), str(jax.make_jaxpr(f)(p0))
        ((va, ga), split), ((vb, gb), whole) = value_and_grad(True), value_and_grad(False)
        assert "shard_map" in split and "shard_map" not in whole  # the 2 plants: one per device
        np.testing.assert_allclose(va, vb, rtol=1e-12)
        for x, y in zip(ga, gb):
            np.testing.assert_allclose(x, y, rtol=1e-9, atol=1e-300)
        print("ok")
        """
    )
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([os.path.dirname(__file__), os.environ.get("PYTHONPATH", "")]))
    env.pop("XLA_FLAGS", None)
    env.pop("JAX_NUM_CPU_DEVICES", None)
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0 and out.stdout.strip().endswith("ok"), out.stderr[-3000:]
