"""The model the controller is designed on (``[model] from``): the paper's rows and box as the
config gives them, or rows and a box derived from the config's ``[arm]`` along its reference, as
the paper built its Appendix box (docs/arm.md)."""

from __future__ import annotations

import functools
import json
from collections.abc import Mapping
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .._design.gains import DesignSummary, summarize
from .._plants.arm import EXOGENOUS, ArmParams, rows_over
from .._plants.reference import Cycloid, desired_state
from .schema import BOX_KEYS, ConfigError
from .tables import Config


def cycloid(trajectory: Mapping[str, Any], dtype) -> Cycloid:
    """The reference (30) of a ``[trajectory]`` table (start, end, duration), in ``dtype``."""
    return Cycloid(*(jnp.asarray(np.asarray(trajectory[k], dtype=np.float64), dtype)
                     for k in ("start", "end", "duration")))  # fmt: skip


#: The arm's design model samples its rows at this many instants evenly over [0,
#: trajectory.duration] (the reference's motion; X_d rests at its end afterwards) x this many
#: payloads evenly over arm.payload_range.
ARM_MODEL_TIMES, ARM_MODEL_PAYLOADS = 81, 11
#: At most this many corners of [arm.uncertainty]'s ranges enter the arm's box: all 2^m corners of
#: m varying entries up to 2^6, else a fixed draw of this many (each costs one evaluation of the
#: ARM_MODEL_TIMES x ARM_MODEL_PAYLOADS grid).
ARM_MODEL_CORNERS = 64


class DesignModel(NamedTuple):
    """The model the FOSMC is designed on: K (16), Omega, alpha, beta (31) and the gamma bounds
    (24)-(26) all follow from it. Rows 3, 6, 9 of A and B, float64 NumPy."""

    source: str  # "paper": [model] A_rows, B_rows and [plant.box]; "arm": derived from [arm]
    A_rows: np.ndarray  # (3, 9) nominal rows of A
    B_rows: np.ndarray  # (3, 3) nominal rows of B (B_bar)
    box: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]  # A_lower, A_upper, B_lower, B_upper
    sampled: str  # where the rows come from, in words


def design_model(cfg: Config, source: str | None = None) -> DesignModel:
    """The design model of a resolved config, from ``source`` (default ``model.from``):
    ``"paper"``: ``[model] A_rows``, ``B_rows`` and ``[plant.box]`` as given; ``"arm"`` (an arm
    plant only): derived from ``[arm]`` along the configured reference (:func:`_arm_model`), once
    per arm, ranges and reference (memoised on their values: the first derivation compiles and
    evaluates the arm's rows, seconds; read-only arrays)."""
    source = source or cfg.model.source
    if source == "arm":
        if cfg.plant.kind != "arm":
            raise ConfigError(not_an_arm(cfg.plant.kind))
        return _arm_model(_arm_model_key(cfg))
    rows = (np.asarray(x, dtype=np.float64) for x in (cfg.model.A_rows, cfg.model.B_rows))
    box = tuple(np.asarray(getattr(cfg.plant.box, k), dtype=np.float64) for k in BOX_KEYS)
    return DesignModel("paper", *rows, box, "[model] A_rows, B_rows and [plant.box]")


def design_summary(cfg: Config, source: str | None = None) -> DesignSummary:
    """:func:`fosmc_jax.summarize` of the config's design model (:func:`design_model`) with its
    C and poles: alpha, beta (31) by vertex enumeration of the box (seconds), K (16), CB and
    the gamma bounds (24)-(26)."""
    d = design_model(cfg, source)
    return summarize(d.A_rows, d.B_rows, d.box, cfg.controller.C, cfg.controller.poles)


def box_of(cfg: Config) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The uncertainty box of the config's design model, float64 (A_lower, A_upper, B_lower,
    B_upper): ``[plant.box]``, or the arm's with ``model.from = "arm"`` (:func:`design_model`)."""
    return design_model(cfg).box


def not_an_arm(plant_kind: str) -> str:
    """The error of ``model.from = "arm"`` on a plant of kind ``plant_kind`` (not an arm)."""
    return (f"model.from: 'arm' derives the design model from [arm], for plant.kind = 'arm' only; got plant.kind "
            f"= '{plant_kind}'")  # fmt: skip


def _arm_model_key(cfg: Config) -> str:
    """What the arm's design model depends on, as JSON text (the memo's key): the nominal arm,
    its relative half-widths, ``arm.payload_range`` and ``[trajectory]``; not the number, seed
    or sampling of ``[arm.uncertainty]``'s arms nor the payloads simulated, so that a config's
    training, plain and held-out problems (``fosmc front``) share one controller."""
    arm = cfg.arm
    inputs = {"arm": arm.params._asdict(), "widths": arm.uncertainty.widths._asdict(),
              "payload_range": arm.payload_range, "trajectory": cfg.trajectory.as_dict()}  # fmt: skip
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
        reference = cycloid(inputs["trajectory"], jnp.float64)
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


def _design_arms(arm: Mapping[str, Any], widths: Mapping[str, Any]) -> tuple[list[ArmParams], str]:
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
