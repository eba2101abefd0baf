"""The digital loop's controller as dependency-free C99 (libm only), for a drive's firmware.

:func:`export_c` writes one sample of a :class:`fosmc_jax.DigitalLoop` (its sensors' estimator,
its sampled law, its computation delay and its voltage limit) as a header and a source file,
printed from the package's own JAX functions by the kernels' jaxpr printer with a scalar C99
target (:mod:`.c99`): ``<name>_update`` is the jaxpr of :meth:`fosmc_jax.DigitalLoop.update` on
the loop's concrete parameters, whose constants (the law's matrices and gains, the boundary
layers, T, u_max, the encoder's resolution) are folded into the code, ``<name>_init`` that of
:meth:`fosmc_jax.DigitalLoop.init`, ``<name>_reference_at`` that of the reference (the cycloid
(30), the sinusoid, or any reference that prints). At sample j the C does what the package's
loop does (fosmc_jax/_loop/digital.py), in its order of operations:

    Y_j = the measurement (encoder counts -> angles; backward differences, or measured rates)
    U_j = the law's update from Y_j and X_d(t_j) (e.g. (23)), its state advanced
    V_j = clip(U_{j-d}, -u_max, u_max)  (0 for j < d)

Any sampled law exports whose update prints (every primitive it uses known to
:mod:`fosmc_jax._simulator.codegen`); the state struct is the loop's state flattened (the
law's state, the estimator's memory, the delay line, the sample counter). The generated code
has no heap, no globals beyond ``static const`` constants, and keeps time as an integer sample
counter; it compiles with ``-std=c99 -Wall -Wextra -Werror -pedantic`` in float32 and float64
(tests/test_export.py runs it in closed loop with the package's arm and compares it with the
package's own rollout).
"""

from __future__ import annotations

import dataclasses
import os
import re
import shutil
import subprocess
import tempfile
import textwrap
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .._io import __version__, write_text
from .._loop.digital import DigitalLoop
from .._plants.reference import Cycloid, Sinusoid
from .._simulator import codegen
from . import c99

#: The precisions of the generated code's ``real`` type.
PRECISIONS = ("float32", "float64")
#: The flags the generated code is written for (and checked with, where a compiler is found).
STRICT_FLAGS = ("-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic")
#: The phrase for the paper's design model, (29): ``export_c``'s ``model`` for its rows.
PAPER_MODEL = "the paper's nominal model (29)"
#: What each part of the loop's state (fosmc_jax._loop.digital.LoopState) is, for the struct's comments.
_STATE = {
    "law": "the law's state",
    "memory": "the estimator's memory (the last measured angles and rates)",
    "pending": "the delay line: voltages computed, not yet applied, oldest first",
}
#: What a parameter of one of these names is, for the list of the folded constants.
_NOTES = {
    "C": "the sliding surface C of (15)",
    "a_rows": "A_r: rows 3, 6, 9 of A of {model}",
    "b_rows": "B_bar: rows 3, 6, 9 of B of {model}",
    "poles": "the poles of A + BK per joint, placed by K of (16) (1/s)",
    "gamma": "gamma of (23)",
    "delta": "the boundary layers delta of f(s)",
    "counts": "encoder counts per revolution (0: exact angles)",
    "u_max": "the amplifiers' limit (V)",
    "period": "the sample period T (s)",
}
#: The reference struct's rows: the angle (rad) and its first three derivatives.
_ROWS = ("theta", "dtheta", "ddtheta", "dddtheta")


