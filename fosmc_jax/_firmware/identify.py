"""The arm's physical parameters identified from a log of an experiment.

A log (:class:`Log`, read by :func:`read_log`; layouts in docs/identify.md) holds the sample
times t_j, the encoder angles theta_j (3,), the voltages u_j (3,) the drive wrote and, where
the drive measures them, the motor currents i_j (3,), in closed or open loop. The voltage written
at sample j reaches the motor ``delay`` samples later and is held until the next sample (zero-order
hold), as in the digital loop (:mod:`fosmc_jax._loop.digital`).

The model is the arm itself (:class:`fosmc_jax.Arm`: L i' = u - R i - Kb theta',
M theta'' + C theta' + G + F theta' + ... = Kt i), integrated between samples with the given
integrator and step at the log's own times, so the fit is differentiable in every
:class:`ArmParams` field and the payload. The fit is **multiple shooting**: the log is cut into
consecutive windows of ``window`` intervals; each window starts from its own free state x_w =
[theta, theta', theta''] per joint (the currents follow from it by :meth:`Arm.init`, so they
scale with the parameters), first estimated from the log by local cubic fits of the encoder
angles (Savitzky-Golay), and the windows are simulated side by side (``vmap``). The residuals
are (predicted - logged) / sigma per channel, sigma the channel's noise measured from the log
itself (the scatter about the local cubic fits, at least the encoder's quantum / sqrt(12)), then,
for a second pass, the channel's own residual. Levenberg-Marquardt minimises their sum of squares
over every x_w and the parameters' coordinates z: z = log(p / p0) for a positive entry (positivity
kept, and relative steps), (p - p0) / scale otherwise; p0 the configured value. Each window's 9
state unknowns are eliminated from the normal equations (Schur complement), so a step costs one
Jacobian (forward mode, 9 + p tangents per window) and a p x p solve. A trust region caps each
step's largest |dz| (:data:`MAX_STEP` at first), and the weakly identified entries (standard
deviation above :data:`WEAK` x the threshold) join only once the others are fitted: without
either, a parameter runs off (Jm or F to zero) while the others are still wrong (docs/identify.md).

**Identifiability.** Angles and voltages alone leave some directions of the parameters
invisible: scaling R, L and Kt of one joint together (the current scales the other way), or
every mass, inertia, F and Kt together, or Jm and I2[yy] of joint 2 (only their sum is in M),
leave the voltage-to-angle map unchanged. The reduced information S = sum_w (C_w - B_w^T
A_w^-1 B_w) (the Gauss-Newton Hessian in z with the window states eliminated) has an
eigen-direction v of standard deviation 1 / sqrt(lambda) (in units of z, i.e. relative) per
eigenvalue lambda; a direction whose standard deviation exceeds ``threshold`` is not identified
by the log. For each one, the entry with the largest weight in what is left of those directions
is fixed at its configured value (ties, within 5%, go to the entry named first), and the others
are fitted: the group's identifiable combinations come out right, its members only as right as
the fixed one. With currents in the log, Kt i is the torque and these scalings disappear.

**Uncertainty.** At the optimum, the Gauss-Newton covariance s^2 S^-1 (s^2 = RSS / (residuals -
unknowns)) and a one-step bootstrap over windows (resampled windows, one Gauss-Newton step from
the optimum with their S and gradient: the spread of the estimate when the windows vary, which
also covers residuals that are not white; skipped below :data:`BOOTSTRAP_WINDOWS` windows, and said
so); the larger of the two standard deviations is reported.
Both hold the fixed entries at their configured values; how each estimate moves with them,
-S_ff^-1 S_f,fixed, is reported beside (``moves_with_fixed``). Both assume the model is right: the
residuals the log's noise. A residual RMS more than :data:`MISFIT` times the angles' noise (the
log's scatter, at least the encoder's quantum / sqrt(12)) is a model error, a wrong parameter left
out of the fit or an effect the arm model lacks, and is reported with a warning (:func:`misfit`):
the estimates are then biased by more than their standard deviations say (docs/identify.md
gives an example).

Run in float64 (``jax.enable_x64``): the encoder's quantum is 1e-6 of the angles.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .._io import atomic_write, write_text
from .._plants.arm import Arm, ArmParams
from .._plants.base import derivative_at
from .._simulator.step import _STEPPERS

#: The name of the payload (kg) among the identifiable parameters (it is :class:`Arm`'s, not a field).
PAYLOAD = "payload"
#: Axis names of the principal inertias I2, I3 (the other (3,) fields are per joint 1, 2, 3).
_AXES = ("xx", "yy", "zz")
#: Half-width (samples) of the local cubic fits that estimate the window states and the noise.
SMOOTHING = 10
#: Largest move of a coordinate z in one step (0.2: about 20% of a positive entry).
MAX_STEP = 0.2
#: Directions with a standard deviation above WEAK x threshold are fitted last.
WEAK = 0.1
#: The delays (samples) :func:`identify` checks the configured one against: 0 to DELAYS (at most SMOOTHING).
DELAYS = 3
#: Levenberg-Marquardt steps (states and free parameters) of each other delay's check, from the fit's optimum.
DELAY_ITERATIONS = 10
#: Another delay whose cost is below the configured one's by more than this share is said to fit the log better
#: (:func:`delay_warning`); a right delay's neighbours cost more (docs/identify.md).
DELAY_MARGIN = 0.05
#: The fewest windows a bootstrap resamples (with fewer, the standard deviations are Gauss-Newton's only).
BOOTSTRAP_WINDOWS = 5
#: The residual RMS, in units of the angles' noise, above which the model does not explain the log
#: (:func:`misfit`): a right model leaves the noise (docs/identify.md), and at 10
#: the model's error is 99% of the residual's power; margin is left for what real logs hold beyond the
#: arm model and for noise the scatter about local cubics understates (correlated over 21 samples).
MISFIT = 10.0


class Log(NamedTuple):
    """A log of an experiment: ``t`` (N,) s, strictly increasing; ``theta`` (N, 3) rad, encoder
    angles; ``u`` (N, 3) V, the voltages written at each sample; ``current`` (N, 3) A or None."""

    t: np.ndarray
    theta: np.ndarray
    u: np.ndarray
    current: np.ndarray | None = None


class Settings(NamedTuple):
    """How :func:`identify` fits: ``window`` intervals per shooting window; ``delay`` samples
    between a logged voltage and the motor; ``integrator`` (``euler``, ``rk4``) and ``dt``, the
    longest integration step (s; each sample interval is cut into the fewest equal steps no longer
    than dt at the log's period, :func:`substeps`; None: one step per sample);
    ``threshold``: the relative standard deviation above which a direction is not identified;
    ``iterations``: Levenberg-Marquardt steps at most; ``bootstrap``: resamples of the windows
    (0: none); ``seed`` of the resamples; ``resolution`` (3,) rad, the encoder's quantum (None:
    unknown; the noise floor is then the log's own scatter)."""

    window: int = 200
    delay: int = 0
    integrator: str = "rk4"
    dt: float | None = None
    threshold: float = 0.05
    iterations: int = 50
    bootstrap: int = 200
    seed: int = 0
    resolution: tuple | None = None


# ---------------------------------------------------------------------------- the log

_COLUMNS = ("t", "theta1", "theta2", "theta3", "u1", "u2", "u3")
_CURRENTS = ("i1", "i2", "i3")


def read_log(path: str | Path) -> Log:
    """A log from a CSV file (a header row naming the columns ``t, theta1, theta2, theta3, u1, u2,
    u3`` and optionally ``i1, i2, i3``, in any order, other columns ignored; lines starting with #
    skipped) or an NPZ file (arrays ``t`` (N,), ``theta`` (N, 3), ``u`` (N, 3), optionally
    ``current`` (N, 3)), checked by :func:`check_log`. A bad file is a one-line ``ValueError``
    that starts with ``--data:``."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"--data: no such file: {path}")
    if path.suffix.lower() == ".npz":
        try:
            with np.load(path, allow_pickle=False) as z:
                arrays = {k: z[k] for k in z.files}
        except (OSError, ValueError) as e:
            raise ValueError(f"--data: cannot read {path} as NPZ: {_one_line(e)}") from None
        missing = [k for k in ("t", "theta", "u") if k not in arrays]
        if missing:
            raise ValueError(f"--data: array(s) {', '.join(missing)} missing from {path.name} "
                             "(expected t (N,), theta (N, 3), u (N, 3), optionally current (N, 3))")  # fmt: skip
        log = Log(arrays["t"], arrays["theta"], arrays["u"], arrays.get("current"))
    else:
        log = _read_csv(path)
    return check_log(log)


def write_log(log: Log, path: str | Path) -> None:
    """Write ``log`` in the layout :func:`read_log` reads (docs/identify.md), atomically: NPZ
    arrays ``t``, ``theta``, ``u`` (and ``current``) for a ``.npz`` path, else CSV columns ``t,
    theta1..3, u1..3`` (and ``i1..3``), every number as Python prints it (exact)."""
    log = check_log(log)
    path = Path(path)
    if path.suffix.lower() == ".npz":
        extra = {} if log.current is None else {"current": log.current}
        atomic_write(path, lambda tmp: np.savez(tmp, t=log.t, theta=log.theta, u=log.u, **extra))
        return
    columns = [log.t[:, None], log.theta, log.u] + ([] if log.current is None else [log.current])
    rows = np.concatenate(columns, axis=1)
    header = ",".join(_COLUMNS + (() if log.current is None else _CURRENTS))
    write_text(path, "\n".join([header, *(",".join(repr(float(x)) for x in row) for row in rows)]) + "\n")


def _read_csv(path: Path) -> Log:
    """The CSV layout of :func:`read_log`; errors name the file's own line numbers (comment and
    blank lines counted)."""
    try:
        with open(path, newline="") as f:
            reader = csv.reader(f)
            rows = [(reader.line_num, row) for row in reader
                    if any(c.strip() for c in row) and not row[0].lstrip().startswith("#")]  # fmt: skip
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise ValueError(f"--data: cannot read {path}: {_one_line(e)}") from None
    if not rows:
        raise ValueError(f"--data: {path.name} is empty (expected a header row: {', '.join(_COLUMNS)}[, i1, i2, i3])")
    line, header = rows[0][0], [name.strip() for name in rows[0][1]]
    missing = [c for c in _COLUMNS if c not in header]
    if missing:
        raise ValueError(f"--data: column(s) {', '.join(missing)} missing from {path.name} "
                         f"(expected {', '.join(_COLUMNS)}[, i1, i2, i3]; found {', '.join(header)})")  # fmt: skip
    twice = [c for c in _COLUMNS + _CURRENTS if header.count(c) > 1]
    if twice:
        where = "; ".join(f"{c} in columns {', '.join(str(k + 1) for k, h in enumerate(header) if h == c)}"
                          for c in twice)  # fmt: skip
        raise ValueError(f"--data: column(s) named more than once in the header (line {line}) of {path.name}: {where}")
    has_current = [c in header for c in _CURRENTS]
    if any(has_current) and not all(has_current):
        raise ValueError(f"--data: column(s) {', '.join(c for c in _CURRENTS if c not in header)} missing "
                         f"from {path.name} (currents: all of i1, i2, i3 or none)")  # fmt: skip
    wanted = _COLUMNS + (_CURRENTS if all(has_current) else ())
    where = [header.index(c) for c in wanted]
    data = np.empty((len(rows) - 1, len(wanted)))
    for n, (line, row) in enumerate(rows[1:]):
        try:
            data[n] = [float(row[i]) for i in where]
        except (ValueError, IndexError):
            raise ValueError(f"--data: line {line} of {path.name}: expected {len(header)} numbers, "
                             f"got {','.join(row)[:60]!r}") from None  # fmt: skip
    return Log(data[:, 0], data[:, 1:4], data[:, 4:7], data[:, 7:10] if all(has_current) else None)


def check_log(log: Log) -> Log:
    """``log`` as float64 arrays, or a one-line ``ValueError`` (``--data: ...``): shapes, finite
    values (the first NaN named by its row and column), strictly increasing time."""
    t = np.asarray(log.t, float)
    if t.ndim != 1:
        raise ValueError(f"--data: t: expected a vector of sample times, got shape {t.shape}")
    arrays = {"theta": log.theta, "u": log.u} | ({} if log.current is None else {"current": log.current})
    out = {}
    for name, a in arrays.items():
        a = np.asarray(a, float)
        if a.shape != (t.size, 3):
            raise ValueError(f"--data: {name}: expected shape ({t.size}, 3) (one row per sample time, one column "
                             f"per joint), got {a.shape}")  # fmt: skip
        out[name] = a
    for name, a in {"t": t[:, None], **out}.items():
        bad = np.argwhere(~np.isfinite(a))
        if bad.size:
            row, col = bad[0]
            where = f"{name}" if name == "t" else f"{name}{col + 1}" if name != "current" else f"i{col + 1}"
            raise ValueError(f"--data: {where} at sample {row} (t = {t[row]:g} s) is not a finite number "
                             f"({a[row, col]}); {len(bad)} such value(s)")  # fmt: skip
    if t.size < 2:
        raise ValueError(f"--data: too short: {t.size} sample(s)")
    step = np.diff(t)
    if np.any(step <= 0):
        j = int(np.argmax(step <= 0))
        raise ValueError(f"--data: t: expected strictly increasing sample times, got t = {t[j]:g} then "
                         f"{t[j + 1]:g} s at samples {j}, {j + 1}")  # fmt: skip
    return Log(t, out["theta"], out["u"], out.get("current"))


def _one_line(e: Exception) -> str:
    return " ".join(str(e).split())


def _clean(x: float) -> float:
    """``x`` to 9 significant digits: the round-off of time differences (0.0010000000000000009 s
    from t = 0.002 - 0.001) gone, a real period (0.000999847 s) kept."""
    return float(f"{x:.9g}")


def sample_period(t: np.ndarray) -> float:
    """The log's sample period (s): the median interval, to 9 significant digits."""
    return _clean(float(np.median(np.diff(np.asarray(t, float)))))


