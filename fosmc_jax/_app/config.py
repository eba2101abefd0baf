"""Configuration: TOML files, validation with one-line errors, and the objects they describe.

Every key is optional; the defaults are the paper's (from :mod:`fosmc_jax._design.paper`). A config
is resolved to a plain nested ``dict`` of Python numbers and lists (JSON-ready), then turned
into simulator inputs by :func:`build`. Errors are :class:`ConfigError` (a ``ValueError``)
with a message that names the key and the expected form.
"""

from __future__ import annotations

import copy
import functools
import json
import math
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .._controllers import KINDS, SPACES
from .._controllers.fosmc import LAWS, SWITCHING, FOSMCParams
from .._controllers.kind import space_of
from .._design import paper
from .._design.gains import CONVENTIONS, DesignError, DesignSummary, check_design, stable_step, summarize
from .._io import read_json
from .._loop.digital import DERIVATIVES, DigitalLoop, Sensors
from .._plants.arm import ARM_PARAMS, EXOGENOUS, PARAM_RULES, PAYLOAD_RANGE, Arm, ArmParams, centre_error, rows_over
from .._plants.linear import UNCERTAINTY, uncertain_plants
from .._plants.reference import Cycloid, desired_state
from .._search.tune import CHATTERING_METRICS, ERROR_METRICS, FORMS, MODES, OPTIMIZERS, SCALES, WORST_CASE
from .._simulator.problem import Problem
from .._simulator.rollout import INTEGRATORS, PAIRINGS
from . import memory

try:  # Python >= 3.11
    import tomllib
except ModuleNotFoundError:  # pragma: no cover - Python 3.10
    import tomli as tomllib


class ConfigError(ValueError):
    """A configuration key is missing its expected form (one-line message naming the key)."""


PLANT_KINDS = ("linear", "arm")
#: What the controller is designed on (``[model] from``): the paper's rows, or rows derived from ``[arm]``.
MODEL_SOURCES = ("paper", "arm")
BOX_KEYS = ("A_lower", "A_upper", "B_lower", "B_upper")
#: Longest run a config may ask for (steps); 1e8 steps of one rollout take minutes.
MAX_STEPS = 10**8
PRECISIONS = ("float32", "float64")
#: How ``[arm.uncertainty]`` draws its arms: uniformly in the ranges, or at their corners.
ARM_SAMPLING = ("uniform", "vertices")
#: The configs that ship with the package, by name (``build("realistic_arm")``).
PRESETS = {path.stem: path for path in sorted((Path(__file__).parent / "presets").glob("*.toml"))}


def defaults() -> dict[str, Any]:
    """The built-in configuration: the paper's model, design, gains and simulation."""
    return {
        "trajectory": {
            "start": paper.THETA_START.tolist(),
            "end": paper.THETA_END.tolist(),
            "duration": paper.TAU,
        },
        "model": {"from": "paper", "A_rows": paper.A_ROWS.tolist(), "B_rows": paper.B_ROWS.tolist()},
        "controller": {
            "C": paper.C.tolist(),
            "poles": paper.POLES.tolist(),
            "gamma": paper.GAMMA.tolist(),
            "switching": "ratio",
            "delta": paper.DELTA_SETS[0].tolist(),
            "law": "paper",
            "sample_period": 0.0,
            "delay_samples": 0,
            "kind": "fosmc",
            # every registered kind's own gains (fosmc_jax._controllers.kind), e.g. SMC's smc_k
            **{key: list(value) for kind in KINDS.values() for key, value in kind.gains.items()},
        },
        "sensors": {
            "encoder_counts": [0, 0, 0],
            "derivatives": "measured",
            "noise_std": [0.0] * 9,
            "seed": 0,
            "realizations": 1,
        },
        "actuator": {},  # u_max absent: no limit
        "plant": {
            "kind": "linear",
            "payloads": list(paper.PAYLOADS),
            "uncertainty": "none",
            "dA_rows": np.zeros((3, 9)).tolist(),
            "dB_rows": np.zeros((3, 3)).tolist(),
            "samples": 16,
            "seed": 0,
            "box": {
                "A_lower": paper.A_LOWER.tolist(),
                "A_upper": paper.A_UPPER.tolist(),
                "B_lower": paper.B_LOWER.tolist(),
                "B_upper": paper.B_UPPER.tolist(),
            },
        },
        "sim": {
            "t_final": paper.T_FINAL,
            "dt": 1e-4,
            "integrator": "rk4",
            "initial_offset": [0.0] * 9,
            "precision": "float64",
            "save_every": 0,
            "divergence_bound": 1e6,
            "pairing": "cross",
        },
        "sample": {"count": 0, "seed": 0, "payloads": [], "offsets": [0.0] * 9},
        # the arm of plant.kind = "arm": every ArmParams field (the calibrated values) and its payload range
        "arm": {
            **{k: np.asarray(v).tolist() for k, v in ARM_PARAMS._asdict().items()},
            "payload_range": list(PAYLOAD_RANGE),
            # relative half-widths of sampled arms (0: the field does not vary), their number and draw
            "uncertainty": {**{k: 0.0 for k in ArmParams._fields}, "samples": 0, "seed": 0, "sampling": "uniform"},
        },  # fmt: skip
        "tune": {
            "params": ["delta", "gamma", "poles"],
            "weight_error": 1.0,
            "weight_chattering": 1.0,
            "worst_case": "none",
            "worst_weight": 0.0,
            "cvar_alpha": 0.9,
            "penalty": 100.0,
            "steps": 100,
            "optimizer": "adam",
            "learning_rate": 0.0,
            "schedule": "cosine",
            "clip": 1.0,
            "mode": "auto",
            "checkpoint_every": 10,
            "remat_steps": 100,
            "gradient_window": 0.0,
            "train_dt": 0.0,
            "train_t_final": 0.0,
            "keep_gamma_bound": False,
            "gamma_bound_convention": "paper",
            "global_candidates": 1024,
            "objective": "weighted",
            "scale": "log",
            "error_metric": "rms_error",
            "chattering_metric": "chattering_hf",
            "error_bound": 0.0,
            "chattering_bound": 0.0,
            "bound_weight": 100.0,
        },
    }


# ---------------------------------------------------------------------------- validators


def _array(shape: tuple[int, ...], what: str, check: Callable[[np.ndarray], bool] | None = None):
    def validate(key: str, value: Any) -> Any:
        if not _all_numbers(value):
            raise ConfigError(f"{key}: expected {what}, got {_short(value)}")
        try:
            a = np.asarray(value, dtype=float)
        except (TypeError, ValueError, OverflowError):
            raise ConfigError(f"{key}: expected {what}, got {_short(value)}") from None
        if a.shape != shape:
            raise ConfigError(f"{key}: expected {what}, got {_short(value)}")
        if not np.all(np.isfinite(a)):
            raise ConfigError(f"{key}: expected {what} (finite), got {_short(value)}")
        if check is not None and not check(a):
            raise ConfigError(f"{key}: expected {what}, got {_short(value)}")
        return a.tolist()

    return validate


def _all_numbers(value: Any) -> bool:
    """True for a number (not a bool) or a (nested) list of them."""
    if isinstance(value, list):
        return all(_all_numbers(v) for v in value)
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _number(what: str, check: Callable[[float], bool] = lambda x: True):
    def validate(key: str, value: Any) -> Any:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{key}: expected {what}, got {_short(value)}")
        try:
            finite = math.isfinite(value)
        except OverflowError:
            finite = False
        if not finite:
            raise ConfigError(f"{key}: expected {what}, got {_short(value)}")
        if not check(value):
            raise ConfigError(f"{key}: expected {what}, got {_short(value)}")
        return float(value)

    return validate


