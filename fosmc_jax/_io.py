"""Atomic file output: nothing the package writes is ever left half-written; every result file
carries the versions that produced it (:func:`versions`)."""

from __future__ import annotations

import glob
import importlib.metadata
import json
import math
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

try:  # the installed distribution's, as pyproject.toml gives it (the package's face re-exports it)
    __version__ = importlib.metadata.version("fosmc_jax")
except importlib.metadata.PackageNotFoundError:  # a source tree on the path, never installed
    __version__ = "0+unknown"

#: Version of the metric definitions in ``fosmc_jax/_simulator/metrics.py`` and docs/metrics.md,
#: raised with every change to what a metric means (each version's meaning: CHANGELOG.md). Files
#: without it predate versioning (1 or 2).
METRICS_VERSION = 3
#: The key under which every result file holds :func:`versions`.
VERSIONS_KEY = "fosmc_jax"


def versions() -> dict[str, Any]:
    """``{"version": fosmc_jax.__version__, "metrics_version": METRICS_VERSION}``: what every
    file the package writes carries under :data:`VERSIONS_KEY` (:func:`stamped`,
    :func:`stamped_arrays`)."""
    return {"version": __version__, "metrics_version": METRICS_VERSION}


def stamped(result: dict[str, Any]) -> dict[str, Any]:
    """``result`` with :func:`versions` under :data:`VERSIONS_KEY`, first (a JSON file's head)."""
    return {VERSIONS_KEY: versions(), **{k: v for k, v in result.items() if k != VERSIONS_KEY}}


def stamped_arrays(arrays: dict[str, Any]) -> dict[str, Any]:
    """Arrays for ``np.savez`` with :func:`versions` as the JSON text of a 0-d string array
    under :data:`VERSIONS_KEY` (read back with ``json.loads(z["fosmc_jax"].item())``; no pickle)."""
    return {VERSIONS_KEY: np.array(json.dumps(versions())), **{k: v for k, v in arrays.items() if k != VERSIONS_KEY}}


def atomic_write(path: str | Path, write: Callable[[str], None]) -> None:
    """Call ``write(tmp)`` on a temporary file beside ``path``, then rename it to ``path``.

    A crash at any moment leaves either the old file or the new one, never a partial one.
    The file gets the permissions a plain ``open`` would give (0666 less the umask). A process
    killed mid-write (SIGKILL, power) cannot remove its temporary: the temporary carries the
    writer's process id, and the next write of ``path`` removes those of processes no longer alive.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    _remove_orphans(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.{os.getpid()}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    try:
        write(tmp)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


def _remove_orphans(path: Path) -> None:
    """Remove the temporaries of ``path`` left by writers that died (see :func:`atomic_write`)."""
    for tmp in path.parent.glob(f".{glob.escape(path.name)}.*"):
        pid = tmp.name[len(path.name) + 2 :].split(".", 1)[0]
        if not pid.isdigit():
            continue
        try:
            os.kill(int(pid), 0)  # signal 0: only asks whether the process exists
        except ProcessLookupError:
            tmp.unlink(missing_ok=True)
        except OSError:
            pass  # alive, owned by another user


def check_writable(path: str | Path, *, folder: bool) -> Path:
    """``path`` as a ``Path`` if a file (``folder`` False) or a folder (True) can be made there
    and written into; a one-line ``ValueError`` otherwise (the caller names the option).

    Run before the work whose results go there, so that a run never ends in an error about its
    output: the nearest part of ``path`` that exists must be a folder (or, for a file, the file
    itself beside a folder), and a probe file is created in that folder and removed, which
    catches what permission bits cannot tell (read-only or virtual file systems, ``root``).
    Nothing is left behind; folders still to be made are made by the writer."""
    path = Path(path)
    here = next((p for p in (path, *path.parents) if p.exists()), Path("."))  # the nearest part that exists
    if folder and not here.is_dir():
        raise ValueError(f"{path} is a file, not a folder" if here == path else
                         f"cannot make the folder {path}: {here} is a file")  # fmt: skip
    if not folder:
        if path.is_dir():
            raise ValueError(f"{path} is a folder, not a file")
        if here != path and not here.is_dir():
            raise ValueError(f"cannot make {path}: {here} is a file")
    probe = here if here.is_dir() else path.parent  # the folder the file's temporary goes in
    try:
        fd, name = tempfile.mkstemp(prefix=".fosmc-probe-", dir=probe)
        os.close(fd)
        os.remove(name)
    except OSError as e:
        raise ValueError(f"cannot write in {probe}: {e.strerror or e}") from None
    return path


def write_text(path: str | Path, text: str) -> None:
    """Atomically write ``text`` to ``path``."""
    atomic_write(path, lambda tmp: Path(tmp).write_text(text))


def read_json(path: str | Path) -> Any:
    """The JSON in the file ``path``; a one-line ``ValueError`` where it cannot be read or is
    not JSON."""
    try:
        return json.loads(Path(path).read_text())
    except OSError as e:
        raise ValueError(f"cannot read {str(path)!r}: {e.strerror or e}") from None
    except ValueError:
        raise ValueError(f"{path} is not JSON") from None


def jsonable(x: Any) -> Any:
    """Arrays to lists, non-finite floats to None (JSON has no NaN/inf)."""
    if isinstance(x, dict):
        return {k: jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if hasattr(x, "__array__") and not isinstance(x, (float, int)):
        return jsonable(np.asarray(x).tolist())
    if isinstance(x, (float, np.floating)):
        return float(x) if math.isfinite(x) else None
    if isinstance(x, (np.bool_, np.integer)):
        return x.item()
    return x
