"""A printer of jaxprs into straight-line C++ over SIMD lanes: the generated kernels' formulas.

A jaxpr of one rollout's step (or of its vector-Jacobian product, which JAX builds) is printed
*scalarized*: every element of every array is one C++ variable holding that element for every
rollout of a block (a GCC vector ``V``, :file:`vecmath.h`'s ``Simd<T>::V``; booleans a lane mask
``M``). Shapes are static, so indexing, broadcasting, reshapes, slices, gathers and scatters of
static indices, transposes and the like print no code: they only rearrange which variable stands
for which element. Arithmetic prints one statement per element; reductions and ``dot_general``
print their sums written out (products with a constant 0 left out, with a constant 1 kept bare);
values that depend on constants only are folded while printing (by JAX itself).

Higher-order primitives are inlined (``jit``, ``remat``, ``custom_jvp_call`` and
``custom_vjp_call``'s primal, ``custom_linear_solve``'s solve, ``cond`` as a select between its
branches). A primitive the printer does not know raises :class:`Unsupported` naming it, and the
caller runs the ``vmap`` path instead.

The printed code follows the jaxpr's operations in order (no FMA: ``-ffp-contract=off``), so a
rollout's numbers are XLA's to the last bits of its transcendental functions.

The syntax is a :class:`Target`'s: the default writes the kernels' C++; the firmware's scalar
C99 (:mod:`fosmc_jax._firmware.c99`, ``fosmc export``) rewrites the same formats for one value at
a time, so the kernels and the firmware are printed from the same jaxprs by the same printer.
"""

from __future__ import annotations

import math
import re
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.extend import core as jcore


class Unsupported(Exception):
    """A jaxpr the printer cannot print; the message names the primitive."""


class Atom(NamedTuple):
    """One element of a value while printing: a C++ expression and its kind, ``V`` (a float
    vector variable), ``M`` (a lane mask variable), or a constant ``c`` (``value`` holds it)."""

    kind: str
    expr: str
    value: Any = None


def _const(x) -> Atom:
    return Atom("c", "", x.item() if hasattr(x, "item") else x)


def literal(value, ctype: str = "T") -> str:
    """``value`` as a C++ expression of type ``ctype`` (exact: ``repr`` of a double round-trips)."""
    if isinstance(value, (bool, np.bool_)):
        return "true" if value else "false"
    v = float(value)
    if math.isnan(v):
        return f"std::numeric_limits<{ctype}>::quiet_NaN()"
    if math.isinf(v):
        return ("" if v > 0 else "-") + f"std::numeric_limits<{ctype}>::infinity()"
    return f"{ctype}({v!r})"


class Target:
    """The syntax the printer writes: this one, the kernels' C++ over SIMD lanes
    (:file:`gen_kernel.h`'s types ``V`` and ``M`` and its helpers ``Bc``, ``Lib``, ``Max``, ...).

    Another language subclasses it (the firmware's scalar C99, :mod:`fosmc_jax._firmware.c99`):
    the type names of the declarations, the literals, and :meth:`rewrite`, which turns each of
    the printer's C++ formats (before the operands go in) into the target's."""

    #: The declared types of a float, a boolean (lane mask) and an integer value.
    vector, mask, integer = "V", "M", "V"  # integers that vary are carried as floats here

    def literal(self, value) -> str:
        """``value`` (a Python bool, int or float) as a constant of the target."""
        return literal(value)

    def rewrite(self, fmt: str, integer: bool = False) -> str:
        """The target's form of the printer's C++ format ``fmt`` (``{0}``... the operands) in an
        equation that gives integers (``integer``) or not."""
        return fmt


# Elementwise primitives: name -> (result kind, C++ format over the operands as vectors).
_FLOAT = {
    "add": "{0} + {1}", "add_any": "{0} + {1}", "sub": "{0} - {1}", "mul": "{0} * {1}", "div": "{0} / {1}",
    "neg": "-{0}",
    "max": "Max({0}, {1})", "min": "Min({0}, {1})", "abs": "Abs({0})", "sign": "Sign({0})",
    "sqrt": "Sqrt({0})", "rsqrt": "Bc(1) / Sqrt({0})", "exp": "Lib({0}, LIB(exp))", "exp2": "Lib({0}, LIB(exp2))",
    "log": "Lib({0}, LIB(log))", "log1p": "Lib({0}, LIB(log1p))", "expm1": "Lib({0}, LIB(expm1))",
    "tanh": "Lib({0}, LIB(tanh))", "tan": "Lib({0}, LIB(tan))", "atan": "Lib({0}, LIB(atan))",
    "asin": "Lib({0}, LIB(asin))", "acos": "Lib({0}, LIB(acos))", "sinh": "Lib({0}, LIB(sinh))",
    "cosh": "Lib({0}, LIB(cosh))", "erf": "Lib({0}, LIB(erf))", "floor": "Lib({0}, LIB(floor))",
    "ceil": "Lib({0}, LIB(ceil))", "atan2": "Lib2({0}, {1}, LIB2(atan2))", "pow": "Lib2({0}, {1}, LIB2(pow))",
    "rem": "Lib2({0}, {1}, LIB2(fmod))", "square": "{0} * {0}", "logistic": "Bc(1) / (Bc(1) + Lib(-{0}, LIB(exp)))",
    "copy": "{0}", "copy_p": "{0}", "stop_gradient": "{0}", "reduce_precision": "{0}",
}  # fmt: skip
_COMPARE = {"lt": "<", "le": "<=", "gt": ">", "ge": ">=", "eq": "==", "ne": "!="}
_LOGIC = {"and": "&", "or": "|", "xor": "^"}
# Primitives that only move data: printed by running them on arrays of element ids.
_MOVES = {
    "broadcast_in_dim", "reshape", "squeeze", "expand_dims", "slice", "concatenate", "transpose", "rev", "gather",
    "scatter", "dynamic_slice", "dynamic_update_slice", "pad", "tile", "stack", "unstack", "copy", "copy_p", "split",
}  # fmt: skip
# What integers that vary by rollout may do (a sample counter): they are carried as floats,
# exact up to 2^24 (float) or 2^53 (double); wrapping on overflow is not reproduced.
_INTEGER = {"add", "sub", "mul", "neg", "div", "rem", "max", "min", "abs", "sign", "select_n",
            "convert_element_type", "copy", "copy_p", *_MOVES}  # fmt: skip
