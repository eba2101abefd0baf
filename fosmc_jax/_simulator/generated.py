"""Generated kernels: the closed loop's step printed from the JAX model into C++, forward and adjoint.

One rollout's step, :func:`fosmc_jax._simulator.step.closed_loop_step` (the plant, the law, the
loop, the integrator, the guard and the metrics, whatever pytrees they are: a user's law or plant
too), is traced on one rollout's flat state and split by what each value depends on:

- on the rollout's parameters only (the plant's and the controller's leaves: K, (CB)^-1, the
  arm's constants): hoisted out of the time loop, computed by JAX once per rollout ("lanes");
- on time only (the step index, dt, the reference; a digital loop's sample index and the batch's
  noise key, so its noise's draws too: :meth:`fosmc_jax.DigitalLoop.with_clock`): computed by JAX
  once per step for every rollout (the "table");
- on the state: printed by :mod:`fosmc_jax._simulator.codegen` into straight-line C++ over SIMD
  lanes, with its vector-Jacobian product (built by ``jax.vjp``, printed the same way).

The skeleton ``gen_kernel.h`` runs the time loop over blocks of lanes on every core, the forward
storing the state every step (every K steps where that would not fit in
:data:`CHECKPOINT_BYTES`), the adjoint recomputing each block from its checkpoint and sweeping
it backwards. It is built once per precision (cached like every build) and runs every model: a
model's library holds its printed steps alone, registered in the skeleton with the model's
layout under an id its calls name (the skeleton's compilation, the XLA FFI header and the loop,
was most of a model's build). A run without derivatives builds the printed steps' library, a
derivative the adjoint's (the steps, their vector-Jacobian products; the steps' objects compiled
once for both, :func:`fosmc_jax._simulator.native.build_generated`). In JAX the kernel is one
function of (state, lanes, table) with a ``custom_jvp`` whose tangent is a ``linear_call``:
forward mode runs a ``lax.scan`` of the same split step, reverse mode the transpose, the adjoint
kernel. The hoisted parts are plain JAX, so derivatives reach every parameter through them.

What cannot be printed (a primitive the printer does not know, a value that is an integer per
rollout) raises :class:`fosmc_jax._simulator.codegen.Unsupported`; the callers then run the
``vmap`` path, with one warning naming it. A step that prints but whose vector-Jacobian product
does not (or whose adjoint does not build) is found at its first derivative: that derivative
differentiates the ``lax.scan`` of the split step instead, with one warning.
"""

from __future__ import annotations

import ctypes
import functools
import hashlib
import math
import os
import re
import threading
import warnings
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

# linear_call's primitive and the table of batching rules (jax.interpreters.batching's is a
# write-only proxy): JAX has no batching rule for linear_call, generated.py adds one
from jax._src.custom_derivatives import linear_call_p as _LINEAR_CALL
from jax._src.interpreters import batching
from jax.custom_derivatives import SymbolicZero, linear_call

from .._loop.digital import DigitalLoop
from . import codegen
from . import native as _native

#: The most memory the forward's checkpoints for the adjoint take (bytes).
CHECKPOINT_BYTES = 256 * 2**20
#: The most memory the tables of one kernel call take where each element of a ``vmap`` has its
#: own (a noisy loop's noise realizations, :func:`_folded_call`), bytes.
TABLE_BYTES = 64 * 2**20
#: About the memory a block of steps' residuals and states take in the adjoint, per thread
#: (bytes): within a core's cache, so that the reverse reads back what the block's recompute
#: stored without going to memory.
RESIDUAL_BYTES = 384 * 2**10
_S, _L, _T = 1, 2, 4  # what a value depends on: the state, the rollout's parameters, time
_INLINE = {"jit", "pjit", "closed_call", "core_call", "remat2", "checkpoint"}


class _Entry(NamedTuple):
    eqn: Any
    ins: list[int]  # value ids
    outs: list[int]
    fn: Any = None  # evaluates the entry instead of binding eqn's primitive (a rewritten solve)


def _record(jaxpr, consts, in_ids, tape: list, values: dict, counter: list) -> list:
    """The equations of ``jaxpr`` appended to ``tape`` with calls inlined, values as ids."""
    env = {}

    def new():
        counter[0] += 1
        return counter[0]

    def read(v):
        if isinstance(v, jax.extend.core.Literal):  # one id per literal value, so that _merge_equal sees them equal
            a = np.asarray(v.val)
            key = ("literal", a.dtype.str, a.shape, a.tobytes())
            if key not in values:
                values[key] = new()
                values[values[key]] = a
            return values[key]
        return env[v]

    for v, c in zip(jaxpr.constvars, consts):
        env[v] = new()
        values[env[v]] = c
    for v, i in zip(jaxpr.invars, in_ids):
        env[v] = i
    for eqn in jaxpr.eqns:
        ins = [read(v) for v in eqn.invars]
        if eqn.primitive.name in _INLINE:
            sub = eqn.params["jaxpr" if "jaxpr" in eqn.params else "call_jaxpr"]
            inner, inner_consts = (sub.jaxpr, sub.consts) if hasattr(sub, "consts") else (sub, [])
            outs = _record(inner, inner_consts, ins, tape, values, counter)
        else:
            outs = [new() for _ in eqn.outvars]
            tape.append(_Entry(eqn, ins, outs))
        for v, o in zip(eqn.outvars, outs):
            env[v] = o
    return [read(v) for v in jaxpr.outvars]


def _merge_equal(tape: list) -> tuple[list, dict]:
    """``tape`` without the equations that repeat an earlier one (the same primitive and
    parameters on the same values), and the ids of their results -> the earlier's. The RK4 stages
    2 and 3 each compute t_k + dt/2 and the plant's terms of it (the arm's external torque): as
    one value, the printer computes them once (its own merging sees equal expressions only, and
    two hoisted values are two expressions). The same operations on the same values: the same
    numbers."""
    seen: dict = {}
    alias: dict = {}
    out = []
    for e in tape:
        ins = [alias.get(i, i) for i in e.ins]
        e = e._replace(ins=ins)
        key = None
        params = e.eqn.params if e.fn is None else None
        # only parameters that their repr spells out whole (no sub-jaxpr whose constants it does not
        # show, no array it may abbreviate), and no effect
        if (
            params is not None
            and not e.eqn.effects
            and not any(jax.extend.core.jaxprs_in_params(params))
            and not any(isinstance(v, (np.ndarray, jax.Array)) for v in params.values())
        ):
            key = (e.eqn.primitive, tuple(ins), tuple(sorted((k, repr(v)) for k, v in params.items())))
        if key is not None and key in seen:
            alias.update(zip(e.outs, seen[key].outs))
            continue
        if key is not None:
            seen[key] = e
        out.append(e)
    return out, alias


def _replay(entries, env: dict) -> None:
    for e in entries:
        if e.fn is not None:
            out = e.fn(*(env[i] for i in e.ins))
        else:
            out = e.eqn.primitive.bind(*(env[i] for i in e.ins), **e.eqn.primitive.get_bind_params(e.eqn.params))
        for i, o in zip(e.outs, out if e.eqn.primitive.multiple_results else [out]):
            env[i] = o


