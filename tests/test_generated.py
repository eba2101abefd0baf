"""The generated kernels (fosmc_jax._simulator.generated, codegen): the closed loop's step printed
from the JAX model, forward and adjoint, against the ``vmap`` path of ``simulate`` (values and
gradients, the issue's tolerances: 1e-9 relative in float64 on smooth loops, 1e-6 on the quantized
digital loop), against central differences, in forward mode, under truncation, and the fallback
where a model cannot be printed. Each model's first build compiles C++ (seconds to tens of
seconds): the default tier holds one small model, the arm's in the slow tier."""

import dataclasses
import functools
import math
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fosmc_jax as fj
from fosmc_jax import paper
from fosmc_jax._simulator import codegen, generated, native, rollout


@pytest.fixture(autouse=True, scope="module")
def _kernels():
    """Skip where there are no generated kernels: no C++ compiler, or not the CPU backend (on a
    GPU the default path runs the vmap path, and these white-box calls have no handler). A
    fixture, not a ``skipif`` evaluated on import: the collection of a worker of ``make test``
    would wait for the kernel's build (tests/conftest.py)."""
    if not native.available() or jax.default_backend() != "cpu":
        pytest.skip("no C++ compiler or not the CPU backend: no generated kernels")


KEY = jax.random.PRNGKey(0)[None]


def _linear(dtype=jnp.float64):
    c = lambda x: jnp.asarray(x, dtype)
    plants = fj.LinearPlant(c(paper.A_ROWS)[None] * c([[1.0], [1.1]])[..., None], c(paper.B_ROWS)[None].repeat(2, 0))
    ref = fj.Cycloid(c(paper.THETA_START), c(paper.THETA_END), c(paper.TAU))
    X0s = fj.desired_state(ref(jnp.zeros((), dtype)))[None] + c([[0.0], [0.02]])
    return plants, ref, X0s, c(1e-3)


def _smc_loop(k, dtype=jnp.float64):
    """SMC (its solve with CB) in a digital loop with a period of 2 steps, delay 1, a limit."""
    c = lambda x: jnp.asarray(x, dtype)
    surface = fj.SurfaceParams(c(paper.C), c(paper.A_ROWS), c(paper.B_ROWS))
    law = fj.SMC(surface, k, c(jnp.full(3, 0.05)))
    return fj.DigitalLoop(law, fj.Sensors(jnp.zeros(3), None, "difference"), c(jnp.full(3, 24.0)), c(2e-3), 2, 1)


def _run(args, n, integrator, path, truncate=0):
    """The generated kernel's result (``path`` "gen") or the vmap path's (simulate_batch with fast=False)."""
    plants, ctrl, ref, X0s, dt = args
    if path == "vmap":
        return rollout.simulate_batch(plants, ctrl, ref, X0s, dt, n_steps=n, integrator=integrator, fast=False,
                                      truncate_every=truncate)  # fmt: skip
    full = (plants, ctrl, ref, X0s, dt, KEY, jnp.asarray(1e6, X0s.dtype), jnp.asarray(10.0, X0s.dtype))
    return generated.simulate_batch(full, n_steps=n, integrator=integrator, paired=False, truncate_every=truncate)


def _both(args, n, integrator, truncate=0):
    """The generated kernel's result and the vmap path's."""
    return _run(args, n, integrator, "gen", truncate), _run(args, n, integrator, "vmap", truncate)


def _loss(res):
    return jnp.sum(res.metrics.rms_error) + 1e-3 * jnp.sum(res.metrics.chattering)


