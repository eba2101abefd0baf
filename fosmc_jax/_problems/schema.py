"""The config's schema: every table's keys with their defaults (:func:`defaults`, the paper's
numbers from :mod:`fosmc_jax._design.paper`) and their validators (:data:`SCHEMA`), each turning
one TOML value into a plain Python value or raising a one-line :class:`ConfigError` naming the
key and the expected form. The tuner's choices (objective forms, optimizers, metrics) are
declared here, below the search that implements them, so that a config can be checked without it.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from .._controllers import KINDS, SPACES
from .._controllers.fosmc import LAWS, SWITCHING
from .._design import paper
from .._design.gains import CONVENTIONS
from .._loop.digital import DERIVATIVES
from .._plants.arm import ARM_PARAMS, PARAM_RULES, PAYLOAD_RANGE, ArmParams
from .._plants.linear import UNCERTAINTY
from .._simulator.rollout import INTEGRATORS, PAIRINGS


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

# the tuner's choices (fosmc_jax._search.tune implements them)
WORST_CASE = ("none", "max", "cvar")
MODES = ("auto", "reverse", "forward")
FORMS = ("weighted", "error_bound", "chattering_bound")
SCALES = ("log", "linear")
ERROR_METRICS = ("rms_error", "max_abs_error")
CHATTERING_METRICS = ("chattering_hf", "chattering")
OPTIMIZERS = ("adam", "lbfgs")


def defaults() -> dict[str, Any]:
    """The built-in configuration: the paper's model, design, gains and simulation (a fresh dict
    of tables, each its own)."""
    return {
        "trajectory": {
            "start": paper.THETA_START.tolist(),
            "end": paper.THETA_END.tolist(),
            "duration": paper.TAU,
        },
        "model": {"from": "paper", "A_rows": paper.A_ROWS.tolist(), "B_rows": paper.B_ROWS.tolist()},
        "controller": _controller_defaults(),
        "sensors": {
            "encoder_counts": [0, 0, 0],
            "derivatives": "measured",
            "noise_std": [0.0] * 9,
            "seed": 0,
            "realizations": 1,
        },
        "actuator": {},  # u_max absent: no limit
        "plant": _plant_defaults(),
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
        "arm": _arm_defaults(),
        "tune": _tune_defaults(),
    }


def _controller_defaults() -> dict[str, Any]:
    """``[controller]``: the paper's FOSMC design (Table 1's first delta), and every registered
    kind's own gains (:attr:`fosmc_jax._controllers.kind.Kind.gains`, e.g. SMC's smc_k)."""
    return {
        "C": paper.C.tolist(),
        "poles": paper.POLES.tolist(),
        "gamma": paper.GAMMA.tolist(),
        "switching": "ratio",
        "delta": paper.DELTA_SETS[0].tolist(),
        "law": "paper",
        "sample_period": 0.0,
        "delay_samples": 0,
        "kind": "fosmc",
        **{key: list(value) for kind in KINDS.values() for key, value in kind.gains.items()},
    }


def _plant_defaults() -> dict[str, Any]:
    """``[plant]``: the paper's linear model at its payloads, its uncertainty box (31)."""
    return {
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
    }


def _arm_defaults() -> dict[str, Any]:
    """``[arm]``, the arm of plant.kind = "arm": every ArmParams field (the calibrated values),
    its payload range, and ``[arm.uncertainty]``: the relative half-widths of sampled arms (0:
    the field does not vary), their number and draw."""
    return {
        **{k: np.asarray(v).tolist() for k, v in ARM_PARAMS._asdict().items()},
        "payload_range": list(PAYLOAD_RANGE),
        "uncertainty": {**{k: 0.0 for k in ArmParams._fields}, "samples": 0, "seed": 0, "sampling": "uniform"},
    }


def _tune_defaults() -> dict[str, Any]:
    """``[tune]``: the tuner's options (``params``: the FOSMC's; a config of another kind tunes
    that kind's own)."""
    return {
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
        "starts": 1,
        "cma_generations": 100,
        "objective": "weighted",
        "scale": "log",
        "error_metric": "rms_error",
        "chattering_metric": "chattering_hf",
        "error_bound": 0.0,
        "chattering_bound": 0.0,
        "bound_weight": 100.0,
    }


# ---------------------------------------------------------------------------- validators