def export_c(
    loop: DigitalLoop,
    reference: Any,
    *,
    precision: str = "float64",
    name: str = "fosmc",
    source: str = "",
    model: str = "",
) -> dict[str, str]:
    """The C99 files of ``loop``'s controller: ``{"<name>.h": text, "<name>.c": text}``.

    ``loop``: a :class:`fosmc_jax.DigitalLoop` (``problem.controller(params)`` of a config with
    ``controller.sample_period`` > 0), with concrete values, around any sampled law whose update
    prints (:class:`fosmc_jax.DiscreteFOSMC`, :class:`fosmc_jax.SMC`,
    :class:`fosmc_jax.SuperTwisting`, a registered kind's); its sensors' noise is the
    simulation's and is not exported. ``reference``: a reference ``t -> (4, 3)``
    (``problem.reference``, e.g. a :class:`fosmc_jax.Cycloid` (30)), exported as
    ``<name>_reference_at``. ``precision``: the C ``real`` type, ``float32`` or ``float64`` (the
    constants are folded in the loop's precision and rounded to it once). ``name``: the prefix
    of every public C identifier and of the files (a C identifier). ``source``: lines for the
    files' head comment (where the constants come from). ``model``: the design model whose rows
    the law holds (its ``a_rows``, ``b_rows``, which K and (CB)^-1 are designed on), in words,
    for the comments: :data:`PAPER_MODEL` for the paper's (29), or e.g. "the design model
    derived from the configured [arm]" (default: "the law's design model", named no further).
    One-line ``ValueError`` for what has no C form (naming the primitive that does not print).
    """
    if precision not in PRECISIONS:
        raise ValueError(f"precision: expected one of {', '.join(PRECISIONS)}, got {precision!r}")
    if not (name.isidentifier() and name.isascii()):
        raise ValueError(f"name: expected a C identifier (letters, digits, _), got {name!r}")
    if not isinstance(loop, DigitalLoop):
        raise ValueError(f"export: expected the digital loop's controller (fosmc_jax.DigitalLoop; a config with "
                         f"controller.sample_period > 0), got {type(loop).__name__}")  # fmt: skip
    if not callable(reference):
        raise ValueError(f"export: the reference must be a function of t giving (4, 3), got {type(reference).__name__}")
    g = _Generator(loop, reference, precision, name, source, model or "the law's design model")
    return {f"{name}.h": g.header(), f"{name}.c": g.source()}


def check_targets(out: str | Path, filenames: Any) -> Path:
    """``out`` as a Path, once it is known that :func:`write` can put ``filenames`` there: a
    one-line ``ValueError`` naming the path where ``out`` or a folder above it exists and is not
    a folder, where a target exists and is not a file, or where the folder that would hold them
    (or create them) is not writable."""
    out = Path(out)
    existing = next((p for p in (out, *out.parents) if p.exists() or p.is_symlink()), None)
    if existing is not None and not existing.is_dir():
        raise ValueError(f"{existing} exists and is not a folder")
    for filename in filenames:
        target = out / filename
        if target.exists() and not target.is_file():
            raise ValueError(f"{target} exists and is not a file")
    if existing is not None and not os.access(existing, os.W_OK | os.X_OK):
        raise ValueError(f"{existing} is not writable")
    return out


def write(files: dict[str, str], out: str | Path) -> list[Path]:
    """Write :func:`export_c`'s files into the folder ``out`` (created; files of the same names
    replaced, each atomically); their paths. Every target is checked first
    (:func:`check_targets`): where one cannot be written, nothing is."""
    out = check_targets(out, files)
    paths = []
    for filename, text in files.items():
        write_text(Path(out) / filename, text)
        paths.append(Path(out) / filename)
    return paths


def c_compiler() -> str | None:
    """The host's C compiler: ``$CC``, else the first of ``cc``, ``gcc``, ``clang`` on the PATH
    (None: none)."""
    for candidate in (os.environ.get("CC"), "cc", "gcc", "clang"):
        if candidate and shutil.which(candidate.split()[0]):
            return candidate
    return None