def substeps(period: float, dt: float | None) -> int:
    """Integration steps per sample interval: the fewest whose length period / n is at most ``dt``
    (1 for None): the step asked for when it divides the period, else the next shorter one, never
    a longer one (``dt`` sets the accuracy; to 1e-9 of a step, so dt = period / 4 is 4 steps)."""
    return 1 if dt is None else max(1, math.ceil(period / dt * (1 - 1e-9)))


# ---------------------------------------------------------------------------- the parameters


class Entry(NamedTuple):
    """One scalar the fit may move: ``name`` (``F[2]``: joint 2; ``I2[yy]``; ``m3``; ``payload``),
    its ``field``, its flat ``index`` in the field, its configured value ``value`` and its
    coordinate: ``log`` (z = log(p / value)) or not (z = (p - value) / ``scale``)."""

    name: str
    field: str
    index: int
    value: float
    log: bool
    scale: float


def entries(params: ArmParams, payload: float, names: Sequence[str]) -> list[Entry]:
    """The scalar entries of the fields ``names`` (:class:`ArmParams` fields and ``payload``) at
    their configured values, in that order; a bad name is a one-line ``ValueError``."""
    known = (*ArmParams._fields, PAYLOAD)
    if not names:
        raise ValueError(f"--params: expected at least one of {', '.join(known)}")
    for name in names:
        if name not in known:
            raise ValueError(f"--params: unknown arm parameter {name!r} (known: {', '.join(known)})")
    dup = sorted({n for n in names if list(names).count(n) > 1})
    if dup:
        raise ValueError(f"--params: {', '.join(dup)} named twice")
    out = []
    for field in names:
        value = np.ravel(np.asarray(payload if field == PAYLOAD else getattr(params, field), float))
        scale = float(np.max(np.abs(value))) or 1.0
        for k, v in enumerate(value):
            label = field if value.size == 1 else f"{field}[{_AXES[k] if field in ('I2', 'I3') else k + 1}]"
            out.append(Entry(label, field, k, float(v), bool(v > 0), scale))
    return out


