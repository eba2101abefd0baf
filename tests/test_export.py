"""`fosmc export`: the digital loop's controller as C99, tested as firmware is tested.

The generated files are compiled here with the host's C compiler (into tmp_path, as a shared
library with a two-line shim that reports sizeof(state)) and driven through ctypes:

- closed loop: the package's arm, advanced one controller sample at a time by the package's own
  rollout (`simulate`, its integrator and metrics), with the C controller called at each sample
  through `jax.pure_callback` (:class:`CLoop`): the encoder is the test's (counts = round(theta /
  q), what `fosmc_jax.quantize` does), the reference sample the C's own `fosmc_reference_at`.
  Compared with the package's rollout of the same point (`problem.simulate(save_every=m)`):
  every applied voltage and the metrics.
- recorded sequences: one measurement sequence fed to the C and to the package's
  `DigitalLoop.update`, with quantization, delay, each estimator and each kind.

"Equal to rounding" in float64 means |dU| <= U_TOL here, not 1 ulp: the C's sample step is
printed from the package's (the same operations in the same order), so what differs is libm's
last bits against XLA's (tanh, sin, cos) and XLA's order within its fused sums, carried through
the estimator's division by T^2 = 1e-6 s^2 and, for super-twisting, through |s|^(1/2), whose
slope is unbounded at s = 0. Over the preset's 4 s in closed loop the largest |dU| seen were
3.1e-14 V (FOSMC), 9.6e-14 V (SMC) and 2.7e-13 V (super-twisting), the metrics within 1.4e-13
and 5e-12 relative; U_TOL and the metrics' 1e-10 leave 100x or more for other machines' libm.

float32 in closed loop: the loops are sensitive far below an encoder count. Moving the initial
angles by 1e-9 rad (1/2400 of a count) moves the package's own float64 metrics over 4 s by up to
1.2% (FOSMC rms_error), 3% (SMC chattering_hf) and 17% (super-twisting rms_error): one count
flipped by a tiny difference sends the quantized sliding motion along another, equally valid
path, and float32's rounding flips counts. So "the float32 metrics within 1%" is asserted as:
each metric within 1%, or within twice the largest relative change (over the joints) that 12
starts moved by up to half an encoder count make in the float64 loop, whichever is larger (the
float32 changes stayed within 0.1-1.3 times that spread); and the float32 voltages on the float64
loop's states within F32_TOL of the largest voltage. The float32 export's sample step runs in
double (fosmc_jax._firmware.export: its estimator differences the angles); what float32 rounds is
its interface, the reference samples, x0 and the voltages.

Without a C compiler the tests that run C code skip (the export itself needs none:
test_export_without_a_compiler_writes_the_files).
"""

from __future__ import annotations

import ctypes
import dataclasses
import functools
import json
import re
import subprocess
import typing
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fosmc_jax as fj
from fosmc_jax import search
from fosmc_jax._app import commands
from fosmc_jax._app.cli import main
from fosmc_jax._firmware import export as firmware
from fosmc_jax._simulator.rollout import simulate

CC = firmware.c_compiler()
needs_cc = pytest.mark.skipif(
    CC is None, reason="no C compiler ($CC, cc, gcc, clang): fosmc export still writes the files, nothing runs them"
)
#: |dU| (V) allowed between the float64 C and the package, per kind (module docstring).
U_TOL = {"fosmc": 1e-11, "smc": 1e-11, "super_twisting": 1e-10}
#: |dU| allowed between the float32 C and the package on the same states, relative to the largest
#: |U|: the float reference samples' rounding (6e-8 rad at 1 rad) through the gains, and through
#: super-twisting's |s|^(1/2); the largest seen 2.8e-6 (FOSMC), 4.9e-6 (SMC), 3e-5 (super-twisting).
F32_TOL = {"fosmc": 2e-5, "smc": 3e-5, "super_twisting": 2e-4}
#: Runs of the float64 loop from initial angles moved by up to half an encoder count: the spread
#: the float32 metrics are held to.
SPREAD_RUNS = 12
KINDS = ("fosmc", "smc", "super_twisting")


def unwrapped(text: str) -> str:
    """The generated text with its long comment lines joined again (the export wraps them
    between words at 96 columns, continued by " *   ", so a temporary path can split a line)."""
    return text.replace("\n *   ", " ")


def config(kind: str = "fosmc", **tables) -> dict:
    """The realistic preset's loop (1 kHz, a 2.6M-count encoder, backward differences, one sample
    of delay, 24 V) on the arm at 10 kg, 50 samples at dt = T (euler); ``tables``: keys to
    change per table (None: drop the table)."""
    cfg = {
        "plant": {"kind": "arm", "payloads": [10.0]},
        "controller": {"kind": kind, "sample_period": 1e-3, "delay_samples": 1},
        "sensors": {"encoder_counts": 2621440, "derivatives": "difference"},
        "actuator": {"u_max": [24.0, 24.0, 24.0]},
        "sim": {"dt": 1e-3, "t_final": 0.05, "integrator": "euler"},
    }
    for table, keys in tables.items():
        if keys is None:
            cfg.pop(table)
        else:
            cfg[table] = {**cfg.get(table, {}), **keys}
    return cfg