def _integer(what: str, check: Callable[[int], bool]):
    def validate(key: str, value: Any) -> Any:
        if isinstance(value, bool) or not isinstance(value, int) or not check(value):
            raise ConfigError(f"{key}: expected {what}, got {_short(value)}")
        return int(value)

    return validate


def _choice(choices: tuple[str, ...] | Callable[[], tuple[str, ...]]):
    """A validator of one of ``choices`` (a callable: read at validation, for registries)."""

    def validate(key: str, value: Any) -> Any:
        allowed = choices() if callable(choices) else choices
        if value not in allowed:
            raise ConfigError(f"{key}: expected one of {', '.join(allowed)}; got {_short(value)}")
        return value

    return validate


def _boolean(key: str, value: Any) -> Any:
    if not isinstance(value, bool):
        raise ConfigError(f"{key}: expected true or false, got {_short(value)}")
    return value


def _names(choices: Callable[[], tuple[str, ...]]):
    def validate(key: str, value: Any) -> Any:
        allowed = choices()
        if not isinstance(value, list) or not value or any(v not in allowed for v in value):
            raise ConfigError(f"{key}: expected a non-empty list drawn from {', '.join(allowed)}; got {_short(value)}")
        return list(dict.fromkeys(value))

    return validate


def _payloads(key: str, value: Any) -> Any:
    what = "a non-empty list of non-negative payloads (kg; within arm.payload_range)"
    if not isinstance(value, list) or not value:
        raise ConfigError(f"{key}: expected {what}, got {_short(value)}")
    return _array((len(value),), what, lambda a: np.all(a >= 0))(key, value)


_payload_range = _array((2,), "[low, high] kg with 0 <= low <= high", lambda a: 0 <= a[0] <= a[1])


def _sample_payloads(key: str, value: Any) -> Any:
    """``[sample] payloads``: a range to draw from, or [] (none drawn)."""
    return [] if value == [] else _payload_range(key, value)


def _half_width(key: str, value: Any) -> Any:
    """A relative half-width in [0, 1): one number, or one per joint for the per-joint fields."""
    what = "a relative half-width in [0, 1) (0.3: x U(0.7, 1.3)), or 3 of them for a per-joint parameter"
    name = key.rsplit(".", 1)[1]
    if isinstance(value, list) and np.ndim(getattr(ARM_PARAMS, name)) == 1:
        return _array((3,), what, lambda a: np.all((a >= 0) & (a < 1)))(key, value)
    return _number(what, lambda x: 0 <= x < 1)(key, value)


def _offset_scales(key: str, value: Any) -> Any:
    what = "a non-negative number or 9 of them (standard deviations of the initial offsets; 0: none drawn)"
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        value = [value] * 9
    return _array((9,), what, lambda a: np.all(a >= 0))(key, value)


def _offsets(key: str, value: Any) -> Any:
    what = "9 numbers, or a non-empty list of lists of 9 numbers"
    a = np.asarray(value, dtype=object)
    if a.ndim == 1:
        return _array((9,), what)(key, value)
    if a.ndim == 2 and a.shape[0] >= 1:
        return _array((a.shape[0], 9), what)(key, value)
    raise ConfigError(f"{key}: expected {what}, got {_short(value)}")


def _counts(key: str, value: Any) -> Any:
    what = "a non-negative integer, or 3 of them (encoder counts per revolution; 0: exact)"
    values = value if isinstance(value, list) else [value]
    if len(values) not in (1, 3) or any(isinstance(v, bool) or not isinstance(v, int) or v < 0 for v in values):
        raise ConfigError(f"{key}: expected {what}, got {_short(value)}")
    return values * 3 if len(values) == 1 else values


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


_finite = lambda a: True
SCHEMA: dict[str, Any] = {
    "trajectory": {
        "start": _array((3,), "3 numbers (rad)"),
        "end": _array((3,), "3 numbers (rad)"),
        "duration": _number("a positive number (s)", lambda x: x > 0),
    },
    "model": {
        "from": _choice(MODEL_SOURCES),
        "A_rows": _array((3, 9), "a 3x9 matrix (rows 3, 6, 9 of A)"),
        "B_rows": _array((3, 3), "a 3x3 matrix (rows 3, 6, 9 of B)"),
    },
    "controller": {
        "C": _array((3, 9), "a 3x9 matrix"),
        "poles": _array((3, 3), "a 3x3 matrix of negative numbers (1/s)", lambda a: np.all(a < 0)),
        "gamma": _array((3,), "3 non-negative numbers", lambda a: np.all(a >= 0)),
        "switching": _choice(SWITCHING),
        "delta": _array((3,), "3 positive numbers", lambda a: np.all(a > 0)),
        "law": _choice(LAWS),
        "sample_period": _number("a non-negative number (s; 0: the ideal loop)", lambda x: x >= 0),
        "delay_samples": _integer("a non-negative integer (controller samples)", lambda n: n >= 0),
        "kind": _choice(lambda: tuple(KINDS)),
    },
    "sensors": {
        "encoder_counts": _counts,
        "derivatives": _choice(DERIVATIVES),
        "noise_std": _array((9,), "9 non-negative numbers", lambda a: np.all(a >= 0)),
        "seed": _integer("a non-negative integer", lambda n: n >= 0),
        "realizations": _integer("a positive integer", lambda n: n >= 1),
    },
    "actuator": {
        "u_max": _array((3,), "3 positive numbers (V)", lambda a: np.all(a > 0)),
    },
    "plant": {
        "kind": _choice(PLANT_KINDS),
        "payloads": _payloads,
        "uncertainty": _choice(UNCERTAINTY),
        "dA_rows": _array((3, 9), "a 3x9 matrix"),
        "dB_rows": _array((3, 3), "a 3x3 matrix"),
        "samples": _integer("a positive integer", lambda n: n >= 1),
        "seed": _integer("a non-negative integer", lambda n: n >= 0),
        "box": {
            "A_lower": _array((3, 9), "a 3x9 matrix"),
            "A_upper": _array((3, 9), "a 3x9 matrix"),
            "B_lower": _array((3, 3), "a 3x3 matrix"),
            "B_upper": _array((3, 3), "a 3x3 matrix"),
        },
    },
    "sim": {
        "t_final": _number("a positive number (s)", lambda x: x > 0),
        "dt": _number("a positive number (s)", lambda x: x > 0),
        "integrator": _choice(INTEGRATORS),
        "initial_offset": _offsets,
        "precision": _choice(PRECISIONS),
        "save_every": _integer("a non-negative integer", lambda n: n >= 0),
        "divergence_bound": _number("a positive number", lambda x: x > 0),
        "pairing": _choice(PAIRINGS),
    },
    "arm": {  # a real arm's ranges (fosmc_jax._plants.arm.PARAM_RULES, which Problem.with_arm checks too)
        **{
            k: _number(what, lambda x, r=rule: bool(r(np.asarray(x))))
            if shape == ()
            else _array(shape, what, lambda a, r=rule: bool(np.all(r(a))))
            for k, (shape, rule, what) in PARAM_RULES.items()
        },  # fmt: skip
        "payload_range": _payload_range,
        "uncertainty": {
            **{k: _half_width for k in ArmParams._fields},
            "samples": _integer(
                "a non-negative integer (0: no sampled arms; with vertices: every corner)", lambda n: n >= 0
            ),  # fmt: skip
            "seed": _integer("a non-negative integer", lambda n: n >= 0),
            "sampling": _choice(ARM_SAMPLING),
        },
    },
    "sample": {
        "count": _integer("a non-negative integer (0: no sampling)", lambda n: n >= 0),
        "seed": _integer("a non-negative integer", lambda n: n >= 0),
        "payloads": _sample_payloads,
        "offsets": _offset_scales,
    },
    "tune": {
        "params": _names(lambda: tuple(name for space in SPACES.values() for name in space.names)),
        "weight_error": _number("a non-negative number", lambda x: x >= 0),
        "weight_chattering": _number("a non-negative number", lambda x: x >= 0),
        "worst_case": _choice(WORST_CASE),
        "worst_weight": _number("a non-negative number", lambda x: x >= 0),
        "cvar_alpha": _number("a number in [0, 1)", lambda x: 0 <= x < 1),
        "penalty": _number("a positive number", lambda x: x > 0),
        "steps": _integer("a positive integer", lambda n: n >= 1),
        "optimizer": _choice(OPTIMIZERS),
        "learning_rate": _number("a non-negative number (0: automatic)", lambda x: x >= 0),
        "schedule": _choice(("cosine", "constant")),
        "clip": _number("a positive number", lambda x: x > 0),
        "mode": _choice(MODES),
        "checkpoint_every": _integer("a non-negative integer", lambda n: n >= 0),
        "remat_steps": _integer("a non-negative integer", lambda n: n >= 0),
        "gradient_window": _number("a non-negative number (s; 0: automatic)", lambda x: x >= 0),
        "train_dt": _number("a non-negative number (s; 0: automatic)", lambda x: x >= 0),
        "train_t_final": _number("a non-negative number (s; 0: sim.t_final)", lambda x: x >= 0),
        "keep_gamma_bound": _boolean,
        "gamma_bound_convention": _choice(CONVENTIONS),
        "global_candidates": _integer("a non-negative integer (0: no global stage)", lambda n: n >= 0),
        "objective": _choice(FORMS),
        "scale": _choice(SCALES),
        "error_metric": _choice(ERROR_METRICS),
        "chattering_metric": _choice(CHATTERING_METRICS),
        "error_bound": _number("a non-negative number (rad; used by objective = 'error_bound')", lambda x: x >= 0),
        "chattering_bound": _number("a non-negative number (used by objective = 'chattering_bound')", lambda x: x >= 0),
        "bound_weight": _number("a positive number", lambda x: x > 0),
    },
}


