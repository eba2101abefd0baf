"""The linear fast path's time loop in a compiled kernel (``kernel.cc``, on ``kernel.h``), called
from XLA, and the build of the kernels generated from the JAX model
(:mod:`fosmc_jax._simulator.generated`).

XLA:CPU runs every step of a ``lax.scan`` as a few dozen separate kernels, each a pass over the
batch in memory; the loop body of :func:`fosmc_jax._simulator.rollout._linear_batch` costs about 0.7 us
per kernel, which holds a scan far below a hand-written SIMD loop (BENCHMARKS.md). ``kernel.cc``
is that body written once in C++ with the time loop inside, the rollouts in SIMD lanes and the
batch spread over XLA's intra-op thread pool (every core, with or without sharding), registered
as an XLA FFI target (``jax.ffi``).

It is built on first use with the host's C++ compiler (``$CXX``, else ``c++``/``g++``; the
headers come with jaxlib) for this CPU (``-march=native``) and cached under
``$FOSMC_JAX_CACHE`` (default ``~/.cache/fosmc_jax``, :func:`fosmc_jax._simulator.cache.cache_dir`), as one
library, keyed by the sources, the flags, the compiler's version, jaxlib's and the CPU. Where no
compiler works, or with ``FOSMC_JAX_NATIVE=0``, the linear fast path runs its ``lax.scan`` and
every other batch ``vmap`` of ``simulate``, with a one-line warning in the first case. Results
equal those paths' to rounding (tests/test_performance_paths.py), and so do derivatives, which
are theirs (``custom_jvp``).
"""

from __future__ import annotations

import concurrent.futures
import ctypes
import functools
import hashlib
import os
import platform
import shutil
import subprocess
import tempfile
import warnings
from pathlib import Path

import jax
import jax.numpy as jnp
import jaxlib
import numpy as np
from jax import Array

from .._controllers.fosmc import LAWS, SWITCHING
from .cache import cache_dir
from .metrics import Accumulator

TARGET = "fosmc_advance"
LANES = 16  # rollouts per SIMD block (kW in kernel.cc): the batch is padded to a multiple

# The kernels' buffer layouts, defined here and written into the header layout.h that both
# kernels include (:func:`layout_header`, at build time): an accumulator field added on the
# Python side without its kernel name fails the build (KeyError), never shifts an offset.
#: The metric accumulator's fields (fosmc_jax._simulator.metrics.Accumulator) as the kernels name them.
ACC_NAMES = {"count": "kCount", "sum_e2": "kSumE2", "max_e": "kMaxE", "last_e": "kLastE", "total_variation": "kTV",
             "sum_u2": "kSumU2", "max_u": "kMaxU", "u_low": "kULow", "sum_hf2": "kSumHf2",
             "saturated": "kSaturated"}  # fmt: skip
ACC = len(Accumulator._fields)
#: The linear kernel's carry rows: x (9), w (3), U (3), the accumulator (ACC x 3, field-major,
#: joint-minor), diverged, diverged_at.
LIN_ACC = 15
LIN_DIV = LIN_ACC + 3 * ACC
ROWS = LIN_DIV + 2


def layout_header() -> str:
    """layout.h: the layouts above as C++ constants, for kernel.cc."""
    fields = ", ".join(f"{ACC_NAMES[name]} = {i}" for i, name in enumerate(Accumulator._fields))
    return "\n".join([
        "// Generated at build time by fosmc_jax._simulator.native.layout_header from the Python side's",
        "// layouts: do not edit.",
        "#pragma once",
        "namespace fosmc {",
        f"namespace acc {{ enum Field {{ {fields} }}; constexpr int kFields = {ACC}; }}",
        f"namespace linear {{ constexpr int kAcc = {LIN_ACC}, kDiv = {LIN_DIV}, kDivAt = {LIN_DIV + 1}, "
        f"kRows = {ROWS}; }}",
        "}  // namespace fosmc",
        "",
    ])  # fmt: skip


# Steps per kernel call: as many as keep the call's time table within 24 KiB, in the core's
# L1 cache (267 Euler float32 steps; 512 steps per call ran slower by hand), at least 64.
TABLE_BYTES = 24 * 1024
_HERE = Path(__file__).parent
_SOURCES = [_HERE / "kernel.cc"]
_HEADERS = [_HERE / "kernel.h", _HERE / "vecmath.h"]
_FLAGS = ["-O3", "-march=native", "-fno-math-errno", "-ffp-contract=off", "-std=c++17", "-shared", "-fPIC"]


