"""Running metrics of a rollout, accumulated while the time loop runs.

Samples k = 0..n, t_k = k dt, n = round(t_final / dt). u_k is the control computed from the
state at t_k (the last one, u_n, included) and e_k = theta(t_k) - theta_d(t_k). Per joint:

- ``rms_error``       sqrt(mean_k e_k^2)                     (rad)
- ``max_abs_error``   max_k |e_k|                            (rad)
- ``final_abs_error`` |e_n|                                  (rad)
- ``chattering``      sum_{k<n} |u_{k+1} - u_k| / t_final    (V/s): total variation rate
- ``control_rms``     sqrt(mean_k u_k^2)                     (V)
- ``max_abs_control`` max_k |u_k|                            (V)
- ``chattering_hf``   sqrt(mean_k (u_k - ubar_k)^2)          (V): RMS of the control's part
  above the cutoff f_c, ubar the first-order low-pass of u (see :func:`lowpass_gain`)
- ``saturation_fraction`` mean_k [|u_k| >= u_max]            (1): share of samples at the
  actuator's limit (0 without a limit)

``chattering`` counts all the motion of u, the smooth voltage the trajectory needs included;
``chattering_hf`` counts only what a low-pass filter with cutoff f_c (default 10 Hz, well
above the content of the reference (30) and below a sampled loop's switching) leaves out:
the switching part of the control. A smooth u of slope u' leaves about u' / (2 pi f_c).

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
    "chattering_hf",
    "saturation_fraction",
)
#: Units of each metric, for tables and axis labels.
UNITS = dict(rms_error="rad", max_abs_error="rad", final_abs_error="rad", chattering="V/s", control_rms="V",
             max_abs_control="V", chattering_hf="V", saturation_fraction="1")  # fmt: skip
#: Default cutoff (Hz) of ``chattering_hf``'s low-pass filter.
CHATTERING_CUTOFF = 10.0


class Metrics(NamedTuple):
    """The per-joint metrics, each of shape (3,) (or (batch, 3) when vmapped)."""

    rms_error: Array
    max_abs_error: Array
    final_abs_error: Array
    chattering: Array
    control_rms: Array
    max_abs_control: Array
    chattering_hf: Array
    saturation_fraction: Array


class Accumulator(NamedTuple):
    """Running sums and maxima over the samples seen so far."""

    count: Array
    sum_e2: Array
    max_e: Array
    last_e: Array
    total_variation: Array
    sum_u2: Array
    max_u: Array
    u_low: Array  # ubar_k, the low-pass filtered control
    sum_hf2: Array  # sum_k (u_k - ubar_k)^2
    saturated: Array  # number of samples with |u_k| >= u_max


def lowpass_gain(dt: Array, cutoff: Array) -> Array:
    """a in ubar_{k+1} = ubar_k + a (u_{k+1} - ubar_k), ubar_0 = u_0: the exact discretisation
    of a first-order low-pass with cutoff ``cutoff`` (Hz) for samples ``dt`` (s) apart."""
    return 1 - jnp.exp(-2 * jnp.pi * cutoff * dt)


def _at_limit(u: Array, u_max: Array | None) -> Array:
    return jnp.zeros_like(u) if u_max is None else (jnp.abs(u) >= u_max).astype(u.dtype)


def start(e: Array, u: Array, u_max: Array | None = None) -> Accumulator:
    """The accumulator after sample k = 0, with error ``e`` (3,) and control ``u`` (3,);
    ``u_max`` (3,) is the actuator's limit (None: no limit)."""
    zero = jnp.zeros_like(u)
    return Accumulator(jnp.ones((), e.dtype), e**2, jnp.abs(e), e, zero, u**2, jnp.abs(u), u, zero, _at_limit(u, u_max))


def add(acc: Accumulator, e: Array, u: Array, u_prev: Array, a: Array, u_max: Array | None = None) -> Accumulator:
    """Fold in one more sample: error ``e``, control ``u``, the previous control, the
    low-pass gain ``a`` (:func:`lowpass_gain`) and the actuator's limit."""
    u_low = acc.u_low + a * (u - acc.u_low)
    return Accumulator(
        acc.count + 1,
        acc.sum_e2 + e**2,
        jnp.maximum(acc.max_e, jnp.abs(e)),
        e,
        acc.total_variation + jnp.abs(u - u_prev),
        acc.sum_u2 + u**2,
        jnp.maximum(acc.max_u, jnp.abs(u)),
        u_low,
        acc.sum_hf2 + (u - u_low) ** 2,
        acc.saturated if u_max is None else acc.saturated + _at_limit(u, u_max),
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
        safe_sqrt(acc.sum_hf2 / acc.count),
        acc.saturated / acc.count,
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