def _hoist_solves(tape: list, cls: dict, counter: list) -> list:
    """A linear solve A x = b whose A depends on the rollout's parameters only and b on the state or time
    (``jnp.linalg.solve(CB, .)`` in a law) becomes x = A^-1 b with A^-1 computed by the same
    solve, once per rollout: the step then holds a product instead of a pivoting solve, whose
    row exchanges vary by rollout. Derivatives are those of A^-1 b (exact: the same function)."""
    out = []
    for e in tape:
        n = e.eqn.params.get("const_lengths") if e.eqn.primitive.name == "custom_linear_solve" else None
        if n is None or e.eqn.invars[-1].aval.ndim != 1 or len(e.ins) != sum(n) + 1:
            out.append(e)
            continue
        *consts, b = e.ins
        if not all(cls[i] in (0, _L) for i in consts) or cls[b] in (0, _L):
            out.append(e)
            continue
        size = e.eqn.invars[-1].aval.shape[0]
        params = e.eqn.primitive.get_bind_params(e.eqn.params)
        solve = lambda *a, p=e.eqn.primitive, params=params: p.bind(*a, **params)[0]
        inverse = lambda *c, solve=solve, size=size, dtype=e.eqn.invars[-1].aval.dtype: jax.vmap(
            lambda col: solve(*c, col), out_axes=1
        )(jnp.eye(size, dtype=dtype))
        counter[0] += 1
        inv_id = counter[0]
        cls[inv_id] = functools.reduce(int.__or__, (cls[i] for i in consts), 0)
        out.append(_Entry(_Multi(False), list(consts), [inv_id], lambda *c, f=inverse: f(*c)))
        out.append(_Entry(_Multi(True), [inv_id, b], list(e.outs), lambda A, v: [A @ v]))
    return out


class _Multi(NamedTuple):
    """Stands in for a rewritten entry's equation: whether it returns a list."""

    multiple: bool

    @property
    def primitive(self):
        return self

    @property
    def multiple_results(self):
        return self.multiple


class Split(NamedTuple):
    """One step split into what is hoisted and what is printed (see the module's docstring)."""

    lane_pre: Any  # lane leaves -> list of hoisted values (one rollout)
    time_pre: Any  # (k, glob leaves) -> list of hoisted values
    core: Any  # (x, lane values, time values) -> x'
    lane_avals: list
    time_avals: list
    varies: list  # per lane value: whether it depends on the controller's leaves (else the plant's alone)


def _trace(step, x_aval, lane_avals, glob_avals):
    return jax.make_jaxpr(step)(x_aval, lane_avals, glob_avals, jax.ShapeDtypeStruct((), jnp.int32))


def split(step, x_aval, lane_avals, glob_avals, closed=None, n_plant: int = 0) -> Split:
    """Traces ``step(x, lane_leaves, glob_leaves, k) -> x'`` (or takes its ``closed`` jaxpr) and
    splits it; the first ``n_plant`` lane leaves are the plant's (see :attr:`Split.varies`)."""
    closed = _trace(step, x_aval, lane_avals, glob_avals) if closed is None else closed
    n_lane, n_glob = len(lane_avals), len(glob_avals)
    tape: list[_Entry] = []
    values: dict = {}
    counter = [0]
    ids = list(range(1, 2 + n_lane + n_glob + 1))
    counter[0] = ids[-1]
    x_id, lane_ids, glob_ids, k_id = ids[0], ids[1 : 1 + n_lane], ids[1 + n_lane : -1], ids[-1]
    out_ids = _record(closed.jaxpr, closed.consts, ids, tape, values, counter)
    values = {i: v for i, v in values.items() if not isinstance(i, tuple)}  # the literals' index dropped
    tape, alias = _merge_equal(tape)
    out_ids = [alias.get(i, i) for i in out_ids]
    cls = {x_id: _S, k_id: _T, **{i: _L for i in lane_ids}, **{i: _T for i in glob_ids}}
    for i in values:
        cls[i] = 0
    for e in tape:
        for o in e.outs:
            cls[o] = functools.reduce(int.__or__, (cls[i] for i in e.ins), 0)
    tape = _hoist_solves(tape, cls, counter)
    controls = set(lane_ids[n_plant:])  # the values that depend on the controller's leaves
    for e in tape:
        if any(i in controls for i in e.ins):
            controls.update(e.outs)
    lane_entries, time_entries, core_entries = [], [], []
    with jax.ensure_compile_time_eval():
        for e in tape:
            c = functools.reduce(int.__or__, (cls[i] for i in e.ins), 0)
            for o in e.outs:
                cls[o] = c
            if c == 0:  # constants: folded now
                _replay([e], values)
            else:
                (lane_entries if c == _L else time_entries if c == _T else core_entries).append(e)
    lane_entries, core_entries = _moves_to_core(lane_entries, core_entries, out_ids, cls)
    core_entries = _live_entries(core_entries, out_ids)
    used = [i for e in core_entries for i in e.ins] + list(out_ids)
    used = list(dict.fromkeys(used))
    in_core = {o for e in core_entries for o in e.outs}
    lane_hoist = [i for i in used if cls[i] == _L and i not in in_core]
    time_hoist = [i for i in used if cls[i] == _T]
    consts = {i: values[i] for i in used if cls[i] == 0}

    def lane_pre(lane):
        env = {**values, **dict(zip(lane_ids, lane))}
        _replay(lane_entries, env)
        return [env[i] for i in lane_hoist]

    def time_pre(k, glob):
        env = {**values, **dict(zip(glob_ids, glob)), k_id: k}
        _replay(time_entries, env)
        return [env[i] for i in time_hoist]

    def core(x, lv, tv):
        env = {**consts, **dict(zip(lane_hoist, lv)), **dict(zip(time_hoist, tv)), x_id: x}
        _replay(core_entries, env)
        return env[out_ids[0]]

    k0 = jax.ShapeDtypeStruct((), jnp.int32)
    return Split(lane_pre, time_pre, core, jax.eval_shape(lane_pre, lane_avals),
                 jax.eval_shape(time_pre, k0, glob_avals), [i in controls for i in lane_hoist])  # fmt: skip


def _live_entries(entries: list, out_ids) -> list:
    """``entries`` without those whose results reach no output: what a step computes and drops
    (a state's part that the kernel does not carry, such as a sampled loop's clock) would
    otherwise be printed, and its inputs hoisted into the table."""
    live, kept = set(out_ids), []
    for e in reversed(entries):
        if any(o in live for o in e.outs):
            kept.append(e)
            live.update(e.ins)
    return kept[::-1]


def _moves_to_core(lane_entries: list, core_entries: list, out_ids, cls: dict) -> tuple[list, list]:
    """The per-rollout data moves (broadcasts, reshapes, static gathers...) that feed the core
    moved into it, where they print nothing: hoisted, each moved element would be one more lane
    row, loaded every step and, in the adjoint, one more cotangent summed every step (a broadcast
    of one parameter to a 3x3 block: 9 rows for 1)."""
    feeds = set(out_ids) | {i for e in core_entries for i in e.ins}
    moved, kept, lane_uses = set(), set(), set()
    for n in range(len(lane_entries) - 1, -1, -1):  # every use of an entry's results comes after it
        e = lane_entries[n]
        name = e.eqn.primitive.name if e.fn is None else None  # a rewritten solve: not a move
        index = codegen._INDEX_OPERANDS.get(name, lambda n: ())(len(e.ins))
        if name in codegen._MOVES and any(o in feeds for o in e.outs) and all(cls[e.ins[j]] == 0 for j in index):
            moved.add(n)
            feeds.update(e.ins)
        if n not in moved or any(o in lane_uses for o in e.outs):  # a move that a hoisted value needs too: in both
            kept.add(n)
            lane_uses.update(e.ins)
    if not moved:
        return lane_entries, core_entries
    # the tape is in dependency order, and every moved entry comes before the core's first use
    # of it: the core's entries stay after the moved ones
    return ([e for n, e in enumerate(lane_entries) if n in kept],
            [e for n, e in enumerate(lane_entries) if n in moved] + core_entries)  # fmt: skip


