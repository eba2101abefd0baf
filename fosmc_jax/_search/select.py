"""Choosing one point of a Pareto front (``fosmc select``): the point that best meets a bound
on one of the front's two axes, and the ``[controller]`` TOML that puts its parameters into a
config.

The axes are the front's own (:data:`fosmc_jax._search.front.AXES`, computed by
:func:`fosmc_jax._search.front.axes`): a ``front.json`` point stores its ``metrics`` per joint,
each a mean over the batch's rollouts (over those that did not diverge, which is every rollout
of every front point unless every evaluated point had a diverged one), and an axis is the mean
of those over the joints, i.e. the mean over rollouts and joints of ``rms_error`` (rad) and of
``chattering_hf`` (V). The ``held_out`` metrics of a point play no part.
"""

from __future__ import annotations

import copy
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from .._controllers.kind import space_of
from .._io import read_json
from .._simulator.metrics import UNITS
from .front import AXES, axes


def select(front: str | Path | dict, *, max_error: float | None = None,
           max_chattering: float | None = None) -> dict[str, Any]:  # fmt: skip
    """The front point that best meets one bound: with ``max_error``, the least mean
    ``chattering_hf`` among the points of mean ``rms_error`` <= max_error (rad); with
    ``max_chattering``, the least mean ``rms_error`` among those of mean ``chattering_hf`` <=
    max_chattering (V). Exactly one bound, positive and finite. Ties go to the lowest index.

    ``front``: a ``front.json`` path or its loaded dict (``fosmc_jax.run_front``'s result).
    Returns ``{"index": i, "params": ..., "metrics": ..., "mean": {"rms_error": e,
    "chattering_hf": c}}``: point i's ``params`` and per-joint ``metrics`` (3,) as in the file,
    and its two axis values. Raises ``ValueError`` (one line) for a bad bound, a file that is
    not a front, or a bound no point meets (naming the least value on that axis)."""
    bounded, bound = _bound(max_error, max_chattering)
    data, name = _load(front)
    values = dict(zip(AXES, _axes(data, name)))
    other = AXES[1 - AXES.index(bounded)]
    meets = values[bounded] <= bound  # NaN (a point with a diverged rollout) never meets it
    if not meets.any():
        least = int(np.nanargmin(values[bounded]))
        unit = UNITS[bounded]
        raise ValueError(f"no point of {name} has mean {bounded} <= {bound:.4g} {unit}; the least is "
                         f"{values[bounded][least]:.4g} {unit} (point {least})")  # fmt: skip
    candidates = np.flatnonzero(meets)
    i = int(candidates[np.argmin(values[other][candidates])])  # argmin: the first of equal values
    point = data["points"][i]
    return {"index": i, "params": copy.deepcopy(point["params"]), "metrics": copy.deepcopy(point["metrics"]),
            "mean": {k: float(values[k][i]) for k in AXES}}  # fmt: skip


def controller_toml(params: dict) -> str:
    """The ``[controller]`` TOML lines (one string, newline-separated) that put a controller
    kind's parameters by name (a front point's or a ``fosmc tune`` result's ``params``) into
    a config: the table header, ``kind = "<kind>"`` and one line per parameter under its config
    key (:class:`fosmc_jax.search.Param`'s ``key``: the FOSMC's ``delta``, ``gamma``,
    ``poles``; SMC's ``smc_k``, ``smc_phi``; super-twisting's ``st_k1``, ``st_k2``), values at
    full precision. Raises ``ValueError`` if the names are no kind's parameter set."""
    space = space_of(params)
    lines = ["[controller]", f'kind = "{space.kind}"']
    for p in space.params:
        if p.name in params:
            try:
                value = json.dumps(np.asarray(params[p.name], float).tolist(), allow_nan=False)
            except ValueError:
                raise ValueError(f"{p.name}: expected finite numbers, got {params[p.name]!r}") from None
            lines.append(f"{p.key} = {value}")
    return "\n".join(lines)


def _bound(max_error: float | None, max_chattering: float | None) -> tuple[str, float]:
    """The bounded axis and the bound, checked: exactly one given, positive and finite."""
    given = {k: v for k, v in (("max_error", max_error), ("max_chattering", max_chattering)) if v is not None}
    if len(given) != 1:
        raise ValueError(f"give exactly one of max_error, max_chattering, got {', '.join(given) or 'neither'}")
    key, value = next(iter(given.items()))
    axis = AXES[0] if key == "max_error" else AXES[1]
    try:
        bound = float(value)
    except (TypeError, ValueError):
        bound = math.nan
    if isinstance(value, bool) or not (math.isfinite(bound) and bound > 0):
        raise ValueError(f"{key}: expected a positive finite number ({UNITS[axis]}), got {value!r}")
    return axis, bound


def _load(front: str | Path | dict) -> tuple[dict, str]:
    """A front's dict and the name its errors use (its path, or "the front")."""
    if isinstance(front, dict):
        data, name = front, "the front"
    else:
        data, name = read_json(front), str(front)
    if not isinstance(data, dict) or not isinstance(data.get("points"), list):
        raise ValueError(f"{name} is not a fosmc front (no list of points; `fosmc front` writes front.json)")
    if not data["points"]:
        raise ValueError(f"{name} is a front of no points")
    if data.get("axes", list(AXES)) != list(AXES):
        raise ValueError(f"{name} is a front in {data['axes']}, not in {list(AXES)}")
    return data, name


def _axes(data: dict, name: str) -> tuple[np.ndarray, np.ndarray]:
    """The front's two axes per point (n,), as the front computes them (NaN: a point with a
    diverged rollout, unless every point has one)."""
    points = data["points"]
    try:
        m = {k: np.asarray([p["metrics"][k] for p in points], float) for k in AXES}
        m["diverged"] = np.asarray([p.get("diverged", 0) for p in points], float)
        ok = all(isinstance(p["params"], dict) for p in points) and all(m[k].ndim == 2 for k in AXES)
    except (KeyError, TypeError, ValueError, AttributeError):
        ok = False
    if not ok:
        raise ValueError(f"{name} is not a fosmc front: every point needs params and per-joint metrics "
                         f"{' and '.join(AXES)}")  # fmt: skip
    return axes(m)
