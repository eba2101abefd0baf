"""The kernels' jaxpr printer with its scalar C99 target (fosmc_jax._firmware.c99), on its own:
a function of many primitives printed as C, compiled with the strict flags, and called through
ctypes on random inputs, against JAX's values of the same function (the firmware's tests,
tests/test_export.py, print whole loops; this one reaches the printer's other formats)."""

from __future__ import annotations

import ctypes
import subprocess
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from fosmc_jax._firmware import c99
from fosmc_jax._firmware import export as exporter
from fosmc_jax._simulator import codegen

CC = exporter.c_compiler()
needs_cc = pytest.mark.skipif(CC is None, reason="no C compiler ($CC, cc, gcc, clang)")

#: A matrix of constants the printed sums fold in (its zero is left out of them).
W = np.array([[0.5, -1.25, 0.0], [2.0, 0.75, -0.5], [0.0, 1.5, 3.0]])


def many(x, y, n):
    """x, y (3,) floats, n an integer that varies (a counter): what the printer's formats cover."""
    a = jnp.tanh(x) + jnp.sin(y) * jnp.cos(y) + jnp.exp(-x) + jnp.log1p(jnp.abs(y)) + jnp.arctan2(x, y)
    b = jnp.where(x > y, jnp.sqrt(jnp.abs(x)), -(y**3)) + jax.nn.sigmoid(x) + jax.lax.rsqrt(1 + x * x)
    c = jnp.clip(x, -0.5, 0.5) + jnp.sign(y) + jnp.maximum(x, y) - jnp.minimum(x, 0.1) + y**-2
    d = jnp.round(3 * x) + jnp.floor(4 * y) + jnp.round(2.5 * y, 0) + jnp.fmod(x, 0.3) + jnp.power(jnp.abs(x), y)
    finite = jnp.isfinite(x / (y - y[0]))  # y[0] - y[0] = 0: not finite there
    first = n == 0
    g = jnp.where(first | ~finite, x, y) + (n * 3 - 1).astype(x.dtype) + jnp.sum(x) + jnp.max(y) + W.astype(x.dtype) @ x
    return a + b + c + d, g, jnp.where(first, n + 7, n // 2)


def _compiled(tmp_path: Path, dtype) -> ctypes.CDLL:
    f32 = np.dtype(dtype) == np.float32
    real = "float" if f32 else "double"
    target = c99.C99(real, f32)
    vec = jax.ShapeDtypeStruct((3,), dtype)
    closed = jax.make_jaxpr(many)(vec, vec, jax.ShapeDtypeStruct((), jnp.int32))
    inputs = [[f"x[{i}]" for i in range(3)], [f"y[{i}]" for i in range(3)], ["*n"]]
    outputs = [[f"out[{i}]" for i in range(3)], [f"out[{3 + i}]" for i in range(3)], ["*m"]]
    body = c99.statements(closed, inputs, outputs, target)
    text = "\n".join(
        ["#include <math.h>", "#include <stdint.h>", "", *c99.prelude("\n".join(body), real, f32),
         f"void many(const {real} *x, const {real} *y, const int32_t *n, {real} *out, int32_t *m);",
         f"void many(const {real} *x, const {real} *y, const int32_t *n, {real} *out, int32_t *m)", "{",
         *("    " + line for line in body), "}", ""]
    )  # fmt: skip
    source = tmp_path / "many.c"
    source.write_text(text)
    exporter.check_compiles(source, CC, (*exporter.STRICT_FLAGS, "-O2"))
    so = tmp_path / "libmany.so"
    subprocess.run([*CC.split(), "-std=c99", "-O2", "-shared", "-fPIC", str(source), "-o", str(so), "-lm"], check=True)
    return ctypes.CDLL(str(so)), text


@needs_cc
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_the_c99_target_computes_what_jax_computes(dtype, tmp_path):
    lib, text = _compiled(tmp_path, dtype)
    assert "Lib(" not in text and "Bc(" not in text and "~" not in text  # the C++ forms all rewritten
    rtol = 1e-13 if dtype == np.float64 else 1e-5
    ptr = lambda a: a.ctypes.data_as(ctypes.c_void_p)  # noqa: E731
    rng = np.random.default_rng(0)
    jitted = jax.jit(many)
    for trial in range(20):
        x, y = rng.uniform(-2, 2, 3).astype(dtype), rng.uniform(-2, 2, 3).astype(dtype)
        y[1] = y[0] if trial % 5 == 0 else y[1]  # a division by zero: isfinite false
        n = np.array(trial % 5 - 2, np.int32)  # negative too: floor division corrects the truncation
        out, m = np.zeros(6, dtype), np.zeros((), np.int32)
        lib.many(ptr(x), ptr(y), ptr(n), ptr(out), ptr(m))
        want = jitted(jnp.asarray(x), jnp.asarray(y), jnp.asarray(n))
        got = (out[:3], out[3:], m)
        for g, w in zip(got[:2], want[:2]):
            w = np.asarray(w, np.float64)
            assert np.allclose(g, w, rtol=rtol, atol=rtol * np.abs(w).max()), (trial, g, w)
        assert int(m) == int(want[2]), trial


def test_an_unknown_primitive_is_named():
    closed = jax.make_jaxpr(lambda x: jnp.sort(x))(jax.ShapeDtypeStruct((3,), np.float32))
    with pytest.raises(codegen.Unsupported, match="sort"):
        c99.statements(closed, [["x[0]", "x[1]", "x[2]"]], [["y[0]", "y[1]", "y[2]"]], c99.C99("float", True))
