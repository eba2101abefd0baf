"""The kernels' jaxpr printer (:mod:`fosmc_jax._simulator.codegen`) with a scalar C99 target: a
JAX function of one sample printed as the straight-line body of a firmware's C function.

The printer writes C++ over SIMD lanes for the kernels; :class:`C99` rewrites the same formats
for one value at a time: the lane vector becomes the export's real type, a lane mask an ``int``
(0 or 1; ``~`` becomes ``!``), integers that vary (a sample counter) ``int64_t``, literals C
constants of the real type (``0.5f`` in float32), libm's functions of that type (``tanhf``) in
place of ``Lib``, and the kernels' ``Max``, ``Min``, ``Sign``, ``SinCos`` small ``static inline``
functions of the same semantics (:func:`prelude`, only those used). So one printer, and the
package's JAX functions, give both the kernels' and the firmware's code.
"""

from __future__ import annotations

import math
import re

import jax
import jax.numpy as jnp
import numpy as np

from .._simulator import codegen

#: The printer's formats that C's integer arithmetic does exactly (XLA's division and remainder
#: of integers truncate toward zero, as C99's): the others run in the real type, exact to 2^24
#: (float) or 2^53 (double), as the kernels carry integers.
_INTEGER = {"Lib({0} / {1}, LIB(trunc))": "{0} / {1}", "Lib2({0}, {1}, LIB2(fmod))": "{0} % {1}"}


class C99(codegen.Target):
    """Scalar C99 in the real type ``real`` (a typedef of ``float`` where ``f32``, else ``double``)."""

    mask, integer = "int", "int64_t"

    def __init__(self, real: str, f32: bool):
        self.vector, self.f32 = real, f32
        suffix = "f" if f32 else ""
        helper = lambda m: m[1] + suffix + "("  # noqa: E731 - the float helpers apart from the double ones
        self._rules = [
            (re.compile(r"\b(Max|Min|Sign|SinCos)\("), helper),
            (re.compile(r"Lib2\((.+?), (.+?), LIB2\((\w+)\)\)"), lambda m: f"{m[3]}{suffix}({m[1]}, {m[2]})"),
            (re.compile(r"Lib\((.+?), LIB\((\w+)\)\)"), lambda m: f"{m[2]}{suffix}({m[1]})"),
            (re.compile(r"Bc\((-?\d+)\)"), lambda m: self.literal(float(m[1]))),
            (re.compile(r"Bc\((\{\d\})\)"), lambda m: m[1]),
            (re.compile(r"\bAbs\("), lambda m: f"fabs{suffix}("),
            (re.compile(r"\bSqrt\("), lambda m: f"sqrt{suffix}("),
            (re.compile(r"\bIsFinite\("), lambda m: "isfinite("),
            (re.compile(r"~(?=\{)"), lambda m: "!"),
            (re.compile(r"\bkTrue\b"), lambda m: "1"),
            (re.compile(r"\bkFalse\b"), lambda m: "0"),
        ]
        self._cache: dict[tuple[str, bool], str] = {}

    def literal(self, value) -> str:
        if isinstance(value, (bool, np.bool_)):
            return "1" if value else "0"
        if isinstance(value, (int, np.integer)):
            return str(int(value))
        v = float(np.float32(value)) if self.f32 else float(value)
        if math.isnan(v):
            return "NAN"
        if math.isinf(v):
            return "INFINITY" if v > 0 else "-INFINITY"
        # the shortest decimal that rounds back to the value in the real type
        text = str(np.float32(v)) if self.f32 else repr(v)
        if "e" not in text and "." not in text:
            text += ".0"
        return text + ("f" if self.f32 else "")

    def rewrite(self, fmt: str, integer: bool = False) -> str:
        if (fmt, integer) not in self._cache:
            out = _INTEGER.get(fmt, fmt) if integer else fmt
            for pattern, repl in self._rules:
                out = pattern.sub(repl, out)
            self._cache[fmt, integer] = out
        return self._cache[fmt, integer]


def prelude(text: str, real: str, f32: bool) -> list[str]:
    """The ``static inline`` helpers that the printed ``text`` calls, in the real type: XLA's
    max and min (NaN if either is NaN), sign (0 and NaN kept) and the sine-cosine pair (named
    with an ``f`` where ``f32``, as libm's)."""
    fn = lambda name: name + ("f" if f32 else "")  # noqa: E731
    zero, one = ("0.0f", "1.0f") if f32 else ("0.0", "1.0")
    helpers = {
        fn("Max"): [f"static inline {real} {fn('Max')}({real} a, {real} b)",
                    "{", "    return a != a ? a : (b > a || b != b) ? b : a;", "}"],
        fn("Min"): [f"static inline {real} {fn('Min')}({real} a, {real} b)",
                    "{", "    return a != a ? a : (b < a || b != b) ? b : a;", "}"],
        fn("Sign"): [f"static inline {real} {fn('Sign')}({real} x)",
                     "{", f"    return x > {zero} ? {one} : x < {zero} ? -{one} : x;", "}"],
        fn("SinCos"): [f"static inline void {fn('SinCos')}({real} x, {real} *s, {real} *c)",
                       "{", f"    *s = {fn('sin')}(x);", f"    *c = {fn('cos')}(x);", "}"],
    }  # fmt: skip
    out = []
    for name, lines in helpers.items():
        if re.search(rf"\b{name}\(", text):
            out += [*lines, ""]
    return out


def statements(closed, inputs: list[list[str]], outputs: list[list[str] | None], target: C99) -> list[str]:
    """The C statements computing the closed jaxpr ``closed``'s outputs.

    ``inputs``: per invar, the C expressions of its elements (flat, row-major; each read where
    used, so an expression, not a name, must be parenthesized); ``outputs``: per outvar, the
    lvalues its elements are assigned to (None: not written). Every value is computed before
    the first assignment, so an output may overwrite an input that another output reads.
    Raises :class:`codegen.Unsupported` naming a primitive the printer does not know."""
    jaxpr, consts = codegen._jaxpr_and_consts(closed)
    dtypes = {np.dtype(v.aval.dtype) for v in jaxpr.invars if jnp.issubdtype(v.aval.dtype, jnp.floating)}
    p = codegen.Printer(dtypes.pop() if len(dtypes) == 1 else jnp.result_type(float), target=target)
    args = [[codegen.Atom("V", e) for e in exprs] for exprs in inputs]
    with jax.ensure_compile_time_eval():
        outs = p.jaxpr(jaxpr, consts, args)
    read = {e for exprs in inputs for e in exprs}
    writes = []
    for lvalues, atoms, var in zip(outputs, outs, jaxpr.outvars, strict=True):
        if lvalues is None:
            continue
        p.integer = bool(jnp.issubdtype(var.aval.dtype, jnp.integer))
        for lvalue, a in zip(lvalues, atoms, strict=True):
            if a.kind == "c":
                value = target.literal(a.value)
            elif a.expr == lvalue:
                continue  # carried unchanged
            elif a.expr in read:  # an input: read into a local before any output is written
                value = p.fresh("M" if a.kind == "M" else "V", a.expr).expr
            else:
                value = a.expr
            writes.append(f"{lvalue} = {value};")
    return codegen._live(p.lines + writes, target.vector)