def _as_float(values, dtype) -> Array:
    """Hoisted values (each flattened, cast to the model's float) as one vector."""
    parts = [jnp.ravel(jnp.asarray(v)).astype(dtype) for v in values]
    return jnp.concatenate(parts) if parts else jnp.zeros((0,), dtype)


def _from_float(vector, avals) -> list:
    out, at = [], 0
    for a in avals:
        n = math.prod(a.shape)
        out.append(vector[at : at + n].reshape(a.shape).astype(a.dtype))
        at += n
    return out


def _size(avals) -> int:
    return sum(math.prod(a.shape) for a in avals)


class Target(NamedTuple):
    """What a kernel call names: the skeleton's FFI target and the model it runs (the id its
    library is registered under, the call's ``model`` attribute)."""

    name: str
    model: int


class Kernels(NamedTuple):
    """A model's adjoint library: its FFI targets and the checkpoints' rows."""

    targets: tuple[Target, Target]  # the forward that stores the checkpoints, the adjoint
    residuals: int  # the most values a step's reverse reads from its forward (the adjoint stores a block's)


class Model(NamedTuple):
    """A generated model: the split steps (held and sampled), printed and built on first use,
    the forward (:meth:`forward`) apart from the adjoint (:meth:`kernels`), which only a
    derivative builds."""

    held: Split | None  # None in the ideal loop (m = 1)
    sampled: Split
    n_state: int
    m: int
    dtype: Any
    dynamic: np.ndarray  # (n_state,) bool: the rows whose derivative a truncation stops
    rows: np.ndarray  # the lane rows, the controller's (Split.varies) first: lanes[rows] = (varying, fixed)
    n_varying: int
    built: dict  # "steps": the printed steps' sources; "forward": its target; with_plant -> Kernels

    def steps(self) -> list[str]:
        """The printed steps' sources (held, sampled), printed once: both libraries compile them."""
        if "steps" not in self.built:
            self.built["steps"] = _print_steps(self)
        return self.built["steps"]

    def forward(self) -> Target:
        """The FFI target of the forward (the steps' library), built on first use."""
        if "forward" not in self.built:
            dtype, flags = np.dtype(self.dtype).name, _native.generated_flags()
            model = _load(tuple(self.steps()), _layout(self, None), dtype, flags)
            self.built["forward"] = Target(_skeleton(dtype, flags) + "FosmcGenForward", model)
        return self.built["forward"]

    def kernels(self, with_plant: bool) -> Kernels:
        """The adjoint's library, whose vector-Jacobian products give cotangents to the fixed
        lane rows (the plant's) too (``with_plant``) or to the controller's only: a derivative
        in the controller alone (the tuner's) skips the plant's share of the reverse sweep. Its
        library holds the printed steps too (their objects compiled once, :func:`native.build_generated`)."""
        if with_plant not in self.built:
            vjps, n_res = _print_vjps(self, with_plant)
            dtype, flags = np.dtype(self.dtype).name, _native.generated_flags()
            model, prefix = _load((*self.steps(), *vjps), _layout(self, n_res), dtype, flags), _skeleton(dtype, flags)
            self.built[with_plant] = Kernels((Target(prefix + "FosmcGenForwardCk", model),
                                              Target(prefix + "FosmcGenAdjoint", model)), n_res)  # fmt: skip
        return self.built[with_plant]

    def lanes(self, lane_leaves) -> tuple[Array, Array]:
        """The hoisted values of one rollout: those that depend on the controller's leaves, then
        those of the plant's alone (:attr:`rows` orders the kernel's lane rows from them)."""
        values, varies = [], []
        for s in (self.held, self.sampled):
            if s is not None:
                values += s.lane_pre(lane_leaves)
                varies += s.varies
        pick = lambda keep: _as_float([v for v, c in zip(values, varies) if c == keep], self.dtype)
        return pick(True), pick(False)

    def assemble(self, lanes: tuple[Array, Array]) -> Array:
        """The kernel's lane rows (n_lane, ...) from :meth:`lanes`' two parts."""
        return jnp.concatenate(lanes)[np.argsort(self.rows)]

    def table_row(self, k, glob_leaves) -> Array:
        parts = [] if self.held is None else self.held.time_pre(k, glob_leaves)
        return _as_float([*parts, *self.sampled.time_pre(k, glob_leaves)], self.dtype)

    def step(self, k1, x, lanes, row) -> Array:
        """One step in JAX from the split pieces (the forward mode's scan): ``k1`` the step's end index."""

        def run(s: Split, lanes, row):
            return s.core(x, _from_float(lanes, s.lane_avals), _from_float(row, s.time_avals))

        if self.held is None:
            return run(self.sampled, lanes, row)
        nl, nt = _size(self.held.lane_avals), _size(self.held.time_avals)
        return jax.lax.cond(k1 % self.m == 0, lambda: run(self.sampled, lanes[nl:], row[nt:]),
                            lambda: run(self.held, lanes[:nl], row[:nt]))  # fmt: skip


_SIGNATURES = {
    "": "const V* x, const V* lv, const T* tv, V* y",
    "_fwd": "const V* x, const V* lv, const T* tv, V* y, V* res",
    "_bwd": "const V* x, const V* lv, const T* tv, const V* res, const V* ct, V* gx, V* glv",
}


def _head(dtype, step: bool = False) -> list[str]:
    """A source's first lines; a printed step's file (``step``) takes gen_kernel.h's types and
    helpers without the skeleton and its XLA FFI header (FOSMC_GEN_STEP)."""
    ctype = "double" if np.dtype(dtype) == np.float64 else "float"
    return ["// Generated by fosmc_jax._simulator.generated from the JAX model: do not edit.",
            f"#define FOSMC_T {ctype}", *(["#define FOSMC_GEN_STEP"] if step else []), '#include "gen_kernel.h"',
            "namespace gen {"]  # fmt: skip


def _one_file(dtype, text: str) -> str:
    """A printed step's source; its functions have C linkage, looked up by name in its library."""
    text = re.sub(r"^void ", 'extern "C" void ', text, flags=re.M)
    return "\n".join([*_head(dtype, step=True), text, "}  // namespace gen", ""])


def _print_steps(model: Model) -> list[str]:
    """The sources of the printed steps, held and sampled (one file each: compiled in parallel)."""
    x_aval = jax.ShapeDtypeStruct((model.n_state,), model.dtype)
    sig = [("x", "V"), ("lv", "V"), ("tv", "T"), ("y", "out")]
    out = []
    for name, s in (("held", model.held), ("sampled", model.sampled)):
        if s is None:  # the ideal loop: no held step (the skeleton never calls it)
            continue
        lv, tv = list(s.lane_avals), list(s.time_avals)
        fwd = jax.make_jaxpr(s.core)(x_aval, lv, tv)
        inputs = [("x", "V")] + [("lv", "V")] * len(lv) + [("tv", "T")] * len(tv)
        out.append(_one_file(model.dtype, codegen.print_function(name, fwd, model.dtype, inputs, [("y", False)], sig)))
    return out