# The operands of a data movement that are indices (constant), by primitive: n -> positions.
_INDEX_OPERANDS = {"gather": lambda n: (1,), "scatter": lambda n: (1,), "dynamic_slice": lambda n: range(1, n),
                   "dynamic_update_slice": lambda n: range(2, n)}  # fmt: skip
_IDENTITY = {"stop_gradient", "optimization_barrier", "reduce_precision"}


def _broadcast(x, shape, broadcast_dimensions, **_):
    expanded = np.reshape(x, [x.shape[broadcast_dimensions.index(d)] if d in broadcast_dimensions else 1
                              for d in range(len(shape))])  # fmt: skip
    return np.broadcast_to(expanded, shape)


# The common moves in NumPy: run by JAX eagerly, each new shape would compile an XLA program
_NUMPY = {
    "reshape": lambda x, new_sizes, dimensions=None, **_: np.reshape(x, new_sizes) if dimensions is None else None,
    "broadcast_in_dim": _broadcast,
    "transpose": lambda x, permutation: np.transpose(x, permutation),
    "squeeze": lambda x, dimensions: np.squeeze(x, tuple(dimensions)),
    "expand_dims": lambda x, dimensions: np.expand_dims(x, tuple(dimensions)),
    "rev": lambda x, dimensions: np.flip(x, tuple(dimensions)),
    "slice": lambda x, start_indices, limit_indices, strides=None: x[
        tuple(map(slice, start_indices, limit_indices, strides or [1] * x.ndim))
    ],
    "concatenate": lambda *xs, dimension: np.concatenate(xs, dimension),
    "pad": lambda x, value, padding_config: (
        None
        if any(lo < 0 or hi < 0 or inner for lo, hi, inner in padding_config)
        else np.pad(x, [(lo, hi) for lo, hi, _ in padding_config], constant_values=value.item())
    ),
    "stack": lambda *xs, axis: np.stack(xs, axis),
    "unstack": lambda x, axis: [np.take(x, i, axis) for i in range(x.shape[axis])],
    "split": lambda x, sizes, axis: np.split(x, np.cumsum(sizes)[:-1], axis),
}


def _numpy_move(eqn, vals):
    """``eqn``'s move in NumPy where it is a common one with the parameters known here, else None."""
    f = _NUMPY.get(eqn.primitive.name)
    if f is None:
        return None
    try:
        return f(*vals, **eqn.params)
    except TypeError:  # a parameter this JAX version adds: JAX runs it
        return None


_INLINE = {"jit": "jaxpr", "pjit": "jaxpr", "closed_call": "call_jaxpr", "core_call": "call_jaxpr",
           "remat2": "jaxpr", "checkpoint": "jaxpr", "custom_jvp_call": "call_jaxpr",
           "custom_vjp_call": "call_jaxpr", "custom_vjp_call_jaxpr": "fun_jaxpr"}  # fmt: skip


def _ID_dtype():
    return np.float64 if jax.config.jax_enable_x64 else np.float32


def _jaxpr_and_consts(j) -> tuple[jcore.Jaxpr, list]:
    return (j.jaxpr, list(j.consts)) if hasattr(j, "consts") else (j, [])