def check_compiles(source: str | Path, compiler: str | None = None, flags: tuple[str, ...] = STRICT_FLAGS) -> str:
    """Compile ``source`` (a generated ``.c``, its header beside it) to an object file with
    ``flags`` (default: :data:`STRICT_FLAGS`), to check it; returns the command that passed.
    ``RuntimeError`` with the compiler's first message where it fails, or where no compiler
    is found."""
    compiler = compiler or c_compiler()
    if compiler is None:
        raise RuntimeError("no C compiler found ($CC, cc, gcc, clang)")
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [*compiler.split(), *flags, "-c", str(source), "-o", str(Path(tmp) / "check.o")]
        done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode:
        lines = done.stderr.strip().splitlines()
        first = next((line for line in lines if "error" in line), lines[0] if lines else "(no message)")
        raise RuntimeError(f"{' '.join(cmd[:-2])} failed: {first}")
    return " ".join([*compiler.split(), *flags, "-c", Path(source).name])


# ---------------------------------------------------------------------------- the generator


def _np(x) -> np.ndarray:
    return np.asarray(jax.device_get(x), dtype=np.float64)


def _key(entry) -> str:
    for attr in ("name", "key", "idx"):
        if hasattr(entry, attr):
            return str(getattr(entry, attr))
    return str(entry)


def _dotted(path) -> str:
    return ".".join(_key(entry) for entry in path)


class _Field:
    """One leaf of the loop's state in the C struct: its member ``cname``, what it is, its shape
    and its C type."""

    def __init__(self, path, aval, real: str):
        self.dotted = _dotted(path)
        self.cname = re.sub(r"\W", "_", self.dotted.replace(".", "_"))
        self.shape, self.dtype = tuple(aval.shape), aval.dtype
        if jnp.issubdtype(aval.dtype, jnp.floating):
            self.ctype = real
        elif self.dotted == "j":
            self.ctype = "uint32_t"
        else:
            self.ctype = "int" if aval.dtype == jnp.bool_ else "int32_t"

    def size(self) -> int:
        return int(np.prod(self.shape, dtype=int))

    def lvalues(self, at: str = "st->") -> list[str]:
        """The C lvalues of its elements, row-major."""
        return [at + self.cname + "".join(f"[{i}]" for i in np.unravel_index(k, self.shape)) if self.shape
                else at + self.cname for k in range(self.size())]  # fmt: skip

    def declaration(self) -> str:
        dims = "".join(f"[{n}]" for n in self.shape)
        part = self.dotted.split(".")[0]
        what = {"j": "the sample counter: the coming sample is at t_j = j T"}.get(part) or _STATE.get(part, "")
        return f"    {self.ctype} {self.cname}{dims}; /* {self.dotted}{': ' + what if what else ''} */"