def _print_vjps(model: Model, with_plant: bool) -> tuple[list[str], int]:
    """The sources of the steps' vector-Jacobian products (held, sampled), each printed as two
    functions: ``*_fwd``, the step that also stores its residuals (the values its reverse reads),
    and ``*_bwd``, the reverse from them (:func:`codegen.print_function`'s ``split``); and the
    most residuals a step stores. ``with_plant``: cotangents for the lane values of the plant's
    alone too."""
    x_aval = jax.ShapeDtypeStruct((model.n_state,), model.dtype)
    sig = [("x", "V"), ("lv", "V"), ("tv", "T"), ("ct", "V"), ("y", "out"), ("gx", "out"), ("glv", "out")]
    texts, n_res = [], 1
    for name, s in (("held", model.held), ("sampled", model.sampled)):
        if s is None:
            continue
        lv, tv = list(s.lane_avals), list(s.time_avals)
        inputs = [("x", "V")] + [("lv", "V")] * len(lv) + [("tv", "T")] * len(tv)
        diff = [jnp.issubdtype(a.dtype, jnp.floating) and (with_plant or c) for a, c in zip(lv, s.varies)]

        def vjp(x, lv_, tv_, ct, s=s, diff=diff):
            f = lambda x, d: s.core(x, _merge(lv_, d, diff), tv_)
            y, back = jax.vjp(f, x, [v for v, ok in zip(lv_, diff) if ok])
            return y, *back(ct)

        bwd = jax.make_jaxpr(vjp)(x_aval, lv, tv, x_aval)
        # the lane rows of a non-float or skipped hoisted value get no cotangent (they stay zero)
        outs = [("y", False), ("gx", False)] + [("glv", True)] * sum(diff)
        text = codegen.print_function(name, bwd, model.dtype, inputs + [("ct", "V")], outs, sig, derivative=True,
                                      split=("ct", {"y"}, {"gx", "glv"}))  # fmt: skip
        if not all(diff):  # a skipped row still takes its place in glv: renumber
            text = _renumber_glv(text, lv, diff)
        n_res = max(n_res, int(re.search(r"// residuals: (\d+)", text).group(1)))
        texts.append(text)
    return [_one_file(model.dtype, t) for t in texts], n_res


class _Layout(ctypes.Structure):
    """gen_kernel.h's ``gen::Model``: a model's layout and its steps, as the skeleton runs it."""

    _fields_ = [*((f, ctypes.c_int64) for f in ("n", "nl_held", "nl_sampled", "nt_held", "nt_sampled", "m", "n_res")),
                ("dynamic", ctypes.c_void_p),
                *((f, ctypes.c_void_p) for f in ("held", "sampled", "held_fwd", "sampled_fwd", "held_bwd",
                                                 "sampled_bwd"))]  # fmt: skip


def _layout(model: Model, n_res: int | None) -> tuple:
    """What the skeleton needs of ``model`` beside its steps (hashable, :func:`_load`'s key): the
    sizes of its state, lane and table rows, m, the most residuals a step's ``*_fwd`` stores
    (``n_res``, None: a forward alone) and the dynamic rows."""
    sizes = [(0, 0) if s is None else (_size(s.lane_avals), _size(s.time_avals)) for s in (model.held, model.sampled)]
    (nlh, nth), (nls, nts) = sizes
    return (model.n_state, nlh, nls, nth, nts, model.m, n_res, tuple(bool(d) for d in model.dynamic),
            model.held is not None)  # fmt: skip


def _skeleton(dtype: str, flags: tuple[str, ...] = ()) -> str:
    """The skeleton of the kernels of ``dtype`` (its name), built (cached) and loaded once per
    process, its FFI targets registered (under a lock: threads of one process build models at
    once, ``fosmc reproduce``'s); returns their names' prefix."""
    with _SKELETON_LOCK:
        if (dtype, flags) not in _SKELETONS:
            source = "\n".join([*_head(dtype), "}  // namespace gen", ""])
            headers = [h.read_text() for h in _native._HEADERS]
            tag = hashlib.sha256("\n".join([source, *flags, *headers]).encode()).hexdigest()[:16]
            lib = ctypes.cdll.LoadLibrary(str(_native.build_generated([source])))
            lib.fosmc_gen_register.argtypes = [ctypes.c_int64, ctypes.POINTER(_Layout)]
            lib.fosmc_gen_register.restype = None
            prefix = f"fosmc_gen_{tag}_"
            for symbol in ("FosmcGenForward", "FosmcGenForwardCk", "FosmcGenAdjoint"):
                jax.ffi.register_ffi_target(prefix + symbol, jax.ffi.pycapsule(getattr(lib, symbol)), platform="cpu")
            _LIBRARIES.append(lib)
            _REGISTER[prefix] = lib.fosmc_gen_register
            _SKELETONS[dtype, flags] = prefix
        return _SKELETONS[dtype, flags]


_SKELETON_LOCK = threading.Lock()
_SKELETONS: dict = {}  # (dtype, flags) -> the prefix of its FFI targets
_REGISTER: dict = {}  # a skeleton's prefix -> its fosmc_gen_register


def _merge(lv, diff_values, diff):
    it = iter(diff_values)
    return [next(it) if ok else v for v, ok in zip(lv, diff)]


def _renumber_glv(text: str, lv, diff) -> str:
    rows, at = [], 0
    for a, ok in zip(lv, diff):
        n = math.prod(a.shape)
        if ok:
            rows.extend(range(at, at + n))
        at += n
    return re.sub(r"glv\[(\d+)\]", lambda mt: f"glv[{rows[int(mt.group(1))]}]", text)


@functools.lru_cache(maxsize=64)
def _load(sources: tuple[str, ...], layout: tuple, dtype: str, flags: tuple[str, ...] = ()) -> int:
    """Builds and loads the library of a model's printed ``sources`` (once per source and extra
    compiler ``flags``, :func:`native.generated_flags`, in a process) and registers its steps with
    ``layout`` (:func:`_layout`) in the skeleton of ``dtype`` (its name): the id its calls name."""
    tag = hashlib.sha256("\n".join([*sources, repr(layout), *flags]).encode()).hexdigest()[:16]
    if os.environ.get("FOSMC_JAX_GENERATED_DUMP"):  # a folder to keep the printed sources in, to read them
        folder = Path(os.environ["FOSMC_JAX_GENERATED_DUMP"])
        folder.mkdir(parents=True, exist_ok=True)
        for i, source in enumerate(sources):
            (folder / f"{tag}-{i}.cc").write_text(source)
    lib = ctypes.cdll.LoadLibrary(str(_native.build_generated(list(sources))))
    n, nlh, nls, nth, nts, m, n_res, dynamic, has_held = layout
    address = lambda name: ctypes.cast(getattr(lib, name), ctypes.c_void_p).value if name else None
    flags_c = (ctypes.c_uint8 * max(n, 1))(*dynamic)
    steps = [s if (has_held or not s.startswith("held")) and (n_res is not None or "_" not in s) else None
             for s in ("held", "sampled", "held_fwd", "sampled_fwd", "held_bwd", "sampled_bwd")]  # fmt: skip
    entry = _Layout(n, nlh, nls, nth, nts, m, 0 if n_res is None else n_res, ctypes.cast(flags_c, ctypes.c_void_p),
                    *map(address, steps))  # fmt: skip
    model = int(tag[:15], 16)  # fits an int64 attribute; the same in every process, as XLA's cache needs
    _REGISTER[_skeleton(dtype, flags)](model, ctypes.byref(entry))
    _LIBRARIES.append(lib)
    return model