class Printer:
    """Prints jaxprs into the statements of one C++ function body (``lines``), with fresh names."""

    def __init__(self, dtype, zeros: bool = False, target: Target | None = None):
        self.zeros = zeros
        self.target = target or Target()
        self.t = lambda fmt: self.target.rewrite(fmt, self.integer)
        self.integer = False  # whether the equation being printed gives integers
        self.seen: dict[tuple[str, str], Atom] = {}
        self.lines: list[str] = []
        self.count = 0
        self.dtype = np.dtype(dtype)
        self.sincos: dict[str, tuple[str, str]] = {}
        # a cotangent's array (``seed``): the derivative's rewrites then reach only the values
        # that depend on it (``tainted``), the primal values are printed as the function's own
        self.seed: str | None = None
        self.tainted: set[str] = set()

    def fresh(self, kind: str, expr: str) -> Atom:
        # every expression is pure: one printed twice (the same accelerations in the plant's
        # derivative and in an observation) is computed once
        if (kind, expr) in self.seen:
            return self.seen[kind, expr]
        name = f"{'v' if kind == 'V' else 'm'}{self.count}"
        self.count += 1
        ctype = self.target.mask if kind == "M" else self.target.integer if self.integer else self.target.vector
        self.lines.append(f"const {ctype} {name} = {expr};")
        self.seen[kind, expr] = Atom(kind, name)
        if self.seed is not None and (f"{self.seed}[" in expr or any(n in self.tainted for n in _NAME.findall(expr))):
            self.tainted.add(name)
        return self.seen[kind, expr]

    def cotangent(self, a: Atom) -> bool:
        """Whether the derivative's rewrites reach ``a``: a value of the cotangent (any, without a seed)."""
        return self.seed is None or (a.kind != "c" and (a.expr.startswith(f"{self.seed}[") or a.expr in self.tainted))

    def vec(self, a: Atom) -> str:
        """``a`` as a float vector expression."""
        if a.kind == "V":
            return a.expr
        if a.kind == "c":
            return self.t("Bc({0})").format(self.target.literal(a.value))
        raise Unsupported("a boolean where a number belongs")

    def mask(self, a: Atom) -> str:
        if a.kind == "M":
            return a.expr
        if a.kind == "c":
            return self.t("kTrue" if bool(a.value) else "kFalse")
        raise Unsupported("a number where a boolean belongs")

    def operand(self, a: Atom) -> str:
        """``a`` in arithmetic: a vector, or a scalar literal (V op T is lane by lane)."""
        return self.target.literal(a.value) if a.kind == "c" else a.expr

    # -- one equation at a time

    def jaxpr(self, jaxpr: jcore.Jaxpr, consts: list, args: list[list[Atom]]) -> list[list[Atom]]:
        """Prints ``jaxpr`` on ``args`` (each invar's atoms, flat, row-major); returns the outvars'."""
        env: dict = {}

        def read(v) -> list[Atom]:
            if isinstance(v, jcore.Literal):
                return [_const(x) for x in np.ravel(np.asarray(v.val))]
            return env[v]

        for v, c in zip(jaxpr.constvars, consts):
            env[v] = [_const(x) for x in np.ravel(np.asarray(c))]
        for v, a in zip(jaxpr.invars, args):
            env[v] = a
        for eqn in jaxpr.eqns:
            ins = [read(v) for v in eqn.invars]
            for v, a in zip(eqn.invars, ins):
                assert len(a) == math.prod(v.aval.shape), (eqn, len(a))
            self.current = (eqn, [jax.core.ShapedArray((), v.aval.dtype) for v in eqn.invars])
            outs = self.eqn(eqn, ins)
            for v, o in zip(eqn.outvars, outs):
                assert len(o) == math.prod(v.aval.shape), (eqn.primitive.name, len(o), v.aval)
                env[v] = o
        return [read(v) for v in jaxpr.outvars]

    def eqn(self, eqn, ins: list[list[Atom]]) -> list[list[Atom]]:
        name = eqn.primitive.name
        avals_in = [v.aval for v in eqn.invars]
        avals_out = [v.aval for v in eqn.outvars]
        if name in _INLINE:
            sub = eqn.params[_INLINE[name]]
            jaxpr, consts = _jaxpr_and_consts(sub)
            return self.jaxpr(jaxpr, consts, ins)
        if all(a.kind == "c" for atoms in ins for a in atoms):  # folded by JAX itself
            return self.fold(eqn, ins, avals_in)
        if name in _IDENTITY or name in ("copy", "copy_p"):
            return ins if eqn.primitive.multiple_results else [ins[0]]
        integer = self.integer = any(jnp.issubdtype(a.dtype, jnp.integer) for a in avals_out)
        for aval in avals_out:
            if jnp.issubdtype(aval.dtype, jnp.floating) and aval.dtype != self.dtype:
                raise Unsupported(f"{name} in {aval.dtype} in a {self.dtype} model")
        if integer and name not in _INTEGER:
            raise Unsupported(f"{name} on integers that vary by rollout")
        if integer and name == "div":
            return [self.elementwise(self.t("Lib({0} / {1}, LIB(trunc))"), ins, "V")]
        if name in _MOVES:
            return self.move(eqn, ins, avals_in)
        if name in _FLOAT:
            return [self.elementwise(self.t(_FLOAT[name]), ins, "V")]
        if name in _COMPARE:
            op = _COMPARE[name]
            return [[self.folded((a, b)) or self.fresh("M", f"{self.vec(a)} {op} {self.vec(b)}")
                     for a, b in zip(*self.broadcast(ins))]]  # fmt: skip
        if name in _LOGIC and avals_out[0].dtype == jnp.bool_:
            op = _LOGIC[name]
            return [[self.folded((a, b)) or self.fresh("M", f"{self.mask(a)} {op} {self.mask(b)}")
                     for a, b in zip(*self.broadcast(ins))]]  # fmt: skip
        if name == "not":
            return [[self.folded((a,)) or self.fresh("M", self.t("~{0}").format(self.mask(a))) for a in ins[0]]]
        if name in ("sin", "cos"):
            return [[self.folded((a,)) or self.sin_cos(a, name) for a in ins[0]]]
        if name == "integer_pow":
            return [[self.folded((a,)) or self.integer_pow(a, eqn.params["y"]) for a in ins[0]]]
        if name == "round":
            how = "nearbyint" if int(eqn.params["rounding_method"]) == 1 else "round"
            return [self.elementwise(self.t(f"Lib({{0}}, LIB({how}))"), ins, "V")]
        if name == "is_finite":
            return [[self.folded((a,)) or self.fresh("M", self.t("IsFinite({0})").format(self.vec(a))) for a in ins[0]]]
        if name == "select_n":
            return [self.select(ins, avals_out[0])]
        if name == "convert_element_type":
            return [self.convert(ins[0], avals_in[0], avals_out[0])]
        if name == "clamp":
            lo, x, hi = self.broadcast(ins)
            clamp = self.t("Min(Max({0}, {1}), {2})")
            return [[self.fresh("V", clamp.format(self.vec(a), self.vec(b), self.vec(c))) for b, a, c in
                     zip(x, lo, hi)]]  # fmt: skip
        if name.startswith("reduce_") or name in ("argmax", "argmin"):
            return [self.reduce(name, ins[0], avals_in[0], eqn.params["axes"])]
        if name == "dot_general":
            return [self.dot_general(ins, avals_in, eqn.params["dimension_numbers"])]
        if name in ("scatter-add", "scatter_add"):
            return [self.linear_map(eqn, ins, avals_in)]
        if name == "triangular_solve":
            return [self.triangular_solve(ins, avals_in, eqn.params)]
        if name == "cond":
            return self.cond(eqn, ins)
        if name == "custom_linear_solve":
            jaxprs = eqn.params["jaxprs"]
            n = eqn.params["const_lengths"]
            start = n.matvec + n.vecmat
            solve_consts, rhs = ins[start : start + n.solve], ins[sum(n) :]
            jaxpr, consts = _jaxpr_and_consts(jaxprs.solve)
            return self.jaxpr(jaxpr, consts, [*solve_consts, *rhs])
        raise Unsupported(name)

    # -- the kinds of equations

    def fold(self, eqn, ins, avals_in) -> list[list[Atom]]:
        vals = [np.asarray([a.value for a in atoms], aval.dtype).reshape(aval.shape) for atoms, aval in
                zip(ins, avals_in)]  # fmt: skip
        with jax.ensure_compile_time_eval():
            out = eqn.primitive.bind(*vals, **eqn.primitive.get_bind_params(eqn.params))
        outs = out if eqn.primitive.multiple_results else [out]
        return [[_const(x) for x in np.ravel(np.asarray(o))] for o in outs]

    def broadcast(self, ins):
        n = max(len(a) for a in ins)
        return [a * n if len(a) == 1 else a for a in ins]

    def elementwise(self, fmt: str, ins, kind: str) -> list[Atom]:
        # an operator takes a scalar literal as it is (V op T acts lane by lane); a function a vector
        functional = not fmt.startswith(("{0}", "-"))
        cast = self.vec if functional else self.operand
        inverse = lambda b: self.fresh("V", self.t("Bc(1) / {0}").format(self.vec(b))).expr  # noqa: E731
        # a derivative divides by few values, many times: reciprocals
        reciprocal = lambda args: fmt == "{0} / {1}" and self.zeros and self.cotangent(args[0])  # noqa: E731
        return [self.folded(args) or self.identity(fmt, args) or
                (self.fresh(kind, f"{cast(args[0])} * {inverse(args[1])}") if reciprocal(args) else
                 self.fresh(kind, fmt.format(*map(cast, args))))
                for args in zip(*self.broadcast(ins))]  # fmt: skip

    def identity(self, fmt: str, args) -> Atom | None:
        """x + 0, x - 0, x * 1, x / 1 as x; in a derivative (``zeros``), x * 0 as 0 (a cotangent
        that is zero stays zero where the primal is not finite; JAX's would be NaN there), and a
        division a product with the reciprocal, computed once per divisor (to rounding)."""
        if len(args) != 2 or not any(a.kind == "c" for a in args):
            return None
        a, b = args
        c = lambda x, v: x.kind == "c" and float(x.value) == v
        if fmt == "{0} + {1}":
            return b if c(a, 0) else a if c(b, 0) else None
        if fmt == "{0} - {1}":
            return a if c(b, 0) else None
        if fmt == "{0} * {1}":
            if self.zeros and (c(a, 0) or c(b, 0)) and self.cotangent(b if c(a, 0) else a):
                return _const(np.zeros((), self.dtype))
            return b if c(a, 1) else a if c(b, 1) else None
        if fmt == "{0} / {1}":
            return a if c(b, 1) else None
        return None

    def folded(self, args) -> Atom | None:
        """The element's value where all its operands are constants (some elements of an
        equation can be when others are not), by the equation's own primitive."""
        if not all(a.kind == "c" for a in args):
            return None
        eqn, avals = self.current
        vals = [np.asarray(a.value, aval.dtype) for a, aval in zip(args, avals)]
        with jax.ensure_compile_time_eval():
            out = eqn.primitive.bind(*vals, **eqn.primitive.get_bind_params(eqn.params))
        return _const(np.asarray(out))

    def sin_cos(self, a: Atom, name: str) -> Atom:
        """sin or cos of ``a``: one SinCos for both where both are taken of the same value."""
        if a.expr not in self.sincos:
            s, c = f"s{self.count}", f"c{self.count}"
            self.count += 1
            self.lines.append(f"{self.target.vector} {s}, {c};")
            self.lines.append(self.t("SinCos({0}, &{1}, &{2});").format(self.vec(a), s, c))
            self.sincos[a.expr] = (s, c)
        return Atom("V", self.sincos[a.expr][0 if name == "sin" else 1])

    def integer_pow(self, a: Atom, y: int) -> Atom:
        # XLA's exponentiation by squaring, so the products are the same
        x, acc = a.expr, None
        n = abs(int(y))
        if n == 0:
            return self.fresh("V", self.t("Bc(1)"))
        while n:
            if n & 1:
                acc = x if acc is None else self.fresh("V", f"{acc} * {x}").expr
            n >>= 1
            if n:
                x = self.fresh("V", f"{x} * {x}").expr
        return self.fresh("V", self.t("Bc(1) / {0}").format(acc) if y < 0 else f"{acc}")

    def select(self, ins, aval) -> list[Atom]:
        pred, *cases = self.broadcast(ins)
        if len(cases) != 2:
            raise Unsupported("select_n of more than two cases")
        kind = "M" if aval.dtype == jnp.bool_ else "V"
        cast = self.mask if kind == "M" else self.vec
        out = []
        for p, a, b in zip(pred, *cases):
            if p.kind == "c":
                out.append(b if p.value else a)
            elif a == b or (a.kind == b.kind == "c" and a.value == b.value):
                out.append(a)
            else:
                m = self.mask(p) if p.kind == "M" else self.t("({0} != Bc(0))").format(p.expr)  # an integer index
                out.append(self.fresh(kind, f"{m} ? {cast(b)} : {cast(a)}"))
        return out

    def convert(self, atoms, aval_in, aval_out) -> list[Atom]:
        if aval_out.dtype == jnp.bool_:
            nonzero = self.t("{0} != Bc(0)")
            return [a if a.kind == "M" else self.folded((a,)) or self.fresh("M", nonzero.format(self.vec(a)))
                    for a in atoms]  # fmt: skip
        if aval_in.dtype == jnp.bool_:
            return [
                self.folded((a,)) or self.fresh("V", self.t("{0} ? Bc(1) : Bc(0)").format(self.mask(a))) for a in atoms
            ]
        if jnp.issubdtype(aval_out.dtype, jnp.integer) and jnp.issubdtype(aval_in.dtype, jnp.floating):
            return [
                self.folded((a,)) or self.fresh("V", self.t("Lib({0}, LIB(trunc))").format(self.vec(a))) for a in atoms
            ]
        return atoms  # integers are floats here; float to float of the same width (others refused before)

    def move(self, eqn, ins, avals_in) -> list[list[Atom]]:
        """A data movement: run on float arrays of element ids (constant operands kept as ids
        too), the result's ids say where each element comes from."""
        table: list[Atom] = []
        vals = []
        index = _INDEX_OPERANDS.get(eqn.primitive.name, lambda n: ())(len(ins))
        if eqn.primitive.name == "gather" and any(a.kind != "c" for a in ins[1]):
            return [self.gather_rows(eqn, ins, avals_in)]
        for i, (atoms, aval) in enumerate(zip(ins, avals_in)):
            if i in index:
                if any(a.kind != "c" for a in atoms):
                    raise Unsupported(f"{eqn.primitive.name} with indices that vary by rollout")
                vals.append(np.asarray([a.value for a in atoms], aval.dtype).reshape(aval.shape))
                continue
            ids = np.arange(len(table), len(table) + len(atoms), dtype=_ID_dtype()) + 1
            table.extend(atoms)
            vals.append(ids.reshape(aval.shape))
        outs = _numpy_move(eqn, vals)
        if outs is None:
            params = eqn.primitive.get_bind_params(eqn.params)
            with jax.ensure_compile_time_eval():
                outs = eqn.primitive.bind(*vals, **params)
        outs = [np.ravel(np.asarray(o)) for o in (outs if eqn.primitive.multiple_results else [outs])]
        for out in outs:
            if np.any(out != np.round(out)) or np.any(out < 1):
                raise Unsupported(f"{eqn.primitive.name} that does more than move elements")
        return [[table[int(i) - 1] for i in out] for out in outs]

    def gather_rows(self, eqn, ins, avals_in) -> list[Atom]:
        """A gather of whole rows (axis 0) by indices that vary by rollout (a pivoting solve's
        permutation): each element a chain of selects over the rows."""
        d = eqn.params["dimension_numbers"]
        shape, idx_shape = avals_in[0].shape, avals_in[1].shape
        rows = (tuple(d.start_index_map) == (0,) and tuple(d.collapsed_slice_dims) == (0,)
                and not d.operand_batching_dims and tuple(eqn.params["slice_sizes"]) == (1, *shape[1:])
                and idx_shape[-1] == 1 and tuple(d.offset_dims) == tuple(range(len(idx_shape) - 1, len(idx_shape)
                                                                                + len(shape) - 2)))  # fmt: skip
        if not rows:
            raise Unsupported("gather with indices that vary by rollout")
        inner = math.prod(shape[1:])
        out = []
        for i in ins[1]:
            for e in range(inner):
                acc = ins[0][(shape[0] - 1) * inner + e]
                for r in range(shape[0] - 2, -1, -1):
                    pick = self.t(f"{{0}} == Bc({r}) ? {{1}} : {{2}}")
                    acc = self.fresh("V", pick.format(self.vec(i), self.vec(ins[0][r * inner + e]), self.vec(acc)))
                out.append(acc)
        return out

    def linear_map(self, eqn, ins, avals_in) -> list[Atom]:
        """An operation linear in its float operands (scatter-add): printed from its Jacobian."""
        floats = [i for i, aval in enumerate(avals_in) if jnp.issubdtype(aval.dtype, jnp.floating)]
        vals = [np.asarray([a.value if a.kind == "c" else 0 for a in atoms]).reshape(aval.shape)
                for atoms, aval in zip(ins, avals_in)]  # fmt: skip
        for i in range(len(vals)):
            if i not in floats and any(a.kind != "c" for a in ins[i]):
                raise Unsupported(f"{eqn.primitive.name} with indices that vary by rollout")
        params = eqn.primitive.get_bind_params(eqn.params)

        def f(*xs):
            args = list(vals)
            for i, x in zip(floats, xs):
                args[i] = x
            return eqn.primitive.bind(*args, **params)

        xs = [np.zeros(avals_in[i].shape, avals_in[i].dtype) for i in floats]
        with jax.ensure_compile_time_eval():
            base = np.ravel(np.asarray(f(*xs)))
            jac = jax.jacfwd(f, argnums=tuple(range(len(floats))))(*xs)
        terms = [[] for _ in range(base.size)]
        for i, J in zip(floats, jac):
            J = np.asarray(J).reshape(base.size, -1)
            for o, j in zip(*np.nonzero(J)):
                terms[o].append((J[o, j], ins[i][j]))
        return [self.sum_of(terms[o], base[o]) for o in range(base.size)]

    def sum_of(self, terms, base=0.0) -> Atom:
        """base + sum of coefficient * atom, in order; constants folded."""
        const = float(base)
        parts = []
        for coef, a in terms:
            if a.kind == "c":
                const += float(coef) * float(a.value)
            elif coef == 1:
                parts.append(a.expr)
            elif coef == -1:
                parts.append(f"(-{a.expr})")
            else:
                parts.append(f"{self.target.literal(coef)} * {a.expr}")
        if not parts:
            return _const(np.asarray(const, self.dtype))
        expr = " + ".join(parts)
        if const:
            expr = f"{self.target.literal(const)} + {expr}"
        return self.fresh("V", expr)

    def reduce(self, name: str, atoms, aval, axes) -> list[Atom]:
        shape = aval.shape
        idx = np.arange(len(atoms)).reshape(shape)
        keep = [d for d in range(len(shape)) if d not in axes]
        groups = np.transpose(idx, keep + list(axes)).reshape(int(np.prod([shape[d] for d in keep])), -1)
        op = {"reduce_sum": "+", "reduce_max": "Max", "reduce_min": "Min", "reduce_and": "&", "reduce_or": "|",
              "reduce_prod": "*"}.get(name)  # fmt: skip
        if op is None:
            raise Unsupported(name)
        out = []
        for g in groups:
            items = [atoms[i] for i in g]
            if op == "+":
                out.append(self.sum_of([(1, a) for a in items]))
                continue
            logic = op in ("&", "|")
            cast = self.mask if logic else self.vec
            acc = cast(items[0])
            for a in items[1:]:
                acc = (
                    f"{acc} {op} {cast(a)}" if op in ("&", "|", "*") else self.t(op + "({0}, {1})").format(acc, cast(a))
                )
                acc = self.fresh("M" if logic else "V", acc).expr
            out.append(Atom("M" if logic else "V", acc) if len(items) > 1 else self.fresh("M" if logic else "V", acc))
        return out

    def dot_general(self, ins, avals, dimension_numbers) -> list[Atom]:
        (lc, rc), (lb, rb) = dimension_numbers
        ls, rs = avals[0].shape, avals[1].shape
        lf = [d for d in range(len(ls)) if d not in lc and d not in lb]
        rf = [d for d in range(len(rs)) if d not in rc and d not in rb]
        li = np.transpose(np.arange(len(ins[0])).reshape(ls), list(lb) + lf + list(lc))
        ri = np.transpose(np.arange(len(ins[1])).reshape(rs), list(rb) + rf + list(rc))
        B = int(np.prod([ls[d] for d in lb]))
        C = int(np.prod([ls[d] for d in lc]))
        li, ri = li.reshape(B, -1, C), ri.reshape(B, -1, C)
        out = []
        for b in range(B):
            for i in range(li.shape[1]):
                for j in range(ri.shape[1]):
                    terms = []
                    for c in range(C):
                        x, y = ins[0][li[b, i, c]], ins[1][ri[b, j, c]]
                        if x.kind == "c" and y.kind == "c":
                            terms.append((float(x.value) * float(y.value), _const(1.0)))
                        elif x.kind == "c":
                            terms.append((x.value, y)) if x.value != 0 else None
                        elif y.kind == "c":
                            terms.append((y.value, x)) if y.value != 0 else None
                        else:
                            terms.append((1, self.fresh("V", f"{x.expr} * {y.expr}")))
                    out.append(self.sum_of(terms))
        return out

    def triangular_solve(self, ins, avals, params) -> list[Atom]:
        """A x = b by substitution, A (n, n) triangular, b (n, k), as ``lax.linalg.triangular_solve``."""
        if not params["left_side"] or len(avals[0].shape) != 2:
            raise Unsupported("triangular_solve other than a batch-free left-side solve")
        n, k = avals[1].shape
        A = [[ins[0][i * n + j] for j in range(n)] for i in range(n)]
        if params["transpose_a"]:
            A = [list(col) for col in zip(*A)]
        lower = params["lower"] != params["transpose_a"]
        order = range(n) if lower else range(n - 1, -1, -1)
        x = [[None] * k for _ in range(n)]
        for c in range(k):
            for i in order:
                others = [j for j in (range(i) if lower else range(i + 1, n))]
                acc = self.sum_of([(1, ins[1][i * k + c])] + [(-1, self.mul(A[i][j], x[j][c])) for j in others])
                x[i][c] = acc if params["unit_diagonal"] else self.fresh("V", f"{self.vec(acc)} / {self.vec(A[i][i])}")
        return [x[i][c] for i in range(n) for c in range(k)]

    def mul(self, a: Atom, b: Atom) -> Atom:
        if a.kind == "c" and b.kind == "c":
            return _const(np.asarray(float(a.value) * float(b.value), self.dtype))
        return self.fresh("V", f"{self.operand(a)} * {self.operand(b)}")

    def cond(self, eqn, ins) -> list[list[Atom]]:
        index, *args = ins
        if index[0].kind != "c":
            raise Unsupported("cond on a value that varies by rollout")
        return self.jaxpr(*_jaxpr_and_consts(eqn.params["branches"][int(index[0].value)]), args)


