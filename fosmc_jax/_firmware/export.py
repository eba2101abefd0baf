"""The digital loop's controller as dependency-free C99 (libm only), for a drive's firmware.

:func:`export_c` writes the sampled law of a :class:`fosmc_jax.DigitalLoop` (the FOSMC's
:class:`fosmc_jax.DiscreteFOSMC`, :class:`fosmc_jax.SMC` or :class:`fosmc_jax.SuperTwisting`)
with its sensors' estimator, its computation delay and its voltage limit as a header and a
source file: the constants of the loop as it was simulated (the law's matrices and gains, the
boundary layers, T, d, u_max, the encoder's resolution), a state struct (the integral, the
estimator's memory, the delay line, the sample counter), ``<name>_init`` from the initial
state, ``<name>_update`` from one sample's measurement and reference sample to the applied
voltages, and the reference generators (the cycloid (30), the sinusoid). At sample j the C does
what :meth:`fosmc_jax.DigitalLoop.update` does (fosmc_jax/_loop/digital.py):

    Y_j = the measurement (encoder counts -> angles; backward differences, or measured rates)
    U_j = the law (23) / SMC / super-twisting from Y_j and X_d(t_j), its state advanced
    V_j = clip(U_{j-d}, -u_max, u_max)  (0 for j < d)

with the constants the package derived for the simulation (:func:`fosmc_jax._controllers.fosmc.derive`),
not re-derived here. The generated code has no heap, no globals beyond ``static const``
constants, and keeps time as an integer sample counter; it compiles with ``-std=c99 -Wall
-Wextra -Werror -pedantic`` in float32 and float64 (tests/test_export.py runs it in closed loop
with the package's arm and compares it with the package's own rollout).
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import tempfile
import textwrap
from pathlib import Path
from typing import Any

import jax
import numpy as np

from .._controllers.fosmc import DiscreteFOSMC, derive
from .._controllers.smc import SMC
from .._controllers.super_twisting import SuperTwisting
from .._design.gains import input_matrix_product
from .._io import __version__, write_text
from .._loop.digital import DigitalLoop
from .._plants.reference import Cycloid, Sinusoid

#: The precisions of the generated code's ``real`` type.
PRECISIONS = ("float32", "float64")
#: The flags the generated code is written for (and checked with, where a compiler is found).
STRICT_FLAGS = ("-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic")

_KIND_OF = {DiscreteFOSMC: "fosmc", SMC: "smc", SuperTwisting: "super_twisting"}
#: The controller kinds (``[controller] kind``) whose sampled law has a C form.
EXPORTED_KINDS = tuple(_KIND_OF.values())
_LONG_NAME = {
    "fosmc": "full-order sliding mode (FOSMC) tracking controller",
    "smc": "conventional sliding mode controller (boundary layer)",
    "super_twisting": "super-twisting controller",
}
#: The phrase for the paper's design model, (29): ``export_c``'s ``model`` for its rows.
PAPER_MODEL = "the paper's nominal model (29)"
_SWITCHING = {"sign": "SGN(s)", "ratio": "s / (|s| + delta), (28)", "sat": "clip(s / delta, -1, 1)",
              "tanh": "tanh(s / delta)"}  # fmt: skip


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

    ``loop``: a :class:`fosmc_jax.DigitalLoop` around a :class:`fosmc_jax.DiscreteFOSMC`,
    :class:`fosmc_jax.SMC` or :class:`fosmc_jax.SuperTwisting` (``problem.controller(params)``
    of a config with ``controller.sample_period`` > 0), with concrete values; ``reference``:
    its :class:`fosmc_jax.Cycloid` (30) or :class:`fosmc_jax.Sinusoid` (``problem.reference``),
    exported as ``<name>_reference_at``. ``precision``: the C ``real`` type, ``float32`` or
    ``float64`` (the constants are the loop's values rounded to it). ``name``: the prefix of
    every public C identifier and of the files (a C identifier). ``source``: lines for the
    files' head comment (where the constants come from). ``model``: the design model whose
    rows the law holds (its ``a_rows``, ``b_rows``, which K and (CB)^-1 are designed on), in
    words, for the comments: :data:`PAPER_MODEL` for the paper's (29), or e.g. "the design
    model derived from the configured [arm]" (default: "the law's design model", named no
    further). One-line ``ValueError`` for what has no C form.
    """
    if precision not in PRECISIONS:
        raise ValueError(f"precision: expected one of {', '.join(PRECISIONS)}, got {precision!r}")
    if not (name.isidentifier() and name.isascii()):
        raise ValueError(f"name: expected a C identifier (letters, digits, _), got {name!r}")
    if not isinstance(loop, DigitalLoop):
        raise ValueError(f"export: expected the digital loop's controller (fosmc_jax.DigitalLoop; a config with "
                         f"controller.sample_period > 0), got {type(loop).__name__}")  # fmt: skip
    kind = _KIND_OF.get(type(loop.law))
    if kind is None:
        raise ValueError(f"export: the law {type(loop.law).__name__} has no C form (exported: "
                         f"{', '.join(k.__name__ for k in _KIND_OF)})")  # fmt: skip
    if not isinstance(reference, (Cycloid, Sinusoid)):
        raise ValueError(f"export: the reference must be a Cycloid or a Sinusoid, got {type(reference).__name__}")
    g = _Generator(loop, reference, kind, precision, name, source, model or "the law's design model")
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