_LIBRARIES: list = []  # the loaded libraries stay loaded while their targets are registered


def build(step_of, state_aval, lane_avals, glob_avals, m: int, dynamic, n_plant: int = 0) -> Model:
    """The model of ``step_of(sample) -> step(x, lane_leaves, glob_leaves, k) -> x'`` (the first
    ``n_plant`` lane leaves the plant's), split and its steps printed; each library is compiled
    (cached) and registered on first use: the forward's by a forward (:meth:`Model.forward`), the
    adjoint's by a derivative (:meth:`Model.kernels`). Raises
    :class:`codegen.Unsupported` or OSError. A model traced again (the same jaxprs
    and constants: a second trace of the same loss) is the one already printed: printing the
    arm's takes tens of seconds."""
    closed = [_trace(step_of(sample), state_aval, lane_avals, glob_avals) for sample in (True, False)[: 1 + (m > 1)]]
    key = _model_key(closed, m, dynamic, n_plant)
    if key is not None and key in _MODELS:
        return _MODELS[key]
    sampled = split(None, state_aval, lane_avals, glob_avals, closed[0], n_plant)
    held = split(None, state_aval, lane_avals, glob_avals, closed[1], n_plant) if m > 1 else None
    sizes, varies = [], []
    for s in (held, sampled):
        if s is not None:
            sizes += [math.prod(a.shape) for a in s.lane_avals]
            varies += s.varies
    row_of = np.split(np.arange(sum(sizes)), np.cumsum(sizes)[:-1]) if sizes else []
    rows = [r for keep in (True, False) for r, c in zip(row_of, varies) if c == keep]
    rows = np.concatenate(rows).astype(int) if rows else np.zeros(0, int)
    n_varying = sum(n for n, c in zip(sizes, varies) if c)
    dtype, n = state_aval.dtype, state_aval.shape[0]
    model = Model(held, sampled, n, m, dtype, np.asarray(dynamic, bool), rows, n_varying, {})
    # printed now, so that what cannot be printed is known here; compiled where it runs: the forward's
    # library by a forward, the adjoint's (with the steps, not the forward's) by a derivative
    model.steps()
    if key is not None:
        _MODELS[key] = model
    return model


_MODELS: dict = {}  # printed models by _model_key, for this process


def _model_key(closed: list, m: int, dynamic, n_plant: int) -> tuple | None:
    """What a printed model depends on: its steps' jaxprs (their text, which names constants but
    does not show them), the constants' values and the mesh it is traced under (its recorded
    values carry that mesh: replayed under another, in a ``shard_map`` of other axes, they are
    refused); None where a constant is not concrete."""
    parts = [m, np.asarray(dynamic, bool).tobytes(), n_plant, repr(jax.sharding.get_abstract_mesh())]
    for c in closed:
        parts.append(str(c.jaxpr))
        for x in c.consts:
            try:
                a = np.asarray(x)
            except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError):
                return None
            parts.append((a.dtype.str, a.shape, hashlib.sha256(a.tobytes()).hexdigest()))
    return tuple(parts)


# ----------------------------------------------------------------------------- in JAX


#: jaxlib's CPU LAPACK kernels (0.10) split a batch of matrices over XLA's intra-op threads once
#: their estimate of its work (flops, ``GetLapackBatchChunkSize``) reaches this, and wait for the
#: pieces on the calling thread, itself one of those threads: when every one of them waits so
#: (two batched solves at once on 2 cores), nobody runs the pieces and the program hangs, every
#: thread idle. A batch whose calls stay below it runs on the calling thread alone.
_LAPACK_SPLIT = 200_000
#: The primitives that run as jaxlib's LAPACK kernels on the CPU.
_LAPACK = {"lu", "triangular_solve", "cholesky", "eig", "eigh", "svd", "geqrf", "geqp3", "householder_product",
           "ormqr", "schur", "hessenberg", "tridiagonal", "tridiagonal_solve"}  # fmt: skip


def _lapack_work(jaxpr) -> int:
    """The largest work of one LAPACK call in ``jaxpr`` (its sub-jaxprs too) per element of a
    ``vmap`` over it: jaxlib's estimate for ``lu`` and ``triangular_solve`` (m n min(m, n), and m n m
    or m n n of the right-hand side), 100 m n max(m, n) for the others (above jaxlib's), times
    the matrices the call holds already, times 3 for complex ones."""
    worst = 0
    for eqn in jaxpr.eqns:
        name = eqn.primitive.name
        if name in _LAPACK:
            aval = eqn.invars[-1 if name in ("triangular_solve", "tridiagonal_solve") else 0].aval
            *batch, m, n = (1, 1, *aval.shape)[-max(2, len(aval.shape)) :]
            if name == "lu":
                cost = m * n * min(m, n)
            elif name == "triangular_solve":
                cost = m * n * (m if eqn.params["left_side"] else n)
            else:
                cost = 100 * m * n * max(m, n)
            cost *= math.prod(batch) * (3 if jnp.issubdtype(aval.dtype, jnp.complexfloating) else 1)
            worst = max(worst, cost)
        for sub in jax.extend.core.jaxprs_in_params(eqn.params):
            worst = max(worst, _lapack_work(sub))
    return worst