_NAME = re.compile(r"\b[vmsc]\d+\b")


def _live(lines: list[str], vector: str = "V") -> list[str]:
    """``lines`` without the statements whose results nothing uses (the primal values a
    vector-Jacobian product computes and does not need): a smaller file to compile. ``vector``:
    the float type's name (:attr:`Target.vector`), which declares a SinCos pair."""
    live: set[str] = set()
    kept = []
    for line in reversed(lines):
        if line.startswith("const "):
            name = line.split(" = ", 1)[0].split()[-1]
            if name not in live:
                continue
            live.update(_NAME.findall(line.split(" = ", 1)[1]))
        elif line.startswith(f"{vector} s"):  # the declaration of a SinCos pair
            if not set(_NAME.findall(line)) & live:
                continue
        elif line.startswith("SinCos"):  # SinCos(x, &s, &c), or a target's variant of it
            if not set(_NAME.findall(line)[-2:]) & live:
                continue
            live.update(_NAME.findall(line)[:-2])
        else:
            live.update(_NAME.findall(line.split(" = ", 1)[-1] if " += " not in line else line))
        kept.append(line)
    return kept[::-1]


def print_function(
    name: str,
    jaxpr,
    dtype,
    inputs: list[tuple[str, str]],
    outputs: list[tuple[str, bool]],
    signature: list[tuple[str, str]],
    derivative: bool = False,
    split: tuple[str, set, set] | None = None,
) -> str:
    """A C++ function ``name`` (external linkage: each is compiled on its own, in parallel) of
    straight-line code computing closed ``jaxpr``'s outputs.

    ``inputs``: per invar, (C array name, ``"V"`` for vectors per lane or ``"T"`` for one
    scalar shared by the lanes), flattened; ``outputs``: per outvar, (C array name, accumulate:
    ``+=`` instead of ``=``). Invars and outvars of the same array name fill it in order.
    ``signature``: the function's parameters in order, (array name, ``"V"``, ``"T"`` or
    ``"out"``). ``derivative``: a vector-Jacobian product, whose products with a constant 0 are 0.
    ``split`` = (the cotangent's array, the primal outputs' arrays, the cotangents' output arrays):
    a vector-Jacobian product with its primal outputs, printed as a forward that stores residuals
    and a backward from them (:func:`_split_function`); its
    rewrites (x * 0 as 0, divisions by reciprocals) then reach the values of the cotangent only,
    so that the primal outputs are computed as the step computes them, to the last bit."""
    closed, consts = _jaxpr_and_consts(jaxpr)
    p = Printer(dtype, zeros=derivative)
    p.seed = None if split is None else split[0]
    args, offsets = [], {}
    with jax.ensure_compile_time_eval():
        for (array, kind), v in zip(inputs, closed.invars, strict=True):
            n = math.prod(v.aval.shape)
            start = offsets.get(array, 0)
            offsets[array] = start + n
            if kind == "V":
                args.append([Atom("V", f"{array}[{start + i}]") for i in range(n)])
            else:
                args.append([p.fresh("V", f"Bc({array}[{start + i}])") for i in range(n)])
        outs = p.jaxpr(closed, consts, args)
    body = list(p.lines)
    offsets = {}
    for (array, accumulate), atoms in zip(outputs, outs, strict=True):
        start = offsets.get(array, 0)
        offsets[array] = start + len(atoms)
        for i, a in enumerate(atoms):
            value = f"{a.expr} ? Bc(1) : Bc(0)" if a.kind == "M" else p.vec(a)
            if not accumulate:
                body.append(f"{array}[{start + i}] = {value};")
            elif a.kind != "c" or a.value != 0:
                body.append(f"{array}[{start + i}] += {value};")
    body = _live(body)
    if split is not None:
        return _split_function(name, body, signature, *split)
    return _function(name, body, signature)


