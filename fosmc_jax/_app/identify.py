"""``fosmc identify`` as a function: ``[arm]`` fields fitted to a log."""

from __future__ import annotations

import json
import math
import numbers
from pathlib import Path
from typing import Any

import numpy as np

from .. import _problems as problems
from .._io import jsonable, stamped, write_text
from .._problems import ConfigError
from .shared import (
    ConfigInput,
    Log,
    _fresh_out,
    _quiet,
    _with_x64,
    config_of,
)


@_with_x64
def run_identify(
    config: ConfigInput = None,
    *,
    data: str | Path,
    params: str | list[str] | tuple[str, ...],
    out: str | Path | None = None,
    payload: float | None = None,
    delay: int | None = None,
    window: float = 0.2,
    dt: float | None = None,
    threshold: float = 0.05,
    iterations: int = 50,
    bootstrap: int = 200,
    seed: int = 0,
    force: bool = False,
    log: Log = _quiet,
) -> dict[str, Any]:
    """``fosmc identify``: the config's ``[arm]`` fields ``params`` (names, a list or
    comma-separated: ``"F,R,Kt,payload"``; ``payload`` is the experiment's payload) fitted to
    the log ``data`` (CSV or NPZ, docs/identify.md) by multiple shooting over windows of
    ``window`` seconds (``fosmc_jax._firmware.identify``), starting from the config's arm.

    ``payload``: the experiment's payload (kg; default: the config's ``plant.payloads`` if it
    lists one). ``delay``: samples between a logged voltage and the motor (default: the config's
    ``controller.delay_samples``). ``dt``: the longest integration step (default: the log's sample
    period, one step of the config's ``sim.integrator`` per sample; a ``dt`` that does not divide
    the period gives the next shorter step that does, said in a ``log`` line). ``window``: in
    seconds, rounded to whole sample periods (at least 2). ``threshold``: the relative standard
    deviation above which the log does not identify a direction. The encoder's quantum comes from
    ``sensors.encoder_counts``. ``out``: folder for ``identified.toml`` (the ``[arm]`` table to
    paste into a config) and ``identify.json`` (this function's result), refused when not empty
    without ``force``, or when a file. A bad option is a one-line :class:`ConfigError` naming it.

    Returns the report: :func:`fosmc_jax._firmware.identify.identify`'s dict (``entries``,
    ``groups``, ``fixed``, ``poorly_identified``, ``warnings``, ``params``, ``payload``, ``fit``,
    ``log``) with the versions, ``names``, ``data``, ``toml`` (``identified.toml``'s text),
    ``config_check`` (``"ok"``, or the config error the identified arm raises, e.g. inertias that
    break the triangle inequality) and ``config``.
    """
    from .._firmware import identify as identification

    names = _checked_options(params, window, threshold, iterations, bootstrap, seed, dt, delay, payload)
    cfg = config_of(config)
    if payload is None:
        if len(cfg.plant.payloads) != 1:
            raise ConfigError(f"--payload: the config lists {len(cfg.plant.payloads)} payloads "
                              f"({list(cfg.plant.payloads)}); give the experiment's (kg)")  # fmt: skip
        payload = cfg.plant.payloads[0]
    if out is not None:
        out = _fresh_out(out, force, "use --force to overwrite")
    result = _fit(cfg, data, names, payload, log, window=window, delay=delay, dt=dt, threshold=threshold,
                  iterations=iterations, bootstrap=bootstrap, seed=seed)  # fmt: skip
    fitted = {k: np.asarray(v).tolist() for k, v in result["params"].items()}
    try:
        problems.replace(cfg, arm=fitted, plant={"kind": "arm", "payloads": [result["payload"]]})
        config_check = "ok"
    except ConfigError as e:
        config_check = str(e)
        log(f"identify: warning: the identified arm is not a valid config: {e}")
    header = _toml_header(config, data, names, result, config_check)
    toml = identification.arm_toml(result, {"payload_range": list(cfg.arm.payload_range)}, header)
    report = stamped({"data": str(data), "names": names, **result, "toml": toml, "config_check": config_check,
                      "config": cfg.as_dict()})  # fmt: skip
    if out is not None:
        try:
            out.mkdir(parents=True, exist_ok=True)
            write_text(out / "identified.toml", toml)
            write_text(out / "identify.json", json.dumps(jsonable(report), indent=1))
        except OSError as e:
            raise ConfigError(f"--out: cannot write in {out}: {e.strerror or e}") from None
    return report