def _cpu() -> str:
    """What ``-march=native`` depends on: the CPU's model and flags."""
    try:
        info = Path("/proc/cpuinfo").read_text().splitlines()
        return "".join(sorted({line for line in info if line.startswith(("model name", "flags"))}))
    except OSError:
        return platform.processor() + platform.machine()


def _compiler() -> str | None:
    for cxx in (os.environ.get("CXX"), "c++", "g++", "clang++"):
        if cxx and shutil.which(cxx):
            return cxx
    return None


def _version(cmd: list[str]) -> str:
    try:
        return subprocess.run(cmd, capture_output=True, text=True, timeout=30).stdout.split("\n")[0]
    except (OSError, subprocess.SubprocessError):
        return ""


def _build() -> Path:
    """The kernel's shared library, compiled once per source, flags, compiler, jaxlib and CPU."""
    cxx = _compiler()
    if cxx is None:
        raise OSError("no C++ compiler found (set CXX)")
    # FOSMC_JAX_KERNEL_FLAGS: extra compiler flags (ablations); in the cache key
    cmd = [cxx, *_FLAGS, *os.environ.get("FOSMC_JAX_KERNEL_FLAGS", "").split(), f"-I{jax.ffi.include_dir()}"]
    text = [path.read_text() for path in (*_SOURCES, *_HEADERS)] + [layout_header()]
    key = "\n".join([*text, " ".join(cmd), _version([cxx, "--version"]), jaxlib.__version__, _cpu()])
    cache = cache_dir()
    lib = cache / f"kernel-{hashlib.sha256(key.encode()).hexdigest()[:16]}.so"
    if not lib.exists():
        cache.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(dir=cache) as tmp:  # written whole, then renamed
            out = Path(tmp) / lib.name
            (Path(tmp) / "layout.h").write_text(text[-1])
            cmd = [*cmd, f"-I{tmp}"]
            # each source compiled in its own process (the two kernels at once on two cores), then linked
            objects = [Path(tmp) / f"{path.stem}.o" for path in _SOURCES]
            jobs = [subprocess.Popen([*cmd, "-c", str(src), "-o", str(obj)], stderr=subprocess.PIPE, text=True)
                    for src, obj in zip(_SOURCES, objects)]  # fmt: skip
            errors = [job.communicate(timeout=600)[1] for job in jobs]
            for job, err in zip(jobs, errors):
                _check(cxx, job.returncode, err)
            link = subprocess.run(
                [*cmd, *map(str, objects), "-o", str(out)], capture_output=True, text=True, timeout=600
            )
            _check(cxx, link.returncode, link.stderr)
            os.replace(out, lib)
    return lib


def generated_flags() -> tuple[str, ...]:
    """The extra compiler flags of the generated kernels: ``FOSMC_JAX_KERNEL_FLAGS`` (every kernel's),
    then ``FOSMC_JAX_GENERATED_FLAGS`` (theirs alone: for ablations, the linear kernel unchanged)."""
    return (
        *os.environ.get("FOSMC_JAX_KERNEL_FLAGS", "").split(),
        *os.environ.get("FOSMC_JAX_GENERATED_FLAGS", "").split(),
    )