_CTYPE = {"V": "const V* __restrict", "T": "const T* __restrict", "out": "V* __restrict"}


def _function(name: str, body: list[str], signature: list[tuple[str, str]]) -> str:
    params = ", ".join(f"{_CTYPE[kind]} {array}" for array, kind in signature)
    return "\n".join([f"void {name}({params}) {{", *("  " + line for line in _schedule(body)), "}", ""])


def _uses(line: str) -> list[str]:
    """The names a body line reads."""
    if line.startswith("V s"):
        return []
    return _NAME.findall(line.split(" = ", 1)[1] if line.startswith("const ") else line if " += " in line
                         else line.split(" = ", 1)[-1])  # fmt: skip


def _schedule(body: list[str]) -> list[str]:
    """``body`` with each output store (``y[i] = v``) moved up to just after the values it reads,
    and each value of the inputs alone (a load, a broadcast) moved down to just before its first
    use: straight-line code holds a value in a register (or spills it) from its definition to
    its last use, and the compiler does not move stores and loads that far. The same statements,
    the same numbers (an array element's stores keep their order)."""
    out_line = lambda line: not line.startswith(("const ", "V s", "SinCos"))
    inputs_only = lambda line: line.startswith("const ") and not _uses(line)
    core = [line for line in body if not out_line(line) and not inputs_only(line)]
    at = {}
    for i, line in enumerate(core):
        for n in _defined(line) if not line.startswith("SinCos") else _NAME.findall(line)[-2:]:
            at[n] = i
    after: dict[int, list[str]] = {}
    last: dict[str, int] = {}
    for line in body:
        if out_line(line):
            element = line.split(" ", 1)[0]
            pos = max([at.get(n, -1) for n in _uses(line)] + [last.get(element, -1)])
            last[element] = pos
            after.setdefault(pos, []).append(line)
    placed = after.get(-1, []) + [x for i, line in enumerate(core) for x in (line, *after.get(i, []))]
    first: dict[str, int] = {}
    for i, line in enumerate(placed):
        for n in _uses(line):
            first.setdefault(n, i)
    before: dict[int, list[str]] = {}
    for line in body:
        if inputs_only(line) and _defined(line)[0] in first:
            before.setdefault(first[_defined(line)[0]], []).append(line)
    return [x for i, line in enumerate(placed) for x in (*before.get(i, []), line)]