def _fit(cfg, data, names: list[str], payload, log: Log, *, window, delay, dt, threshold, iterations, bootstrap,
         seed) -> dict[str, Any]:  # fmt: skip
    """:func:`fosmc_jax._firmware.identify.identify` of the log ``data`` from the config's arm,
    with the options as its settings (the window in whole sample periods, the encoder's quantum
    from the config); a bad log or option as a one-line :class:`ConfigError`."""
    from .._firmware import identify as identification

    counts = np.asarray(cfg.sensors.encoder_counts, float)
    try:
        record = identification.read_log(data)
        period = identification.sample_period(record.t)
        samples = round(window / period)
        if samples < 2:
            raise ValueError(f"--window: expected at least 2 of the log's sample periods ({2 * period:g} s), "
                             f"got {window:g} s")  # fmt: skip
        settings = identification.Settings(
            window=samples,
            delay=cfg.controller.delay_samples if delay is None else int(delay),
            integrator=cfg.sim.integrator,
            dt=None if dt is None else float(dt),
            threshold=float(threshold),
            iterations=int(iterations),
            bootstrap=int(bootstrap),
            seed=int(seed),
            resolution=tuple(np.where(counts > 0, 2 * np.pi / np.maximum(counts, 1), 0.0)),
        )
        arm = problems.arm_params_of(cfg, np.float64)
        result = identification.identify(arm, float(payload), record, names, settings, progress=log)
    except ValueError as e:
        raise ConfigError(str(e)) from None
    return result


def _checked_options(params, window, threshold, iterations, bootstrap, seed, dt, delay, payload) -> list[str]:
    """The names of the fields to fit, once every numeric option is in range (a one-line
    :class:`ConfigError` naming the first that is not)."""
    # (option, value, integer?, least, strictly above it?, what); None: the default, for the last three
    checks = (("--window", window, False, 0, True, "a positive number (s)"),
              ("--threshold", threshold, False, 0, True, "a positive number"),
              ("--iterations", iterations, True, 1, False, "a positive integer"),
              ("--bootstrap", bootstrap, True, 0, False, "a non-negative integer"),
              ("seed", seed, True, 0, False, "a non-negative integer"),
              ("--dt", dt, False, 0, True, "a positive number (s)"),
              ("--delay", delay, True, 0, False, "a non-negative integer (samples)"),
              ("--payload", payload, False, 0, False, "a non-negative mass (kg)"))  # fmt: skip
    for name, value, integer, least, strict, what in checks:
        if value is None and name in ("--dt", "--delay", "--payload"):
            continue
        ok = isinstance(value, numbers.Integral if integer else numbers.Real) and not isinstance(value, bool)
        ok = ok and (integer or math.isfinite(value)) and (value > least if strict else value >= least)
        if not ok:
            raise ConfigError(f"{name}: expected {what}, got {repr(value) if isinstance(value, str) else value}")
    if isinstance(params, str):
        return [n.strip() for n in params.split(",") if n.strip()]
    if isinstance(params, (list, tuple)) and all(isinstance(n, str) for n in params):
        return list(params)
    raise ConfigError(f"--params: expected names, comma-separated or a list of strings, got {params!r}")


def _toml_header(config, data, names: list[str], result: dict, config_check: str) -> str:
    """``identified.toml``'s opening comment: what was fitted to what, the residuals against
    the noise, what the standard deviations assume, and every warning."""
    origin = str(config) if isinstance(config, (str, Path)) else "the paper's defaults" if config is None else "a dict"
    fit = result["fit"]
    rms = np.array2string(np.asarray(fit["rms_theta"]), precision=2)
    noise = np.array2string(np.asarray(fit["noise_floor_theta"]), precision=2)
    ratio = "" if fit["misfit"] is None else f", up to {fit['misfit']:.3g} x"
    header = (f"fosmc identify: {', '.join(names)} fitted to {data} ({result['log']['samples']} samples, "
              f"{result['log']['duration']:g} s{', with currents' if result['log']['currents'] else ''}), starting "
              f"from the [arm] of {origin}.\nResidual RMS {rms} rad{ratio} the angles' noise {noise} rad.\n"
              f"+- is one standard deviation ({fit['stds']}), assuming the model is right (the residuals the log's "
              "noise).")  # fmt: skip
    for warning in result["warnings"]:
        header += f"\nWARNING: {warning}."
    if config_check != "ok":
        header += f"\nWARNING: not a valid config as it stands: {config_check}"
    return header
