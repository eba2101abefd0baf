"""Running metrics of a rollout, accumulated while the time loop runs.

Samples k = 0..n, t_k = k dt, n = round(t_final / dt). u_k is the control computed from the
state at t_k (the last one, u_n, included) and e_k = theta(t_k) - theta_d(t_k). Per joint:

- ``rms_error``       sqrt(mean_k e_k^2)                     (rad)
- ``max_abs_error``   max_k |e_k|                            (rad)
- ``final_abs_error`` |e_n|                                  (rad)
- ``chattering``      sum_{k<n} |u_{k+1} - u_k| / t_final    (V/s): total variation rate
- ``control_rms``     sqrt(mean_k u_k^2)                     (V)
- ``max_abs_control`` max_k |u_k|                            (V)

No trajectory is stored: the accumulator is O(1) in the number of steps.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
from jax import Array

from ._controller import safe_sqrt

#: The metric names, in the order of :class:`Metrics`' fields.
METRIC_NAMES = (
    "rms_error",
    "max_abs_error",
    "final_abs_error",
    "chattering",
    "control_rms",
    "max_abs_control",
)


class Metrics(NamedTuple):
    """The six per-joint metrics, each of shape (3,) (or (batch, 3) when vmapped)."""

    rms_error: Array
    max_abs_error: Array
    final_abs_error: Array
    chattering: Array
    control_rms: Array
    max_abs_control: Array


class Accumulator(NamedTuple):
    """Running sums and maxima over the samples seen so far."""

    count: Array
    sum_e2: Array
    max_e: Array
    last_e: Array
    total_variation: Array
    sum_u2: Array
    max_u: Array


def start(e: Array, u: Array) -> Accumulator:
    """The accumulator after sample k = 0, with error ``e`` (3,) and control ``u`` (3,)."""
    return Accumulator(jnp.ones((), e.dtype), e**2, jnp.abs(e), e, jnp.zeros_like(u), u**2, jnp.abs(u))


def add(acc: Accumulator, e: Array, u: Array, u_prev: Array) -> Accumulator:
    """Fold in one more sample: error ``e``, control ``u``, and the previous control."""
    return Accumulator(
        acc.count + 1,
        acc.sum_e2 + e**2,
        jnp.maximum(acc.max_e, jnp.abs(e)),
        e,
        acc.total_variation + jnp.abs(u - u_prev),
        acc.sum_u2 + u**2,
        jnp.maximum(acc.max_u, jnp.abs(u)),
    )


def finish(acc: Accumulator, t_final: Array) -> Metrics:
    """The metrics from a finished accumulator; ``t_final`` = n dt (s)."""
    return Metrics(
        safe_sqrt(acc.sum_e2 / acc.count),
        acc.max_e,
        jnp.abs(acc.last_e),
        acc.total_variation / t_final,
        safe_sqrt(acc.sum_u2 / acc.count),
        acc.max_u,
    )


def batch_summary(metrics: Metrics, diverged) -> dict:
    """Mean and worst (max) of each metric over the rollouts of a batch that did not diverge
    (leading batch axis), with the number excluded. NumPy, for reports."""
    import numpy as np

    ok = ~np.asarray(diverged, dtype=bool)
    out = {"rollouts": int(ok.size), "diverged_excluded": int((~ok).sum()), "mean": {}, "max": {}}
    for name in METRIC_NAMES:
        v = np.asarray(getattr(metrics, name))[ok]
        out["mean"][name] = v.mean(axis=0).tolist() if v.size else [float("nan")] * 3
        out["max"][name] = v.max(axis=0).tolist() if v.size else [float("nan")] * 3
    return out