def _defined(line: str) -> list[str]:
    """The names a body line declares."""
    if line.startswith("const "):
        return [line.split(" = ", 1)[0].split()[-1]]
    if line.startswith("V s"):  # a SinCos pair's declaration
        return _NAME.findall(line)
    return []


def _split_function(name: str, body: list[str], signature, seed: str, forward: set, backward: set) -> str:
    """A vector-Jacobian product's body (with the primal outputs too) printed as two functions:
    ``name`` + ``_fwd`` (the primal outputs, and the residuals: the values that the statements
    depending on the cotangent ``seed`` read, stored in ``res``) and ``name`` + ``_bwd`` (those
    statements, from the residuals). A statement of the inputs alone (a load, a broadcast) is
    repeated in the second instead of stored. ``forward`` / ``backward``: the signature's arrays
    each one takes; the second takes ``res`` before ``seed``. Returns the two functions' text
    and the residuals' count in a comment line ``// residuals: n``."""
    back: set[str] = set()
    fwd, bwd = [], []
    for line in body:
        rhs = line.split(" = ", 1)[-1] if " += " not in line else line
        target = line.split("[", 1)[0] if not line.startswith(("const ", "V ", "SinCos")) else None
        if target in forward:
            fwd.append(line)
        elif target in backward or f"{seed}[" in rhs or any(n in back for n in _NAME.findall(rhs)):
            if line.startswith("SinCos"):  # of a value of the cotangent: its pair is declared here too
                pair = set(_NAME.findall(line)[-2:])
                fwd = [f for f in fwd if not (f.startswith("V s") and set(_NAME.findall(f)) == pair)]
                bwd.append(f"V {', '.join(_NAME.findall(line)[-2:])};")
                back.update(pair)
            back.update(_defined(line))
            bwd.append(line)
        else:
            fwd.append(line)
    defs = {n: line for line in fwd for n in _defined(line)}
    inputs_only = {n for n, line in defs.items() if line.startswith("const ") and not _uses(line)}
    used = dict.fromkeys(n for line in bwd for n in _uses(line) if n in defs)
    residuals = [n for n in used if n not in inputs_only]
    repeated = [line for line in fwd if any(n in used and n in inputs_only for n in _defined(line))]
    cast = lambda n, kind: f"({kind})" if n.startswith("m") else ""  # a mask is stored as the float vector's bits
    stores = [f"res[{i}] = {cast(n, 'V')}{n};" for i, n in enumerate(residuals)]
    kind = lambda n: "M" if n.startswith("m") else "V"
    loads = [f"const {kind(n)} {n} = {cast(n, 'M')}res[{i}];" for i, n in enumerate(residuals)]
    fwd_sig = [(a, k) for a, k in signature if a in forward or k != "out"]
    fwd_sig = [(a, k) for a, k in fwd_sig if a != seed] + [("res", "out")]
    bwd_sig = [(a, k) for a, k in signature if a not in forward]
    at = next(i for i, (a, _) in enumerate(bwd_sig) if a == seed)
    bwd_sig = [*bwd_sig[:at], ("res", "V"), *bwd_sig[at:]]
    return "\n".join([_function(name + "_fwd", _live(fwd + stores), fwd_sig),
                      _function(name + "_bwd", _live(repeated + loads + bwd), bwd_sig),
                      f"// residuals: {len(residuals)}", ""])  # fmt: skip