def _apply(entries: Sequence[Entry], params: ArmParams, payload, z):
    """(ArmParams, payload) with each entry moved to its coordinate z_k (z = 0: as configured)."""
    fields = {f: jnp.ravel(jnp.asarray(getattr(params, f), z.dtype)) for f in {e.field for e in entries} - {PAYLOAD}}
    payload = jnp.ravel(jnp.asarray(payload, z.dtype))
    for k, e in enumerate(entries):
        p = e.value * jnp.exp(z[k]) if e.log else e.value + e.scale * z[k]
        if e.field == PAYLOAD:
            payload = payload.at[e.index].set(p)
        else:
            fields[e.field] = fields[e.field].at[e.index].set(p)
    shaped = {f: v.reshape(jnp.shape(getattr(params, f))) for f, v in fields.items()}
    return params._replace(**shaped), payload[0]


def physical(entries: Sequence[Entry], z: np.ndarray) -> np.ndarray:
    """The entries' values (NumPy) at coordinates ``z``."""
    z = np.asarray(z, float)
    return np.array([e.value * math.exp(zk) if e.log else e.value + e.scale * zk for e, zk in zip(entries, z)])


# ---------------------------------------------------------------------------- the windows


class Windows(NamedTuple):
    """The log cut for multiple shooting, each array with a leading window axis W: ``u`` (W, n, 3)
    the voltage held over each of the n intervals, ``t`` (W, n + 1) the sample times (s), ``theta`` (W,
    n + 1, 3) the encoder angles at the samples, ``current`` (W, n + 1, 3) or None, ``start``
    (W,) the first sample's index in the log, ``x0`` (W, 9) the estimated starting states."""

    u: np.ndarray
    t: np.ndarray
    theta: np.ndarray
    current: np.ndarray | None
    start: np.ndarray
    x0: np.ndarray


def smoother(half: int = SMOOTHING) -> np.ndarray:
    """Savitzky-Golay weights (3, 2 half + 1): rows give, from 2 half + 1 equally spaced samples
    centred on a point, the local cubic's value, first and second derivative (per unit step)."""
    k = np.arange(-half, half + 1, dtype=float)
    V = np.vander(k, 4, increasing=True)
    w = np.linalg.pinv(V)[:3]
    w[2] *= 2.0
    return w


def noise_levels(x: np.ndarray, half: int = SMOOTHING) -> np.ndarray:
    """Each column's noise (N, c) -> (c,): the RMS scatter about local cubic fits over 2 half + 1
    samples, scaled by sqrt(width / (width - 4)) for the fit's four degrees of freedom."""
    w = smoother(half)[0]
    width = w.size
    if x.shape[0] < width + 1:
        return np.zeros(x.shape[1])
    smooth = np.stack([np.convolve(x[:, c], w[::-1], mode="valid") for c in range(x.shape[1])], axis=1)
    scatter = x[half : x.shape[0] - half] - smooth
    return np.sqrt(np.mean(scatter**2, axis=0) * width / (width - 4))