# ---------------------------------------------------------------------------- the C, through ctypes

SHIM = '#include <stddef.h>\n#include "{name}.h"\nsize_t shim_size(void) {{ return sizeof({name}_state); }}\n'


class Compiled:
    """A generated controller compiled as a shared library, called as a drive calls it."""

    def __init__(self, loop, reference, precision: str, where: Path, name: str = "fosmc", files=None):
        files = files or firmware.export_c(loop, reference, precision=precision, name=name)
        firmware.write(files, where)
        (where / "shim.c").write_text(SHIM.format(name=name))
        so = where / f"lib{name}.so"
        cmd = [*CC.split(), "-std=c99", "-O2", "-shared", "-fPIC", str(where / f"{name}.c"), str(where / "shim.c"),
               "-o", str(so), "-lm"]  # fmt: skip
        subprocess.run(cmd, check=True, capture_output=True)
        self.lib, self.name = ctypes.CDLL(str(so)), name
        self.lib.shim_size.restype = ctypes.c_size_t
        self.size = self.lib.shim_size()
        self.real = np.float32 if precision == "float32" else np.float64
        sensors = loop.sensors
        self.counts = np.asarray(sensors.counts, np.float64)
        self.q = 2 * np.pi / np.where(self.counts > 0, self.counts, 1)  # fosmc_jax.quantize's q
        self.mode = ("measured" if sensors.derivatives == "measured" else "counts" if np.all(self.counts > 0)
                     else "angles")  # fmt: skip
        self.files = files

    def fn(self, what: str):
        return getattr(self.lib, f"{self.name}_{what}")

    def init(self, x0) -> ctypes.Array:
        state = (ctypes.c_uint8 * self.size)()
        self.fn("init")(state, _ptr(np.asarray(x0, self.real)))
        return state

    def sensor(self, X) -> np.ndarray:
        """What the drive reads from the true state X (9,): the encoders' counts, the angles, or
        the measurement [theta quantized, theta', theta''] per joint."""
        theta = np.asarray(X, np.float64)[0::3]
        if self.mode == "counts":
            return np.round(theta / self.q).astype(np.int32)
        quantized = np.where(self.counts > 0, self.q * np.round(theta / self.q), theta)
        if self.mode == "angles":
            return quantized.astype(self.real)
        y = np.asarray(X, np.float64).reshape(3, 3).copy()
        y[:, 0] = quantized
        return y.reshape(9).astype(self.real)

    def update(self, state, X, r) -> np.ndarray:
        u = np.zeros(3, self.real)
        self.fn("update")(state, _ptr(self.sensor(X)), _ptr(np.asarray(r, self.real)), _ptr(u))
        return u.astype(np.float64)

    def reference_at(self, j: int) -> np.ndarray:
        r = np.zeros((4, 3), self.real)  # the struct: theta[3], dtheta[3], ddtheta[3], dddtheta[3]
        self.fn("reference_at")(ctypes.c_uint32(j), _ptr(r))
        return r

    def run(self, X0, Xs) -> np.ndarray:
        """The voltages (n, 3) for the true states Xs (n, 9), from init(X0), the reference the C's."""
        state = self.init(X0)
        return np.stack([self.update(state, X, self.reference_at(j)) for j, X in enumerate(Xs)])


def _ptr(a: np.ndarray):
    return np.ascontiguousarray(a).ctypes.data_as(ctypes.c_void_p)


# ---------------------------------------------------------------------------- the C in the package's loop

#: Bytes of the C state carried through the rollout (every export's state fits: asserted).
STATE_BYTES = 512
#: The C controller the callbacks call: one rollout compiles for every export (same shapes).
_ACTIVE: dict = {}


def _c_init(X0):
    c = _ACTIVE["c"]
    state = np.zeros(STATE_BYTES, np.uint8)
    state[: c.size] = np.frombuffer(c.init(X0), np.uint8)
    return state


def _c_update(state, X):
    c = _ACTIVE["c"]
    buffer = (ctypes.c_uint8 * c.size).from_buffer_copy(np.asarray(state)[: c.size].tobytes())
    j = ctypes.c_uint32.from_buffer(buffer).value  # the struct's first field: the sample counter
    u = c.update(buffer, X, c.reference_at(j))
    out = np.array(state)
    out[: c.size] = np.frombuffer(buffer, np.uint8)
    return u.astype(np.asarray(X).dtype), out


@functools.partial(jax.tree_util.register_dataclass, data_fields=["u_max"], meta_fields=["sample_steps"])
@dataclasses.dataclass(frozen=True)
class CLoop:
    """The compiled controller as a controller of :func:`fosmc_jax.simulate` (a
    ``fosmc_jax.SampledLoop``): its state the C struct's bytes, each sample a callback."""

    u_max: jax.Array
    sample_steps: int

    def init(self, X0, r0, key=None):
        return jax.pure_callback(_c_init, jax.ShapeDtypeStruct((STATE_BYTES,), jnp.uint8), X0)

    def update(self, state, X, r, t):
        shapes = (jax.ShapeDtypeStruct((3,), X.dtype), jax.ShapeDtypeStruct((STATE_BYTES,), jnp.uint8))
        return jax.pure_callback(_c_update, shapes, state, X)