def build_generated(sources: list[str]) -> Path:
    """The shared library of a generated kernel's ``sources`` (C++ that includes gen_kernel.h):
    each source compiled in its own process (as many at once as there are cores, the largest
    first) into an object cached on its own, then linked; once per sources, headers, flags,
    compiler, jaxlib and CPU, cached as the kernels are. The forward's and the adjoint's
    libraries share the printed steps' sources: the adjoint's build compiles them no more."""
    cxx = _compiler()
    if cxx is None:
        raise OSError("no C++ compiler found (set CXX)")
    # -O2: as fast as -O3 on the printed straight-line code, and builds sooner (BENCHMARKS.md)
    flags = [f if f != "-O3" else "-O2" for f in _FLAGS]
    cmd = [cxx, *flags, *generated_flags(), f"-I{jax.ffi.include_dir()}", f"-I{_HERE}"]
    headers = [path.read_text() for path in (*_HEADERS, _HERE / "gen_kernel.h")]
    common = "\n".join([*headers, " ".join(cmd), _version([cxx, "--version"]), jaxlib.__version__, _cpu()])
    digest = lambda *parts: hashlib.sha256("\n".join(parts).encode()).hexdigest()[:16]
    cache = cache_dir()
    lib = cache / f"generated-{digest(*sources, common)}.so"
    if not lib.exists():
        cache.mkdir(parents=True, exist_ok=True)
        objects = [cache / f"generated-{digest(source, common)}.o" for source in sources]
        with tempfile.TemporaryDirectory(dir=cache) as tmp:  # each file written whole, then renamed
            todo = sorted({o: s for s, o in zip(sources, objects) if not o.exists()}.items(), key=lambda j: -len(j[1]))
            for obj, source in todo:
                (Path(tmp) / obj.name).with_suffix(".cc").write_text(source)
            jobs = [[*cmd, "-c", str((Path(tmp) / obj.name).with_suffix(".cc")), "-o", str(Path(tmp) / obj.name)]
                    for obj, _ in todo]  # fmt: skip
            with concurrent.futures.ThreadPoolExecutor(os.cpu_count() or 1) as pool:
                runs = list(pool.map(lambda c: subprocess.run(c, capture_output=True, text=True, timeout=900), jobs))
            for run in runs:
                _check(cxx, run.returncode, run.stderr)
            for obj, _ in todo:
                os.replace(Path(tmp) / obj.name, obj)
            out = Path(tmp) / lib.name
            link = subprocess.run([*cmd, *map(str, objects), "-o", str(out)], capture_output=True, text=True,
                                  timeout=600)  # fmt: skip
            _check(cxx, link.returncode, link.stderr)
            os.replace(out, lib)
    return lib


def _check(cxx: str, returncode: int, stderr: str) -> None:
    if returncode:
        errors = [line for line in stderr.splitlines() if "error" in line] or [f"exit {returncode}"]
        raise OSError(f"{cxx} failed: {errors[0].strip()}")


def _load() -> ctypes.CDLL:
    """The built kernel, loaded; a cached library that does not load is rebuilt once."""
    path = _build()
    try:
        return ctypes.cdll.LoadLibrary(str(path))
    except OSError:
        path.unlink(missing_ok=True)
        return ctypes.cdll.LoadLibrary(str(_build()))


@functools.cache
def available() -> bool:
    """Whether the kernel is built and registered (built on the first call)."""
    if os.environ.get("FOSMC_JAX_NATIVE", "1") == "0":
        return False
    try:
        lib = _load()
        jax.ffi.register_ffi_target(TARGET, jax.ffi.pycapsule(lib.FosmcAdvance), platform="cpu")
    except Exception as e:  # any failure leaves the scan loop, which needs none of this
        warnings.warn(f"fosmc_jax: the native kernel is not available ({e}); the fast path runs lax.scan", stacklevel=2)
        return False
    return True


def advance(carry: Array, ab: Array, consts: Array, table, k0: Array, n_steps: int, *, rk4: bool, switching: str,
            law: str) -> Array:  # fmt: skip
    """``n_steps`` steps of the kernel from step ``k0``: ``carry`` (ROWS, N) and ``ab`` (36, N),
    N a multiple of LANES, ``consts`` (100,) as in ``kernel.cc``, all of one dtype;
    ``table(k)`` gives the rows of steps ``k`` (a vector of step indices), (len(k), R). Calls
    of a few hundred steps (see TABLE_BYTES) in a scan."""
    call = jax.ffi.ffi_call(TARGET, jax.ShapeDtypeStruct(carry.shape, carry.dtype), vmap_method="sequential")
    # the kernel's codes are the positions in these tuples (its Sw and Law template arguments)
    attrs = dict(rk4=np.int32(rk4), switching=np.int32(SWITCHING.index(switching)), law=np.int32(LAWS.index(law)))

    def chunk(c, k, length):
        return call(ab, consts, table(k + jnp.arange(length)), c, **attrs)

    row = (27 if rk4 else 9) + 14  # X_d at the stage times, then X_d, Omega, rho_ref, t'
    steps = max(64, TABLE_BYTES // (row * carry.dtype.itemsize))
    chunks, rest = divmod(n_steps, steps)
    if chunks:
        body = lambda c, i: (chunk(c, k0 + i * steps, steps), None)
        carry = jax.lax.scan(body, carry, jnp.arange(chunks))[0]
    if rest:
        carry = chunk(carry, k0 + chunks * steps, rest)
    return carry