def cut(log: Log, window: int, delay: int) -> Windows:
    """The log's windows: consecutive, ``window`` intervals each, from the first sample whose
    voltage is known (``delay``) and whose angles can be smoothed; the voltage held over the
    interval from sample j is the one written at j - ``delay``. At least one window, or a
    ``ValueError`` saying how many samples the fit needs."""
    n = log.t.size
    first = max(delay, SMOOTHING)
    count = (n - first - SMOOTHING - 1) // window
    if count < 1:
        need = first + SMOOTHING + window + 1
        raise ValueError(f"--data: too short: {n} samples; one window of {window} sample intervals (--window) "
                         f"needs {need} (with the delay of {delay} and {SMOOTHING} for the smoother)")  # fmt: skip
    start = first + window * np.arange(count)
    span = start[:, None] + np.arange(window + 1)
    u = np.concatenate([np.zeros((delay, 3)), log.u])[:n][span[:, :-1]]
    w = smoother()
    T = np.median(np.diff(log.t))
    around = start[:, None] + np.arange(-SMOOTHING, SMOOTHING + 1)
    est = np.einsum("dk,wkj->wjd", w, log.theta[around]) / np.array([1.0, T, T * T])  # (W, 3 joints, 3)
    x0 = est.reshape(count, 9)
    current = None if log.current is None else log.current[span]
    return Windows(u, log.t[span], log.theta[span], current, start, x0)


def _residual_fn(entries, params, payload, integrator, substeps, has_current):
    """r(x0 (9,), z (p,), u (n, 3), t (n + 1,), theta (n + 1, 3), current, sigma) -> residuals of
    one window: ((predicted - logged) / sigma) of the angles, then of the currents; the arm
    integrated over each sample interval [t_j, t_j+1] in ``substeps`` equal steps under u_j, at
    the log's own times (the arm's external torque depends on time)."""
    stepper = _STEPPERS[integrator]

    def residual(x0, z, u, t, theta, current, sigma):
        p, m = _apply(entries, params, payload, z)
        arm = Arm(p, m)
        state0 = arm.init(x0)

        def interval(state, inputs):
            U, t0, t1 = inputs
            step = (t1 - t0) / substeps
            f = lambda s, y: derivative_at(arm, y, U, s)
            sub = lambda y, k: (stepper(f, t0 + k * step, y, step), None)
            if substeps == 1:
                state = sub(state, 0.0)[0]
            else:
                state = jax.lax.scan(sub, state, jnp.arange(substeps, dtype=t.dtype))[0]
            return state, (jnp.stack(state.theta), jnp.stack(state.current))

        _, (th, cu) = jax.lax.scan(interval, state0, (u, t[:-1], t[1:]))
        th = jnp.concatenate([jnp.stack(state0.theta)[None], th])
        r = ((th - theta) / sigma[:3]).ravel()
        if has_current:
            cu = jnp.concatenate([jnp.stack(state0.current)[None], cu])
            r = jnp.concatenate([r, ((cu - current) / sigma[3:]).ravel()])
        return r

    return residual


class _Model(NamedTuple):
    """The windows' residuals and Jacobians, compiled once; ``sigma`` (3 or 6,) the channels'
    noise levels (an argument: reweighting does not recompile)."""

    residuals: Callable  # (x0s (W, 9), z (p,), sigma) -> (W, m)
    jacobians: Callable  # (x0s, z, sigma) -> (r (W, m), Jx (W, m, 9), Jz (W, m, p))
    compiled: tuple  # the jitted (residuals, jacobians) of any windows' data: another delay's windows reuse them


def _model(entries, params, payload, windows: Windows, integrator, substeps, compiled: tuple = ()) -> _Model:
    has_current = windows.current is not None
    one = _residual_fn(entries, params, payload, integrator, substeps, has_current)
    data = (windows.u, windows.t, windows.theta, windows.current if has_current else windows.theta)
    data = tuple(jnp.asarray(a) for a in data)
    twice = lambda x0, z, *rest: (one(x0, z, *rest),) * 2

    def both(x0, z, *rest):
        (Jx, Jz), r = jax.jacfwd(twice, argnums=(0, 1), has_aux=True)(x0, z, *rest)
        return r, Jx, Jz

    axes = (0, None, 0, 0, 0, 0, None)
    res, jac = compiled or (jax.jit(jax.vmap(one, in_axes=axes)), jax.jit(jax.vmap(both, in_axes=axes)))
    return _Model(lambda x0s, z, sigma: res(x0s, z, *data, sigma), lambda x0s, z, sigma: jac(x0s, z, *data, sigma),
                  (res, jac))  # fmt: skip


# ---------------------------------------------------------------------------- the normal equations


def _reduce(Jx, Jz, r, free, damping=0.0):
    """Per window, the parameters' normal equations with the window's states eliminated:
    S_w = C_w - B_w^T A_w^-1 B_w (p, p) and g_w = Jz^T r - B_w^T A_w^-1 Jx^T r (p,), and what the
    back-substitution needs; the states' blocks damped by ``damping`` x their diagonal."""
    Jz = Jz[:, :, free]
    A = np.einsum("wmi,wmj->wij", Jx, Jx)
    A = A + damping * np.einsum("wii->wi", A)[:, :, None] * np.eye(9)
    B = np.einsum("wmi,wmj->wij", Jx, Jz)
    C = np.einsum("wmi,wmj->wij", Jz, Jz)
    gx, gz = np.einsum("wmi,wm->wi", Jx, r), np.einsum("wmi,wm->wi", Jz, r)
    AiB = np.linalg.solve(A, B)
    Aig = np.linalg.solve(A, gx[..., None])[..., 0]
    S = C - np.einsum("wij,wik->wjk", B, AiB)
    g = gz - np.einsum("wij,wi->wj", B, Aig)
    return S, g, (A, B, gx)


def _step(Jx, Jz, r, free, lam, radius):
    """One Levenberg-Marquardt step (dx (W, 9), dz (p_free,)) with damping ``lam`` x diagonal,
    the parameters' move cut to ``radius`` (largest |dz|) and the states' re-solved for it."""
    S, g, (A, B, gx) = _reduce(Jx, Jz, r, free, lam)
    S, g = S.sum(0), g.sum(0)
    S = S + lam * np.diag(np.diag(S))
    dz = -np.linalg.lstsq(S, g, rcond=1e-14)[0] if len(S) else np.zeros(0)
    big = np.max(np.abs(dz), initial=0.0)
    if big > radius:
        dz = dz * (radius / big)
    dx = -np.linalg.solve(A, (gx + B @ dz)[..., None])[..., 0]
    return dx, dz, big > radius


