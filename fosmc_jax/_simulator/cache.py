"""Where fosmc_jax keeps what it compiles: the native kernels' library (:mod:`fosmc_jax._simulator.native`)
and, when asked, XLA's compiled programs (JAX's persistent compilation cache).

Most of a short run's time is compilation (``fosmc reproduce`` compiles about ten programs; a
tuning run a few), and the same programs come back run after run. The command line turns JAX's
persistent compilation cache on (:func:`use_compilation_cache`), so a second run of a command
loads its programs instead of compiling them; from Python it is one call away. Importing the
package changes no JAX setting.
"""

from __future__ import annotations

import os
from pathlib import Path

import jax

#: Programs that compile faster than this (s) are not written to the cache (JAX's default: 1 s).
MIN_COMPILE_SECONDS = 0.5


def cache_dir() -> Path:
    """``$FOSMC_JAX_CACHE``, else ``$XDG_CACHE_HOME/fosmc_jax``, else ``~/.cache/fosmc_jax``."""
    if os.environ.get("FOSMC_JAX_CACHE"):
        return Path(os.environ["FOSMC_JAX_CACHE"])
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "fosmc_jax"


def use_compilation_cache(path: str | Path | None = None) -> Path | None:
    """Turn on JAX's persistent compilation cache in ``path`` (default: ``cache_dir() / "xla"``)
    for this process, and return its directory.

    JAX's own ``JAX_COMPILATION_CACHE_DIR`` wins over ``path`` (JAX reads it itself), and
    ``FOSMC_JAX_COMPILATION_CACHE=0`` turns the cache off (returns None). Entries are keyed by
    the program, the compiler options, the backend and the jax/jaxlib versions, so a stale entry
    is never used; processes may share the directory (each entry is written once; an entry that
    cannot be read is compiled again, with a warning from JAX)."""
    if os.environ.get("FOSMC_JAX_COMPILATION_CACHE", "1") == "0":
        return None
    if os.environ.get("JAX_COMPILATION_CACHE_DIR"):
        return Path(os.environ["JAX_COMPILATION_CACHE_DIR"])
    directory = Path(path) if path is not None else cache_dir() / "xla"
    jax.config.update("jax_compilation_cache_dir", str(directory))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_SECONDS)
    return directory