def closed_loop(c: Compiled, problem, plant: int = 0):
    """The package's rollout of ``problem``'s plant with the C controller ``c``, traced at every sample."""
    assert c.size <= STATE_BYTES
    _ACTIVE["c"] = c
    loop = problem.controller()
    options = {k: v for k, v in problem.options.items() if k not in ("pairing", "switching", "law")}
    plant_i = jax.tree.map(lambda x: x[plant], problem.plants)
    X0 = problem.X0s[0]
    return simulate(plant_i, CLoop(loop.u_max, loop.sample_steps), problem.reference, X0, problem.dt,
                    **dict(options, save_every=loop.sample_steps))  # fmt: skip


@jax.jit
def replay(loop, X0, Xs, rs):
    """The package's DigitalLoop on the true states Xs (n, 9) with reference samples rs (n, 4, 3):
    its voltages (n, 3)."""
    state = loop.init(X0, rs[0])

    def sample(state, x):
        U, state = loop.update(state, x[0], x[1], jnp.zeros((), X0.dtype))
        return state, U

    return jax.lax.scan(sample, state, (Xs, rs))[1]


def recorded(problem, n: int = 300, seed: int = 0) -> np.ndarray:
    """A recorded run's true states (n, 9) around the reference: each angle off by up to 3e-3 rad
    (two sines and a random walk), its rates and accelerations those of the offset, sampled at T."""
    T = float(problem.controller().period)
    t = np.arange(n) * T
    X_d = np.asarray(jax.vmap(lambda t: fj.desired_state(problem.reference(t)))(jnp.asarray(t)))
    rng = np.random.default_rng(seed)
    walk = np.cumsum(rng.normal(0.0, 2e-5, (n, 3)), axis=0)
    w = np.array([7.0, 11.0, 13.0])
    offset = 1e-3 * np.sin(w * t[:, None]) + 1e-3 * np.sin(3 * w * t[:, None] + 1.0) + walk
    rate = 1e-3 * w * np.cos(w * t[:, None]) + 3e-3 * w * np.cos(3 * w * t[:, None] + 1.0)
    acc = -1e-3 * w**2 * np.sin(w * t[:, None]) - 9e-3 * w**2 * np.sin(3 * w * t[:, None] + 1.0)
    X = X_d.reshape(n, 3, 3) + np.stack([offset, rate, acc], axis=2)
    return X.reshape(n, 9)


# ---------------------------------------------------------------------------- tests

VARIANTS = {
    "fosmc": config(),
    "fosmc-sign-equivalent-measured-no-limit": config(
        controller={"switching": "sign", "law": "equivalent", "delay_samples": 0},
        sensors={"derivatives": "measured"},
        actuator=None,
    ),  # fmt: skip
    "fosmc-sat-3-delays-no-encoder": config(
        controller={"switching": "sat", "delay_samples": 3}, sensors={"encoder_counts": 0}
    ),  # fmt: skip
    "fosmc-tanh-coarse-encoder": config(controller={"switching": "tanh"}, sensors={"encoder_counts": 4096}),
    "smc": config("smc"),
    "smc-measured-no-delay-no-limit": config(
        "smc", controller={"delay_samples": 0}, sensors={"derivatives": "measured"}, actuator=None
    ),
    "super_twisting": config("super_twisting"),
}


@needs_cc
@pytest.mark.parametrize("precision", firmware.PRECISIONS)
@pytest.mark.parametrize("variant", VARIANTS)
def test_the_generated_code_compiles_cleanly_under_strict_flags(variant, precision, tmp_path):
    problem = fj.build(VARIANTS[variant])
    paths = firmware.write(firmware.export_c(problem.controller(), problem.reference, precision=precision), tmp_path)
    # -O2: with the warnings that need the optimizer's analyses (-Wmaybe-uninitialized)
    assert firmware.check_compiles(paths[1], CC, (*firmware.STRICT_FLAGS, "-O2")).endswith("-c fosmc.c")
    text = paths[1].read_text()
    assert "malloc" not in text
    # no mutable globals: every file-scope declaration that is not a function is a static const
    declarations = [line for line in text.splitlines() if re.match(r"[A-Za-z_]", line) and "(" not in line]
    assert all(line.startswith("static const ") for line in declarations), declarations
    assert re.search(r"^void fosmc_update\(", text, re.M)