def _fit(model: _Model, sigma, x0s, z, free, iterations, log=None):
    """Levenberg-Marquardt over the window states and z[free], in a trust region on z: a step
    moves no coordinate z by more than the radius (first :data:`MAX_STEP`), which doubles after
    a step that cut and was predicted well (actual / predicted decrease > 0.75) and shrinks after
    a poor one (< 0.25); far from the optimum a parameter cannot run off along a direction the
    other, still wrong, parameters make look attractive (R, Kt, Jm driven to 0 otherwise).
    Returns (x0s, z, costs, (r, Jx, Jz) at the end)."""
    cost = lambda r: 0.5 * float(np.sum(np.asarray(r) ** 2))
    r, Jx, Jz = (np.asarray(a) for a in model.jacobians(jnp.asarray(x0s), jnp.asarray(z), jnp.asarray(sigma)))
    c, lam, radius, history = cost(r), 1e-3, MAX_STEP, []
    for it in range(iterations):
        history.append(c)
        for _ in range(16):
            dx, dz, cut_ = _step(Jx, Jz, r, free, lam, radius)
            z_new = z.copy()
            z_new[free] += dz
            x_new = x0s + dx
            c_new = cost(model.residuals(jnp.asarray(x_new), jnp.asarray(z_new), jnp.asarray(sigma)))
            predicted = c - cost(r + np.einsum("wmi,wi->wm", Jx, dx) + Jz[:, :, free] @ dz)
            ratio = (c - c_new) / predicted if predicted > 0 else -1.0
            if np.isfinite(c_new) and c_new < c:
                break
            lam, radius = lam * 4.0, radius / 2.0
        else:
            break
        if ratio > 0.75 and cut_:
            radius = min(2.0 * radius, 1.0)
        elif ratio < 0.25:
            radius /= 2.0
        gain = (c - c_new) / max(c, 1e-300)
        x0s, z, c, lam = x_new, z_new, c_new, max(lam / 3.0, 1e-12)
        if log:
            log(f"identify: iteration {it + 1}: cost {c:.6e} (relative decrease {gain:.2e})")
        r, Jx, Jz = (np.asarray(a) for a in model.jacobians(jnp.asarray(x0s), jnp.asarray(z), jnp.asarray(sigma)))
        if gain < 1e-10:
            break
    history.append(c)
    return x0s, z, history, (r, Jx, Jz)


# ---------------------------------------------------------------------------- identifiability