def _vmap(fn, args: tuple, in_axes=0, out_axes=0):
    """``jax.vmap(fn, in_axes, out_axes)(*args)``, or, where one of ``fn``'s LAPACK calls batched
    so would reach :data:`_LAPACK_SPLIT` (and could hang, see there), the same by ``lax.map`` over
    batches that stay below it (each matrix's LAPACK call is the same one: the same values)."""
    in_axes = (in_axes,) * len(args) if isinstance(in_axes, int) else in_axes
    size = next(jnp.shape(x)[d] for x, d in zip(args, in_axes) if d is not None)
    held = [i for i, d in enumerate(in_axes) if d is not None]
    one = [jax.ShapeDtypeStruct(tuple(n for j, n in enumerate(jnp.shape(args[i])) if j != in_axes[i]), args[i].dtype)
           for i in held]  # fmt: skip

    def inner(*mapped):
        full = list(args)
        for i, x in zip(held, mapped):
            full[i] = x
        return fn(*full)

    work = _lapack_work(jax.make_jaxpr(inner)(*one).jaxpr)
    floats = [j for j, a in enumerate(one) if jnp.issubdtype(a.dtype, jnp.inexact)]
    if work and floats:  # a derivative's calls too (a solve's cotangents: as wide as its right-hand sides)

        def pullback(*xs):
            def f(*moving):
                full = list(xs)
                for j, x in zip(floats, moving):
                    full[j] = x
                return inner(*full)

            out, back = jax.vjp(f, *(xs[j] for j in floats))
            return back(out)

        work = max(work, _lapack_work(jax.make_jaxpr(pullback)(*one).jaxpr))
    if size * work < _LAPACK_SPLIT:
        return jax.vmap(fn, in_axes, out_axes)(*args)
    out = jax.lax.map(lambda xs: inner(*xs), [jnp.moveaxis(args[i], in_axes[i], 0) for i in held],
                      batch_size=max(1, (_LAPACK_SPLIT - 1) // work))  # fmt: skip
    return jax.tree.map(lambda y: jnp.moveaxis(y, 0, out_axes), out)


def _pad(x: Array, W: int) -> Array:
    return jnp.pad(x, ((0, 0), (0, (-x.shape[1]) % W)), mode="edge")


def _linear_call_batched(axis_data, args, dims, *, callee, transpose_thunk, num_callee_consts, num_res):
    """A batching rule for ``linear_call`` (JAX has none): the call with its function and its
    transpose batched (``batching.batch_jaxpr``), so that under ``vmap`` of a gradient the
    adjoint kernel runs once for the whole batch (:func:`_folded_call`). ``jax.jacfwd`` and
    ``vmap`` of a gradient need it."""
    size = axis_data.size
    res = [d is not None for d in dims[num_callee_consts : num_callee_consts + num_res]]
    lin = [True] * (len(args) - num_callee_consts - num_res)  # their cotangents are mapped anyway
    batched = [d is not None for d in dims[:num_callee_consts]] + res + lin
    args = [jnp.moveaxis(x, d, 0) if d is not None else jnp.broadcast_to(x, (size, *x.shape)) if b else x
            for x, d, b in zip(args, dims, batched)]  # fmt: skip
    callee = batching.batch_jaxpr(callee, axis_data, batched, [True] * len(callee.out_avals))[0]

    def batched_transpose():
        transpose, consts = transpose_thunk()
        mapped = [False] * len(consts) + res + [True] * (len(transpose.in_avals) - len(consts) - num_res)
        return batching.batch_jaxpr(transpose, axis_data, mapped, [True] * len(transpose.out_avals))[0], consts

    out = _LINEAR_CALL.bind(*args, callee=callee, transpose_thunk=batched_transpose,
                            num_callee_consts=num_callee_consts, num_res=num_res)  # fmt: skip
    return out, [0] * len(out)


def _folded_call(target: Target, shapes, n: int, W: int, ckpt_in: bool = False, ckpt_out: bool = False, **attrs):
    """``jax.ffi.ffi_call(target, shapes)`` with ``attrs``, on buffers whose last axis holds the
    rollouts (``n`` of them, padded to whole blocks of ``W``), but for the table (the second
    input) and the checkpoints (``ckpt_in``: the third input; ``ckpt_out``: the second output),
    whose layout is the kernel's own (block-major); the call names ``target``'s model. Under
    ``vmap`` with a shared table, the mapped axis C is folded into the rollouts: one call runs
    C x n rollouts in whole blocks (C calls of a block each waste most of their lanes on
    padding where n is small, as in tuning, and run on one core); the checkpoints of the
    folded call are kept as C rows of the declared shape (the first ones hold them), which only
    a folded adjoint call reads. Where the table is mapped too (a noisy loop's R keys: each its
    own draws), each element's rollouts fill whole blocks of their own and the kernel reads the
    element's table for them (C tables: C x :data:`TABLE_BYTES` at most per call, lax.map over
    groups beyond). Where the checkpoints are not mapped (a ``vmap`` over the cotangents
    alone), one call per element."""
    attrs = {**attrs, "model": np.int64(target.model)}
    run = jax.custom_batching.custom_vmap(
        lambda *xs: jax.ffi.ffi_call(target.name, shapes, vmap_method="sequential")(*xs, **attrs)
    )

    @run.def_vmap
    def rule(C, batched, *xs):
        mapped = [i for i, b in enumerate(batched) if b]

        def one(values):
            args = list(xs)
            for i, v in zip(mapped, values):
                args[i] = v
            return run(*args)

        group = max(1, TABLE_BYTES // (math.prod(xs[1].shape[1:]) * xs[1].dtype.itemsize)) if batched[1] else C
        if (ckpt_in and not batched[2]) or group < C:
            out = jax.lax.map(one, [xs[i] for i in mapped], batch_size=None if group >= C or group == 1 else group)
            return out, jax.tree.map(lambda _: True, out)
        # per element: its n rollouts (a table each: their padding to whole blocks too), else n only
        width = n + (-n) % W if batched[1] else n
        F = C * width
        Fp = F + (-F) % W

        def fold(x, b):  # (C, ..., n + padding) -> (..., Fp)
            x = (x if b else jnp.broadcast_to(x, (C, *x.shape)))[..., :width]
            x = jnp.moveaxis(x, 0, -2).reshape(*x.shape[1:-1], F)
            return jnp.pad(x, [(0, 0)] * (x.ndim - 1) + [(0, Fp - F)], mode="edge")

        def unfold(y):  # (..., Fp) -> (C, ..., n + padding)
            y = jnp.moveaxis(y[..., :F].reshape(*y.shape[:-1], C, width), -2, 0)[..., :n]
            return jnp.pad(y, [(0, 0)] * (y.ndim - 1) + [(0, (-n) % W)], mode="edge")

        outs = list(shapes) if isinstance(shapes, (tuple, list)) else [shapes]
        wide = [jax.ShapeDtypeStruct((*s.shape[:-1], Fp), s.dtype) for s in outs]
        if ckpt_out:  # the folded checkpoints (their first B x rows x Fp values) in C of the declared rows
            wide[1] = jax.ShapeDtypeStruct((C, *outs[1].shape), outs[1].dtype)
        args = [x if i == 1 else fold(x, b) for i, (x, b) in enumerate(zip(xs, batched))]
        if ckpt_in:
            args[2] = xs[2].reshape(-1)[: xs[2][0].size // xs[2].shape[-1] * Fp]
        call = jax.ffi.ffi_call(target.name, wide if len(wide) > 1 else wide[0], vmap_method="sequential")
        out = call(*args, **attrs)
        out = [out] if len(wide) == 1 else list(out)
        out = [y if ckpt_out and i == 1 else unfold(y) for i, y in enumerate(out)]
        out = tuple(out) if isinstance(shapes, (tuple, list)) else out[0]
        return out, jax.tree.map(lambda _: True, out)

    return run


def _checkpoint_every(residuals: int, n_state: int, N: int, L: int, W: int, dtype) -> int:
    """K: the adjoint's carry stored every K of the L steps. The adjoint recomputes each block of
    K steps storing its residuals, then sweeps it backwards: a block's residuals and states in
    about RESIDUAL_BYTES (a core's cache), and the checkpoints within CHECKPOINT_BYTES."""
    per_row = (N + (-N) % W) * np.dtype(dtype).itemsize
    K = max(1, RESIDUAL_BYTES // ((residuals + n_state) * 64), -(-L * n_state * per_row // CHECKPOINT_BYTES))
    return min(K, L)


def advance(model: Model, x0: Array, lanes: tuple[Array, Array], table: Array, truncate: int = 0) -> Array:
    """The state rows (n_state, N) after the table's L steps from ``x0`` (n_state, N), with the
    rollouts' ``lanes`` (:meth:`Model.lanes`' two parts, rows by N): the generated kernel,
    differentiable in ``x0`` and ``lanes`` (reverse mode: the adjoint kernel; forward mode: a
    ``lax.scan`` of the split step) and, by the scan, in ``table``. ``truncate`` > 0: the dynamic
    rows' derivatives stop every ``truncate`` steps (:func:`fosmc_jax.simulate`'s ``truncate_every``).

    (Long: the forward call, the scan, the adjoint's tangent and transpose and the JVP rule that
    picks between them are closures over one model, its padding and its shapes.)"""
    dtype = model.dtype
    W = 64 // np.dtype(dtype).itemsize
    L, N, n_state = table.shape[0], x0.shape[1], x0.shape[0]
    truncate = truncate if 0 < truncate < L else 0

    def forward(x0, varying, fixed, table):
        xp, lp = _pad(x0, W), _pad(model.assemble((varying, fixed)), W)
        target = model.forward()
        call = _folded_call(target, jax.ShapeDtypeStruct(xp.shape, dtype), N, W, k0=np.int64(0))
        return call(lp, table, xp)[:, :N]

    def scan(x0, varying, fixed, table):
        dyn = jnp.asarray(model.dynamic)[:, None]
        lanes = model.assemble((varying, fixed))

        def body(x, k):
            if truncate:
                x = jnp.where(dyn & (k % truncate == 0), jax.lax.stop_gradient(x), x)
            one = lambda x, lane: model.step(k + 1, x, lane, table[k])
            return _vmap(one, (x, lanes), 1, 1), None

        return jax.lax.scan(body, x0, jnp.arange(L))[0]

    def linear(moving: tuple[int, ...]):
        """The tangent map and its transpose (the adjoint kernel) in the inputs ``moving`` (of
        x0, the varying lanes, the fixed lanes): the others' tangents are zero, so they get no
        cotangent (a linear_call's every linear input must be one)."""
        kernels = model.kernels(with_plant=2 in moving)
        K = _checkpoint_every(kernels.residuals, n_state, N, L, W, dtype)

        def tangent(res, lin):
            primals = res[:3]
            full = [jnp.zeros_like(p) for p in primals]
            for i, t in zip(moving, lin):
                full[i] = t
            return jax.jvp(lambda *xs: scan(*xs, res[3]), primals, tuple(full))[1]

        def transpose(res, ct):
            _, varying, fixed, table, ckpt = res
            lp, cp = _pad(model.assemble((varying, fixed)), W), _pad(ct, W)
            shapes = (jax.ShapeDtypeStruct(cp.shape, dtype), jax.ShapeDtypeStruct(lp.shape, dtype))
            call = _folded_call(kernels.targets[1], shapes, N, W, ckpt_in=True, k0=np.int64(0), K=np.int64(K),
                                truncate=np.int64(truncate))  # fmt: skip
            g_x, g_lanes = call(lp, table, ckpt, cp)
            g_lanes = g_lanes[model.rows, :N]
            g = (g_x[:, :N], g_lanes[: model.n_varying], g_lanes[model.n_varying :])
            return tuple(g[i] for i in moving)

        return kernels, K, tangent, transpose

    run = jax.custom_jvp(forward)

    def rule(primals, tangents):
        zero = [isinstance(t, SymbolicZero) for t in tangents]
        full = lambda: tuple(jnp.zeros(t.aval.shape, t.aval.dtype) if z else t for t, z in zip(tangents, zero))
        if not zero[3]:  # a derivative in dt or the reference: the scan
            return jax.jvp(scan, primals, full())
        x0, varying, fixed, table = primals
        moving = tuple(i for i in range(3) if not zero[i])
        try:  # the adjoint is printed and built here, on a derivative's first use
            kernels, K, tangent, transpose = linear(moving)
        except (codegen.Unsupported, OSError) as e:  # what the forward printed but its VJP does not
            warnings.warn(f"fosmc_jax: the generated adjoint cannot be built ({e}); the derivatives "
                          "differentiate a lax.scan of the split step", stacklevel=2)  # fmt: skip
            return jax.jvp(scan, primals, full())
        xp, lp = _pad(x0, W), _pad(model.assemble((varying, fixed)), W)
        shapes = (jax.ShapeDtypeStruct(xp.shape, dtype),
                  jax.ShapeDtypeStruct((-(-L // K), n_state, xp.shape[1]), dtype))  # fmt: skip
        call = _folded_call(kernels.targets[0], shapes, N, W, ckpt_out=True, k0=np.int64(0), K=np.int64(K))
        out, ckpt = call(lp, table, xp)
        lin = tuple(tangents[i] for i in moving)
        return out[:, :N], linear_call(tangent, transpose, (x0, varying, fixed, table, ckpt), lin)

    run.defjvp(rule, symbolic_zeros=True)
    return run(x0, *lanes, table)


#: What the generated kernels run (``FOSMC_JAX_GENERATED``): ``all`` (default), every batch whose
#: model prints (the package's arm and laws, a user's law or plant), forward and derivatives;
#: ``0``, none (the ``vmap`` path). A model's first build takes seconds (BENCHMARKS.md), cached
#: after (:mod:`fosmc_jax._simulator.cache`).
MODES = ("all", "0")


def mode() -> str:
    """The ``FOSMC_JAX_GENERATED`` mode where kernels can be built here
    (:func:`fosmc_jax._simulator.native.available`), else ``0``."""
    value = os.environ.get("FOSMC_JAX_GENERATED", "all")
    if value not in MODES:
        raise ValueError(f"FOSMC_JAX_GENERATED: expected one of {', '.join(MODES)}, got {value!r}")
    return value if _native.available() else "0"


def jvp_perturbed(fn, primals: tuple, tangents: tuple):
    """``jax.jvp(fn, primals, tangents)`` for a ``custom_jvp`` rule with symbolic zeros: the
    inputs whose tangent is a symbolic zero stay constants, so what they feed (the table of a
    kernel) is known to have none."""
    is_zero = lambda x: isinstance(x, SymbolicZero)
    leaves, treedef = jax.tree.flatten(primals)
    t_leaves = jax.tree.leaves(tangents, is_leaf=is_zero)
    moving = [i for i, t in enumerate(t_leaves) if not is_zero(t)]

    def f(*xs):
        ls = list(leaves)
        for i, x in zip(moving, xs):
            ls[i] = x
        return fn(*jax.tree.unflatten(treedef, ls))

    return jax.jvp(f, tuple(leaves[i] for i in moving), tuple(t_leaves[i] for i in moving))


if _LINEAR_CALL not in batching.fancy_primitive_batchers:  # a later JAX may bring its own
    batching.fancy_primitive_batchers[_LINEAR_CALL] = _linear_call_batched


def warn_unsupported(reason: Exception) -> None:
    warnings.warn(f"fosmc_jax: the generated kernel cannot run this model ({reason}); the vmap path runs",
                  stacklevel=3)  # fmt: skip


def _state_layout(carry) -> tuple[Any, list, np.ndarray]:
    """The carry's flat layout without its step count: (treedef, leaf avals, dynamic rows)."""
    from .step import _DYNAMIC

    rest = tuple(carry[1:])
    leaves, treedef = jax.tree.flatten(rest)
    dynamic = []
    for name, field in zip(carry._fields[1:], rest):
        n = sum(math.prod(jnp.shape(x)) for x in jax.tree.leaves(field))
        dynamic += [name in _DYNAMIC] * n
    return treedef, [jax.ShapeDtypeStruct(jnp.shape(x), x.dtype) for x in leaves], np.asarray(dynamic, bool)


def simulate_batch(
    args: tuple, *, n_steps: int, integrator: str, paired: bool, truncate_every: int = 0, save_every: int = 0
):
    """:func:`fosmc_jax.simulate_batch` of ``args`` = (plants, ctrl, reference, X0s, dt, keys,
    divergence_bound, chattering_cutoff) on the generated kernel, plants crossed with initial
    states or (``paired``) the i-th with the i-th, with each of the R noise ``keys`` (N x R
    rollouts, realization-minor; R > 1: the keys in groups whose tables, one per key, take
    :data:`TABLE_BYTES` at most, each group's in one kernel call); with ``save_every``, its trace
    too (the kernel run in blocks of ``save_every`` steps, a multiple of the controller's
    sample period, each block's carries sampled in JAX as :func:`fosmc_jax.simulate` samples
    them); raises :class:`codegen.Unsupported` or OSError where the model cannot be printed or
    built."""
    from .step import _Carry, closed_loop_step, sample_steps, start_batch

    plants, ctrl, reference, X0s, dt, keys, bound, cutoff = args
    dtype = X0s.dtype
    dt = jnp.asarray(dt, dtype)
    P = jax.tree.leaves(plants)[0].shape[0]
    O = 1 if paired else X0s.shape[0]
    N = P * O
    # a digital loop's sample index and key are functions of the step and of the batch's one key
    # (DigitalLoop.with_clock): they come with the time values, so that its noise's draws are
    # computed by JAX once per step for every rollout (the table) instead of printed per rollout
    clocked = isinstance(ctrl, DigitalLoop)
    unclocked = lambda c: c._replace(ctrl_state=ctrl.without_clock(c.ctrl_state)) if clocked else c
    begin = lambda key: start_batch(plants, ctrl, reference, X0s, key, bound, paired)
    raw_key = lambda carry: carry.ctrl_state.key[0] if clocked else None  # DigitalLoop.init's raw key

    def layout_of(key):  # one rollout's carry at t = 0, and the key its loop holds
        c = begin(key)
        return unclocked(jax.tree.map(lambda x: x[0], c)), raw_key(c)

    one_carry, key_aval = jax.eval_shape(layout_of, keys[0])
    lane_plants = jax.tree.map(lambda x: jnp.repeat(x, O, axis=0), plants)
    lane_leaves, lane_def = jax.tree.flatten((lane_plants, ctrl))
    n_plant = len(jax.tree.leaves(lane_plants))
    # the controller's leaves are one rollout's (shared); the plants' carry the batch axis
    lane_avals = [jax.ShapeDtypeStruct(x.shape[1:] if i < n_plant else jnp.shape(x), x.dtype)
                  for i, x in enumerate(lane_leaves)]  # fmt: skip
    glob_of = lambda key: jax.tree.flatten((reference, dt, jnp.asarray(bound, dtype), jnp.asarray(cutoff, dtype), key))
    glob_def = glob_of(key_aval)[1]
    glob_avals = [jax.ShapeDtypeStruct(jnp.shape(x), jnp.result_type(x)) for x in glob_of(key_aval)[0]]
    state_def, state_avals, dynamic = _state_layout(one_carry)
    n_state = _size(state_avals)
    m = sample_steps(ctrl)

    def flatten(c) -> Array:
        return _as_float(jax.tree.leaves(tuple(unclocked(c)[1:])), dtype)

    def unflatten(k, x, key) -> Any:
        leaves = [v.astype(a.dtype) if a.dtype != jnp.bool_ else v != 0
                  for v, a in zip(_from_float(x, state_avals), state_avals)]  # fmt: skip
        c = _Carry(k, *jax.tree.unflatten(state_def, leaves))
        return c._replace(ctrl_state=ctrl.with_clock(c.ctrl_state, k, key)) if clocked else c

    def step_of(sample: bool):
        def step(x, lane, glob, k):
            plant, ctrl_ = jax.tree.unflatten(lane_def, lane)
            ref, dt_, bound_, cutoff_, key_ = jax.tree.unflatten(glob_def, glob)
            advance_one = closed_loop_step(plant, ctrl_, ref, dt_, integrator, bound_, cutoff_)
            return flatten(advance_one(unflatten(k, x, key_), sample))

        return step

    # float views of the avals for the flat state (the bool rows are 0 / 1 floats there)
    state_aval = jax.ShapeDtypeStruct((n_state,), dtype)
    model = build(step_of, state_aval, lane_avals, glob_avals, m, dynamic, n_plant)
    per_lane = [x if i < n_plant else jnp.broadcast_to(x, (N, *jnp.shape(x))) for i, x in enumerate(lane_leaves)]
    lanes = tuple(part.T for part in _vmap(lambda *leaves: model.lanes(list(leaves)), tuple(per_lane)))
    one = lambda key: _run_batch(model, begin(key), raw_key, flatten, unflatten, glob_of, lanes, lane_plants, args,
                                 n_steps, save_every, truncate_every)  # fmt: skip
    R = keys.shape[0]
    if R == 1:
        return one(keys[0])
    group = R  # the keys' tables are one where no draw depends on them: one call for all
    if clocked and ctrl.sensors.noise_size():
        row = _size(model.sampled.time_avals) + (0 if model.held is None else _size(model.held.time_avals))
        group = min(R, max(1, TABLE_BYTES // max(1, n_steps * row * np.dtype(dtype).itemsize)))
    result = jax.vmap(one)(keys) if group == R else jax.lax.map(one, keys, batch_size=group if group > 1 else None)
    return jax.tree.map(lambda x: jnp.swapaxes(x, 0, 1).reshape((-1,) + x.shape[2:]), result)


def _run_batch(model: Model, carry, raw_key, flatten, unflatten, glob_of, lanes, lane_plants, args, n_steps: int,
               save_every: int, truncate_every: int):  # fmt: skip
    """:func:`simulate_batch`'s run of one key from the batch's ``carry`` at t = 0: the table, the
    kernel (in blocks of ``save_every`` steps for a trace), the metrics."""
    from . import metrics as _metrics
    from .step import Result, as_trace, snapshot, traced

    _, ctrl, reference, _, dt, _, _, _ = args
    dt = jnp.asarray(dt, model.dtype)
    key = raw_key(carry)
    glob_leaves = glob_of(key)[0]
    x0 = jax.vmap(flatten)(carry).T
    table = _vmap(lambda k: model.table_row(k, glob_leaves), (jnp.arange(n_steps, dtype=jnp.int32),))
    trace = None
    if save_every:
        # (k, x): blocks of steps from step k, their rows of the table sliced at run time (k0 = 0
        # in the kernel: every block starts at a controller sample, save_every being a multiple of m)
        block = lambda c, steps: (
            c[0] + steps,
            advance(model, c[1], lanes, jax.lax.dynamic_slice_in_dim(table, c[0], steps)),
        )
        samples_of = lambda c: jax.vmap(lambda plant, x: snapshot(plant, ctrl, dt, unflatten(c[0], x, key)))(
            lane_plants, c[1].T
        )
        (_, x), samples = traced(samples_of, block, (jnp.zeros((), jnp.int32), x0), n_steps, save_every)
        trace = jax.vmap(lambda *rollout: as_trace(reference, dt, *rollout), 1)(*samples)  # time-major -> rollouts
    else:
        x = advance(model, x0, lanes, table, truncate_every)
    final = jax.vmap(lambda x: unflatten(jnp.asarray(n_steps, jnp.int32), x, key))(x.T)
    metrics = jax.vmap(lambda c: _metrics.masked(_metrics.finish(c.acc, n_steps * dt), c.diverged))(final)
    return Result(metrics, final.diverged, final.diverged_at, trace)