def _rel(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return float(np.max(np.abs(a - b) / np.maximum(np.abs(b), 1e-300)))


@functools.partial(jax.tree_util.register_dataclass, data_fields=["K", "a_rows", "b_rows"], meta_fields=[])
@dataclasses.dataclass(frozen=True)
class TanhPD:
    """A user's law: feedforward (10) plus pole placement (16) through a tanh limit of 24 V."""

    K: jax.Array
    a_rows: jax.Array
    b_rows: jax.Array

    def init(self, X0, r0, key=None):
        return ()

    def update(self, state, Y, r, t):
        U = fj.feedforward(self.a_rows, self.b_rows, r) + self.K @ (Y - fj.desired_state(r))
        return 24.0 * jnp.tanh(U / 24.0), state


def _users_law_loss(path):
    """mean rms + chattering of a user's law (:class:`TanhPD`) on two linear plants, Euler, 60
    steps, in the law's gains and the plants' rows, on ``path`` ("gen" or "vmap")."""
    plants, ref, X0s, dt = _linear()

    def loss(K, a_rows):
        law = TanhPD(K, plants.a_rows[0], plants.b_rows[0])
        return _loss(_run((plants._replace(a_rows=a_rows), law, ref, X0s, dt), 60, "euler", path))

    return loss, (-jnp.kron(jnp.eye(3), jnp.array([[60.0, 12.0, 0.5]])), plants.a_rows)


def test_a_users_law_runs_on_the_kernel_with_the_vmap_paths_values_and_gradients():
    """The default tier's one model (the linear plant, a user's law, Euler, 60 steps): a forward
    builds the forward's library alone; a gradient in the law's gains and in the plants then
    builds the adjoint's, whose checkpointing forward gives the forward's value bit for bit;
    values and gradients equal the vmap path's."""
    gen, args = _users_law_loss("gen")
    before = set(generated._MODELS)
    v = jax.jit(gen)(*args)
    new = [m for key, m in generated._MODELS.items() if key not in before]
    assert len(new) == 1 and set(new[0].built) == {"steps", "forward"}  # no adjoint built for a forward
    v_g, g = jax.jit(jax.value_and_grad(gen, argnums=(0, 1)))(*args)
    assert True in new[0].built  # the adjoint with the plant's cotangents (the gradient in a_rows)
    assert np.asarray(v_g) == np.asarray(v)
    w, h = jax.jit(jax.value_and_grad(_users_law_loss("vmap")[0], argnums=(0, 1)))(*args)
    assert np.isfinite(v) and v > 0 and _rel(v, w) < 1e-12
    assert _rel(g[0], h[0]) < 1e-9 and _rel(g[1], h[1]) < 1e-9
    assert np.any(np.asarray(g[0]) != 0) and np.any(np.asarray(g[1]) != 0)


def test_a_model_traced_under_one_mesh_runs_under_another():
    """A printed model is kept per mesh: fosmc tune's global stage traced it under a shard_map of
    one axis ('candidates') and its gradient replayed it under another ('batch'), which JAX
    refused (fosmc tune on realistic_arm failed so from 56dfce3 until the mesh joined the key)."""
    gen, args = _users_law_loss("gen")
    P = jax.sharding.PartitionSpec

    def under(axis):
        mesh = jax.sharding.Mesh(np.array(jax.devices()[:1]), (axis,))
        f = jax.shard_map(lambda K: gen(K, args[1])[None], mesh=mesh, in_specs=P(), out_specs=P(axis))
        return jax.jit(f)(args[0])

    np.testing.assert_array_equal(under("candidates"), under("batch"))


@pytest.mark.slow
def test_the_adjoint_from_every_kth_carry_gives_the_gradients_of_every_carry(monkeypatch):
    """Where the checkpoints' budget admits only every K-th carry, the adjoint recomputes each
    block from it: the same gradients as from every step's carry."""
    gen, args = _users_law_loss("gen")
    g = jax.jit(jax.grad(gen, argnums=(0, 1)))(*args)
    monkeypatch.setattr(generated, "CHECKPOINT_BYTES", 4096)  # 60 steps of 64-byte rows: K >= 2
    g_k = jax.jit(jax.grad(gen, argnums=(0, 1)))(*args)
    assert _rel(g_k[0], g[0]) < 1e-12 and _rel(g_k[1], g[1]) < 1e-12
    assert np.any(np.asarray(g[0]) != 0)


@pytest.mark.slow
def test_a_vjp_that_does_not_print_leaves_the_derivative_to_the_scan_with_a_warning(monkeypatch):
    """The adjoint is printed at a derivative's first use: where its VJP does not print, that
    derivative differentiates the lax.scan of the split step, one warning naming why."""

    def refuse(*args):
        raise codegen.Unsupported("a primitive of the VJP")

    monkeypatch.setattr(generated, "_MODELS", {})  # the model printed anew
    monkeypatch.setattr(generated, "_print_vjps", refuse)
    gen, args = _users_law_loss("gen")
    with pytest.warns(UserWarning, match="adjoint cannot be built .*a primitive of the VJP.*lax.scan"):
        g = jax.jit(jax.grad(gen, argnums=(0, 1)))(*args)
    h = jax.jit(jax.grad(_users_law_loss("vmap")[0], argnums=(0, 1)))(*args)
    assert _rel(g[0], h[0]) < 1e-9 and _rel(g[1], h[1]) < 1e-9


@pytest.mark.slow
def test_a_digital_smc_loop_runs_on_the_kernel_with_the_vmap_paths_values_and_gradients():
    """SMC (its solve with CB becomes a product with the hoisted inverse), sampled every 2 steps,
    differenced rates, a delay, the limit: values and gradients in the gains and the plants."""
    plants, ref, X0s, dt = _linear()
    k0 = jnp.array([20.0, 25.0, 30.0])

    def run(path):
        def loss(k, a_rows):
            gen, vm = _both((plants._replace(a_rows=a_rows), _smc_loop(k), ref, X0s, dt), 60, "euler")
            return _loss(gen if path == "gen" else vm)

        return jax.jit(jax.value_and_grad(loss, argnums=(0, 1)))(k0, plants.a_rows)

    (v_gen, g_gen), (v_vm, g_vm) = run("gen"), run("vmap")
    assert np.isfinite(v_gen) and v_gen > 0
    assert _rel(v_gen, v_vm) < 1e-12
    # the kernel's SMC multiplies by the hoisted (CB)^-1 where the law solves with CB: rounding
    assert _rel(g_gen[0], g_vm[0]) < 1e-9 and _rel(g_gen[1], g_vm[1]) < 1e-9
    assert np.all(np.asarray(g_gen[0]) != 0) and np.any(np.asarray(g_gen[1]) != 0)


@pytest.mark.slow
def test_forward_mode_runs_the_split_step_and_equals_the_vmap_path():
    plants, ref, X0s, dt = _linear()
    k0 = jnp.array([20.0, 25.0, 30.0])

    def loss(k, path):
        gen, vm = _both((plants, _smc_loop(k), ref, X0s, dt), 60, "euler")
        return _loss(gen if path == "gen" else vm)

    t = jnp.array([1.0, -0.5, 0.25])
    _, d_gen = jax.jvp(lambda k: loss(k, "gen"), (k0,), (t,))
    _, d_vm = jax.jvp(lambda k: loss(k, "vmap"), (k0,), (t,))
    assert _rel(d_gen, d_vm) < 1e-9 and d_vm != 0


@pytest.mark.slow  # 4 s: the default tier keeps to 4 minutes on 2 cores
def test_a_primitive_the_printer_does_not_know_is_named_and_the_batch_runs_the_vmap_path():
    @functools.partial(jax.tree_util.register_dataclass, data_fields=["K"], meta_fields=[])
    @dataclasses.dataclass(frozen=True)
    class Looping:
        K: jax.Array

        def init(self, X0, r0, key=None):
            return ()

        def update(self, state, Y, r, t):
            e = Y - fj.desired_state(r)
            # a while loop: nothing the printer prints
            U = jax.lax.while_loop(lambda u: jnp.sum(u * u) > 1e6, lambda u: u / 2, self.K @ e)
            return U, state

    plants, ref, X0s, dt = _linear()
    ctrl = Looping(-jnp.ones((3, 9)))
    full = (plants, ctrl, ref, X0s, dt, KEY, jnp.asarray(1e6), jnp.asarray(10.0))
    with pytest.raises(codegen.Unsupported, match="while"):
        generated.simulate_batch(full, n_steps=5, integrator="euler", paired=False)
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("FOSMC_JAX_GENERATED", "all")
        with pytest.warns(UserWarning, match="cannot run this model .*while.*vmap path runs"):
            res = rollout.simulate_batch(plants, ctrl, ref, X0s, dt, n_steps=5, integrator="euler")
    want = rollout.simulate_batch(plants, ctrl, ref, X0s, dt, n_steps=5, integrator="euler", fast=False)
    np.testing.assert_array_equal(res.metrics.rms_error, want.metrics.rms_error)


def _lapack_calls(text: str) -> list[tuple[str, tuple, int]]:
    """The LAPACK calls of a lowered program: (kind, shape, jaxlib 0.10's work estimate of the
    batch: m n min(m, n) per LU, m n m (left side) or m n n per triangular solve of m x n)."""
    calls = []
    for line in text.splitlines():
        found = re.search(r"custom_call @lapack_[sdcz](getrf|trsm)_ffi", line)
        if found:
            types = re.findall(r"tensor<((?:\d+x)*)[a-z]\w*>", line.rsplit(" : (", 1)[-1].split("->")[0])
            *batch, m, n = (int(d) for d in types[-1 if found[1] == "trsm" else 0].rstrip("x").split("x"))
            cost = m * n * min(m, n) if found[1] == "getrf" else m * n * (m if "side = 76" in line else n)
            calls.append((found[1], (*batch, m, n), math.prod(batch) * cost))
    return calls


def _solves(v):
    """A 3 x 3 solve with 9 right-hand sides and one with 1 (jaxlib's work: 81 and 9, LU 27)."""
    M = jnp.diag(3 + jnp.cos(v[:3])) + 0.1 * jnp.outer(jnp.sin(v[3:6]), jnp.cos(v[6:9]))
    b = jnp.outer(jnp.tanh(v[9:12]), jnp.arange(1.0, 10.0))
    return jnp.linalg.solve(M, b), jnp.linalg.solve(M, b[:, 0])


def test_batched_lapack_calls_stay_below_jaxlibs_split_and_keep_their_values():
    """jaxlib's CPU LAPACK kernels split a batch of 200,000 flops or more over XLA's intra-op
    threads and wait for the pieces on one of them: two such calls at once on 2 cores hung the
    arm's gradient of 3,072 rollouts (the solves of its hoisted lanes, 3 x 9 right-hand sides).
    ``generated._vmap`` maps such a batch in pieces below that, values bitwise unchanged, its
    derivatives' calls too; a batch below it is the plain ``vmap``."""
    assert generated._lapack_work(jax.make_jaxpr(_solves)(jnp.zeros(12)).jaxpr) == 81
    x = jnp.asarray(np.random.default_rng(0).normal(size=(3072, 12)))
    plain = jax.jit(jax.vmap(_solves)).lower(x).as_text()
    assert max(w for *_, w in _lapack_calls(plain)) == 3072 * 81  # the premise: plain vmap splits
    mapped = lambda x: generated._vmap(_solves, (x,))
    grad = jax.grad(lambda x: jnp.sum(mapped(x)[0] ** 2) + jnp.sum(mapped(x)[1]))
    for f in (mapped, grad):
        calls = _lapack_calls(jax.jit(f).lower(x).as_text())
        assert calls and max(w for *_, w in calls) < generated._LAPACK_SPLIT, calls
    halves = [jax.jit(jax.vmap(_solves))(h) for h in (x[:1536], x[1536:])]  # 1,536 x 81: one thread each
    for got, want in zip(jax.jit(mapped)(x), zip(*halves)):
        np.testing.assert_array_equal(got, np.concatenate(want))
    small = x[:2048]  # 2,048 x 81 < 200,000: the plain vmap's calls, whole
    calls = _lapack_calls(jax.jit(mapped).lower(small).as_text())
    assert calls == _lapack_calls(jax.jit(jax.vmap(_solves)).lower(small).as_text()) and calls[0][1][0] == 2048


def test_the_mode_is_checked():
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("FOSMC_JAX_GENERATED", "always")
        with pytest.raises(ValueError, match="FOSMC_JAX_GENERATED: expected one of all, 0"):
            generated.mode()


# ------------------------------------------------------------------------------ the arm (slow)


def _arm(cfg="realistic_arm", steps=300, **sim):
    c = fj.config.load(cfg)
    c = fj.config.replace(c, sim={"t_final": steps * c.sim.dt, **sim})
    return fj.build(c)


@pytest.mark.slow
@pytest.mark.parametrize("cfg, tol", [("arm_ideal", 1e-9), ("realistic_arm", 1e-6)])
def test_the_arms_gradient_on_the_default_path_is_the_generated_adjoints_and_equals_the_vmap_paths(cfg, tol):
    # The public default path: the hand-written kernel forward, the generated kernel's derivatives.
    if cfg == "arm_ideal":
        problem = _arm("tuning/configs/arm_ideal_set2.toml", 300, integrator="rk4")
    else:
        problem = _arm(cfg, 300)
    p0 = problem.params()

    def loss(p, fast):
        m = problem.simulate(p, fast=fast).mean()
        return jnp.mean(m.rms_error) + 1e-3 * jnp.mean(m.chattering)

    v, g = jax.jit(jax.value_and_grad(lambda p: loss(p, True)))(p0)
    w, h = jax.jit(jax.value_and_grad(lambda p: loss(p, False)))(p0)
    assert _rel(v, w) < 1e-12
    for name in p0:
        assert _rel(g[name], h[name]) < tol, (name, g[name], h[name])
        assert np.any(np.asarray(h[name]) != 0)


@pytest.mark.slow
def test_the_arms_gradient_in_its_physical_parameters_and_payloads_equals_the_vmap_paths():
    problem = _arm("tuning/configs/arm_ideal_set2.toml", 200, integrator="rk4")
    arm = problem.arm_params()

    def loss(F, Kt, fast):
        m = problem.with_arm({"F": F, "Kt": Kt}).simulate(fast=fast).mean()
        return jnp.mean(m.rms_error)

    g = jax.jit(jax.grad(lambda F, Kt: loss(F, Kt, True), argnums=(0, 1)))(arm["F"], arm["Kt"])
    h = jax.jit(jax.grad(lambda F, Kt: loss(F, Kt, False), argnums=(0, 1)))(arm["F"], arm["Kt"])
    assert _rel(g[0], h[0]) < 1e-9 and _rel(g[1], h[1]) < 1e-9


@pytest.mark.slow
def test_the_generated_gradient_matches_central_differences_on_a_smooth_loop():
    problem = _arm("tuning/configs/arm_ideal_set2.toml", 200, integrator="rk4")
    delta = problem.params()["delta"]
    loss = jax.jit(lambda d: jnp.mean(problem.simulate({"delta": d}).mean().rms_error))
    g = np.asarray(jax.grad(loss)(delta))
    for i in range(3):
        h = 1e-4 * float(delta[i])
        e = jnp.zeros(3).at[i].set(h)
        fd = (float(loss(delta + e)) - float(loss(delta - e))) / (2 * h)
        assert abs(g[i] - fd) <= 1e-5 * abs(fd) + 1e-12, (i, g[i], fd)


@pytest.mark.slow
def test_truncated_gradients_stop_in_the_adjoint_as_in_the_scan():
    problem = _arm("tuning/configs/arm_ideal_set2.toml", 200, integrator="rk4")
    p0 = problem.params()

    def loss(p, fast):
        return jnp.mean(problem.simulate(p, fast=fast, truncate_every=50).mean().rms_error)

    g = jax.jit(jax.grad(lambda p: loss(p, True)))(p0)
    h = jax.jit(jax.grad(lambda p: loss(p, False)))(p0)
    full = jax.jit(jax.grad(lambda p: jnp.mean(problem.simulate(p, fast=False).mean().rms_error)))(p0)
    for name in p0:
        assert _rel(g[name], h[name]) < 1e-9, name
    assert _rel(h["delta"], full["delta"]) > 1e-6  # the truncation changes the gradient


@pytest.mark.slow
def test_a_users_law_with_a_state_of_its_own_runs_on_the_arm_kernel_in_float32():
    @functools.partial(jax.tree_util.register_dataclass, data_fields=["K", "Ki", "a_rows", "b_rows"], meta_fields=[])
    @dataclasses.dataclass(frozen=True)
    class PIDTanh:
        """Feedforward (10) + pole placement + an integral of the angle error, through tanh."""

        K: jax.Array
        Ki: jax.Array
        a_rows: jax.Array
        b_rows: jax.Array

        def init(self, X0, r0, key=None):
            return jnp.zeros(3, X0.dtype)

        def update(self, z, Y, r, t):
            e = Y - fj.desired_state(r)
            z = z + 1e-4 * e[0::3]
            U = fj.feedforward(self.a_rows, self.b_rows, r) + 24.0 * jnp.tanh((self.K @ e + self.Ki * z) / 24.0)
            return U, z

    problem = _arm("tuning/configs/arm_ideal_set2.toml", 200, integrator="euler", precision="float32")
    base = problem.params()  # noqa: F841 (the problem's FOSMC is replaced by the user's law)
    c = lambda x: jnp.asarray(x, jnp.float32)
    law = PIDTanh(c(-jnp.kron(jnp.eye(3), jnp.array([[400.0, 40.0, 1.0]]))), c(jnp.full(3, -100.0)),
                  c(paper.A_ROWS), c(paper.B_ROWS))  # fmt: skip
    plants, ref, X0s, dt = problem.plants, problem.reference, problem.X0s, problem.dt
    from fosmc_jax._plants.arm import without_idle_terms

    plants = without_idle_terms(plants)

    def loss(Ki, path):
        gen, vm = _both((plants, dataclasses.replace(law, Ki=Ki), ref, X0s, dt), 200, "euler")
        return _loss(gen if path == "gen" else vm)

    v, g = jax.value_and_grad(lambda k: loss(k, "gen"))(law.Ki)
    w, h = jax.value_and_grad(lambda k: loss(k, "vmap"))(law.Ki)
    assert _rel(v, w) < 1e-4 and _rel(g, h) < 1e-3  # float32: to rounding over 200 steps


@pytest.mark.slow
def test_the_arms_gradients_of_3072_rollouts_for_8_parameter_sets_call_no_lapack():
    """The hang of 3,072 arm rollouts (64 payloads x 48 offsets, RK4), and of a ``vmap`` over
    parameter sets around it (8 x 3,072, which no sizing of pieces inside could foresee): the
    law's and the arm's 3 x 3 solves are written out (``_design/linalg.py``), so the gradients'
    program (lowered, not run: the hang is one of threads, a run on many cores may pass) holds no
    LAPACK call that jaxlib could split over threads
    (:func:`test_batched_lapack_calls_stay_below_jaxlibs_split_and_keep_their_values`)."""
    c = fj.config.load("tuning/configs/arm_ideal_set2.toml").as_dict()
    c["plant"]["payloads"] = np.linspace(0, 10, 64).tolist()
    c["plant"].pop("uncertainty", None)
    offsets = np.random.default_rng(1).uniform(-0.05, 0.05, (48, 9)).tolist()
    c["sim"].update(integrator="rk4", t_final=20 * c["sim"]["dt"], initial_offset=offsets)
    problem = fj.build(c)
    loss = lambda p: jnp.mean(problem.simulate(p).mean().rms_error)
    sets = jax.tree.map(lambda x: x * jnp.linspace(0.9, 1.1, 8).reshape((8,) + (1,) * jnp.ndim(x)), problem.params())
    text = jax.jit(jax.vmap(jax.value_and_grad(loss))).lower(sets).as_text()
    assert problem.rollouts == 3072 and "fosmc_gen_" in text  # the generated adjoint's program
    assert "@lapack_" not in text, _lapack_calls(text)


@pytest.mark.slow
def test_jacfwd_and_vmap_of_grad_run_through_the_arms_default_path():
    """Forward mode and vmapped gradients (a front's many points) through the generated kernel's
    linear_call: both equal to the vmap path's."""
    problem = _arm("tuning/configs/arm_ideal_set2.toml", 50, integrator="rk4")
    d = problem.params()["delta"]
    loss = lambda d, fast: jnp.mean(problem.simulate({"delta": d}, fast=fast).mean().rms_error)
    assert _rel(jax.jacfwd(lambda d: loss(d, True))(d), jax.jacfwd(lambda d: loss(d, False))(d)) < 1e-9
    ds = jnp.stack([d, 1.1 * d])
    g = jax.vmap(jax.grad(lambda d: loss(d, True)))(ds)
    assert _rel(g, jax.vmap(jax.grad(lambda d: loss(d, False)))(ds)) < 1e-9


def test_the_printers_numpy_moves_equal_jaxs():
    """Each data move the printer runs in NumPy on element ids gives JAX's own result."""
    x = jnp.arange(1.0, 25.0).reshape(2, 3, 4)
    moves = [
        lambda x: x.reshape(6, 4), lambda x: jnp.broadcast_to(x[:, :1, :], (5, 2, 3, 4)),
        lambda x: x.transpose(2, 0, 1), lambda x: x[:1].squeeze(0), lambda x: x[None], lambda x: x[::-1],
        lambda x: x[:, 1:3, ::2], lambda x: jnp.concatenate([x, x[:, :1]], 1),
        lambda x: jax.lax.pad(x, 0.0, ((1, 0, 0), (0, 2, 0), (0, 0, 0))),
        lambda x: jnp.stack([x, x], 1), lambda x: jnp.split(x, [1, 3], axis=2), lambda x: list(x),
    ]  # fmt: skip
    seen = set()
    for f in moves:
        for eqn in jax.make_jaxpr(f)(x).eqns:
            vals = [np.asarray(v.val) if hasattr(v, "val") else np.arange(1.0, 1.0 + np.prod(v.aval.shape))
                    .reshape(v.aval.shape) for v in eqn.invars]  # fmt: skip
            ours = codegen._numpy_move(eqn, vals)
            if ours is None:
                continue
            with jax.ensure_compile_time_eval():
                theirs = eqn.primitive.bind(*vals, **eqn.primitive.get_bind_params(eqn.params))
            ours, theirs = (ours, theirs) if eqn.primitive.multiple_results else ([ours], [theirs])
            assert len(ours) == len(theirs)
            for a, b in zip(ours, theirs):
                assert np.shape(a) == np.shape(b) and np.array_equal(a, b), eqn
            seen.add(eqn.primitive.name)
    assert {"reshape", "broadcast_in_dim", "transpose", "squeeze", "slice", "concatenate", "pad", "rev"} <= seen


@functools.partial(jax.tree_util.register_dataclass, data_fields=["inner", "tau"], meta_fields=[])
@dataclasses.dataclass(frozen=True)
class LaggedPlant:
    """A user's plant with a state of its own (12 rows): the linear plant driven through a
    first-order actuator lag of time constant tau (s) per plant."""

    inner: fj.LinearPlant
    tau: jax.Array

    def init(self, X0):
        return self.inner.init(X0), jnp.zeros(3, X0.dtype)

    def observe(self, state):
        return self.inner.observe(state[0])

    def derivative(self, state, U):
        x, v = state
        return self.inner.derivative(x, v), (U - v) / self.tau


@pytest.mark.slow
def test_a_users_plant_with_a_state_of_its_own_runs_on_the_kernel():
    """A user's plant (an actuator lag: 12 state rows) under a user's law, RK4: values and
    gradients in the lag's time constants and the law's gains, against the vmap path."""
    plants, ref, X0s, dt = _linear()
    K0 = -jnp.kron(jnp.eye(3), jnp.array([[60.0, 12.0, 0.5]]))
    tau0 = jnp.array([0.01, 0.02])

    def run(path):
        def loss(K, tau):
            args = (LaggedPlant(plants, tau), TanhPD(K, plants.a_rows[0], plants.b_rows[0]), ref, X0s, dt)
            gen, vm = _both(args, 80, "rk4")
            return _loss(gen if path == "gen" else vm)

        return jax.jit(jax.value_and_grad(loss, argnums=(0, 1)))(K0, tau0)

    (v, g), (w, h) = run("gen"), run("vmap")
    assert np.isfinite(v) and v > 0 and _rel(v, w) < 1e-12
    assert _rel(g[0], h[0]) < 1e-9 and _rel(g[1], h[1]) < 1e-9
    assert np.all(np.asarray(g[1]) != 0)


def test_the_split_computes_a_repeated_time_value_and_its_terms_once():
    """RK4's stages 2 and 3 each compute t_k + dt/2 and what depends on it: the split merges the
    repeated equations (one hoisted time value, one sin in the printed step), same numbers."""

    def step(x, lane, glob, k):
        (dt,), (f,) = glob, lane
        t2, t3 = k * dt + dt / 2, k * dt + dt / 2  # two stages' times, computed apart
        return x + jnp.sin(f * t2) * x[0] + jnp.sin(f * t3) * x[1]

    f64 = lambda *s: jax.ShapeDtypeStruct(s, jnp.float64)
    s = generated.split(step, f64(2), [f64()], [f64()])
    assert len(s.time_avals) == 1  # t_k + dt/2 once
    core = jax.make_jaxpr(s.core)(f64(2), s.lane_avals, s.time_avals)
    assert [e.primitive.name for e in core.eqns].count("sin") == 1
    x, f, dt, k = jnp.array([0.3, -0.7]), jnp.asarray(2.5), jnp.asarray(1e-3), jnp.int32(7)
    got = s.core(x, s.lane_pre([f]), s.time_pre(k, [dt]))
    np.testing.assert_array_equal(got, step(x, [f], [dt], k))