def directions(S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eigen-directions of the reduced information ``S`` (p, p): their standard deviations
    1 / sqrt(lambda) (p,), largest first (inf where lambda <= 0), and the directions as the
    columns of a (p, p) matrix, in that order."""
    lam, V = np.linalg.eigh((S + S.T) / 2)
    with np.errstate(divide="ignore"):
        std = np.where(lam > 0, 1.0 / np.sqrt(np.maximum(lam, 1e-300)), np.inf)
    order = np.argsort(-std)
    return std[order], V[:, order]


def choose_fixed(N: np.ndarray, tie: float = 0.05) -> list[int]:
    """One entry to fix per column of ``N`` (p, k), an orthonormal basis of the directions the log
    does not identify: greedily the entry with the largest weight (row norm) in the directions
    left, ties within ``tie`` (relative) going to the first (the order of ``--params``); the
    directions are then restricted to those that leave the fixed entry alone."""
    N = np.array(N, float)
    fixed: list[int] = []
    while N.shape[1]:
        weight = np.linalg.norm(N, axis=1)
        weight[fixed] = 0.0
        top = weight.max()
        i = int(np.argmax(weight >= (1 - tie) * top))
        fixed.append(i)
        # the directions with no component along entry i: null space of row i within span(N)
        _, _, Vt = np.linalg.svd(N[i : i + 1], full_matrices=True)
        N = N @ Vt[1:].T
        if N.size:
            q, rr = np.linalg.qr(N)
            N = q[:, np.abs(np.diag(rr)) > 1e-12] if rr.size else q
    return fixed


def groups(N: np.ndarray, fixed: Sequence[int], entries: Sequence[Entry], S: np.ndarray, floor: float = 0.01):
    """The directions ``N`` (p, k) the log does not identify, one per fixed entry f: the moves of
    the other entries that, with f's coordinate z moved by 1, leave the log unchanged to first
    order (the columns of N N[fixed]^-1: 1 at f, 0 at the other fixed entries), as {entry: move}
    for the moves above ``floor``, with the standard deviation along that direction (unit length,
    from the information ``S``)."""
    if not len(fixed):
        return []
    C = N @ np.linalg.inv(N[list(fixed), :])
    out = []
    for j, f in enumerate(fixed):
        c = C[:, j]
        u = c / np.linalg.norm(c)
        info = float(u @ S @ u)
        order = sorted(range(len(c)), key=lambda i: (i != f, -round(abs(c[i]), 4), i))  # the fixed entry first
        members = {entries[i].name: round(float(c[i]), 4) for i in order if abs(c[i]) > floor}
        out.append({"fixed": entries[f].name, "moves": members,
                    "std": 1.0 / math.sqrt(info) if info > 0 else math.inf})  # fmt: skip
    return out


def _variances(S: np.ndarray, s2: float) -> np.ndarray:
    """The diagonal of s2 S^-1 for a symmetric ``S``: infinite for a coordinate that has a part
    along a direction of no information (an eigenvalue below 1e-14 of the largest)."""
    lam, V = np.linalg.eigh((S + S.T) / 2)
    none = lam <= lam.max(initial=0.0) * 1e-14
    var = s2 * (V[:, ~none] ** 2 / lam[~none]).sum(axis=1)
    return np.where(np.any(np.abs(V[:, none]) > 1e-8, axis=1), np.inf, var)


# ---------------------------------------------------------------------------- the fit


def identify(
    params: ArmParams,
    payload: float,
    log: Log,
    names: Sequence[str],
    settings: Settings | None = None,
    *,
    progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Fit the :class:`ArmParams` fields (and ``payload``) ``names`` to ``log``, starting from
    ``params`` and ``payload`` (kg), by multiple shooting (module docstring). Bad input is a
    one-line ``ValueError`` naming the option or the log's column.

    Returns a dict (NumPy values):

    - ``entries``: per scalar entry {name, field, index, initial, estimate, status ("fitted",
      "fixed", or "poorly identified": fitted, but its relative standard deviation at the optimum
      exceeds the threshold), std, relative_std, std_gauss_newton, std_bootstrap (``std`` is the
      larger of the two), moves_with_fixed {fixed entry: d z(entry) / d z(fixed)} (how the estimate
      moves with a fixed entry's value, where above 0.001; z = log for positive entries)};
    - ``groups``: the directions the log does not identify (at the configured parameters, before
      the fit), one per fixed entry: {fixed, moves {entry: move of its z per unit move of the fixed
      entry's z, the log unchanged}, std (along that direction)};
    - ``fixed``, ``poorly_identified``: entry names;
    - ``warnings``: sentences, e.g. :func:`misfit`'s when the model does not explain the log;
    - ``params`` {field: value, every entry as fitted}, ``payload`` (kg);
    - ``fit``: ``cost_start``, ``cost_states_only`` (after the states alone), ``cost`` (half the sum
      of squared residuals, each in units of its channel's noise: n / 2 for a model that explains
      the log to its noise; the last with the reweighted noise), ``iterations``, ``rms_theta``
      (3,) rad and ``rms_current`` (3,) A (residuals), ``noise_theta``, ``noise_current`` (the
      weights, after reweighting), ``noise_floor_theta`` (3,) rad (the angles' noise the log
      explains: its scatter about local cubics, at least the quantum / sqrt(12)), ``misfit`` (the
      largest ratio of ``rms_theta`` to it: about 1 when the model explains the log; a warning
      above :data:`MISFIT`), ``windows``, ``window_samples``, ``window_s``, ``substeps``, ``step``
      (s), ``residual_variance`` s^2, ``threshold``, ``bootstrap`` (resamples; 0 when skipped),
      ``bootstrap_skipped`` (why, or None), ``stds`` (where the standard deviations come from);
    - ``log``: samples, duration, period, currents, delay.

    Its length (the stages are :func:`_fit`, :func:`_fit_passes`, :func:`_delay_costs`,
    :func:`_uncertainty`): the report draws on the values of every stage, kept in one place.
    """
    settings = settings or Settings()
    progress = progress or (lambda _: None)
    ents = entries(params, payload, names)
    if settings.integrator not in _STEPPERS:
        raise ValueError(f"sim.integrator: expected one of {', '.join(_STEPPERS)}, got {settings.integrator!r}")
    if settings.window < 2:
        raise ValueError(f"--window: expected at least 2 sample intervals, got {settings.window}")
    log = check_log(log)
    windows = cut(log, settings.window, settings.delay)
    period = sample_period(log.t)
    steps = substeps(period, settings.dt)
    step = _clean(period / steps)
    floors = _floors(log, settings.resolution)
    noise = noise_levels(log.theta if log.current is None else np.concatenate([log.theta, log.current], axis=1))
    sigma = np.maximum(noise, floors)
    noise_theta = sigma[:3].copy()  # what the log explains: the angles' scatter, at least the quantum / sqrt(12)
    W, p = len(windows.start), len(ents)
    units = "rad" if log.current is None else "rad, A"
    asked = "" if settings.dt is None or abs(step - settings.dt) <= 1e-8 * settings.dt else (
        f": --dt {settings.dt:g} does not divide the sample period, so the next shorter step that does")  # fmt: skip
    progress(f"identify: {p} entries of {', '.join(names)}; {W} windows of {settings.window} samples "
             f"({_clean(settings.window * period):g} s); step {step:g} s ({steps} {settings.integrator} step(s) per "
             f"{period:g} s sample{asked}); noise {np.array2string(sigma, precision=2)} ({units}); "
             "compiling ...")  # fmt: skip
    model = _model(ents, params, payload, windows, settings.integrator, steps)
    z = np.zeros(p)
    r0 = np.asarray(model.residuals(jnp.asarray(windows.x0), jnp.asarray(z), jnp.asarray(sigma)))
    bad = np.flatnonzero(~np.all(np.isfinite(r0), axis=1))
    if bad.size:
        raise ValueError(f"--data: the configured arm driven by the logged voltages does not stay finite in "
                         f"{bad.size} window(s), the first from t = {log.t[windows.start[bad[0]]]:g} s "
                         "(check the voltage columns' units and --delay)")  # fmt: skip

    # the window states alone first (parameters as configured), then what the log identifies there
    x0s, _, pre, (r, Jx, Jz) = _fit(model, sigma, windows.x0.copy(), z, np.zeros(p, bool), 5)
    S0 = _reduce(Jx, Jz, r, np.ones(p, bool))[0].sum(0)
    std0, V = directions(S0)
    k = int(np.sum(std0 > settings.threshold))
    fixed = choose_fixed(V[:, :k])
    free = np.ones(p, bool)
    free[fixed] = False
    names_of = lambda idx: ", ".join(ents[i].name for i in idx)
    progress(f"identify: {k} direction(s) not identified by the log (standard deviation above "
             f"{settings.threshold:g}){'; fixed as configured: ' + names_of(fixed) if k else ''}")  # fmt: skip

    x0s, z, sigma, costs, iterations, (r, Jx, Jz) = _fit_passes(model, sigma, floors, x0s, z, free, V, std0, k,
                                                                names_of, units, settings, progress)  # fmt: skip
    delays = _delay_costs(ents, params, payload, log, model, sigma, x0s, z, free, steps, costs[-1], settings)
    delay_note = delay_warning(delays, settings.delay)
    if delay_note:
        progress(f"identify: warning: {delay_note}")
    unc = _uncertainty(Jx, Jz, r, free, x0s.size, settings)
    if unc["skipped"]:
        progress(f"identify: bootstrap skipped ({unc['skipped']}): the standard deviations are Gauss-Newton's only")
    rows = _rows(ents, z, free, fixed, unc, settings.threshold)
    p_fit, m_fit = _apply(ents, params, payload, jnp.asarray(z))
    per = np.asarray(r).reshape(W, -1, settings.window + 1, 3)
    rms = np.sqrt(np.mean(per**2, axis=(0, 2))) * sigma.reshape(-1, 3)
    ratio, warning = misfit(rms[0], noise_theta)
    if warning:
        progress(f"identify: warning: {warning}")
    return {
        "entries": rows,
        "groups": groups(V[:, :k], fixed, ents, S0),
        "fixed": [ents[i].name for i in fixed],
        "poorly_identified": [row["name"] for row in rows if row["status"] == "poorly identified"],
        "params": {f: np.asarray(getattr(p_fit, f)) for f in ArmParams._fields},
        "payload": float(m_fit),
        "warnings": [w for w in (warning, delay_note) if w],
        "fit": {
            "cost_start": pre[0],
            "cost_states_only": pre[-1],
            "cost": costs[-1],
            "iterations": iterations,
            "residuals": r.size,
            "rms_theta": rms[0],
            "rms_current": rms[1] if log.current is not None else None,
            "noise_theta": sigma[:3],
            "noise_floor_theta": noise_theta,
            "misfit": ratio,
            "noise_current": sigma[3:] if log.current is not None else None,
            "windows": W,
            "window_samples": settings.window,
            "window_s": _clean(settings.window * period),
            "substeps": steps,
            "step": step,
            "residual_variance": unc["s2"],
            "threshold": settings.threshold,
            "bootstrap": unc["resamples"],
            "bootstrap_skipped": unc["skipped"],
            "stds": unc["source"],
        },
        "log": {
            "samples": int(log.t.size),
            "duration": float(log.t[-1] - log.t[0]),
            "period": period,
            "currents": log.current is not None,
            "delay": settings.delay,
            "delay_costs": {str(d): c for d, c in sorted(delays.items())},
        },  # fmt: skip
    }


def _fit_passes(model, sigma, floors, x0s, z, free, V, std0, k, names_of, units, settings: Settings, progress):
    """The fits from the states-only optimum: the well-identified entries first, then every
    free one (a weakly identified entry moved while the strong ones are still wrong runs off:
    F to 0 against Kb's damping), then each channel weighted by its own residual (the scatter
    about local cubics overstates the noise of a current that follows a chattering voltage)
    and fitted again. Returns (x0s, z, sigma, costs, iterations, (r, Jx, Jz))."""
    W = x0s.shape[0]
    weak = int(np.sum(std0 > settings.threshold * WEAK))
    first = free.copy()
    first[choose_fixed(V[:, :weak])] = False
    costs, iterations, r = [], 0, None
    passes = [(first, "without the weakly identified " + names_of(np.flatnonzero(free & ~first)))] * (weak > k)
    for mask, what in passes + [(free, "every free entry"), (free, "reweighted")]:
        if what == "reweighted":
            rms = np.sqrt(np.mean(np.asarray(r).reshape(W, -1, settings.window + 1, 3) ** 2, axis=(0, 2)))
            sigma = np.maximum(rms.ravel() * sigma, floors)
            what += f": noise {np.array2string(sigma, precision=2)} ({units})"
        progress(f"identify: fitting {what}")
        x0s, z, history, (r, Jx, Jz) = _fit(model, sigma, x0s, z, mask, settings.iterations, progress)
        costs.append(history[-1])
        iterations += len(history) - 1
    return x0s, z, sigma, costs, iterations, (r, Jx, Jz)


def _delay_costs(ents, params, payload, log, model, sigma, x0s, z, free, steps, cost, settings: Settings) -> dict:
    """{delay: cost}: the fit's ``cost`` at ``settings.delay`` and each other delay from 0 to
    :data:`DELAYS` refitted (states and free entries) from this optimum, on the same windows
    (delays up to :data:`SMOOTHING` leave them where they are) and the same compiled model."""
    delays = {settings.delay: cost}
    for d in range(max(DELAYS, settings.delay) + 1 if settings.delay <= SMOOTHING else 0):
        if d != settings.delay:
            other = _model(ents, params, payload, cut(log, settings.window, d), settings.integrator, steps,
                           model.compiled)  # fmt: skip
            delays[d] = _fit(other, sigma, x0s, z, free, DELAY_ITERATIONS)[2][-1]
    return delays


def delay_warning(costs: dict[int, float], delay: int, margin: float = DELAY_MARGIN) -> str | None:
    """A warning when some other delay's ``costs`` (each delay's fit cost, half the sum of
    squared residuals in units of the noise, :func:`identify`'s delay check) are below the
    configured ``delay``'s by more than ``margin`` of it: a drive logs its voltages either as it
    writes them (the loop's delay) or as they act (0), and a wrong delay biases the estimates by
    more than their standard deviations (docs/identify.md); else None."""
    best = min(costs, key=costs.get)
    if best == delay or not costs[best] < (1 - margin) * costs[delay]:
        return None
    return (f"--delay {delay}: the log fits --delay {best} better (cost {costs[best]:.4g} against "
            f"{costs[delay]:.4g}, in units of the noise): each logged voltage reaches the motor {best} sample(s) "
            f"later, not {delay}, and the estimates are biased by the wrong delay: fit again with "
            f"--delay {best}")  # fmt: skip


def _floors(log: Log, resolution) -> np.ndarray:
    """The channels' least noise: the encoder's quantum / sqrt(12) (rad; 1e-12 when unknown),
    and 1e-6 of each current's largest magnitude (A)."""
    floor = np.full(3, 1e-12)
    if resolution is not None:
        floor = np.maximum(floor, np.asarray(resolution, float) / math.sqrt(12.0))
    if log.current is None:
        return floor
    return np.concatenate([floor, 1e-6 * np.maximum(np.abs(log.current).max(0), 1e-3)])


def misfit(rms: np.ndarray, noise: np.ndarray, limit: float = MISFIT) -> tuple[float | None, str | None]:
    """How far the model is from explaining the log: the largest ratio over the joints of the
    fit's residual RMS ``rms`` (3,) rad to the angles' noise ``noise`` (3,) rad (the log's scatter
    about local cubics, at least the encoder's quantum / sqrt(12); a joint whose noise is unknown,
    at the 1e-12 guard, left out; None when every one is), and a warning when it exceeds ``limit``
    (:data:`MISFIT`), else None. The standard deviations assume residuals that are the log's
    noise; a model error (a parameter left out of the fit that is wrong, a wrong delay, an effect
    the arm model lacks) leaves a systematic residual and biases the estimates by more than them."""
    rms, noise = np.asarray(rms, float), np.asarray(noise, float)
    known = noise > 1e-12
    if not known.any():
        return None, None
    ratios = np.where(known, rms / np.where(known, noise, 1.0), -np.inf)
    j = int(np.argmax(ratios))
    ratio = float(ratios[j])
    if not ratio > limit:
        return ratio, None
    return ratio, (f"the residual RMS is {ratio:.3g} x the angles' noise on joint {j + 1} ({rms[j]:.2g} against "
                   f"{noise[j]:.2g} rad; more than {limit:g} x): the arm model does not explain the log (a parameter "
                   "left out of --params that is wrong, a wrong --delay, or an effect the model lacks), and the "
                   "estimates may be off by far more than their standard deviations")  # fmt: skip


def _uncertainty(Jx, Jz, r, free, states: int, settings: Settings) -> dict[str, Any]:
    """At the optimum: the Gauss-Newton standard deviations of the free coordinates (s^2 S^-1),
    a one-step bootstrap's over the windows (each resample's z* - S_b^-1 g_b; skipped, and why,
    with fewer than :data:`BOOTSTRAP_WINDOWS` windows or no free entry), their larger, where they
    come from (``source``, a phrase), and the slopes d z_free / d z_fixed = -S_ff^-1 S_f,fixed of
    the estimates in the fixed entries."""
    S_w, g_w, _ = _reduce(Jx, Jz, r, np.ones(len(free), bool))
    S = S_w.sum(0)
    F, X = np.flatnonzero(free), np.flatnonzero(~free)
    s2 = float(np.sum(r**2)) / max(r.size - states - F.size, 1)
    std_gn = np.sqrt(np.maximum(_variances(S[np.ix_(F, F)], s2), 0.0))
    W = len(S_w)
    skipped = None
    if settings.bootstrap and not F.size:
        skipped = "no entry fitted"
    elif settings.bootstrap and W < BOOTSTRAP_WINDOWS:
        skipped = f"{W} window(s), fewer than the {BOOTSTRAP_WINDOWS} it resamples; more with a shorter --window"
    resamples = 0 if skipped else settings.bootstrap
    std_boot = np.full(F.size, np.nan)
    if resamples:
        rng = np.random.default_rng(settings.seed)
        picks = rng.integers(0, W, (resamples, W))
        draws = [-np.linalg.lstsq(S_w[b].sum(0)[np.ix_(F, F)], g_w[b].sum(0)[F], rcond=1e-14)[0] for b in picks]
        std_boot = np.std(np.asarray(draws), axis=0, ddof=1)
    slopes = -np.linalg.lstsq(S[np.ix_(F, F)], S[np.ix_(F, X)], rcond=1e-14)[0] if X.size and F.size else None
    source = f"the larger of Gauss-Newton's and the bootstrap's over {resamples} resamples of the {W} windows"
    if not resamples:
        source = "Gauss-Newton's only: " + (f"bootstrap skipped, {skipped}" if skipped else "no bootstrap")
    return {"s2": s2, "std_gn": std_gn, "std_boot": std_boot, "std": np.fmax(std_gn, np.nan_to_num(std_boot)),
            "slopes": slopes, "resamples": resamples, "skipped": skipped, "source": source}  # fmt: skip


def _rows(ents: Sequence[Entry], z, free, fixed, unc: dict, threshold: float) -> list[dict]:
    """The report's entries (see :func:`identify`), standard deviations in the entries' units."""
    values = physical(ents, z)
    F = list(np.flatnonzero(free))
    rows = []
    for i, e in enumerate(ents):
        row = {"name": e.name, "field": e.field, "index": e.index, "initial": e.value, "estimate": float(values[i]),
               "status": "fixed", "std": None, "relative_std": None, "std_gauss_newton": None,
               "std_bootstrap": None, "moves_with_fixed": {}}  # fmt: skip
        if free[i]:
            a = F.index(i)
            size = abs(values[i]) if e.log else e.scale  # |d p / d z|
            relative = size / max(abs(values[i]), 1e-300)
            moves = {} if unc["slopes"] is None else {
                ents[f].name: round(float(unc["slopes"][a, j]), 4) for j, f in enumerate(fixed)
                if abs(unc["slopes"][a, j]) > 0.001}  # fmt: skip
            row.update(std=float(unc["std"][a] * size), relative_std=float(unc["std"][a] * relative),
                       std_gauss_newton=float(unc["std_gn"][a] * size),
                       std_bootstrap=float(unc["std_boot"][a] * size), moves_with_fixed=moves)  # fmt: skip
            row["status"] = "fitted" if row["relative_std"] <= threshold else "poorly identified"
        rows.append(row)
    return rows


# ---------------------------------------------------------------------------- the [arm] table


def _toml_number(x: float) -> str:
    text = f"{float(x):.8g}"
    return text if any(c in text for c in ".einn") else text + ".0"


def arm_toml(result: dict[str, Any], extra: dict[str, Any] | None = None, header: str = "") -> str:
    """The identified arm as a TOML ``[arm]`` table with every :class:`ArmParams` field (and the
    ``extra`` keys, e.g. ``payload_range``), ready to paste into a config: each fitted field with
    its entries' standard deviations in a comment, each fixed one marked, and the fitted payload
    as a commented ``[plant] payloads`` line. ``header``: comment lines put first."""
    rows = {}
    for row in result["entries"]:
        rows.setdefault(row["field"], []).append(row)
    lines = [f"# {line}" if line else "#" for line in header.splitlines()]
    lines.append("[arm]")
    for field, value in list(result["params"].items()) + list((extra or {}).items()):
        v = np.asarray(value, float)
        text = _toml_number(v) if v.ndim == 0 else "[" + ", ".join(_toml_number(x) for x in v.ravel()) + "]"
        lines.append(f"{field} = {text}{_note(rows.get(field, []))}")
    for row in rows.get(PAYLOAD, []):
        value = _toml_number(row["estimate"])
        lines.append(f"# the experiment's payload (kg), for [plant] payloads: {value}{_note([row])}")
    return "\n".join(lines) + "\n"


def _note(rows: list[dict]) -> str:
    """`` # fitted +- [...]; fixed ...`` for a field's entries (empty when none was named)."""
    if not rows:
        return ""
    parts = []
    fitted = [r for r in rows if r["status"] != "fixed"]
    if fitted:
        std = ", ".join(f"{r['std']:.2g}" for r in fitted)
        which = "" if len(fitted) == len(rows) else " (" + ", ".join(r["name"] for r in fitted) + ")"
        parts.append(f"fitted{which} +- {std if len(fitted) == 1 else '[' + std + ']'} (1 sigma)")
    poor = [r["name"] for r in rows if r["status"] == "poorly identified"]
    if poor:
        parts.append(f"poorly identified: {', '.join(poor)}")
    fixed = [r["name"] for r in rows if r["status"] == "fixed"]
    if fixed:
        parts.append(f"not identified by the log, as configured: {', '.join(fixed)}")
    return "  # " + "; ".join(parts)