def _array(shape: tuple[int, ...], what: str, check: Callable[[np.ndarray], bool] | None = None):
    def validate(key: str, value: Any) -> Any:
        if not _all_numbers(value):
            raise ConfigError(f"{key}: expected {what}, got {short(value)}")
        try:
            a = np.asarray(value, dtype=float)
        except (TypeError, ValueError, OverflowError):
            raise ConfigError(f"{key}: expected {what}, got {short(value)}") from None
        if a.shape != shape:
            raise ConfigError(f"{key}: expected {what}, got {short(value)}")
        if not np.all(np.isfinite(a)):
            raise ConfigError(f"{key}: expected {what} (finite), got {short(value)}")
        if check is not None and not check(a):
            raise ConfigError(f"{key}: expected {what}, got {short(value)}")
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
            raise ConfigError(f"{key}: expected {what}, got {short(value)}")
        try:
            finite = math.isfinite(value)
        except OverflowError:
            finite = False
        if not finite:
            raise ConfigError(f"{key}: expected {what}, got {short(value)}")
        if not check(value):
            raise ConfigError(f"{key}: expected {what}, got {short(value)}")
        return float(value)

    return validate


def _integer(what: str, check: Callable[[int], bool]):
    def validate(key: str, value: Any) -> Any:
        if isinstance(value, bool) or not isinstance(value, int) or not check(value):
            raise ConfigError(f"{key}: expected {what}, got {short(value)}")
        return int(value)

    return validate


def _choice(choices: tuple[str, ...] | Callable[[], tuple[str, ...]]):
    """A validator of one of ``choices`` (a callable: read at validation, for registries)."""

    def validate(key: str, value: Any) -> Any:
        allowed = choices() if callable(choices) else choices
        if value not in allowed:
            raise ConfigError(f"{key}: expected one of {', '.join(allowed)}; got {short(value)}")
        return value

    return validate


def _boolean(key: str, value: Any) -> Any:
    if not isinstance(value, bool):
        raise ConfigError(f"{key}: expected true or false, got {short(value)}")
    return value


def _names(choices: Callable[[], tuple[str, ...]]):
    def validate(key: str, value: Any) -> Any:
        allowed = choices()
        if not isinstance(value, list) or not value or any(v not in allowed for v in value):
            raise ConfigError(f"{key}: expected a non-empty list drawn from {', '.join(allowed)}; got {short(value)}")
        return list(dict.fromkeys(value))

    return validate


def _payloads(key: str, value: Any) -> Any:
    what = "a non-empty list of non-negative payloads (kg; within arm.payload_range)"
    if not isinstance(value, list) or not value:
        raise ConfigError(f"{key}: expected {what}, got {short(value)}")
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
    raise ConfigError(f"{key}: expected {what}, got {short(value)}")


def _counts(key: str, value: Any) -> Any:
    what = "a non-negative integer, or 3 of them (encoder counts per revolution; 0: exact)"
    values = value if isinstance(value, list) else [value]
    if len(values) not in (1, 3) or any(isinstance(v, bool) or not isinstance(v, int) or v < 0 for v in values):
        raise ConfigError(f"{key}: expected {what}, got {short(value)}")
    return values * 3 if len(values) == 1 else values


def short(value: Any) -> str:
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
        "starts": _integer(
            "a positive integer (the global stage's best candidates tuned at once; 1: its best)", lambda n: n >= 1
        ),
        "cma_generations": _integer("a non-negative integer (0: no CMA-ES stage)", lambda n: n >= 0),
        "objective": _choice(FORMS),
        "scale": _choice(SCALES),
        "error_metric": _choice(ERROR_METRICS),
        "chattering_metric": _choice(CHATTERING_METRICS),
        "error_bound": _number("a non-negative number (rad; used by objective = 'error_bound')", lambda x: x >= 0),
        "chattering_bound": _number("a non-negative number (used by objective = 'chattering_bound')", lambda x: x >= 0),
        "bound_weight": _number("a positive number", lambda x: x > 0),
    },
}


def full_schema() -> dict[str, Any]:
    """:data:`SCHEMA` with every registered controller kind's gains (3 positive numbers each)."""
    positive = _array((3,), "3 positive numbers", lambda a: np.all(a > 0))
    gains = {key: positive for kind in KINDS.values() for key in kind.gains}
    return dict(SCHEMA, controller={**SCHEMA["controller"], **gains})


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
