"""What the commands' functions share: the config argument, the option checks with their one-line
errors, float64 inside the call, the warning on a batch of one plant."""

from __future__ import annotations

import functools
import numbers
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import numpy as np

from .. import _problems as problems
from .._io import check_writable
from .._problems import ConfigError
from .._simulator.metrics import UNITS

#: What a command takes as its config: a TOML path, a preset's name, a dict of TOML tables, a resolved
#: config, or None (the paper's defaults).
ConfigInput = str | Path | dict | problems.Config | None
Log = Callable[[str], None]


def _quiet(_: str) -> None:
    pass


def _with_x64(f):
    @functools.wraps(f)
    def wrapped(*args, **kwargs):
        with jax.enable_x64(True):
            return f(*args, **kwargs)

    return wrapped


def config_of(config: ConfigInput) -> problems.Config:
    """The resolved config (:func:`fosmc_jax._problems.as_config`: a TOML path, a preset's
    name, a user dict, a resolved config, or ``None`` for the paper's defaults)."""
    return problems.as_config(config)


def _fresh_out(out: str | Path, flags: bool, hint: str) -> Path:
    """``out``, a folder that can be made and written (:func:`writable`), empty unless ``flags``
    (``--force``, ``--resume``); else a :class:`ConfigError` naming ``--out``, before any work."""
    out = writable(out, "--out", folder=True)
    if out.exists() and any(out.iterdir()) and not flags:
        raise ConfigError(f"--out: {out} exists and is not empty ({hint})")
    return out


def writable(path: str | Path, option: str, *, folder: bool = False) -> Path:
    """``path`` (:func:`fosmc_jax._io.check_writable`: a file or folder that can be made and
    written there, probed now), or a one-line :class:`ConfigError` naming ``option``."""
    try:
        return check_writable(path, folder=folder)
    except ValueError as e:
        raise ConfigError(f"{option}: {e}") from None


def _is_integer(value: Any) -> bool:
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def _is_real(value: Any) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def one_plant(cfg: problems.Config) -> str | None:
    """What the one plant of a resolved config's batch is, or None where the batch holds several.

    One plant: ``plant.kind = "linear"`` with ``plant.uncertainty = "none"`` (the nominal model,
    the default config's) or ``"fixed"`` (the model plus ``plant.dA_rows``, ``plant.dB_rows``),
    or ``"sample"`` / ``"vertices"`` with ``plant.samples = 1`` or a box of zero width;
    ``plant.kind = "arm"`` with one distinct payload (drawn by ``[sample]`` or listed) and no
    sampled arms (``[arm.uncertainty]``). Initial offsets (``sim.initial_offset``)
    and noise realizations (``sensors.realizations``) vary the start and the measurements, not
    the plant, so they do not count."""
    plant = cfg.plant
    if plant.kind == "arm":
        payloads = sorted(set(plant.payloads))
        varied = (cfg.sample.count > 1 and cfg.sample.payloads) or problems.arm_varies(cfg)
        return f"the arm with a {payloads[0]:g} kg payload" if len(payloads) == 1 and not varied else None
    if plant.uncertainty == "none":
        return "the nominal linear model"
    if plant.uncertainty == "fixed":
        return "the linear model plus plant.dA_rows, plant.dB_rows"
    box = plant.box
    flat = np.array_equal(box.A_lower, box.A_upper) and np.array_equal(box.B_lower, box.B_upper)
    return "one plant of the box" if plant.samples == 1 or flat else None


def metric_label(name: str) -> str:
    """A metric's name with its unit, and what it is where its name does not say it."""
    return f"{name} ({UNITS[name]}{', total variation' if name == 'chattering' else ''})"


def _warn_one_plant(cfg: problems.Config, command: str) -> None:
    """``tune`` and ``front`` on a batch of :func:`one_plant`: a UserWarning that what they find
    holds for that plant only, and which keys add plant uncertainty."""
    what = one_plant(cfg)
    if what is not None:
        warnings.warn(
            f"{command}: the config's batch holds one plant ({what}) and no plant uncertainty: what {command} "
            "finds is optimal for that plant only. For an uncertain plant set [plant] uncertainty = 'sample' or "
            "'vertices' with samples > 1 (plants from [plant.box]) for kind = 'linear', or several [plant] "
            "payloads for kind = 'arm' (as tuning/configs/realistic_arm.toml does)",
            UserWarning,
            stacklevel=4,  # the caller of run_tune / run_front (through _with_x64)
        )