def _schema() -> dict[str, Any]:
    """:data:`SCHEMA` with every registered controller kind's gains (3 positive numbers each)."""
    positive = _array((3,), "3 positive numbers", lambda a: np.all(a > 0))
    gains = {key: positive for kind in KINDS.values() for key in kind.gains}
    return dict(SCHEMA, controller={**SCHEMA["controller"], **gains})


def _merge(schema: dict, base: dict, user: Any, prefix: str) -> dict:
    if not isinstance(user, dict):
        raise ConfigError(f"{prefix or 'config'}: expected a table, got {_short(user)}")
    out = dict(base)
    for key, value in user.items():
        shown = key if str(key).isidentifier() else repr(key)
        name = f"{prefix}.{shown}" if prefix else shown
        if key not in schema:
            known = ", ".join(sorted(schema))
            raise ConfigError(f"{name}: unknown key (known here: {known})")
        rule = schema[key]
        out[key] = _merge(rule, base[key], value, name) if isinstance(rule, dict) else rule(name, _plain(name, value))
    return out


def _plain(key: str, value: Any) -> Any:
    """NumPy and JAX arrays and scalars as the Python numbers and lists a TOML file gives."""
    if isinstance(value, (list, tuple)):
        return [_plain(key, v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    if hasattr(value, "__array__") and not isinstance(value, (str, bytes)):
        if isinstance(value, jax.core.Tracer):
            raise ConfigError(f"{key}: expected concrete numbers, got a traced value (build the config outside jit)")
        return np.asarray(value).tolist()
    return value


def resolve(user: dict | None = None) -> dict[str, Any]:
    """Validate a user configuration (nested dict, e.g. parsed TOML) and fill in defaults.

    ``[tune] params`` defaults to every parameter of the config's ``controller.kind``.
    Raises :class:`ConfigError` naming the first offending key.
    """
    cfg = _merge(_schema(), defaults(), copy.deepcopy(user or {}), "")
    if "params" not in (user or {}).get("tune", {}):
        cfg["tune"]["params"] = list(SPACES[cfg["controller"]["kind"]].names)
    _check_consistency(cfg)
    return cfg


def load(path: str | Path | None) -> dict[str, Any]:
    """Read and :func:`resolve` a TOML file, or a preset's by its name (:data:`PRESETS`, e.g.
    ``"realistic_arm"``; a file of that name in the working folder comes first); ``None``: the
    defaults."""
    if path is None:
        return resolve({})
    if isinstance(path, str) and path in PRESETS and not Path(path).exists():
        path = PRESETS[path]
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as e:
        raise ConfigError(f"cannot read config file {str(path)!r}: {e.strerror or e}") from None
    try:
        text = data.decode("utf-8")  # TOML is UTF-8 whatever the locale
    except UnicodeDecodeError as e:
        raise ConfigError(f"{path}: not UTF-8 text (a TOML file is UTF-8; byte {e.start} is {data[e.start]:#04x}); "
                          "save it as UTF-8") from None  # fmt: skip
    try:
        user = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{path}: not valid TOML: {e}") from None
    return resolve(user)


def check_horizon(t_final: Any, dt: Any, names: tuple[str, str] = ("sim.t_final", "sim.dt")) -> None:
    """The rules of ``[sim] t_final`` and ``dt``: each a positive finite number, dt at most
    t_final, at most :data:`MAX_STEPS` steps; a :class:`ConfigError` naming ``names`` (the
    keys, or a command's options: ``fosmc reproduce --t-final``, ``--dt``) otherwise."""
    t_name, dt_name = names
    SCHEMA["sim"]["t_final"](t_name, t_final)
    SCHEMA["sim"]["dt"](dt_name, dt)
    if dt > t_final:
        raise ConfigError(f"{dt_name}: expected at most {t_name} = {t_final}, got {dt}")
    if t_final / dt > MAX_STEPS:
        raise ConfigError(f"{dt_name}: t_final / dt must be at most {MAX_STEPS:.0e} steps, got {t_final / dt:.3g}")


def _check_consistency(cfg: dict) -> None:
    sim, ctl, model, box = cfg["sim"], cfg["controller"], cfg["model"], cfg["plant"]["box"]
    if sim["dt"] > sim["t_final"]:
        raise ConfigError(f"sim.dt: expected at most sim.t_final = {sim['t_final']}, got {sim['dt']}")
    sample = cfg["sample"]
    drawn = bool(sample["payloads"]) or any(sample["offsets"])
    if sample["count"] and not drawn:
        raise ConfigError("sample.count: nothing to draw (set sample.payloads = [low, high] or sample.offsets)")
    if drawn and not sample["count"]:
        key = "payloads" if sample["payloads"] else "offsets"
        raise ConfigError(f"sample.{key}: draws nothing without sample.count, the number of draws (0 by default)")
    if sample["payloads"] and cfg["plant"]["kind"] != "arm":
        raise ConfigError("sample.payloads: applies to plant.kind = 'arm' only")
    _check_arm(cfg)
    if cfg["plant"]["kind"] == "arm" and cfg["plant"]["uncertainty"] != "none":
        raise ConfigError("plant.uncertainty: applies to kind = 'linear' only (the arm's uncertainty is its payloads)")
    tune = cfg["tune"]
    for form, key in (("error_bound", "error_bound"), ("chattering_bound", "chattering_bound")):
        if tune["objective"] == form and not tune[key] > 0:
            raise ConfigError(f"tune.{key}: expected a positive bound with tune.objective = '{form}', got {tune[key]}")
    train_t = cfg["tune"]["train_t_final"] or sim["t_final"]
    if train_t > sim["t_final"]:
        raise ConfigError(f"tune.train_t_final: expected at most sim.t_final = {sim['t_final']}, got {train_t}")
    if cfg["tune"]["train_dt"] > train_t:
        raise ConfigError(
            f"tune.train_dt: expected at most the training horizon {train_t}, got {cfg['tune']['train_dt']}"
        )
    check_horizon(sim["t_final"], sim["dt"])
    _check_loop(cfg)
    for m in ("A", "B"):
        if np.any(np.asarray(box[f"{m}_lower"]) > np.asarray(box[f"{m}_upper"])):
            raise ConfigError(f"plant.box.{m}_lower: must not exceed plant.box.{m}_upper entrywise")
    if abs(np.linalg.det(np.asarray(model["B_rows"]))) < 1e-12:
        raise ConfigError("model.B_rows: must be invertible (B_bar)")
    _check_model_from(cfg)
    design = design_model(cfg)  # with from = "arm": derived here, once per arm (memoised)
    try:
        check_design(design.B_rows, np.asarray(ctl["C"]), np.asarray(ctl["poles"]))
    except DesignError as e:
        raise ConfigError(f"controller: {e}") from None
    h = stable_step(design.A_rows, design.B_rows, ctl["poles"], sim["integrator"])
    if sim["dt"] > h:
        warnings.warn(
            f"sim.dt = {sim['dt']} s exceeds the {sim['integrator']} stability limit {h:.3g} s of the "
            "nominal model's fastest mode: expect divergence",
            stacklevel=2,
        )


def _check_arm(cfg: dict) -> None:
    """The ``[arm]`` table's cross-field rules, and the payloads within its range."""
    arm = cfg["arm"]
    unc = arm["uncertainty"]
    varying = [k for k in ArmParams._fields if np.any(np.asarray(unc[k]) > 0)]
    varies = bool(varying)
    if varies and cfg["plant"]["kind"] != "arm":
        raise ConfigError(f"arm.uncertainty.{varying[0]}: applies to plant.kind = 'arm' only")
    if cfg["plant"]["kind"] != "arm":  # an [arm] table the linear model would ignore
        base = defaults()["arm"]
        for k in (*ArmParams._fields, "payload_range"):
            if not np.array_equal(np.asarray(arm[k], float), np.asarray(base[k], float)):
                raise ConfigError(f"arm.{k}: applies to plant.kind = 'arm' only")
    if varies and not unc["samples"] and unc["sampling"] == "uniform":
        raise ConfigError("arm.uncertainty.samples: expected a positive number of sampled arms with half-widths set")
    if unc["samples"] and not varies:
        raise ConfigError("arm.uncertainty.samples: nothing varies (set a half-width, e.g. arm.uncertainty.F = 0.3)")
    for k in varying:  # relative half-widths: a zero stays zero (the Coulomb and disturbance defaults)
        width, nominal = np.asarray(unc[k], float), np.asarray(arm[k])
        if np.ndim(width) and np.any((width > 0) & (nominal == 0)) or not np.any((width > 0) & (nominal != 0)):
            raise ConfigError(f"arm.uncertainty.{k}: a relative half-width of arm.{k} = {_short(arm[k])} varies "
                              f"nothing where it is zero (a zero stays zero); set arm.{k}, the nominal")  # fmt: skip
    # parameters of a term that is absent in every joint: a half-width on them varies nothing either
    for k, term in (("v_coulomb", "Fc"), ("f_sin", "tau_sin"), ("t_step", "tau_step")):
        if k in varying and not np.any(np.asarray(arm[term])):
            raise ConfigError(f"arm.uncertainty.{k}: varies nothing while arm.{term} is zero; set arm.{term}")
    silent = (np.asarray(arm["tau_sin"]) != 0) & (np.asarray(arm["f_sin"]) == 0)
    if np.any(silent):
        joint = np.flatnonzero(silent)[0] + 1
        raise ConfigError(f"arm.tau_sin: a sinusoid at arm.f_sin = 0 Hz is zero (joint {joint}); set arm.f_sin")
    for j in (2, 3):
        if error := centre_error(arm[f"c{j}"], arm[f"l{j}"], j):
            raise ConfigError(error)
    lo, hi = arm["payload_range"]
    for key, values in (("plant.payloads", cfg["plant"]["payloads"]), ("sample.payloads", cfg["sample"]["payloads"])):
        if values and not lo <= min(values) <= max(values) <= hi:
            raise ConfigError(f"{key}: expected payloads within arm.payload_range = [{lo:g}, {hi:g}] kg, "
                              f"got {_short(values)}")  # fmt: skip


def arm_params_of(cfg: dict, dtype) -> ArmParams:
    """The ``[arm]`` table's :class:`fosmc_jax.ArmParams`, as arrays of ``dtype``."""
    return ArmParams(**{k: jnp.asarray(np.asarray(cfg["arm"][k], dtype=float), dtype) for k in ArmParams._fields})


def sample_steps(cfg: dict) -> int:
    """m = controller.sample_period / sim.dt (1 for the ideal loop)."""
    T = cfg["controller"]["sample_period"]
    return max(1, round(T / cfg["sim"]["dt"])) if T else 1


def _check_loop(cfg: dict) -> None:
    ctl, sens, sim = cfg["controller"], cfg["sensors"], cfg["sim"]
    T, dt = ctl["sample_period"], sim["dt"]
    if T == 0:
        digital = {"controller.delay_samples": ctl["delay_samples"] != 0,
                   "sensors.encoder_counts": any(sens["encoder_counts"]),
                   "sensors.derivatives": sens["derivatives"] != "measured",
                   "sensors.noise_std": any(sens["noise_std"]),
                   "sensors.realizations": sens["realizations"] != 1,
                   "actuator.u_max": "u_max" in cfg["actuator"]}  # fmt: skip
        for key, set_ in digital.items():
            if set_:
                raise ConfigError(
                    f"{key}: needs controller.sample_period > 0 (the ideal loop reads the exact state; "
                    f"sample_period = sim.dt = {dt} gives a digital loop at the simulation's rate)"
                )
        return
    horizon = sim["t_final"]
    if T > horizon:  # a period past the horizon samples once, at t = 0 (and overflows the step count)
        raise ConfigError(f"controller.sample_period: expected at most sim.t_final = {horizon} s (the controller "
                          f"samples every period), got {T}")  # fmt: skip
    m = T / dt
    if round(m) < 1 or abs(m - round(m)) > 1e-9 * max(1.0, m):
        raise ConfigError(f"controller.sample_period: expected an integer multiple (>= 1) of sim.dt = {dt}, got {T}")
    samples = math.ceil(round(horizon / dt) / round(m))  # the controller's samples within the horizon
    if ctl["delay_samples"] >= samples:
        raise ConfigError(f"controller.delay_samples: expected fewer than the {samples} controller sample(s) within "
                          f"sim.t_final = {horizon} s (a delay of that many or more means the controller never acts "
                          f"on the plant), got {ctl['delay_samples']}")  # fmt: skip
    train_t = cfg["tune"]["train_t_final"]
    if train_t and ctl["delay_samples"] >= math.ceil(train_t / T - 1e-9):  # tune's training horizon
        raise ConfigError(f"tune.train_t_final: expected more than controller.delay_samples = "
                          f"{ctl['delay_samples']} controller samples of {T} s (within it the controller would never "
                          f"act), got {train_t}")  # fmt: skip
    if sim["save_every"] % round(m):
        raise ConfigError(
            f"sim.save_every: expected a multiple of controller.sample_period / sim.dt = {round(m)}, "
            f"got {sim['save_every']}"
        )
    train_dt = cfg["tune"]["train_dt"]
    if train_dt and (T / train_dt < 1 - 1e-9 or abs(T / train_dt - round(T / train_dt)) > 1e-9 * T / train_dt):
        raise ConfigError(f"tune.train_dt: expected a step that divides controller.sample_period = {T}, got {train_dt}")
    if sens["derivatives"] == "difference" and any(np.asarray(sens["noise_std"])[[1, 2, 4, 5, 7, 8]]):
        raise ConfigError(
            "sensors.noise_std: with sensors.derivatives = 'difference' only the theta entries (1, 4, 7) may be "
            f"non-zero (the rates are differences of the measured angles), got {sens['noise_std']}"
        )


# ---------------------------------------------------------------------------- objects


def box_of(cfg: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The uncertainty box of the config's design model, float64 (A_lower, A_upper, B_lower,
    B_upper): ``[plant.box]``, or the arm's with ``model.from = "arm"`` (:func:`design_model`)."""
    return design_model(cfg).box


def controller_of(cfg: dict, dtype, gamma=None) -> FOSMCParams:
    """The :class:`FOSMCParams` a config describes (``gamma`` overrides ``controller.gamma``),
    on the nominal rows of its design model (:func:`design_model`)."""
    cast = lambda x: jnp.asarray(np.asarray(x, dtype=np.float64), dtype)
    ctl, design = cfg["controller"], design_model(cfg)
    gamma = ctl["gamma"] if gamma is None else gamma
    return FOSMCParams(
        cast(ctl["C"]),
        cast(ctl["poles"]),
        cast(gamma),
        cast(ctl["delta"]),
        cast(design.A_rows),
        cast(design.B_rows),
    )


# ---------------------------------------------------------------------------- the design model

#: The arm's design model samples its rows at this many instants evenly over [0,
#: trajectory.duration] (the reference's motion; X_d rests at its end afterwards) x this many
#: payloads evenly over arm.payload_range: the 81 x 11 grid fosmc bounds sampled the arm on before.
ARM_MODEL_TIMES, ARM_MODEL_PAYLOADS = 81, 11
#: At most this many corners of [arm.uncertainty]'s ranges enter the arm's box: all 2^m corners of
#: m varying entries up to 2^6, else a fixed draw of this many (each costs one evaluation of the
#: 81 x 11 grid, 35-70 ms on 2 cores under load).
ARM_MODEL_CORNERS = 64


class DesignModel(NamedTuple):
    """The model the FOSMC is designed on: K (16), Omega, alpha, beta (31) and the gamma bounds
    (24)-(26) all follow from it. Rows 3, 6, 9 of A and B, float64 NumPy."""

    source: str  # "paper": [model] A_rows, B_rows and [plant.box]; "arm": derived from [arm]
    A_rows: np.ndarray  # (3, 9) nominal rows of A
    B_rows: np.ndarray  # (3, 3) nominal rows of B (B_bar)
    box: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]  # A_lower, A_upper, B_lower, B_upper
    sampled: str  # where the rows come from, in words


def design_model(cfg: dict, source: str | None = None) -> DesignModel:
    """The design model of a resolved config, from ``source`` (default ``model.from``):
    ``"paper"``: ``[model] A_rows``, ``B_rows`` and ``[plant.box]`` as given; ``"arm"`` (an arm
    plant only): derived from ``[arm]`` along the configured reference (:func:`_arm_model`), once
    per arm, ranges and reference (memoised on their values: the first derivation compiles and
    evaluates the arm's rows, seconds; read-only arrays)."""
    source = source or cfg["model"]["from"]
    if source == "arm":
        if cfg["plant"]["kind"] != "arm":
            raise ConfigError(_not_an_arm(cfg))
        return _arm_model(_arm_model_key(cfg))
    rows = (np.asarray(cfg["model"][k], dtype=np.float64) for k in ("A_rows", "B_rows"))
    box = tuple(np.asarray(cfg["plant"]["box"][k], dtype=np.float64) for k in BOX_KEYS)
    return DesignModel("paper", *rows, box, "[model] A_rows, B_rows and [plant.box]")


def design_summary(cfg: dict, source: str | None = None) -> DesignSummary:
    """:func:`fosmc_jax.summarize` of the config's design model (:func:`design_model`) with its
    C and poles: alpha, beta (31) by vertex enumeration of the box (seconds), K (16), CB and
    the gamma bounds (24)-(26)."""
    d = design_model(cfg, source)
    return summarize(d.A_rows, d.B_rows, d.box, cfg["controller"]["C"], cfg["controller"]["poles"])


def _not_an_arm(cfg: dict) -> str:
    return (f"model.from: 'arm' derives the design model from [arm], for plant.kind = 'arm' only; got plant.kind "
            f"= '{cfg['plant']['kind']}'")  # fmt: skip


def _check_model_from(cfg: dict) -> None:
    """``model.from = "arm"``: an arm plant, and none of the paper's rows or box it replaces set."""
    if cfg["model"]["from"] != "arm":
        return
    if cfg["plant"]["kind"] != "arm":
        raise ConfigError(_not_an_arm(cfg))
    base = defaults()
    tables = (("model", cfg["model"], base["model"], ("A_rows", "B_rows")),
              ("plant.box", cfg["plant"]["box"], base["plant"]["box"], BOX_KEYS))  # fmt: skip
    for name, table, default, keys in tables:
        for k in keys:
            if table[k] != default[k]:  # a resolved config holds the defaults: only a user's value differs
                raise ConfigError(f"{name}.{k}: not used with model.from = 'arm' (the design model is derived from "
                                  "[arm]); remove it, or set model.from = 'paper'")  # fmt: skip


def _arm_model_key(cfg: dict) -> str:
    """What the arm's design model depends on, as JSON text (the memo's key): the nominal arm,
    its relative half-widths, ``arm.payload_range`` and ``[trajectory]``; not the number, seed
    or sampling of ``[arm.uncertainty]``'s arms nor the payloads simulated, so that a config's
    training, plain and held-out problems (``fosmc front``) share one controller."""
    arm = cfg["arm"]
    inputs = {"arm": {k: arm[k] for k in ArmParams._fields},
              "widths": {k: arm["uncertainty"][k] for k in ArmParams._fields},
              "payload_range": arm["payload_range"], "trajectory": cfg["trajectory"]}  # fmt: skip
    return json.dumps(inputs, sort_keys=True)


@functools.lru_cache(maxsize=16)
def _arm_model(key: str) -> DesignModel:
    """The arm's design model (``key``: :func:`_arm_model_key`), as the paper built its Appendix
    box (docs/arm.md): the instantaneous rows :func:`fosmc_jax.third_order_rows` of each design arm
    (the nominal ``[arm]`` and the corners of ``[arm.uncertainty]``'s ranges, :func:`_design_arms`)
    at ``ARM_MODEL_PAYLOADS`` payloads evenly over ``arm.payload_range`` x the reference's states
    X_d(t) at ``ARM_MODEL_TIMES`` instants evenly over [0, duration]; each arm's elementwise min
    and max widened by the piecewise-linear interpolation error h^2/8 max|f''| along each axis
    (h^2 f'' estimated by the largest second difference), so that the box also holds the rows
    between the samples; the box is their hull and the nominal its midpoint."""
    inputs = json.loads(key)
    arms, which = _design_arms(inputs["arm"], inputs["widths"])
    low, high = inputs["payload_range"]
    duration = inputs["trajectory"]["duration"]
    lower = upper = None
    with jax.enable_x64(True):  # (not ensure_compile_time_eval: rows_over would compile a second time)
        reference = reference_of(inputs, jnp.float64)
        times = jnp.linspace(0.0, duration, ARM_MODEL_TIMES, dtype=jnp.float64)
        states = jax.vmap(lambda t: desired_state(reference(t)))(times)
        payloads = jnp.linspace(low, high, ARM_MODEL_PAYLOADS, dtype=jnp.float64)
        for params in arms:
            a, b = rows_over(params, payloads, states)
            rows = np.concatenate([np.asarray(a), np.asarray(b)], axis=-1)  # (payloads, times, 3, 12)
            margin = sum(np.abs(np.diff(rows, 2, axis=axis)).max(axis=(0, 1)) for axis in (0, 1)) / 8
            lo, hi = rows.min(axis=(0, 1)) - margin, rows.max(axis=(0, 1)) + margin
            lower = lo if lower is None else np.minimum(lower, lo)
            upper = hi if upper is None else np.maximum(upper, hi)
    nominal = (lower + upper) / 2

    def frozen(x: np.ndarray) -> np.ndarray:
        x = np.array(x)
        x.flags.writeable = False  # shared by every caller of the memo
        return x

    box = tuple(frozen(x[:, cols]) for cols in (slice(9), slice(9, None)) for x in (lower, upper))
    sampled = (f"{which}, at {ARM_MODEL_PAYLOADS} payloads over [{low:g}, {high:g}] kg x {ARM_MODEL_TIMES} states "
               f"along the reference over [0, {duration:g}] s")  # fmt: skip
    return DesignModel("arm", frozen(nominal[:, :9]), frozen(nominal[:, 9:]), box, sampled)


def _design_arms(arm: dict, widths: dict) -> tuple[list[ArmParams], str]:
    """The arms the design model is taken over, and their description: the nominal ``arm``
    ({field: value}), then the corners nominal x (1 +- h) of the relative half-widths ``widths``
    (every corner of the m entries that move the rows, h > 0 on a non-zero nominal outside the
    external torque, up to ``ARM_MODEL_CORNERS``, else the distinct ones of that many corners
    drawn with a fixed seed, whatever ``arm.uncertainty.seed``). Corners, not the sampled arms:
    the rows are monotone in most parameters (B_bar = M^-1 diag(Kt/L), the R/L and F terms), so
    every corner bounds the rows of every arm drawn in the ranges (a drawn subset of them need
    not), and the design does not change with the draw."""
    nominal = {k: np.asarray(arm[k], dtype=np.float64) for k in ArmParams._fields}
    h = {k: np.broadcast_to(np.asarray(widths[k], dtype=np.float64), v.shape) for k, v in nominal.items()}
    flat = np.concatenate([w.ravel() for w in h.values()])
    # the entries that move the rows: drawn (h > 0, nominal not 0: a zero stays zero), and not the
    # external torque's (outside the rows, third_order_rows)
    enters = np.concatenate([np.full(v.size, k not in EXOGENOUS) & (v.ravel() != 0) for k, v in nominal.items()])
    live = np.flatnonzero((flat > 0) & enters)
    m = live.size
    if not m:
        return [ArmParams(**nominal)], "the nominal arm"
    if 2**m <= ARM_MODEL_CORNERS:
        signs = 2.0 * ((np.arange(2**m)[:, None] >> np.arange(m)) & 1) - 1.0
        which = f"the nominal arm and the {2**m} corners of [arm.uncertainty]'s ranges"
    else:
        signs = np.unique(np.random.default_rng(0).choice([-1.0, 1.0], (ARM_MODEL_CORNERS, m)), axis=0)
        which = f"the nominal arm and {len(signs)} of the 2^{m} corners of [arm.uncertainty]'s ranges (a fixed draw)"
    u = np.zeros((len(signs), flat.size))
    u[:, live] = signs
    arms = [ArmParams(**nominal)]
    for row in u:
        fields, i = {}, 0
        for k, v in nominal.items():
            fields[k] = v * (1.0 + h[k] * row[i : i + v.size].reshape(v.shape))
            i += v.size
        arms.append(ArmParams(**fields))
    return arms, which


def _law_and_loop(cfg: dict, dtype) -> tuple[Callable[[FOSMCParams], Any], Callable[[Any], Any]]:
    """(law, loop): FOSMC parameters -> the config's kind of law with the config's gains,
    sampled with period T (T = 0: the ideal loop's); a law -> the controller of the config's
    loop (the ideal loop: the law itself, super-twisting's v integrated with the plant)."""
    ctl, sens = cfg["controller"], cfg["sensors"]
    cast = lambda x: jnp.asarray(np.asarray(x, dtype=np.float64), dtype)
    T = cast(ctl["sample_period"])
    sampled = bool(ctl["sample_period"])
    kind = KINDS[ctl["kind"]]
    table = dict(ctl, **{key: cast(ctl[key]) for key in kind.gains})  # the kind's gains as arrays
    law = lambda params: kind.law(params, table, T)
    if not sampled:
        return law, kind.ideal or (lambda law: law)
    noise_std = cast(sens["noise_std"]) if any(sens["noise_std"]) else None  # all zero: nothing to draw
    sensors = Sensors(cast(sens["encoder_counts"]), noise_std, sens["derivatives"])
    u_max = cast(cfg["actuator"].get("u_max", [np.inf] * 3))
    m, d = sample_steps(cfg), ctl["delay_samples"]
    return law, lambda law: DigitalLoop(law, sensors, u_max, T, m, d)


def keys_of(cfg: dict) -> Any:
    """One PRNG key per noise realization (``sensors.seed``, ``sensors.realizations``); None for
    the ideal loop."""
    if not cfg["controller"]["sample_period"]:
        return None
    return jax.random.split(jax.random.PRNGKey(cfg["sensors"]["seed"]), cfg["sensors"]["realizations"])


def reference_of(cfg: dict, dtype) -> Cycloid:
    """The reference (30) a config describes."""
    traj = cfg["trajectory"]
    return Cycloid(*(jnp.asarray(np.asarray(traj[k], dtype=np.float64), dtype) for k in ("start", "end", "duration")))


def n_steps(cfg: dict) -> int:
    """n = round(t_final / dt)."""
    return max(1, round(cfg["sim"]["t_final"] / cfg["sim"]["dt"]))


def as_config(config: str | Path | dict | None) -> dict[str, Any]:
    """The resolved config of a TOML path, a preset's name (:data:`PRESETS`), a user dict
    (validated, defaults filled in; NumPy and JAX arrays welcome where lists are), a resolved
    config (checked again, returned as a copy), or ``None`` (the paper's defaults)."""
    if config is None or isinstance(config, (str, Path)):
        return load(config)
    if isinstance(config, dict):
        return resolve(config)
    raise ConfigError(f"config: expected a TOML path, a preset name ({', '.join(PRESETS)}), a dict or None, "
                      f"got {type(config).__name__}")  # fmt: skip


def draws(cfg: dict) -> dict[str, np.ndarray]:
    """The ``[sample]`` table's Monte-Carlo draws, float64, seeded by ``sample.seed``: ``payloads``
    (count,) ~ U(low, high) kg when ``sample.payloads`` is set (drawn first), ``offsets``
    (count, 9) ~ N(0, diag(sample.offsets)^2) when any scale is positive (a scale of 0 leaves
    that state's offset 0); {} without sampling."""
    sample, out = cfg["sample"], {}
    arms = arm_samples(cfg)
    if arms is not None:
        out["arms"] = arms
    if not sample["count"]:
        return out
    rng, n = np.random.default_rng(sample["seed"]), sample["count"]
    if sample["payloads"]:
        out["payloads"] = rng.uniform(*sample["payloads"], size=n)
    if any(sample["offsets"]):
        out["offsets"] = rng.standard_normal((n, 9)) * np.asarray(sample["offsets"])
    return out


def arm_varies(cfg: dict) -> bool:
    """Whether ``[arm.uncertainty]`` sets a half-width, so :func:`arm_samples` draws arms (known
    without drawing them)."""
    return any(np.any(np.asarray(cfg["arm"]["uncertainty"][k], float) > 0) for k in ArmParams._fields)


def arm_samples(cfg: dict) -> dict[str, np.ndarray] | None:
    """``[arm.uncertainty]``'s arms, {field: (N, ...)} float64 (None: none): each field x (1 + h u),
    h its relative half-width, u ~ U(-1, 1) per entry (``sampling = "uniform"``, ``samples``
    arms, seeded), or u = +-1 at the corners of the ranges (``"vertices"``: every corner of the
    m varying entries when ``samples`` is 0 or at least 2^m, else that many distinct corners,
    seeded). The nominal arm is not one of them."""
    unc, arm = cfg["arm"]["uncertainty"], cfg["arm"]
    widths = {k: np.broadcast_to(np.asarray(unc[k], float), np.shape(arm[k])) for k in ArmParams._fields}
    flat = np.concatenate([w.ravel() for w in widths.values()])
    live = np.flatnonzero(flat > 0)
    if not live.size:
        return None
    rng = np.random.default_rng(unc["seed"])
    if unc["sampling"] == "uniform":
        u = rng.uniform(-1.0, 1.0, (unc["samples"], flat.size))
    else:
        m = live.size
        if m > 24:
            raise ConfigError(f"arm.uncertainty.sampling: 'vertices' of {m} varying entries is 2^{m} corners; "
                              "use 'uniform'")  # fmt: skip
        n = 2**m if not unc["samples"] or unc["samples"] >= 2**m else unc["samples"]
        codes = np.arange(n) if n == 2**m else rng.choice(2**m, size=n, replace=False)
        u = np.zeros((n, flat.size))
        u[:, live] = 2.0 * ((codes[:, None] >> np.arange(m)) & 1) - 1.0
    out, i = {}, 0
    for k, w in widths.items():
        size = w.size
        out[k] = np.asarray(arm[k], float) * (1.0 + w * u[:, i : i + size].reshape((-1,) + w.shape))
        i += size
    return out


def _paired_length(lengths: dict[str, int]) -> int:
    """The common length of what ``sim.pairing = "paired"`` pairs (a length of 1 is repeated)."""
    longer = {n for n in lengths.values() if n > 1}
    if len(longer) > 1:
        named = ", ".join(f"{name} ({n})" for name, n in lengths.items())
        raise ConfigError(f"sim.pairing: 'paired' needs as many of each, or one: got {named}")
    return longer.pop() if longer else 1


def _repeat(x, n: int):
    """``x`` (leading length 1 or n) with leading length n."""
    return x if len(x) == n else (jnp if isinstance(x, jax.Array) else np).repeat(x, n, axis=0)


def build(config: str | Path | dict | None = None) -> Problem:
    """The simulation a config describes (a TOML path, a preset's name such as
    ``"realistic_arm"``, a dict, or ``None``: the paper's defaults; see :func:`as_config`), as a
    :class:`fosmc_jax.Problem` in the config's ``sim.precision``: ``problem.simulate(params)``
    runs its batch.

    The plants are the linear model's uncertainty realizations (``kind = "linear"``) or one arm
    per payload (``kind = "arm"``). The initial states are X_d(0) + each ``sim.initial_offset``;
    the batch is every plant crossed with every initial state, crossed with every noise
    realization of a digital loop (in that order); with ``sim.pairing = "paired"`` the i-th plant
    runs from the i-th initial state only (one plant or one initial state: repeated). A
    ``[sample]`` table's draws (:func:`draws`) replace ``plant.payloads`` and
    ``sim.initial_offset``. The problem's ``base`` holds the kind's
    parameters: the FOSMC's :class:`FOSMCParams`, or the SMC's or super-twisting's law with
    the config's gains.

    A batch that cannot fit in the memory this process may use (:mod:`fosmc_jax._app.memory`:
    a lower bound of its memory above the smaller of the available memory and ``ulimit -v``) is
    refused before anything is drawn, naming the key to change.

    ``sim.precision = "float64"`` (the default) needs JAX's 64-bit mode, which only the user
    may switch on (it changes every array of the process):
    ``jax.config.update("jax_enable_x64", True)`` first, or ``with jax.enable_x64(True):``
    around the script, or ``[sim] precision = "float32"``.
    """
    cfg = as_config(config)
    too_large = memory.refusal(cfg)  # before anything is drawn
    if too_large is not None:
        raise ConfigError(too_large)
    return problem_of(cfg)


def problem_of(cfg: dict) -> Problem:
    """:func:`build` of a resolved config without its memory check, for a caller that holds
    the batch against memory itself (``fosmc simulate`` runs it in chunks:
    :func:`fosmc_jax._app.memory.plan`)."""
    if cfg["sim"]["precision"] == "float64" and not jax.config.jax_enable_x64:
        raise ConfigError('sim.precision: "float64" needs JAX\'s 64-bit mode: call jax.config.update('
                          '"jax_enable_x64", True) before building, or set [sim] precision = "float32"')  # fmt: skip
    dtype = jnp.dtype(cfg["sim"]["precision"])
    cast = lambda x: jnp.asarray(np.asarray(x, dtype=float), dtype)
    ctl, model, plant = cfg["controller"], cfg["model"], cfg["plant"]
    reference = reference_of(cfg, dtype)
    drawn = draws(cfg)
    paired = cfg["sim"]["pairing"] == "paired"
    offsets = np.atleast_2d(np.asarray(drawn.get("offsets", cfg["sim"]["initial_offset"]), dtype=float))
    if plant["kind"] == "arm":
        payloads = np.asarray(drawn.get("payloads", plant["payloads"]), dtype=float)
        arms = drawn.get("arms") or {k: np.asarray(cfg["arm"][k], float)[None] for k in ArmParams._fields}
        n_arms = len(arms["F"])
        if paired:  # the i-th arm sample with the i-th payload and the i-th initial state
            n = _paired_length({"arm samples": n_arms, "payloads": len(payloads), "initial offsets": len(offsets)})
            arms, payloads, offsets = ({k: _repeat(v, n) for k, v in arms.items()}, _repeat(payloads, n),
                                       _repeat(offsets, n))  # fmt: skip
        else:  # every arm sample with every payload, the arm sample first
            arms = {k: np.repeat(v, len(payloads), axis=0) for k, v in arms.items()}
            payloads = np.tile(payloads, n_arms)
        plants = Arm(ArmParams(**{k: cast(v) for k, v in arms.items()}), cast(payloads))
    else:
        plants = uncertain_plants(
            model["A_rows"], model["B_rows"], plant["uncertainty"], box=box_of(cfg),
            dA_rows=plant["dA_rows"], dB_rows=plant["dB_rows"], samples=plant["samples"], seed=plant["seed"],
        )  # fmt: skip
        plants = type(plants)(*(cast(x) for x in plants))
        if paired:
            n = _paired_length({"plants": len(plants.a_rows), "initial offsets": len(offsets)})
            plants, offsets = jax.tree.map(lambda x: _repeat(x, n), plants), _repeat(offsets, n)
    X0s = desired_state(reference(jnp.zeros((), dtype)))[None] + cast(offsets)
    options = {
        "n_steps": n_steps(cfg),
        "integrator": cfg["sim"]["integrator"],
        "switching": ctl["switching"],
        "law": ctl["law"],
        "save_every": cfg["sim"]["save_every"],
        "divergence_bound": cfg["sim"]["divergence_bound"],
        "pairing": cfg["sim"]["pairing"],
    }
    dt = jnp.asarray(cfg["sim"]["dt"], dtype)
    params = controller_of(cfg, dtype)
    law, loop = _law_and_loop(cfg, dtype)
    if ctl["kind"] == "fosmc":
        base, make = params, lambda params: loop(law(params))
    else:  # the kind's parameters are fields of its law
        base, make = law(params), loop
    arm = arm_params_of(cfg, dtype) if plant["kind"] == "arm" else None  # the nominal, sampled arms around it
    return Problem(plants, base, reference, X0s, dt, options, keys_of(cfg), make, ctl["kind"], arm)


#: The automatic ``[tune] gradient_window`` (s) where the whole horizon's gradient explodes:
#: growth starts between 20 and 50 ms at 1 and 2 kHz alike (tuning/results/truncation.md).
GRADIENT_WINDOW = 0.02


def tuning_problems(cfg: dict):
    """(plain, train, p0): the :class:`fosmc_jax._simulator.problem.Problem` of ``[sim]`` (every result
    is evaluated on it), the training problem (``tune.train_dt``, ``tune.train_t_final``, the
    scan rematerialised every ``tune.remat_steps``; a digital loop without ``tune.train_dt``
    trains with dt = ``controller.sample_period``), and the config's values of its kind's
    parameters (``fosmc_jax._controllers.SPACES[kind].values``: the FOSMC's :class:`Tunable` of
    delta, gamma, poles; SMC's k, phi; super-twisting's k1, k2). The problems' ``base`` is what
    those parameters are fields of: the FOSMC's :class:`FOSMCParams`, or the SMC or
    super-twisting law built with the config's gains."""
    space = SPACES[cfg["controller"]["kind"]]
    train_cfg = copy.deepcopy(cfg)
    for key, sim_key in (("train_dt", "dt"), ("train_t_final", "t_final")):
        if cfg["tune"][key]:
            train_cfg["sim"][sim_key] = cfg["tune"][key]
    if not cfg["tune"]["train_dt"] and cfg["controller"]["sample_period"] > cfg["sim"]["dt"]:
        # a digital loop trains on one integration step per controller sample: it ranks candidates
        # like [sim]'s step (tuning/results/fidelity.md: Spearman's rho >= 0.9999 on both axes, the
        # same front, at 0.12-0.14 of the cost on three configs); results are re-evaluated on [sim]
        train_cfg["sim"]["dt"] = cfg["controller"]["sample_period"]

    def problem(c: dict, **options) -> Problem:
        b = build(c)
        return b._replace(options=dict(b.options, save_every=0, **options))

    plain = problem(cfg)
    # the gradient follows the loop over windows of tune.gradient_window (truncate_every): over the
    # whole horizon it grows exponentially on a digital loop that quantizes or differences its
    # measurements (at tune's start, the near-sign law of the global stage: to 9e226 on
    # realistic_arm, every step skipped, 4e34 over 1 s with measured rates) and is uphill under the
    # sign law, while 0.02 s windows give finite gradients that lower the plain loss; in the ideal
    # loop with a smooth law the whole horizon's is finite and tunes best (tuning/results/truncation.md)
    window_s = cfg["tune"]["gradient_window"]
    sensors, period = cfg["sensors"], cfg["controller"]["sample_period"]
    rough = period > cfg["sim"]["dt"] and (any(n > 0 for n in sensors["encoder_counts"])
                                           or sensors["derivatives"] == "difference")  # fmt: skip
    if not window_s and (rough or cfg["controller"]["switching"] == "sign"):
        window_s = GRADIENT_WINDOW
    window = int(round(window_s / train_cfg["sim"]["dt"]))
    remat = {"checkpoint_every": cfg["tune"]["remat_steps"], "truncate_every": window}
    # no surrogate: the same simulation (the same make and keys tell fosmc_jax._search.front so)
    train = problem(train_cfg, **remat) if train_cfg != cfg else plain._replace(options=dict(plain.options, **remat))
    p0 = space.values(*(getattr(plain.base, name) for name in space.names))
    return plain, train, p0


def with_params(cfg: dict, path: str | Path, point: int | None = None) -> dict:
    """``cfg`` with its controller kind's parameters (the FOSMC's delta, gamma, poles; SMC's
    k, phi; super-twisting's k1, k2) taken from a ``fosmc tune`` result file (its
    ``final.params``) or from point ``point`` of a ``fosmc front`` file, and put back into
    their config keys (``smc_k``, ...), validated like those keys. A file of another kind's
    parameters is refused."""
    try:
        data = read_json(path)
    except ValueError as e:
        raise ConfigError(f"--params: {e}") from None
    if isinstance(data, dict) and "points" in data:
        if point is None:
            raise ConfigError(f"--point: {path} is a front of {len(data['points'])} points: name one with --point I "
                              "(e.g. the one `fosmc select` names)")  # fmt: skip
        if not 0 <= point < len(data["points"]):
            raise ConfigError(f"--point: expected an index in [0, {len(data['points'])}) for the front {path}, "
                              f"got {point}")  # fmt: skip
        params = data["points"][point]["params"]
    else:
        if point is not None:
            raise ConfigError(f"--point: {path} is a tune result, not a front")
        try:
            params = data["final"]["params"]
        except (KeyError, TypeError):
            raise ConfigError(f"--params: {path} is not a fosmc tune result (no final.params) or front") from None
    try:
        space = space_of(params)
    except ValueError as e:
        raise ConfigError(f"--params: {path}'s {e}") from None
    kind = cfg["controller"]["kind"]
    if space.kind != kind:
        raise ConfigError(f"--params: {path} holds {space.kind} parameters ({', '.join(space.names)}), but the "
                          f"config's controller.kind is '{kind}' (set [controller] kind = '{space.kind}')")  # fmt: skip
    user = copy.deepcopy(cfg)
    user["controller"].update({p.key: params[p.name] for p in space.params if p.name in params})
    return resolve(user)