@needs_cc
@pytest.mark.parametrize("precision", firmware.PRECISIONS)
def test_the_reference_generators_match_the_package(precision, tmp_path):
    problem = fj.build(config())
    c = Compiled(problem.controller(), problem.reference, precision, tmp_path)
    j = np.arange(0, 2600, 7)  # through the cycloid's end at tau = 2 s
    t = jnp.asarray(j * 1e-3)
    want = np.asarray(jax.vmap(problem.reference)(t))
    got = np.stack([c.reference_at(int(k)) for k in j]).astype(np.float64)
    rtol = 1e-12 if precision == "float64" else 2e-6
    scale = np.abs(want).max(axis=0, keepdims=True)  # per derivative order and joint
    assert np.all(np.abs(got - want) <= rtol * scale + 1e-300), np.abs(got - want).max()
    # a sinusoid as the exported trajectory, and with parameters given at run time
    sinusoid = fj.Sinusoid(*(jnp.asarray(v) for v in ([0.1, -0.2, 0.3], [0.5, 0.2, 0.1], [3.0, 5.0, 7.0],
                                                       [0.0, 1.0, 2.0])))  # fmt: skip
    exported = Compiled(problem.controller(), sinusoid, precision, tmp_path / "sinusoid")
    got = np.stack([exported.reference_at(int(k)) for k in j]).astype(np.float64)
    wants = np.asarray(jax.vmap(sinusoid)(t))
    # x 4: the phase w t + phase reaches 18 rad, whose rounding every derivative carries
    assert np.all(np.abs(got - wants) <= 4 * rtol * np.abs(wants).max(axis=0, keepdims=True))
    params = np.concatenate([np.asarray(v, c.real) for v in sinusoid])
    r = np.zeros((4, 3), c.real)
    for k, want in zip(j, wants):
        c.fn("sinusoid")(_ptr(params), ctypes.c_uint32(int(k)), _ptr(r))
        assert np.all(np.abs(r - want) <= 4 * rtol * np.abs(wants).max(axis=0))


#: The recorded-sequence cases of the default tier (each a compilation of the package's loop).
REPLAYED = ("fosmc-tanh-coarse-encoder", "fosmc-sign-equivalent-measured-no-limit", "super_twisting")


def _replay_case(variant: str, precision: str, tmp_path: Path, n: int = 300):
    """(the package loop's voltages, the C's, the problem, the states) on a recorded sequence."""
    problem = fj.build(VARIANTS[variant])
    loop = problem.controller()
    c = Compiled(loop, problem.reference, precision, tmp_path)
    Xs = recorded(problem, n)
    rs = jax.vmap(problem.reference)(jnp.arange(n) * loop.period)
    want = np.asarray(replay(loop, jnp.asarray(Xs[0]), jnp.asarray(Xs), rs))
    return want, c.run(Xs[0], Xs), problem, Xs


@needs_cc
@pytest.mark.parametrize("variant", REPLAYED)
def test_a_recorded_sequence_gives_the_package_loops_voltages(variant, tmp_path):
    """Quantization (a 4,096-count encoder: steps of 1.5e-3 rad), the delay line, measured and
    differenced rates: the C's voltages on a recorded sequence are the package's, to rounding in
    float64 and to F32_TOL of the largest voltage in float32."""
    want, got, problem, Xs = _replay_case(variant, "float64", tmp_path / "64")
    loop = problem.controller()
    assert np.abs(want).max() > 1.0 and np.all(want[: loop.delay] == 0)  # it did something; the delay's zeros
    assert np.abs(got - want).max() <= U_TOL[problem.kind], np.abs(got - want).max()
    got32 = Compiled(loop, problem.reference, "float32", tmp_path / "32").run(Xs[0], Xs)
    assert np.abs(got32 - want).max() <= F32_TOL[problem.kind] * np.abs(want).max(), np.abs(got32 - want).max()


@needs_cc
def test_the_c_controller_drives_the_arm_as_the_package_loop_does(tmp_path):
    """The quick closed loop: 50 samples of the C controller on the arm inside the package's
    rollout; the package's DigitalLoop, fed the states that loop visited, gives the same voltage
    at every sample (float64), and the float32 build stays within F32_TOL of the largest voltage."""
    problem = fj.build(config())
    loop = problem.controller()
    X0 = problem.X0s[0]
    for precision, tol in (("float64", U_TOL["fosmc"]), ("float32", None)):
        c = Compiled(loop, problem.reference, precision, tmp_path / precision)
        res = closed_loop(c, problem)
        assert not bool(res.diverged)
        X, U = np.asarray(res.trace.X), np.asarray(res.trace.U)
        rs = jax.vmap(problem.reference)(res.trace.t)
        want = np.asarray(replay(loop, X0, jnp.asarray(X), rs))
        assert np.abs(U).max() > 1.0
        assert np.abs(U - want).max() <= (tol or F32_TOL["fosmc"] * np.abs(want).max()), np.abs(U - want).max()


#: The user's law's gains on each joint's error, rate error and acceleration error.
USER_K = [[400.0, 60.0, 1.0], [600.0, 80.0, 1.0], [300.0, 40.0, 0.5]]


class IntegralState(typing.NamedTuple):
    e: jax.Array  # (3,) the integral of the angle errors


@functools.partial(jax.tree_util.register_dataclass, data_fields=["k", "ki", "u_scale", "period"], meta_fields=[])
@dataclasses.dataclass(frozen=True)
class TanhPlusIntegral:
    """A user's sampled law, not the package's: U = u_scale tanh(-k . Z / u_scale) - ki e, with
    e the sum of T (theta - theta_d) over the samples (its own state)."""

    k: jax.Array  # (3, 3) gains on each joint's error, rate error and acceleration error
    ki: jax.Array  # (3,)
    u_scale: jax.Array
    period: jax.Array

    def init(self, X0, r0, key=None):
        return IntegralState(jnp.zeros(3, X0.dtype))

    def update(self, state, Y, r, t):
        Z = (Y - fj.desired_state(r)).reshape(3, 3)
        U = self.u_scale * jnp.tanh(-jnp.sum(self.k * Z, axis=1) / self.u_scale) - self.ki * state.e
        return U, IntegralState(state.e + self.period * Z[:, 0])


