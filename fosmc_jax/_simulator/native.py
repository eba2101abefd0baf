"""The build of the kernels generated from the JAX model (:mod:`fosmc_jax._simulator.generated`):
the host's C++ compiler (``$CXX``, else ``c++``/``g++``/``clang++``; the headers come with jaxlib),
for this CPU (``-march=native``), each printed source compiled into an object cached on its own
and the objects linked into a library, cached under ``$FOSMC_JAX_CACHE`` (default
``~/.cache/fosmc_jax``, :func:`fosmc_jax._simulator.cache.cache_dir`), keyed by the sources, the
headers, the flags, the compiler's version, jaxlib's and the CPU. Where no compiler is, or with
``FOSMC_JAX_NATIVE=0``, every batch runs ``vmap`` of ``simulate``, with the same results.
"""

from __future__ import annotations

import concurrent.futures
import functools
import hashlib
import os
import platform
import shutil
import subprocess
import tempfile
from pathlib import Path

import jax
import jaxlib

from .cache import cache_dir

_HERE = Path(__file__).parent
_HEADERS = [_HERE / "kernel.h", _HERE / "vecmath.h", _HERE / "gen_kernel.h"]
_FLAGS = ["-O2", "-march=native", "-fno-math-errno", "-ffp-contract=off", "-std=c++17", "-shared", "-fPIC"]


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


def generated_flags() -> tuple[str, ...]:
    """The extra compiler flags of the generated kernels: ``FOSMC_JAX_KERNEL_FLAGS`` (every kernel's),
    then ``FOSMC_JAX_GENERATED_FLAGS`` (for ablations)."""
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
    cmd = [cxx, *_FLAGS, *generated_flags(), f"-I{jax.ffi.include_dir()}", f"-I{_HERE}"]
    headers = [path.read_text() for path in _HEADERS]
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


@functools.cache
def available() -> bool:
    """Whether kernels can be built here: a C++ compiler, the CPU backend, ``FOSMC_JAX_NATIVE`` not
    0 (a compiler that then fails says so in a warning at the build, and its batch runs the
    ``vmap`` path)."""
    return os.environ.get("FOSMC_JAX_NATIVE", "1") != "0" and jax.default_backend() == "cpu" and _compiler() is not None
