"""The written-out 3x3 inverse and solve against LAPACK's (NumPy), to a bound in the condition number."""

import jax.numpy as jnp
import numpy as np

from fosmc_jax._design.linalg import inv3, solve3


def test_solve3_and_inv3_equal_numpys_to_rounding_times_the_condition_number():
    rng = np.random.default_rng(0)
    M = rng.normal(size=(500, 3, 3))
    b = rng.normal(size=(500, 3, 4))
    want = np.linalg.solve(M, b)
    got = np.stack([np.asarray(solve3(jnp.asarray(m), jnp.asarray(x))) for m, x in zip(M[:50], b[:50])])
    err = np.abs(got - want[:50]).max((1, 2)) / np.abs(want[:50]).max((1, 2))
    assert np.all(err <= 10 * np.finfo(float).eps * np.linalg.cond(M[:50]))
    inv = np.asarray(inv3(jnp.asarray(M)))  # batched over the leading axis
    err = np.abs(inv - np.linalg.inv(M)).max((1, 2)) / np.abs(np.linalg.inv(M)).max((1, 2))
    assert inv.shape == (500, 3, 3) and np.all(err <= 10 * np.finfo(float).eps * np.linalg.cond(M))


def test_a_singular_matrix_gives_non_finite_values():
    M = jnp.asarray([[1.0, 2.0, 3.0], [2.0, 4.0, 6.0], [0.0, 1.0, 1.0]])
    assert not np.all(np.isfinite(np.asarray(inv3(M))))
