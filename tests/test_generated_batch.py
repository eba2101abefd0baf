"""``vmap`` of the generated kernels' gradients (fosmc_jax._simulator.generated: ``_folded_call``
and the batching rule of ``linear_call``): a batch of candidate controllers runs as one call of
the forward and one of the adjoint, its rollouts folded into the SIMD lanes, and every candidate's
value and gradient equals its own unbatched call's, in the three ways a batch can reach the
kernels: candidates sharing the time table (folded), a batch of references (a table each: one
call per candidate) and a batch of cotangents alone (one call each, the checkpoints shared). The
model is tests/test_generated.py's default one (its build is cached after that file's)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_generated import TanhPD, _linear, _loss, _rel  # the default model, its build cached

from fosmc_jax._simulator import generated, native

pytestmark = pytest.mark.slow  # a kernel build and vmapped gradients (~20 s cold)

KEY = jax.random.PRNGKey(0)[None]


@pytest.fixture(autouse=True, scope="module")
def _kernels():
    if not native.available() or jax.default_backend() != "cpu":
        pytest.skip("no C++ compiler or not the CPU backend: no generated kernels")


def _simulate(K, plants, ref, X0s, dt):
    full = (plants, TanhPD(K, plants.a_rows[0], plants.b_rows[0]), ref, X0s, dt, KEY, jnp.asarray(1e6, X0s.dtype),
            jnp.asarray(10.0, X0s.dtype))  # fmt: skip
    return generated.simulate_batch(full, n_steps=60, integrator="euler", paired=False)


def _candidates(C):
    """C gains around tests/test_generated.py's, 4 rollouts each: 5 candidates fold into 20
    lanes, three blocks of 8 in float64, the last one padded."""
    K0 = -jnp.kron(jnp.eye(3), jnp.array([[60.0, 12.0, 0.5]]))
    return K0[None] * (1.0 + 0.1 * jnp.arange(C))[:, None, None]


@pytest.mark.parametrize("checkpoint_bytes", [None, 4096])  # every carry kept; every K-th (K >= 2)
def test_a_batch_of_candidates_folds_and_each_gradient_is_its_own(monkeypatch, checkpoint_bytes):
    if checkpoint_bytes:
        monkeypatch.setattr(generated, "CHECKPOINT_BYTES", checkpoint_bytes)
    plants, ref, X0s, dt = _linear()
    Ks = _candidates(5)
    value_and_grad = jax.value_and_grad(lambda K: _loss(_simulate(K, plants, ref, X0s, dt)))
    program = jax.jit(jax.vmap(value_and_grad)).lower(Ks).as_text()
    assert program.count("stablehlo.while") == 0  # one call for the batch, no per-candidate loop
    vb, gb = jax.jit(jax.vmap(value_and_grad))(Ks)
    one = jax.jit(value_and_grad)
    for c in range(Ks.shape[0]):
        v, g = one(Ks[c])
        assert _rel(vb[c], v) < 1e-14 and _rel(gb[c], g) < 1e-12, c
        assert np.any(np.asarray(g) != 0)


def test_a_batch_of_references_runs_one_call_each_with_their_own_gradients():
    plants, ref, X0s, dt = _linear()
    K = _candidates(1)[0]
    taus = jnp.array([0.8, 1.0, 1.3]) * ref.duration
    loss = lambda K, tau: _loss(_simulate(K, plants, ref._replace(duration=tau), X0s, dt))
    gb = jax.jit(jax.vmap(jax.grad(loss), in_axes=(None, 0)))(K, taus)
    one = jax.jit(jax.grad(loss))
    for c, tau in enumerate(taus):
        assert _rel(gb[c], one(K, tau)) < 1e-12, c
    assert _rel(gb[0], gb[2]) > 1e-3  # the references differ, and so do their gradients


def test_a_batch_of_cotangents_shares_the_forwards_checkpoints():
    plants, ref, X0s, dt = _linear()
    K = _candidates(1)[0]
    out, pullback = jax.vjp(lambda K: _simulate(K, plants, ref, X0s, dt).metrics.rms_error, K)
    cts = jnp.stack(
        [jnp.ones_like(out), jnp.zeros_like(out).at[0, 0].set(1.0), jnp.arange(out.size).reshape(out.shape)]
    )
    batched = jax.jit(jax.vmap(pullback))(cts)[0]
    for c in range(cts.shape[0]):
        assert _rel(batched[c], jax.jit(pullback)(cts[c])[0]) < 1e-12, c


def test_the_tuners_check_of_the_adjoint_kernel_sees_it():
    """``fosmc tune``'s gradient mode ``auto`` takes reverse without timing forward mode where the
    gradient's program calls the adjoint kernel (a forward-mode compilation takes minutes)."""
    from fosmc_jax._search import tune

    plants, ref, X0s, dt = _linear()
    loss = lambda K: (_loss(_simulate(K, plants, ref, X0s, dt)), ())
    assert tune._on_adjoint_kernel(loss, _candidates(1)[0])
    assert not tune._on_adjoint_kernel(lambda K: (jnp.sum(K**2), ()), _candidates(1)[0])