class WithAWhileLoop(TanhPlusIntegral):
    def update(self, state, Y, r, t):
        U, state = super().update(state, Y, r, t)
        return jax.lax.while_loop(lambda u: jnp.abs(u).sum() > 1e3, lambda u: u / 2, U), state


def _user_loop(law_class=TanhPlusIntegral):
    problem = fj.build(config())
    template = problem.controller()
    law = law_class(jnp.array(USER_K), jnp.array([50.0, 80.0, 20.0]), jnp.asarray(20.0), template.period)
    return problem, dataclasses.replace(template, law=law)


@needs_cc
def test_a_users_sampled_law_exports_and_replays_as_the_package_runs_it(tmp_path):
    """Not a table of kinds: a law the package does not know, with a state of its own, exports
    because its update prints, and its C gives the package loop's voltages."""
    problem, loop = _user_loop()
    Xs = recorded(problem, 300)
    rs = jax.vmap(problem.reference)(jnp.arange(300) * loop.period)
    want = np.asarray(replay(loop, jnp.asarray(Xs[0]), jnp.asarray(Xs), rs))
    assert np.abs(want).max() > 1.0
    for precision in firmware.PRECISIONS:
        c = Compiled(loop, problem.reference, precision, tmp_path / precision)
        assert "TanhPlusIntegral" in c.files["fosmc.c"] and "law_e[3]" in c.files["fosmc.h"]
        firmware.check_compiles(tmp_path / precision / "fosmc.c", CC, (*firmware.STRICT_FLAGS, "-O2"))
        tol = U_TOL["fosmc"] if precision == "float64" else F32_TOL["fosmc"] * np.abs(want).max()
        assert np.abs(c.run(Xs[0], Xs) - want).max() <= tol, (precision, np.abs(c.run(Xs[0], Xs) - want).max())


class IntegralGains(typing.NamedTuple):
    ki: jax.Array


#: TanhPlusIntegral as a controller kind of its own, registered as a user registers one.
TANH_INTEGRAL = search.Kind(
    search.Space("tanh_integral", IntegralGains, (search.Param("ki", "ti_ki", 1, (-2.0, 2.0)),)),
    {"ti_ki": (50.0, 80.0, 20.0)},
    lambda params, controller, T: TanhPlusIntegral(
        jnp.asarray(USER_K, T.dtype), controller["ti_ki"], jnp.asarray(20.0, T.dtype), T
    ),
)


@needs_cc
def test_a_registered_kind_exports_from_its_config(tmp_path):
    """The kinds that export are those whose law prints: a kind registered through
    fosmc_jax.search.register, built from its config as the package builds its own."""
    search.register(TANH_INTEGRAL)
    try:
        problem = fj.build(config("tanh_integral", controller={"ti_ki": [40.0, 60.0, 10.0]}))
    finally:
        from fosmc_jax._controllers import KINDS

        KINDS.pop("tanh_integral")
    loop = problem.controller()
    assert type(loop.law) is TanhPlusIntegral and np.allclose(loop.law.ki, [40.0, 60.0, 10.0])
    c = Compiled(loop, problem.reference, "float64", tmp_path)
    Xs = recorded(problem, 300)
    want = np.asarray(replay(loop, jnp.asarray(Xs[0]), jnp.asarray(Xs), jax.vmap(problem.reference)(
        jnp.arange(300) * loop.period)))  # fmt: skip
    assert np.abs(want).max() > 1.0
    assert np.abs(c.run(Xs[0], Xs) - want).max() <= U_TOL["fosmc"]


def test_a_law_that_does_not_print_is_refused_in_one_line_naming_the_primitive():
    problem, loop = _user_loop(WithAWhileLoop)
    with pytest.raises(
        ValueError, match=r"^export: the sample step of WithAWhileLoop .* does not print as C: while"
    ) as e:
        firmware.export_c(loop, problem.reference)
    assert "\n" not in str(e.value)