class _Generator:
    """The text of both files for one loop (see :func:`export_c`)."""

    def __init__(self, loop: DigitalLoop, reference, precision: str, name: str, source: str, model: str):
        self.noise = loop.sensors.noise_std is not None
        loop = dataclasses.replace(loop, sensors=dataclasses.replace(loop.sensors, noise_std=None))
        self.loop, self.reference, self.name, self.origin, self.model = loop, reference, name, source, model
        self.f32 = precision == "float32"
        self.precision = precision
        self.P, self.M = name, name.upper()
        self.real = f"{name}_real"
        self.target = c99.C99(self.real, self.f32)
        # The sample step and its state in double in float32 too: the loop's estimator differences
        # the measured angles twice, and float's resolution at 1 rad (6e-8 rad) over T^2 = 1e-6 s^2
        # would move the voltages by volts (docs/firmware.md, "Precision").
        self.work = "double" if self.f32 else self.real
        self.step = c99.C99(self.work, False)
        self.counts = _np(loop.sensors.counts)
        self.difference = loop.sensors.derivatives == "difference"
        self.encoder = bool(np.all(self.counts > 0))  # counts in: every joint has an encoder
        self.u_max = _np(loop.u_max)
        self.T = float(_np(loop.period))
        self.delay = int(loop.delay)
        self.input_name = ("counts" if self.encoder else "theta") if self.difference else "measurement"
        self.dtype = jnp.result_type(loop.period)  # the loop's float: its constants are folded in it
        self.printed = self._print()

    # ------------------------------------------------------------------------ printing

    def lit(self, x: float) -> str:
        """``x`` as a C literal of the real type: the shortest decimal that rounds back to it."""
        return self.target.literal(float(x))

    def _print(self) -> dict[str, list[str]]:
        """The bodies of the printed functions, by function."""
        loop, reference, dtype = self.loop, self.reference, self.dtype
        scalar = jax.ShapeDtypeStruct((), dtype)
        try:
            r_aval = jax.eval_shape(reference, scalar)
        except Exception as e:  # a reference JAX cannot trace
            raise ValueError(f"export: the reference does not trace as a function of t: {e}".splitlines()[0]) from None
        if getattr(r_aval, "shape", None) != (4, 3):
            raise ValueError(f"export: the reference must give (4, 3) (the angle and 3 derivatives per joint), got "
                             f"{getattr(r_aval, 'shape', type(r_aval).__name__)}")  # fmt: skip
        x_aval = jax.ShapeDtypeStruct((9,), dtype)
        # the key feeds the sensors' noise alone, which is not exported: a constant here
        key = jax.random.key_data(jax.random.key(0))
        start = lambda X0: loop.init(X0, reference(jnp.zeros((), dtype)), key)  # noqa: E731
        state = jax.eval_shape(start, x_aval)
        paths, self.treedef = jax.tree_util.tree_flatten_with_path(state._replace(key=None))
        self.fields = [_Field(path, aval, self.work) for path, aval in paths]
        leaf_avals = [aval for _, aval in paths]

        def init(X0):
            return jax.tree.leaves(start(X0)._replace(key=None)), X0

        def update(leaves, X, r, t):
            U, state = loop.update(self.treedef.unflatten(leaves)._replace(key=key), X, r, t)
            return U, jax.tree.leaves(state._replace(key=None))

        st = [f.lvalues() for f in self.fields]
        x0 = [f"st->x0[{k}]" for k in range(9)] if self.difference else None
        if self.input_name == "measurement":
            X = [f"measurement[{k}]" for k in range(9)]
        else:  # the angles read now; the rates are those of the initial state, which the first sample reads
            X = [f"theta[{k // 3}]" if k % 3 == 0 else f"st->x0[{k}]" for k in range(9)]
        r = [f"r->{_ROWS[k // 3]}[{k % 3}]" for k in range(12)]
        t = f"(({self.work})st->j * {self.step.literal(self.T)})"
        law = type(loop.law).__name__
        bodies = {}
        try:
            what = f"the sample step of {law} (DigitalLoop.update)"
            bodies["update"] = self._statements(jax.make_jaxpr(update)(leaf_avals, x_aval, r_aval, scalar),
                                                [*st, X, r, [t]], [[f"u[{i}]" for i in range(3)], *st],
                                                self.step)  # fmt: skip
            what = f"the initial state of {law} (DigitalLoop.init)"
            bodies["init"] = self._statements(jax.make_jaxpr(init)(x_aval), [[f"x0[{k}]" for k in range(9)]],
                                              [*st, x0], self.step)  # fmt: skip
            what = f"the reference {type(reference).__name__}"
            bodies["reference_at"] = self._statements(jax.make_jaxpr(reference)(scalar), [["t"]], [r])
            vec = jax.ShapeDtypeStruct((3,), dtype)
            what = "the cycloid (30)"
            cycloid = jax.make_jaxpr(lambda a, b, tau, t: Cycloid(a, b, tau)(t))(vec, vec, scalar, scalar)
            bodies["cycloid"] = self._statements(
                cycloid, [[f"p->{f}[{i}]" for i in range(3)] for f in ("start", "end")] + [["p->duration"], ["t"]], [r]
            )
            what = "the sinusoid"
            sinusoid = jax.make_jaxpr(lambda *a: Sinusoid(*a[:4])(a[4]))(vec, vec, vec, vec, scalar)
            fields = ("offset", "amplitude", "frequency", "phase")
            bodies["sinusoid"] = self._statements(
                sinusoid, [[f"p->{f}[{i}]" for i in range(3)] for f in fields] + [["t"]], [r]
            )
        except codegen.Unsupported as e:
            raise ValueError(f"export: {what} does not print as C: {e}") from None
        return bodies

    def _statements(self, closed, inputs, outputs, target: c99.C99 | None = None) -> list[str]:
        return ["    " + line for line in c99.statements(closed, inputs, outputs, target or self.target)]

    # ------------------------------------------------------------------------ header

    def describe(self) -> list[str]:
        """What the files hold, for both head comments."""
        P, law = self.P, self.loop.law
        listed = ", ".join(str(int(c)) for c in self.counts)
        if self.encoder:
            sensors = f"encoders of {listed} counts per revolution (counts in)"
        elif np.any(self.counts > 0):
            sensors = f"angles in, quantized by the drive's encoders ({listed} counts per revolution; 0: exact)"
        else:
            sensors = "angles in (no encoder modelled: exact angles)"
        rates = ("theta' and theta'' from backward differences of the angles (the estimator)" if self.difference
                 else "theta' and theta'' measured and passed in")  # fmt: skip
        limited = bool(np.any(np.isfinite(self.u_max)))
        limit = ("no voltage limit" if not limited
                 else f"voltages clipped to +-[{', '.join(f'{u:g}' for u in self.u_max)}] V")  # fmt: skip
        statics = [f"{f.name} '{getattr(law, f.name)}'" for f in dataclasses.fields(law)
                   if isinstance(getattr(law, f.name), str)] if dataclasses.is_dataclass(law) else []  # fmt: skip
        cls = type(law)
        where = "fosmc_jax" if cls.__module__.startswith("fosmc_jax.") else cls.__module__  # the public name
        kind = f"{where}.{cls.__qualname__}" + (f" ({', '.join(statics)})" if statics else "")
        design = f"  designed on {self.model} (A_r, B_bar: its rows 3, 6, 9 of A, B),"
        lines = [
            *textwrap.wrap(f"The sampled law {kind} in the digital loop of fosmc_jax (fosmc_jax.DigitalLoop), printed "
                           "from their JAX functions (fosmc_jax/_loop/digital.py and the law's file):", 96),
            *textwrap.wrap(design, 96, subsequent_indent="    "),
            f"  sample period T = {self.T:g} s ({1 / self.T:g} Hz), computation delay d = {self.delay} sample(s),",
            f"  {sensors},",
            f"  {rates},",
            f"  {limit}.",
            f"At sample j (t_j = j T): {P}_update reads the measurement Y_j and the reference sample X_d(t_j),",
            f"computes U_j and returns the voltages to apply now, U_{{j-d}}{' clipped' if limited else ''} (0 V while "
            "j < d), held until sample j + 1.",
        ]  # fmt: skip
        if self.noise:
            lines.append("(The config's sensors.noise_std models the sensors in simulation: nothing of it is here.)")
        return lines

    def _header_head(self) -> list[str]:
        """The lines of the header's head comment: where it comes from, the loop, how to call it."""
        P, r = self.P, self.real
        return [
            f"{P}.h: generated by fosmc_jax {__version__} (`fosmc export`, {self.precision}). Do not edit: "
            "export again.",
            *_lines(self.origin),
            "",
            *self.describe(),
            "",
            "Dependency-free C99 (libm only): no heap, no globals beyond the constants in " + f"{P}.c.",
            "Use, once per sample (e.g. in the sampling interrupt):",
            *_aligned(
                (f"static {P}_state st;", f"{P}_init(&st, x0) once, before the first sample"),
                (f"{P}_reference r;", ""),
                (f"{r} u[3];", ""),
                (f"{P}_reference_at(st.j, &r);", "the reference sample at t_j = j T"),
                (f"{P}_update(&st, {self.input_name}, &r, u);", "u: the voltages to apply now"),
            ),
        ]

    def header(self) -> str:
        """``<name>.h``: its head comment, the types and the state, then the functions' prototypes."""
        P, M, r = self.P, self.M, self.real
        head = self._header_head()
        out = ["/*", *[(" * " + line).rstrip() for line in head], " */", f"#ifndef {M}_H", f"#define {M}_H", ""]
        out += ["#include <stdint.h>", ""]
        out += [f"/* The real type of the export ({self.precision}). */",
                f"typedef {'float' if self.f32 else 'double'} {r};", ""]  # fmt: skip
        out += [
            f"#define {M}_SAMPLE_PERIOD {self.lit(self.T)} /* T (s) */",
            f"#define {M}_SAMPLE_RATE {self.lit(1 / self.T)} /* 1 / T (Hz) */",
            f"#define {M}_DELAY_SAMPLES {self.delay} /* d: the computation delay (samples) */",
            "",
            "/* A reference sample X_d(t) per joint: the angle (rad) and its first three derivatives (rad/s,",
            " * rad/s^2, rad/s^3); fosmc_jax's reference(t), rows 0-3. */",
            "typedef struct {",
            f"    {r} theta[3], dtheta[3], ddtheta[3], dddtheta[3];",
            f"}} {P}_reference;",
            "",
            f"/* The controller's state: what {P}_update remembers from one sample to the next, the loop's",
            " * state of fosmc_jax (fosmc_jax._loop.digital.LoopState) flattened, each member named by its path"
            + (" (double in float32 too: the estimator differences its angles). */" if self.f32 else "). */"),
            "typedef struct {",
        ]
        counter = [f for f in self.fields if f.dotted == "j"]
        out += [f.declaration() for f in counter + [f for f in self.fields if f.dotted != "j"] if f.size()]
        if self.difference:
            out.append(f"    {self.work} x0[9]; /* the initial state, whose rates the first sample reads (the "
                       "estimator starts from the exact state) */")  # fmt: skip
        out += [f"}} {P}_state;", ""]
        out += [
            "/* The cycloid (30): from start to end (rad) in duration (s), at rest before and after. */",
            "typedef struct {",
            f"    {r} start[3], end[3], duration;",
            f"}} {P}_cycloid_params;",
            "",
            "/* The sinusoid theta_d = offset + amplitude sin(frequency t + phase) (rad, rad, rad/s, rad). */",
            "typedef struct {",
            f"    {r} offset[3], amplitude[3], frequency[3], phase[3];",
            f"}} {P}_sinusoid_params;",
            "",
            "/* Start: x0 is the state at the first sample, [theta_1, theta_1', theta_1'', theta_2, ..., theta_3'']",
            " * (rad, rad/s, rad/s^2; at rest: the angles and zeros). The counter starts at 0. */",
            f"void {P}_init({P}_state *st, const {r} x0[9]);",
            "",
        ]
        out += self._update_prototype()
        if self.encoder:
            out += [
                "",
                "/* The angles (rad) of encoder counts: theta_i = counts_i 2 pi / counts per revolution. */",
                f"void {P}_angles(const int32_t counts[3], {r} theta[3]);",
            ]
        out += [
            "",
            "/* The reference sample at t_j = j T of the exported trajectory (the config's). */",
            f"void {P}_reference_at(uint32_t j, {P}_reference *r);",
            "/* The cycloid (30) and the sinusoid at t_j = j T, for other moves. */",
            f"void {P}_cycloid(const {P}_cycloid_params *p, uint32_t j, {P}_reference *r);",
            f"void {P}_sinusoid(const {P}_sinusoid_params *p, uint32_t j, {P}_reference *r);",
            "",
            f"#endif /* {M}_H */",
            "",
        ]
        return "\n".join(out)

    def _update_prototype(self) -> list[str]:
        """``<name>_update``'s prototype and comment: its input the encoder counts, the angles, or
        the whole measurement, as the loop reads them."""
        P, r = self.P, self.real
        if self.difference and self.encoder:
            return [
                "/* One sample: counts[i] the encoder of joint i now (angle = counts * 2 pi / counts per revolution,",
                " * 0 at the model's zero angle), r the reference sample X_d(t_j); u receives the voltages (V). */",
                f"void {P}_update({P}_state *st, const int32_t counts[3], const {P}_reference *r, {r} u[3]);",
            ]
        if self.difference:
            return [
                "/* One sample: theta the measured angles now (rad), r the reference sample X_d(t_j); u receives the",
                " * voltages (V). */",
                f"void {P}_update({P}_state *st, const {r} theta[3], const {P}_reference *r, {r} u[3]);",
            ]
        return [
            "/* One sample: measurement = [theta_1, theta_1', theta_1'', theta_2, ...] (rad, rad/s,",
            " * rad/s^2; the angles as the encoders give them), r the reference sample X_d(t_j); u receives",
            " * the voltages (V). */",
            f"void {P}_update({P}_state *st, const {r} measurement[9], const {P}_reference *r, {r} u[3]);",
        ]

    # ------------------------------------------------------------------------ source

    def parameters(self) -> list[str]:
        """The loop's and the reference's parameters, as folded into the code, for the head comment."""
        out = [f"The parameters folded into the code below (rounded to {self.precision}), by their names in",
               "fosmc_jax (the loop's fields, the reference's):"]  # fmt: skip
        for prefix, tree in (("loop", self.loop), ("reference", self.reference)):
            for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]:
                if not jnp.issubdtype(jnp.result_type(leaf), jnp.number):
                    continue
                values = np.asarray(jax.device_get(leaf))
                note = _NOTES.get(_key(path[-1]), "").format(model=self.model) if path else ""
                shape = f"({', '.join(map(str, values.shape))}{',' if values.ndim == 1 else ''})"
                out.append(f"  {prefix}.{_dotted(path)} {shape}" + (f", {note}" if note else "") + ":")
                items = [self.lit(v).removesuffix("f") for v in np.ravel(values.astype(np.float64))]
                out += _wrap(items, "    ", "    ", width=96)
        return out

    def function(self, signature: str, body: list[str], params: tuple[str, ...], before: list[str] = ()) -> list[str]:
        text = "\n".join([*before, *body])
        unused = [f"    (void){p};" for p in params if not re.search(rf"\b{p}\b", text)]
        return [signature, "{", *unused, *before, *body, "}", ""]

    def source(self) -> str:
        P, M, r = self.P, self.M, self.real
        head = [f"{P}.c: generated by fosmc_jax {__version__} (`fosmc export`, {self.precision}). Do not edit: "
                "export again.", *_lines(self.origin), "", *self.describe(), "", *self.parameters(), "",
                "Equation numbers: the paper's (docs/paper.md of fosmc_jax)."]  # fmt: skip
        out = ["/*", *[(" * " + line).rstrip() for line in head], " */", f'#include "{P}.h"', "",
               "#include <math.h>", ""]  # fmt: skip
        bodies = self.printed
        text = lambda *names: "\n".join(line for name in names for line in bodies[name])  # noqa: E731
        references = ("reference_at", "cycloid", "sinusoid")
        if self.f32:  # the sample step's helpers in double, the references' in float
            helpers = c99.prelude(text("update", "init"), self.work, False) + c99.prelude(text(*references), r, True)
        else:
            helpers = c99.prelude(text("update", "init", *references), r, False)
        if self.encoder or helpers:
            out += ["/* ---------------------------------------------------------------- helpers */", ""]
        if self.encoder:
            listed = ", ".join(str(int(c)) for c in self.counts)
            out += _comment(f"The encoders' resolution q = 2 pi / counts per revolution (rad per count; {listed} "
                            "counts).")  # fmt: skip
            out += [f"static const {r} RAD_PER_COUNT[3] = {{",
                    *_wrap([self.lit(2 * np.pi / c) for c in self.counts], "    ", "    "), "};", ""]  # fmt: skip
        out += helpers
        law = type(self.loop.law).__name__
        out += ["/* ---------------------------------------------------------------- the controller */", ""]
        out += _comment(f"DigitalLoop.init: the estimator's memory and {law}'s state from x0 and the reference at "
                        "t = 0, the counter at 0.")  # fmt: skip
        out += self.function(f"void {P}_init({P}_state *st, const {r} x0[9])", bodies["init"], ("x0",))
        if self.encoder:
            out += [f"void {P}_angles(const int32_t counts[3], {r} theta[3])", "{", "    int i;",
                    "    for (i = 0; i < 3; i++)", f"        theta[i] = ({r})counts[i] * RAD_PER_COUNT[i];", "}",
                    ""]  # fmt: skip
        arg = {"counts": "const int32_t counts[3]", "theta": f"const {r} theta[3]",
               "measurement": f"const {r} measurement[9]"}[self.input_name]  # fmt: skip
        before = [f"    {r} theta[3];", f"    {P}_angles(counts, theta);"] if self.input_name == "counts" else []
        out += _comment(f"DigitalLoop.update: measure, {law}.update, delay, clip (the module's head comment), one "
                        "statement per operation of the JAX model, in its order; t_j = j T.")  # fmt: skip
        out += self.function(f"void {P}_update({P}_state *st, {arg}, const {P}_reference *r, {r} u[3])",
                             bodies["update"], (self.input_name, "r"), before)  # fmt: skip
        out += ["/* ---------------------------------------------------------------- references */", ""]
        t = [f"    const {r} t = ({r})j * {M}_SAMPLE_PERIOD;"]
        out += _comment(f"The exported trajectory ({type(self.reference).__name__}) at t_j = j T.")
        out += self.function(f"void {P}_reference_at(uint32_t j, {P}_reference *r)", bodies["reference_at"], ("j",), t)
        out += _comment("(30): theta_d = start + Delta / (2 pi) (w t - sin(w t)), w = 2 pi / tau, Delta = end - "
                        "start, for 0 <= t < tau; end afterwards (theta_d''' jumps at 0 and tau).")  # fmt: skip
        out += self.function(f"void {P}_cycloid(const {P}_cycloid_params *p, uint32_t j, {P}_reference *r)",
                             bodies["cycloid"], ("p", "j"), t)  # fmt: skip
        out += ["/* theta_d = offset + amplitude sin(frequency t + phase) and its derivatives. */"]
        out += self.function(f"void {P}_sinusoid(const {P}_sinusoid_params *p, uint32_t j, {P}_reference *r)",
                             bodies["sinusoid"], ("p", "j"), t)  # fmt: skip
        return "\n".join(out)


