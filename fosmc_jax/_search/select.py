"""Choosing one point of a Pareto front (``fosmc select``): the point that best meets a bound
on one of the front's two axes, and the ``[controller]`` TOML that puts its parameters into a
config.

The axes are the front's own (:data:`fosmc_jax._search.front.AXES`, computed by
:func:`fosmc_jax._search.front.axes`): a ``front.json`` point stores its ``metrics`` per joint,
each a mean over the batch's rollouts (over those that did not diverge, which is every rollout
of every front point unless every evaluated point had a diverged one), and an axis is the mean
of those over the joints, i.e. the mean over rollouts and joints of ``rms_error`` (rad) and of
``chattering_hf`` (V). Where the front holds each point's ``held_out`` metrics (``fosmc front``
evaluates every point on a batch training did not see: other payloads, fresh sampled arms), a
point is judged on the larger of its training and held-out value on each axis, and a point with
a diverged held-out rollout meets no bound: on the robust realistic front, points at 1-1.4 V that
hold on their training arms lose joint 3 by radians on an arm with a weaker motor
(tuning/results/held_out_split_realistic_robust.md).
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
           max_chattering: float | None = None, held_out: bool | None = None) -> dict[str, Any]:  # fmt: skip
    """The front point that best meets one bound: with ``max_error``, the least mean
    ``chattering_hf`` among the points of mean ``rms_error`` <= max_error (rad); with
    ``max_chattering``, the least mean ``rms_error`` among those of mean ``chattering_hf`` <=
    max_chattering (V). Exactly one bound, positive and finite. Ties go to the lowest index.

    ``held_out``: judge each point on the larger of its training and held-out means on each axis
    (a diverged held-out rollout: it meets no bound); None (the default): where every point of
    the front has held-out metrics, else on training alone; False: on training alone.

    ``front``: a ``front.json`` path or its loaded dict (``fosmc_jax.run_front``'s result).
    Returns ``{"index": i, "params": ..., "metrics": ..., "mean": {"rms_error": e,
    "chattering_hf": c}, "judged_on": "training" | "training and held-out"}``: point i's
    ``params`` and per-joint ``metrics`` (3,) as in the file, its two axis values as judged,
    and with held-out metrics ``"training_mean"`` and ``"held_out_mean"`` beside them. Raises
    ``ValueError`` (one line) for a bad bound, a file that is not a front, ``held_out=True``
    on a front without held-out metrics, or a bound no point meets (naming the least value on
    that axis)."""
    bounded, bound = _bound(max_error, max_chattering)
    data, name = _load(front)
    training = dict(zip(AXES, _axes(data, name)))
    has_held = all(isinstance(p.get("held_out"), dict) for p in data["points"])
    if held_out and not has_held:
        raise ValueError(f"{name} has no held-out metrics for every point (fronts before issue 25 do not): "
                         "select on training alone")  # fmt: skip
    use_held = has_held if held_out is None else held_out
    values, judged = training, "training"
    if use_held:
        held = dict(zip(AXES, _held_out_axes(data, name)))
        values, judged = {k: np.maximum(training[k], held[k]) for k in AXES}, "training and held-out"
    other = AXES[1 - AXES.index(bounded)]
    meets = values[bounded] <= bound  # NaN (a point with a diverged rollout) never meets it
    if not meets.any():
        if np.all(np.isnan(values[bounded])):
            raise ValueError(f"no point of {name} has mean {bounded} <= {bound:.4g} {UNITS[bounded]}: "
                             f"every point has a diverged rollout ({judged})")  # fmt: skip
        least = int(np.nanargmin(values[bounded]))
        unit = UNITS[bounded]
        raise ValueError(f"no point of {name} has mean {bounded} <= {bound:.4g} {unit} ({judged}); the least is "
                         f"{values[bounded][least]:.4g} {unit} (point {least})")  # fmt: skip
    candidates = np.flatnonzero(meets)
    i = int(candidates[np.argmin(values[other][candidates])])  # argmin: the first of equal values
    point = data["points"][i]
    out = {"index": i, "params": copy.deepcopy(point["params"]), "metrics": copy.deepcopy(point["metrics"]),
           "mean": {k: float(values[k][i]) for k in AXES}, "judged_on": judged}  # fmt: skip
    if use_held:
        out["training_mean"] = {k: float(training[k][i]) for k in AXES}
        out["held_out_mean"] = {k: float(held[k][i]) for k in AXES}
    return out


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


def _held_out_axes(data: dict, name: str) -> tuple[np.ndarray, np.ndarray]:
    """The two axes of each point's held-out metrics (n,): NaN where a held-out rollout diverged
    (``held_out_diverged``, or a joint's mean missing: every rollout diverged)."""
    points = data["points"]
    try:
        m = {k: np.asarray([[np.nan if x is None else x for x in p["held_out"][k]] for p in points], float)
             for k in AXES}  # fmt: skip
    except (KeyError, TypeError, ValueError):
        raise ValueError(f"{name}: a point's held_out needs per-joint metrics {' and '.join(AXES)}") from None
    bad = np.asarray([p.get("held_out_diverged", 0) for p in points], float) > 0
    bad |= np.isnan(m[AXES[0]]).any(-1) | np.isnan(m[AXES[1]]).any(-1)  # NaN on both axes: the point never meets
    return tuple(np.where(bad, np.nan, np.mean(m[k], -1)) for k in AXES)