@needs_cc
@pytest.mark.slow
@pytest.mark.parametrize("kind", KINDS)
def test_the_whole_horizon_in_closed_loop_equals_the_package_rollout(kind, tmp_path):
    """The realistic preset's 4 s (rk4, dt = 1e-4 s, the arm at 0 and 10 kg): float64, every
    applied voltage within U_TOL of the package's rollout and every metric within 1e-10
    relative; float32, the voltages on the float64 run's states within F32_TOL of the largest,
    and every metric within 1% or within twice what half an encoder count at the start does
    (module docstring)."""
    q = 2 * np.pi / 2621440
    draws = np.random.default_rng(0).uniform(-q / 2, q / 2, (SPREAD_RUNS, 3))
    offsets = np.zeros((SPREAD_RUNS + 1, 9))
    offsets[1:, 0::3] = draws  # the angles only: the loop reads its first rates exactly
    sim = {"dt": 1e-4, "t_final": 4.0, "integrator": "rk4", "initial_offset": offsets.tolist()}
    problem = fj.build(config(kind, plant={"payloads": [0.0, 10.0]}, sim=sim))
    want = problem.simulate(save_every=problem.controller().sample_steps)  # plant-major: 2 x 13 rollouts
    assert not np.any(np.asarray(want.diverged))
    metrics = lambda res, i=...: np.stack([np.asarray(m)[i] for m in res.metrics])  # (8 metrics, 3 joints)
    for precision in firmware.PRECISIONS:
        c = Compiled(problem.controller(), problem.reference, precision, tmp_path / precision)
        for plant in range(2):
            row = plant * len(offsets)
            got = closed_loop(c, problem, plant=plant)
            assert not bool(got.diverged)
            U, m, m64 = np.asarray(want.trace.U[row]), metrics(got), metrics(want, row)
            if precision == "float64":
                assert np.abs(np.asarray(got.trace.U) - U).max() <= U_TOL[kind]
                assert np.all(np.abs(m - m64) <= 1e-10 * np.abs(m64) + 1e-14), (plant, m, m64)
                continue
            X = np.asarray(want.trace.X[row])
            assert np.abs(c.run(X[0], X) - U).max() <= F32_TOL[kind] * np.abs(U).max()
            spread = np.max([np.abs(metrics(want, row + k) - m64) for k in range(1, len(offsets))], axis=0)
            # the metric's relative spread, the largest over the joints (0 where the metric is 0: no saturation)
            nonzero = m64 != 0
            relative = np.where(nonzero, spread / np.where(nonzero, np.abs(m64), 1.0), 0.0).max(axis=1, keepdims=True)
            tol = np.maximum(np.maximum(1e-2, 2 * relative) * np.abs(m64), 2 * spread) + 1e-12
            assert np.all(np.abs(m - m64) <= tol), (plant, (np.abs(m - m64) / tol).max(axis=1))


@needs_cc
@pytest.mark.slow
@pytest.mark.parametrize("variant", sorted(set(VARIANTS) - set(REPLAYED)))
def test_every_variant_replays_a_recorded_sequence(variant, tmp_path):
    want, got, problem, _ = _replay_case(variant, "float64", tmp_path, n=1000)
    assert np.abs(got - want).max() <= U_TOL[problem.kind], np.abs(got - want).max()


# ---------------------------------------------------------------------------- the command


def test_fosmc_export_writes_the_point_of_a_front(tmp_path, capsys):
    front = tmp_path / "front.json"
    point = {"delta": [11.0, 22.0, 33.0], "gamma": [300.0, 250.0, 25.0],
             "poles": [[-1.0, -2.0, -3.0], [-1.5, -2.5, -3.5], [-0.5, -0.6, -0.7]]}  # fmt: skip
    front.write_text(json.dumps({"points": [{"params": {}}, {"params": point}]}))
    toml = tmp_path / "loop.toml"
    toml.write_text('[plant]\nkind = "arm"\n[controller]\nsample_period = 1e-3\n[sensors]\nencoder_counts = 4096\n'
                    'derivatives = "difference"\n')  # fmt: skip
    out = tmp_path / "fw"
    assert main(["export", "--config", str(toml), "--params", str(front), "--point", "1", "--out", str(out),
                 "--precision", "float32", "--name", "arm_ctl"]) == 0  # fmt: skip
    assert sorted(p.name for p in out.iterdir()) == ["arm_ctl.c", "arm_ctl.h"]
    source, header = (out / "arm_ctl.c").read_text(), (out / "arm_ctl.h").read_text()
    assert np.array_equal(_listed(source, "delta"), [11.0, 22.0, 33.0])
    assert (
        "typedef float arm_ctl_real;" in header
        and "void arm_ctl_update(arm_ctl_state *st, const int32_t counts[3]" in header
    )
    assert f"params: {front}, point 1" in unwrapped(header)
    printed = capsys.readouterr()
    for path in (out / "arm_ctl.h", out / "arm_ctl.c"):  # each written file named once, on stdout or stderr
        assert (printed.out + printed.err).count(str(path)) == 1, printed
    problem = fj.build(fj.config.with_params(fj.config.load(str(toml)), front, 1))
    listed = _listed(source, "poles").reshape(3, 3).astype(np.float32)  # float32's shortest decimals
    assert np.array_equal(listed, np.asarray(problem.base.poles, np.float32))
    if CC is None:
        return
    # the written files compute the point's loop: the package's DigitalLoop of these parameters
    loop = problem.controller()
    c = Compiled(loop, problem.reference, "float32", out, name="arm_ctl", files={"arm_ctl.h": header,
                                                                                 "arm_ctl.c": source})  # fmt: skip
    Xs = recorded(problem, 300)
    want = np.asarray(replay(loop, jnp.asarray(Xs[0]), jnp.asarray(Xs), jax.vmap(problem.reference)(
        jnp.arange(300) * loop.period)))  # fmt: skip
    assert np.abs(want).max() > 1.0
    assert np.abs(c.run(Xs[0], Xs) - want).max() <= F32_TOL["fosmc"] * np.abs(want).max()


