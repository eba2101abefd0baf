"""Running metrics of a rollout, accumulated while the time loop runs.

Samples k = 0..n, t_k = k dt, n = round(t_final / dt). u_k is the control computed from the
state at t_k (the last one, u_n, included) and e_k = theta(t_k) - theta_d(t_k). Per joint:

- ``rms_error``       sqrt(mean_k e_k^2)                     (rad)
- ``max_abs_error``   max_k |e_k|                            (rad)
- ``final_abs_error`` |e_n|                                  (rad)
- ``chattering``      sum_{k<n} |u_{k+1} - u_k| / t_final    (V/s): total variation rate
- ``control_rms``     sqrt(mean_k u_k^2)                     (V)
- ``max_abs_control`` max_k |u_k|                            (V)
- ``chattering_hf``   sqrt(1/t_final int_0^t_final (u(t) - ubar(t))^2 dt)   (V): RMS of the
  control's part above the cutoff f_c, over the applied control u(t) = u_k on [t_k, t_k+1)
  and its first-order low-pass ubar' = 2 pi f_c (u - ubar), ubar(0) = u_0, integrated
  exactly over each step (see :func:`lowpass`)
- ``saturation_fraction`` mean_k [|u_k| >= u_max]            (1): share of samples at the
  actuator's limit (0 without a limit)

``chattering`` counts all the motion of u, the smooth voltage the trajectory needs included;
``chattering_hf`` counts only what a low-pass filter with cutoff f_c (default 10 Hz, well
above the content of the reference (30) and below a sampled loop's switching) leaves out:
the switching part of the control. A smooth u of slope u' leaves about u' / (2 pi f_c).
Because it is the exact integral of the held control, a run with the control held over m
steps of dt / m gives the same ``chattering_hf`` as one step of dt (a sample form,
sqrt(mean_k (u_k - ubar_k)^2) with ubar updated by each new sample first, would lose about
a = 1 - exp(-2 pi f_c dt) of every jump: 2.8% between dt = 1 ms and 0.1 ms).

No trajectory is stored: the accumulator is O(1) in the number of steps.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
from jax import Array

from .._controllers.fosmc import safe_sqrt

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
    u_low: Array  # ubar(t_k), the low-pass filtered control
    sum_hf2: Array  # int_0^t_k (u - ubar)^2 dt (V^2 s)
    saturated: Array  # number of samples with |u_k| >= u_max


def lowpass(dt: Array, cutoff: Array) -> tuple[Array, Array]:
    """(decay, weight) of a first-order low-pass with cutoff ``cutoff`` (Hz) over a step of
    ``dt`` (s) with its input held at u: the residual r = u - ubar decays as r(t) = r_0 e^(-w t),
    w = 2 pi f_c, so ubar(dt) = u - r_0 decay, decay = e^(-w dt), and int_0^dt r^2 dt' = r_0^2
    weight, weight = (1 - e^(-2 w dt)) / (2 w) (s)."""
    w = 2 * jnp.pi * cutoff
    return jnp.exp(-w * dt), -jnp.expm1(-2 * w * dt) / (2 * w)


def _at_limit(u: Array, u_max: Array | None) -> Array:
    return jnp.zeros_like(u) if u_max is None else (jnp.abs(u) >= u_max).astype(u.dtype)


def start(e: Array, u: Array, u_max: Array | None = None) -> Accumulator:
    """The accumulator after sample k = 0, with error ``e`` (3,) and control ``u`` (3,);
    ``u_max`` (3,) is the actuator's limit (None: no limit)."""
    zero = jnp.zeros_like(u)
    return Accumulator(jnp.ones((), e.dtype), e**2, jnp.abs(e), e, zero, u**2, jnp.abs(u), u, zero, _at_limit(u, u_max))


def add(acc: Accumulator, e: Array, u: Array, u_prev: Array, lowpass_step: tuple[Array, Array],
        u_max: Array | None = None) -> Accumulator:  # fmt: skip
    """Fold in one more step: the error ``e`` and control ``u`` at its end, the control
    ``u_prev`` held over it, the low-pass's (decay, weight) over it (:func:`lowpass`) and the
    actuator's limit."""
    decay, weight = lowpass_step
    r = u_prev - acc.u_low  # the residual at the step's start, decaying while u_prev is held
    return Accumulator(
        acc.count + 1,
        acc.sum_e2 + e**2,
        jnp.maximum(acc.max_e, jnp.abs(e)),
        e,
        acc.total_variation + jnp.abs(u - u_prev),
        acc.sum_u2 + u**2,
        jnp.maximum(acc.max_u, jnp.abs(u)),
        u_prev - r * decay,
        acc.sum_hf2 + r * r * weight,
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
        safe_sqrt(acc.sum_hf2 / t_final),
        acc.saturated / acc.count,
    )


def masked(metrics: Metrics, diverged: Array) -> Metrics:
    """``metrics`` with NaN wherever the rollout diverged (``diverged``: bool, the metrics'
    leading shape): a diverged rollout's sums stop at its divergence and would pass for a good
    rollout's (a NaN initial state diverges at t = 0 with every sum 0). Derivatives through the
    NaN entries are 0."""
    d = jnp.asarray(diverged)
    return Metrics(*(jnp.where(d.reshape(d.shape + (1,) * (jnp.ndim(m) - d.ndim)), jnp.nan, m) for m in metrics))


def mean_over_survivors(x: Array, diverged: Array) -> Array:
    """Mean of ``x`` (B, ...) over the rollouts (leading axis) that did not diverge
    (``diverged`` (B,) bool); NaN where all did. A diverged rollout's metrics are partial sums
    up to its divergence and never enter a mean. Traceable (the front's evaluator runs it under
    ``vmap``); NumPy arrays in, NumPy out (reports keep their float64 where JAX's x64 is off)."""
    xp = np if isinstance(x, np.ndarray) and isinstance(diverged, np.ndarray) else jnp
    ok = ~xp.asarray(diverged, bool)
    w = ok.reshape(ok.shape + (1,) * (xp.ndim(x) - 1))
    mean = xp.sum(xp.where(w, x, 0), 0) / xp.maximum(xp.sum(ok), 1)
    return xp.where(xp.any(ok), mean, xp.nan)


#: The percentiles :func:`batch_summary` gives.
PERCENTILES = (5, 50, 95)


def batch_summary(metrics: Metrics, diverged) -> dict:
    """Mean, worst (max) and :data:`PERCENTILES` of each metric per joint over the rollouts of a
    batch that did not diverge (leading batch axis), with the number excluded. NumPy, for
    reports."""
    ok = ~np.asarray(diverged, dtype=bool).reshape(-1)
    out = {"rollouts": int(ok.size), "diverged_excluded": int((~ok).sum()), "mean": {}, "max": {}}
    out.update({f"p{q}": {} for q in PERCENTILES})
    for name in METRIC_NAMES:
        v = np.asarray(getattr(metrics, name)).reshape(ok.size, -1)
        out["mean"][name] = np.asarray(mean_over_survivors(v, ~ok)).tolist()
        out["max"][name] = v[ok].max(axis=0).tolist() if ok.any() else [float("nan")] * v.shape[1]
        for q in PERCENTILES:
            out[f"p{q}"][name] = np.percentile(v[ok], q, axis=0).tolist() if ok.any() else [float("nan")] * v.shape[1]
    return out