class _Generator:
    """The text of both files for one loop (see :func:`export_c`)."""

    def __init__(self, loop: DigitalLoop, reference, kind: str, precision: str, name: str, source: str, model: str):
        self.loop, self.reference, self.kind, self.name, self.origin = loop, reference, kind, name, source
        self.model = model
        self.f32 = precision == "float32"
        self.precision = precision
        self.P, self.M = name, name.upper()
        law = loop.law
        self.counts = _np(loop.sensors.counts)
        self.difference = loop.sensors.derivatives == "difference"
        self.encoder = bool(np.all(self.counts > 0))  # counts in: every joint has an encoder
        self.u_max = _np(loop.u_max)
        self.T = float(_np(loop.period))
        self.delay = int(loop.delay)
        surface = law.params if kind == "fosmc" else law.surface
        self.C, self.a_rows, self.b_rows = _np(surface.C), _np(surface.a_rows), _np(surface.b_rows)
        if kind == "fosmc":
            d = derive(law.params)
            self.K, self.CB_inv, self.S = _np(d.K), _np(d.CB_inv), _np(d.S)
            self.gamma, self.delta, self.poles = _np(law.params.gamma), _np(law.params.delta), _np(law.params.poles)
            self.switching, self.law_form = law.switching, law.law
        else:
            self.CB_inv = np.linalg.inv(_np(input_matrix_product(surface.C, surface.b_rows)))
            self.switching = None
        if kind == "smc":
            self.k, self.phi = _np(law.k), _np(law.phi)
        if kind == "super_twisting":
            self.k1, self.k2 = _np(law.k1), _np(law.k2)
        self.B_inv = np.linalg.inv(self.b_rows)
        self.input_name = ("counts" if self.encoder else "theta") if self.difference else "measurement"

    # ------------------------------------------------------------------------ literals

    def lit(self, x: float) -> str:
        """``x`` as a C literal of the real type: the shortest decimal that rounds back to it."""
        x = float(x)
        if np.isinf(x):
            return "INFINITY" if x > 0 else "-INFINITY"
        text = str(np.float32(x)) if self.f32 else repr(x)
        if "e" not in text and "." not in text:
            text += ".0"
        return text + ("f" if self.f32 else "")

    def fn(self, libm: str) -> str:
        """libm's function of the real type (``sqrtf`` for float32)."""
        return libm + ("f" if self.f32 else "")

    def array(self, cname: str, values: np.ndarray, comment: str) -> list[str]:
        values = np.asarray(values)
        dims = "".join(f"[{n}]" for n in values.shape)
        if values.ndim == 1:
            body = _wrap([self.lit(v) for v in values], "    ", "    ")
        else:
            body = []
            for i, row in enumerate(values):
                entries = [self.lit(v) for v in row]
                entries[0], entries[-1] = "{" + entries[0], entries[-1] + ("}," if i + 1 < len(values) else "}")
                body += _wrap(entries, "    ", "     ")
        return [*_comment(comment), f"static const {self.P}_real {cname}{dims} = {{", *body, "};", ""]

    # ------------------------------------------------------------------------ header

    def describe(self) -> list[str]:
        """What the files hold, for both head comments."""
        P = self.P
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
        law = f"The {_LONG_NAME[self.kind]}"
        if self.kind == "fosmc":
            law += f" (switching f(s) = {_SWITCHING[self.switching]}; law '{self.law_form}' (23))"
        design = f"  designed on {self.model} (A_r, B_bar: its rows 3, 6, 9 of A, B),"
        lines = [
            *textwrap.wrap(law + ", as the digital loop of fosmc_jax (fosmc_jax.DigitalLoop) runs it:", 96),
            *textwrap.wrap(design, 96, subsequent_indent="    "),
            f"  sample period T = {self.T:g} s ({1 / self.T:g} Hz), computation delay d = {self.delay} sample(s),",
            f"  {sensors},",
            f"  {rates},",
            f"  {limit}.",
            f"At sample j (t_j = j T): {P}_update reads the measurement Y_j and the reference sample X_d(t_j),",
            f"computes U_j and returns the voltages to apply now, U_{{j-d}}{' clipped' if limited else ''} (0 V while "
            "j < d), held until sample j + 1.",
        ]
        if self.loop.sensors.noise_std is not None:
            lines.append("(The config's sensors.noise_std models the sensors in simulation: nothing of it is here.)")
        return lines

    def header(self) -> str:
        P, M, r = self.P, self.M, f"{self.P}_real"
        head = [
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
            f"/* The controller's state: what {P}_update remembers from one sample to the next. */",
            "typedef struct {",
            "    uint32_t j; /* the sample counter: the coming sample is at t_j = j T */",
        ]
        if self.kind == "fosmc":
            out.append(f"    {r} w[3]; /* the integral w of (14), summed: w_(j+1) = w_j + T (CA + CBK) Z_j */")
        if self.kind == "super_twisting":
            out.append(f"    {r} v[3]; /* the integral term v, summed: v_(j+1) = v_j - T k2 sign(s_j) */")
        if self.difference:
            if self.encoder:
                out.append("    int32_t counts[3]; /* the estimator's memory: the last counts, */")
            else:
                out.append(f"    {r} theta[3]; /* the estimator's memory: the last angles (rad), */")
            out.append(f"    {r} dtheta[3]; /* the last rates (rad/s) */")
            out.append(f"    {r} ddtheta[3]; /* and accelerations (rad/s^2); after init: the initial state's */")
        if self.delay:
            out.append(f"    {r} pending[{M}_DELAY_SAMPLES][3]; /* the delay line: voltages computed, not yet "
                       "applied, oldest first */")  # fmt: skip
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
        if self.difference and self.encoder:
            out += [
                "/* One sample: counts[i] the encoder of joint i now (angle = counts * 2 pi / counts per revolution,",
                " * 0 at the model's zero angle), r the reference sample X_d(t_j); u receives the voltages (V). */",
                f"void {P}_update({P}_state *st, const int32_t counts[3], const {P}_reference *r, {r} u[3]);",
            ]
        elif self.difference:
            out += [
                "/* One sample: theta the measured angles now (rad), r the reference sample X_d(t_j); u receives the",
                " * voltages (V). */",
                f"void {P}_update({P}_state *st, const {r} theta[3], const {P}_reference *r, {r} u[3]);",
            ]
        else:
            out += [
                "/* One sample: measurement = [theta_1, theta_1', theta_1'', theta_2, ...] (rad, rad/s,",
                " * rad/s^2; the angles as the encoders give them), r the reference sample X_d(t_j); u receives",
                " * the voltages (V). */",
                f"void {P}_update({P}_state *st, const {r} measurement[9], const {P}_reference *r, {r} u[3]);",
            ]
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

    # ------------------------------------------------------------------------ source

    def constants(self) -> list[str]:
        out = []
        if self.kind == "fosmc":
            out += self.array("C_SURFACE", self.C, "The sliding surface C of (15); columns [theta_1, theta_1', "
                              "theta_1'', theta_2, ...], as every 9-vector here.")  # fmt: skip
            out += self.array("CA_PLUS_CBK", self.S, "CA + CBK = C (A + BK): the integrand of w in (14), with K "
                              "of (16) placing the poles below.")  # fmt: skip
            if self.law_form == "equivalent":
                out += self.array("K_GAIN", self.K, "K of (16): the nominal equivalent control K Z of the law "
                                  "'equivalent'.")  # fmt: skip
            out += self.array("CB_INV", self.CB_inv, "(CB)^-1 of (23).")
            out += self.array("GAMMA", self.gamma, "gamma of (23): rho = gamma_1 ||Z|| + gamma_2 ||X_d|| + "
                              "gamma_3 ||Omega||.")  # fmt: skip
            if self.switching != "sign":
                out += self.array("DELTA", self.delta, f"delta: the boundary layers of f(s) = "
                                  f"{_SWITCHING[self.switching]}.")  # fmt: skip
        else:
            out += self.array("C_SURFACE", self.C, "The sliding surface s = C Z; columns [theta_1, theta_1', "
                              "theta_1'', theta_2, ...], as every 9-vector here.")  # fmt: skip
            out += self.array("CB_INV", self.CB_inv, f"(CB)^-1, B the input rows of {self.model}.")
        out += self.array("A_R", self.a_rows, f"A_r: rows 3, 6, 9 of A of {self.model}.")
        if self.kind == "fosmc":
            out += self.array("B_BAR_INV", self.B_inv, f"B_bar^-1: the inverse of rows 3, 6, 9 of B of {self.model}.")
        if self.kind == "smc":
            out += self.array("K_SWITCH", self.k, "k: the switching gains (V-scaled).")
            out += self.array("PHI", self.phi, "phi: the boundary-layer widths of sat(s / phi).")
        if self.kind == "super_twisting":
            out += self.array("K1", self.k1, "k1: the gains of |s|^(1/2) sign(s).")
            out += self.array("K2", self.k2, "k2: the gains of the integral term, v' = -k2 sign(s).")
        if self.encoder:
            listed = ", ".join(str(int(c)) for c in self.counts)
            out += self.array("RAD_PER_COUNT", 2 * np.pi / self.counts, "The encoders' resolution q = 2 pi / counts "
                              f"per revolution (rad per count; {listed} counts).")  # fmt: skip
        if np.any(np.isfinite(self.u_max)):
            out += self.array("U_MAX", self.u_max, "The amplifiers' limit u_max (V).")
        ref = self.reference
        if isinstance(ref, Cycloid):
            start, end, tau = _np(ref.start), _np(ref.end), float(_np(ref.duration))
            out += [
                "/* The exported trajectory: the cycloid (30). */",
                f"static const {self.P}_cycloid_params TRAJECTORY = {{",
                f"    {{{', '.join(self.lit(v) for v in start)}}}, /* start (rad) */",
                f"    {{{', '.join(self.lit(v) for v in end)}}}, /* end (rad) */",
                f"    {self.lit(tau)} /* duration (s) */",
                "};",
                "",
            ]
        else:
            fields = ("offset", "amplitude", "frequency", "phase")
            rows = [f"    {{{', '.join(self.lit(v) for v in _np(getattr(ref, f)))}}}, /* {f} */" for f in fields]
            rows[-1] = rows[-1].replace("}, /*", "} /*")
            out += ["/* The exported trajectory: a sinusoid. */",
                    f"static const {self.P}_sinusoid_params TRAJECTORY = {{", *rows, "};", ""]  # fmt: skip
        out += [f"static const {self.P}_real TWO_PI = {self.lit(2 * np.pi)};", ""]
        return out

    def helpers(self) -> list[str]:
        r = f"{self.P}_real"
        out = [
            "/* y = M x for a 3 x 9 matrix M. */",
            f"static void times9(const {r} M[3][9], const {r} x[9], {r} y[3])",
            "{",
            "    int i, k;",
            "    for (i = 0; i < 3; i++) {",
            "        y[i] = M[i][0] * x[0];",
            "        for (k = 1; k < 9; k++)",
            "            y[i] += M[i][k] * x[k];",
            "    }",
            "}",
            "",
            "/* y = M x for a 3 x 3 matrix M. */",
            f"static void times3(const {r} M[3][3], const {r} x[3], {r} y[3])",
            "{",
            "    int i;",
            "    for (i = 0; i < 3; i++)",
            "        y[i] = M[i][0] * x[0] + M[i][1] * x[1] + M[i][2] * x[2];",
            "}",
            "",
        ]
        if self.kind == "fosmc":
            out += [
                "/* The Euclidean norm of x (n entries). */",
                f"static {r} norm(const {r} *x, int n)",
                "{",
                f"    {r} sum = x[0] * x[0];",
                "    int k;",
                "    for (k = 1; k < n; k++)",
                "        sum += x[k] * x[k];",
                f"    return {self.fn('sqrt')}(sum);",
                "}",
                "",
            ]
        if self.kind != "smc" and (self.kind == "super_twisting" or self.switching == "sign"):
            out += [
                "/* sign(x): -1, 0 or 1. */",
                f"static {r} sign(const {r} x)",
                "{",
                f"    return x > {self.lit(0)} ? {self.lit(1)} : x < {self.lit(0)} ? {self.lit(-1)} : {self.lit(0)};",
                "}",
                "",
            ]
        clip = self.kind == "smc" or (self.kind == "fosmc" and self.switching == "sat")
        if clip or np.any(np.isfinite(self.u_max)):
            out += [
                "/* x clipped to [lo, hi]. */",
                f"static {r} clip(const {r} x, const {r} lo, const {r} hi)",
                "{",
                "    return x < lo ? lo : x > hi ? hi : x;",
                "}",
                "",
            ]
        if self.kind == "fosmc":
            body = {
                "sign": "    (void)delta; /* SGN has no boundary layer */\n    return sign(s);",
                "ratio": f"    return s / ({self.fn('fabs')}(s) + delta);",
                "sat": f"    return clip(s / delta, {self.lit(-1)}, {self.lit(1)});",
                "tanh": f"    return {self.fn('tanh')}(s / delta);",
            }[self.switching]
            out += [
                f"/* The switching function f(s) = {_SWITCHING[self.switching]}. */",
                f"static {r} switching(const {r} s, const {r} delta)",
                "{",
                *body.split("\n"),
                "}",
                "",
            ]
        return out

    def init(self) -> list[str]:
        P, r = self.P, f"{self.P}_real"
        joint = []  # per joint i
        if self.kind == "fosmc":
            joint.append(f"        st->w[i] = {self.lit(0)};")
        if self.kind == "super_twisting":
            joint.append(f"        st->v[i] = {self.lit(0)};")
        if self.difference:
            if self.encoder:
                joint.append("        st->counts[i] = 0; /* read at the first sample */")
            else:
                joint.append("        st->theta[i] = x0[3 * i];")
            joint += ["        st->dtheta[i] = x0[3 * i + 1];", "        st->ddtheta[i] = x0[3 * i + 2];"]
        if self.delay:
            joint += [
                f"        for (k = 0; k < {self.M}_DELAY_SAMPLES; k++)",
                f"            st->pending[k][i] = {self.lit(0)}; /* 0 V until the first computed voltage */",
            ]
        body = ["    st->j = 0;"]
        if joint:
            body = [f"    int i{', k' if self.delay else ''};", *body, "    for (i = 0; i < 3; i++) {", *joint, "    }"]
        if not self.difference:
            body.append("    (void)x0; /* measured rates: nothing of x0 is remembered */")
        out = [f"void {P}_init({P}_state *st, const {r} x0[9])", "{", *body, "}", ""]
        if self.encoder:
            out += [
                f"void {P}_angles(const int32_t counts[3], {r} theta[3])",
                "{",
                "    int i;",
                "    for (i = 0; i < 3; i++)",
                f"        theta[i] = ({r})counts[i] * RAD_PER_COUNT[i];",
                "}",
                "",
            ]
        return out

    def measure(self) -> list[str]:
        """The measurement Y (9,) from the update's input, advancing the estimator."""
        M = self.M
        if not self.difference:
            return ["    for (k = 0; k < 9; k++)", "        y[k] = measurement[k];"]
        angle = ("(" + f"{self.P}_real)counts[i] * RAD_PER_COUNT[i]") if self.encoder else "theta[i]"
        out = [
            "    for (i = 0; i < 3; i++) {",
            f"        y[3 * i] = {angle};",
            "        if (st->j == 0) { /* the first sample: the rates of the initial state (init) */",
            "            y[3 * i + 1] = st->dtheta[i];",
            "            y[3 * i + 2] = st->ddtheta[i];",
            "        } else { /* backward differences */",
        ]
        if self.encoder:
            out.append(f"            y[3 * i + 1] = ({self.P}_real)(counts[i] - st->counts[i]) * RAD_PER_COUNT[i] * "
                       f"{M}_SAMPLE_RATE;")  # fmt: skip
        else:
            out.append(f"            y[3 * i + 1] = (y[3 * i] - st->theta[i]) * {M}_SAMPLE_RATE;")
        out += [
            f"            y[3 * i + 2] = (y[3 * i + 1] - st->dtheta[i]) * {M}_SAMPLE_RATE;",
            "        }",
            "        st->counts[i] = counts[i];" if self.encoder else "        st->theta[i] = y[3 * i];",
            "        st->dtheta[i] = y[3 * i + 1];",
            "        st->ddtheta[i] = y[3 * i + 2];",
            "    }",
        ]
        return out

    def law(self) -> list[str]:
        """U (3,) from y and the reference terms, advancing the law's state."""
        if self.kind == "fosmc":
            out = [
                "    /* Z = Y - X_d; s = C Z - w (14) */",
                "    for (k = 0; k < 9; k++)",
                "        z[k] = y[k] - x_d[k];",
                "    times9(C_SURFACE, z, s);",
                "    for (i = 0; i < 3; i++)",
                "        s[i] -= st->w[i];",
                "    /* U = Omega - (CB)^-1 rho f(s) (23), rho = gamma_1 ||Z|| + gamma_2 ||X_d||",
                "     * + gamma_3 ||Omega|| */",
                "    rho = GAMMA[0] * norm(z, 9) + GAMMA[1] * norm(x_d, 9) + GAMMA[2] * norm(omega, 3);",
                "    for (i = 0; i < 3; i++)",
                f"        f[i] = rho * switching(s[i], {'DELTA[i]' if self.switching != 'sign' else self.lit(0)});",
                "    times3(CB_INV, f, tmp);",
                "    for (i = 0; i < 3; i++)",
                "        u_new[i] = omega[i] - tmp[i];",
            ]
            if self.law_form == "equivalent":
                out += [
                    "    /* the law 'equivalent': plus the nominal equivalent control K Z (18) */",
                    "    times9(K_GAIN, z, tmp);",
                    "    for (i = 0; i < 3; i++)",
                    "        u_new[i] += tmp[i];",
                ]
            out += [
                "    /* w_(j+1) = w_j + T (CA + CBK) Z_j: the integral of (14) as a sum */",
                "    times9(CA_PLUS_CBK, z, tmp);",
                "    for (i = 0; i < 3; i++)",
                f"        st->w[i] += {self.M}_SAMPLE_PERIOD * tmp[i];",
            ]
            return out
        out = [
            *_comment(f"s = C Z and ce = C e, e = X_d' - N(Y), N(Y) the rates of {self.model} without input", 4),
            "    times9(A_R, y, jerk);",
            "    for (i = 0; i < 3; i++) {",
            "        z[3 * i] = y[3 * i] - x_d[3 * i];",
            "        z[3 * i + 1] = y[3 * i + 1] - x_d[3 * i + 1];",
            "        z[3 * i + 2] = y[3 * i + 2] - x_d[3 * i + 2];",
            "        e[3 * i] = r->dtheta[i] - y[3 * i + 1];",
            "        e[3 * i + 1] = r->ddtheta[i] - y[3 * i + 2];",
            "        e[3 * i + 2] = r->dddtheta[i] - jerk[i];",
            "    }",
            "    times9(C_SURFACE, z, s);",
            "    times9(C_SURFACE, e, ce);",
        ]
        if self.kind == "smc":
            out += [
                "    /* U = U_eq - (CB)^-1 k sat(s / phi), U_eq = (CB)^-1 C (X_d' - N(Y)) */",
                "    for (i = 0; i < 3; i++)",
                f"        ce[i] -= K_SWITCH[i] * clip(s[i] / PHI[i], {self.lit(-1)}, {self.lit(1)});",
                "    times3(CB_INV, ce, u_new);",
            ]
        else:
            sqrt = self.fn("sqrt")
            fabs = self.fn("fabs")
            out += [
                "    /* U = U_eq - (CB)^-1 (k1 |s|^(1/2) sign(s) - v), U_eq = (CB)^-1 C (X_d' - N(Y)) */",
                "    for (i = 0; i < 3; i++)",
                f"        ce[i] -= K1[i] * {sqrt}({fabs}(s[i])) * sign(s[i]) - st->v[i];",
                "    times3(CB_INV, ce, u_new);",
                "    /* v_(j+1) = v_j - T k2 sign(s_j) */",
                "    for (i = 0; i < 3; i++)",
                f"        st->v[i] -= {self.M}_SAMPLE_PERIOD * K2[i] * sign(s[i]);",
            ]
        return out

    def update(self) -> list[str]:
        P, M, r = self.P, self.M, f"{self.P}_real"
        arg = {"counts": "const int32_t counts[3]", "theta": f"const {r} theta[3]",
               "measurement": f"const {r} measurement[9]"}[self.input_name]  # fmt: skip
        body = ["    /* the measurement Y_j */", *self.measure(), ""]
        if self.kind == "fosmc":
            body += _comment(f"X_d (6) and Omega = B_bar^-1 (theta_d''' - A_r X_d) (10): the input under which "
                             f"{self.model} follows X_d", 4)  # fmt: skip
        else:
            body += ["    /* X_d (6) */"]
        body += [
            "    for (i = 0; i < 3; i++) {",
            "        x_d[3 * i] = r->theta[i];",
            "        x_d[3 * i + 1] = r->dtheta[i];",
            "        x_d[3 * i + 2] = r->ddtheta[i];",
            "    }",
        ]
        if self.kind == "fosmc":
            body += [
                "    times9(A_R, x_d, tmp);",
                "    for (i = 0; i < 3; i++)",
                "        tmp[i] = r->dddtheta[i] - tmp[i];",
                "    times3(B_BAR_INV, tmp, omega);",
            ]
        body += ["", "    /* the law: U_j */", *self.law(), ""]
        if self.delay:
            body += [
                f"    /* the computation delay: apply U_(j-d), computed d = {M}_DELAY_SAMPLES sample(s) ago */",
                "    for (i = 0; i < 3; i++) {",
                "        applied[i] = st->pending[0][i];",
                f"        for (k = 0; k + 1 < {M}_DELAY_SAMPLES; k++)",
                "            st->pending[k][i] = st->pending[k + 1][i];",
                f"        st->pending[{M}_DELAY_SAMPLES - 1][i] = u_new[i];",
                "    }",
            ]
            src = "applied"
        else:
            src = "u_new"
        if np.any(np.isfinite(self.u_max)):
            body += ["    /* the amplifiers' limit */", "    for (i = 0; i < 3; i++)",
                     f"        u[i] = clip({src}[i], -U_MAX[i], U_MAX[i]);"]  # fmt: skip
        else:
            body += [
                "    /* no voltage limit configured */",
                "    for (i = 0; i < 3; i++)",
                f"        u[i] = {src}[i];",
            ]
        body += ["    st->j++;"]
        text = "\n".join(line.split("/*")[0] for line in body)  # the code, without its comments
        sizes = {
            "y": 9,
            "x_d": 9,
            "omega": 3,
            "z": 9,
            "e": 9,
            "s": 3,
            "f": 3,
            "ce": 3,
            "jerk": 3,
            "tmp": 3,
            "u_new": 3,
            "applied": 3,
        }
        reals = [f"{n}[{k}]" for n, k in sizes.items() if re.search(rf"\b{n}\[", text)]
        reals += ["rho"] if re.search(r"\brho\b", text) else []
        ints = [n for n in ("i", "k") if re.search(rf"\b{n}\b", text)]
        decl = [f"    {r} {', '.join(reals)};", f"    int {', '.join(ints)};", ""]
        return [f"void {P}_update({P}_state *st, {arg}, const {P}_reference *r, {r} u[3])", "{", *decl, *body, "}", ""]

    def references(self) -> list[str]:
        P, M, r = self.P, self.M, f"{self.P}_real"
        sin, cos = self.fn("sin"), self.fn("cos")
        at = "cycloid" if isinstance(self.reference, Cycloid) else "sinusoid"
        return [
            f"void {P}_reference_at(uint32_t j, {P}_reference *r)",
            "{",
            f"    {P}_{at}(&TRAJECTORY, j, r);",
            "}",
            "",
            "/* (30): theta_d = start + Delta / (2 pi) (w t - sin(w t)), w = 2 pi / tau, Delta = end - start, for",
            " * 0 <= t < tau; end afterwards (theta_d''' jumps at 0 and tau). */",
            f"void {P}_cycloid(const {P}_cycloid_params *p, uint32_t j, {P}_reference *r)",
            "{",
            f"    const {r} t = ({r})j * {M}_SAMPLE_PERIOD;",
            f"    const {r} tau = p->duration, w = TWO_PI / tau;",
            "    const int inside = t < tau;",
            f"    const {r} wt = w * (inside ? t : tau);",
            f"    const {r} sn = {sin}(wt), cs = {cos}(wt);",
            "    int i;",
            "    for (i = 0; i < 3; i++) {",
            f"        const {r} delta = p->end[i] - p->start[i];",
            "        r->theta[i] = p->start[i] + delta / TWO_PI * (wt - sn);",
            f"        r->dtheta[i] = inside ? delta / tau * ({self.lit(1)} - cs) : {self.lit(0)};",
            f"        r->ddtheta[i] = inside ? delta * w / tau * sn : {self.lit(0)};",
            f"        r->dddtheta[i] = inside ? delta * w * w / tau * cs : {self.lit(0)};",
            "    }",
            "}",
            "",
            "/* theta_d = offset + amplitude sin(frequency t + phase) and its derivatives. */",
            f"void {P}_sinusoid(const {P}_sinusoid_params *p, uint32_t j, {P}_reference *r)",
            "{",
            f"    const {r} t = ({r})j * {M}_SAMPLE_PERIOD;",
            "    int i;",
            "    for (i = 0; i < 3; i++) {",
            f"        const {r} a = p->amplitude[i], w = p->frequency[i], x = w * t + p->phase[i];",
            f"        const {r} sn = {sin}(x), cs = {cos}(x);",
            "        r->theta[i] = p->offset[i] + a * sn;",
            "        r->dtheta[i] = a * w * cs;",
            "        r->ddtheta[i] = -a * w * w * sn;",
            "        r->dddtheta[i] = -a * w * w * w * cs;",
            "    }",
            "}",
            "",
        ]

    def source(self) -> str:
        P = self.P
        head = [f"{P}.c: generated by fosmc_jax {__version__} (`fosmc export`, {self.precision}). Do not edit: "
                "export again.", *_lines(self.origin), "", *self.describe()]  # fmt: skip
        if self.kind == "fosmc":
            head += ["", "The design behind the constants: K of (16) places the poles of A + BK per joint at"]
            head += [f"  joint {i + 1}: {', '.join(f'{p:g}' for p in row)} (1/s)" for i, row in enumerate(self.poles)]
        head += ["", "Equation numbers: the paper's (docs/paper.md of fosmc_jax)."]
        out = ["/*", *[(" * " + line).rstrip() for line in head], " */", f'#include "{P}.h"', "",
               "#include <math.h>", ""]  # fmt: skip
        out += ["/* ---------------------------------------------------------------- the exported constants */", ""]
        out += self.constants()
        out += ["/* ---------------------------------------------------------------- helpers */", ""]
        out += self.helpers()
        out += ["/* ---------------------------------------------------------------- the controller */", ""]
        out += self.init()
        out += self.update()
        out += ["/* ---------------------------------------------------------------- references */", ""]
        out += self.references()
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