def test_fosmc_export_refuses_what_has_no_c_form(tmp_path, capsys):
    toml = tmp_path / "ideal.toml"
    toml.write_text('[plant]\nkind = "arm"\n')
    assert main(["export", "--config", str(toml), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert (
        err.startswith("fosmc: error: controller.sample_period: fosmc export needs a digital loop") and "\n" not in err
    )
    assert not (tmp_path / "o").exists()
    with pytest.raises(fj.ConfigError, match="^--point: needs --params"):
        commands.run_export(config(), point=3)
    with pytest.raises(fj.ConfigError, match="^--name: expected a C identifier"):
        commands.run_export(config(), name="2fast")
    with pytest.raises(fj.ConfigError, match="^--precision: expected one of float32, float64"):
        commands.run_export(config(), precision="float16")


def test_export_without_a_compiler_writes_the_files(tmp_path, monkeypatch):
    monkeypatch.setattr(firmware, "c_compiler", lambda: None)
    r = commands.run_export(config("smc"), out=tmp_path)
    assert r["check"] == "not compiled: no C compiler found ($CC, cc, gcc, clang)"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fosmc.c", "fosmc.h"]
    assert (tmp_path / "fosmc.c").read_text() == r["files"]["fosmc.c"]
    assert _listed(r["files"]["fosmc.c"], "k").shape == (3,)  # the SMC's switching gains


@needs_cc
def test_the_interrupt_example_of_the_docs_compiles(tmp_path):
    """docs/firmware.md's example, with stub drivers, against the realistic preset's export."""
    text = (Path(__file__).resolve().parent.parent / "docs" / "firmware.md").read_text()
    example = next(block for block in text.split("```c\n")[1:] if "sample_isr" in block).split("```")[0]
    stubs = ("static void read_encoders(int32_t counts[3]) { counts[0] = counts[1] = counts[2] = 0; }\n"
             "static void write_voltages(const fosmc_real u[3]) { (void)u; }\n")  # fmt: skip
    problem = fj.build(config())
    firmware.write(firmware.export_c(problem.controller(), problem.reference), tmp_path)
    head, body = example.split("static fosmc_state st;")
    (tmp_path / "isr.c").write_text(head + stubs + "static fosmc_state st;" + body)
    firmware.check_compiles(tmp_path / "isr.c", CC, (*firmware.STRICT_FLAGS, "-O2"))


def _loop_toml(tmp_path: Path) -> Path:
    toml = tmp_path / "loop.toml"
    toml.write_text('[plant]\nkind = "arm"\n[controller]\nsample_period = 1e-3\n')
    return toml


def test_fosmc_export_refuses_an_out_it_cannot_write_whole_in_one_line(tmp_path, capsys):
    """A file as --out, or below it, or a folder where a target goes: exit status 2, one line
    naming --out, and nothing written (no fosmc.h before a failing fosmc.c)."""
    toml = _loop_toml(tmp_path)
    a_file = tmp_path / "notes.txt"
    a_file.write_text("mine")
    blocked = tmp_path / "blocked"
    (blocked / "fosmc.c").mkdir(parents=True)
    cases = ((a_file, f"{a_file} exists and is not a folder"), (a_file / "fw", f"{a_file} exists and is not a folder"),
             (blocked, f"{blocked / 'fosmc.c'} exists and is not a file"))  # fmt: skip
    for out, why in cases:
        assert main(["export", "--config", str(toml), "--out", str(out)]) == 2
        err = capsys.readouterr().err.strip()
        assert err == f"fosmc: error: --out: {why} (nothing written)", err
    assert a_file.read_text() == "mine"
    assert [p.name for p in blocked.iterdir()] == ["fosmc.c"] and not any((blocked / "fosmc.c").iterdir())
    # the library's write checks both targets before writing either, too
    with pytest.raises(ValueError, match="fosmc.c exists and is not a file"):
        firmware.write({"fosmc.h": "h", "fosmc.c": "c"}, blocked)
    assert [p.name for p in blocked.iterdir()] == ["fosmc.c"]


def test_run_export_takes_a_dict_of_parameters_as_simulate_does(tmp_path):
    """``params`` as a dict by the kind's names (what run_tune's final.params and
    Problem.params() are) exports what the same parameters in a result.json export, and the
    config's point where the dict is the problem's own."""
    point = {"delta": [11.0, 22.0, 33.0], "gamma": [300.0, 250.0, 25.0]}
    result = tmp_path / "result.json"
    result.write_text(json.dumps({"final": {"params": point}}))
    from_file = commands.run_export(config(), params=result)["files"]
    from_dict = fj.run_export(config(), params=point)["files"]
    drop = lambda text: [line for line in unwrapped(text).splitlines() if " * params: " not in line]  # noqa: E731
    for filename in ("fosmc.h", "fosmc.c"):
        assert drop(from_dict[filename]) == drop(from_file[filename])
    assert np.array_equal(_listed(from_dict["fosmc.c"], "delta"), [11.0, 22.0, 33.0])
    assert " * params: a dict of delta, gamma (the config's for the rest)" in from_dict["fosmc.h"]
    own = commands.run_export(config("smc"), params=fj.build(config("smc")).params())["files"]["fosmc.c"]
    assert drop(own) == drop(commands.run_export(config("smc"))["files"]["fosmc.c"])


@pytest.mark.parametrize(
    "options, message",
    [
        ({"point": 2.5}, r"^--point: expected an integer \(the index of a front's point\), got 2\.5"),
        ({"point": True}, r"^--point: expected an integer"),
        ({"params": 3.0}, r"^--params: expected a fosmc tune result\.json or fosmc front front\.json \(a path\), "
                          r"or a dict of the controller kind's parameters by name, got float"),
        ({"params": {"delta": [1.0, 2.0, 3.0]}, "point": 1}, r"^--point: needs --params FRONT\.json \(not a dict"),
        ({"params": {"delta": [1.0, 2.0]}}, r"^params\.delta: expected shape \(3,\), got \(2,\)"),
        ({"params": {"delta": [-1.0, 2.0, 3.0]}}, r"^params\.delta: expected 3 positive numbers"),
        ({"params": {"k": [1.0, 2.0, 3.0]}}, r"^params: unknown name\(s\) 'k' for controller kind 'fosmc'"),
        ({"params": {"delta": "abc"}}, r"^params"),
    ],
)  # fmt: skip
def test_run_export_refuses_wrong_options_in_one_line_naming_them(options, message):
    with pytest.raises(fj.ConfigError, match=message) as e:
        commands.run_export(config(), **options)
    assert "\n" not in str(e.value)


def test_a_front_without_a_point_asks_for_one(tmp_path):
    front = tmp_path / "front.json"
    front.write_text(json.dumps({"points": [{"params": {}}, {"params": {}}]}))
    with pytest.raises(fj.ConfigError, match=rf"^--point: {front} is a front of 2 points: name the one to export "
                                             r"with --point I"):  # fmt: skip
        commands.run_export(config(), params=front)


def _listed(source: str, name: str) -> np.ndarray:
    """The values of the parameter ``name`` (the last part of its path, e.g. ``a_rows``) as the
    source's head comment lists the constants folded into the code."""
    lines = source.splitlines()
    at = next(i for i, line in enumerate(lines) if re.match(rf" \*   loop\.[\w.]*\b{name} \(", line))
    values = []
    for line in lines[at + 1 :]:
        if not line.startswith(" *     "):
            break
        values += [float(x) for x in line[7:].replace(",", " ").split()]
    return np.array(values)


@pytest.mark.parametrize("kind", ["fosmc", "smc"])
def test_the_files_name_the_design_model_their_rows_come_from(kind, monkeypatch):
    """The rows A_r, B_bar of the export are the config's design model's, and the comments say
    which: the paper's (29), the config's own [model] rows, or the arm's ([model] from = "arm";
    its derivation, seconds of compilation, replaced here by stand-in rows)."""
    from fosmc_jax._design import paper
    from fosmc_jax._problems import design

    A, B = paper.A_ROWS * 1.25, paper.B_ROWS * 0.8  # not the paper's: where the constants come from shows
    box = (np.minimum(A * 0.9, A * 1.1), np.maximum(A * 0.9, A * 1.1), B * 0.9, B * 1.1)
    monkeypatch.setattr(
        design, "_arm_model", lambda key: design.DesignModel("arm", A, B, box, "a test's stand-in rows")
    )
    cases = {
        "paper": ({}, paper.A_ROWS, paper.B_ROWS, "the paper's nominal model (29)"),
        "own": ({"model": {"A_rows": A.tolist(), "B_rows": B.tolist()}}, A, B,
                "the config's nominal model ([model] A_rows, B_rows)"),
        "arm": ({"model": {"from": "arm"}}, A, B, "the model derived from the configured [arm] along the reference"),
    }  # fmt: skip
    for case, (tables, a_rows, b_rows, words) in cases.items():
        r = commands.run_export(config(kind, **tables))
        header, source = r["files"]["fosmc.h"], r["files"]["fosmc.c"]
        assert r["model"] == words
        assert np.array_equal(_listed(source, "a_rows").reshape(3, 9), a_rows), case
        assert np.array_equal(_listed(source, "b_rows").reshape(3, 3), b_rows), case
        flat = " ".join(" ".join(line.strip(" /*") for line in source.splitlines()).split())
        assert f"A_r: rows 3, 6, 9 of A of {words}:" in flat and f"designed on {words} (A_r, B_bar" in flat
        assert ("(29)" in header + source) == (case == "paper"), case
        source_line = "from = 'arm', the midpoint of the rows' box over a test's stand-in rows" if case == "arm" else \
            "from = 'paper'"  # fmt: skip
        assert f" * design model: [model] {source_line}" in header


@pytest.mark.slow  # the arm's design model of the small_arm preset: a compilation and 60 arms, ~10-20 s
def test_the_small_arm_export_holds_and_names_the_arms_rows(tmp_path, capsys):
    assert main(["export", "--config", "small_arm", "--out", str(tmp_path)]) == 0
    source = (tmp_path / "fosmc.c").read_text()
    design = fj.config.design_model(fj.config.load("small_arm"))
    assert design.source == "arm"
    assert np.array_equal(_listed(source, "a_rows").reshape(3, 9), design.A_rows)
    assert np.array_equal(_listed(source, "b_rows").reshape(3, 3), design.B_rows)
    assert "(29)" not in source and "(29)" not in (tmp_path / "fosmc.h").read_text()
    assert "designed on the model derived from the configured [arm]" in source