def _lines(text: str) -> list[str]:
    """``text``'s lines wrapped at 96 columns (a long one continued indented by 2) between words,
    never inside one (a path stays whole)."""
    wrap = lambda line: textwrap.wrap(line, 96, subsequent_indent="  ", break_long_words=False, break_on_hyphens=False)
    return [part for line in text.splitlines() for part in wrap(line) or [""]]


def _comment(text: str, indent: int = 0) -> list[str]:
    """``text`` as a C comment indented by ``indent``, wrapped at 100 columns."""
    pad = " " * indent
    lines = textwrap.wrap(text, 96 - indent)
    if len(lines) == 1:
        return [f"{pad}/* {lines[0]} */"]
    return [f"{pad}/* " + lines[0], *[f"{pad} * " + line for line in lines[1:-1]], f"{pad} * " + lines[-1] + " */"]


def _wrap(entries: list[str], first: str, rest: str, width: int = 100) -> list[str]:
    """``entries`` joined by ", " into lines of at most ``width`` columns (``first``, then
    ``rest``, as indentation)."""
    lines, line = [], first
    for k, entry in enumerate(entries):
        piece = entry + ("," if k + 1 < len(entries) and not entry.endswith(",") else "")
        if line.strip() and len(line) + 1 + len(piece) > width:
            lines.append(line.rstrip())
            line = rest
        line += ("" if not line.strip() else " ") + piece
    return [*lines, line.rstrip()]


def _aligned(*rows: tuple[str, str]) -> list[str]:
    """Code lines (indented 4) with their ``//`` comments in one column."""
    width = max(len(code) for code, _ in rows) + 2
    return [("    " + code.ljust(width) + (f"// {note}" if note else "")).rstrip() for code, note in rows]
