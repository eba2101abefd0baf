"""A simulated bench: the log of an experiment (:class:`fosmc_jax._firmware.identify.Log`, in
docs/identify.md's layout) from a config's simulation, as a drive would record it: to try
``fosmc identify`` on an arm whose parameters are known, or to see what a log of a planned
experiment identifies before running it."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .. import _problems as problems
from .._firmware import identify as identification
from .._loop.digital import quantize
from .._plants.arm import Arm, ArmParams


def identification_log(
    config: Any = None,
    path: str | Path | None = None,
    *,
    delay: int | None = None,
    currents: bool = False,
) -> identification.Log:
    """The log of the config's first rollout (its first payload, its first ``[sample]`` draw
    and ``[arm.uncertainty]`` arm where it has them; ``[plant] kind = "arm"`` with a digital
    loop, ``controller.sample_period`` > 0): the times t (N,) s of the controller's samples,
    the angles theta (N, 3) rad as the encoder reads them (``sensors.encoder_counts``; exact
    where 0), the voltages u (N, 3) V as the drive logs them: u_j reaches the motor ``delay``
    samples later (default: ``controller.delay_samples``, a drive that logs what it writes; 0:
    a drive that logs the voltage acting over the coming period; the last ``delay`` ones, which
    act after the run, repeat the last that acts), and the motor currents (N, 3) A with
    ``currents`` (where the arm is the config's own: no drawn arms or payloads). Written to
    ``path`` when given (``.npz``, else CSV: :func:`fosmc_jax._firmware.identify.write_log`);
    ``fosmc identify --delay D`` with the same D reads it as it was simulated. A config that
    is no such loop is a ``ConfigError``."""
    cfg = problems.as_config(config)
    ctl = cfg.controller
    if cfg.plant.kind != "arm":
        raise problems.ConfigError(f"plant.kind: a log of an experiment needs the arm, got '{cfg.plant.kind}'")
    if not ctl.sample_period > 0:
        raise problems.ConfigError("controller.sample_period: a log of an experiment needs a digital loop (a drive "
                                  "sampling at a period > 0), got 0 (the ideal loop)")  # fmt: skip
    delay = ctl.delay_samples if delay is None else delay
    if not (isinstance(delay, (int, np.integer)) and not isinstance(delay, bool) and delay >= 0):
        raise ValueError(f"delay: expected a non-negative integer (samples), got {delay!r}")
    if currents and (cfg.arm.uncertainty.samples or (cfg.sample.count and cfg.sample.payloads)):
        raise problems.ConfigError("currents: the first rollout's arm is drawn ([arm.uncertainty] samples or [sample] "
                                  "payloads), and its currents need that arm: log without currents")  # fmt: skip
    cfg = problems.replace(cfg, sim={"save_every": problems.sample_steps(cfg)})
    trace = problems.build(cfg).simulate().trace
    t, X, U = (np.asarray(a[0]) for a in (trace.t, trace.X, trace.U))
    theta = np.asarray(quantize(jnp.asarray(X[:, 0::3]), jnp.asarray(cfg.sensors.encoder_counts, float)))
    u = np.concatenate([U[delay:], np.repeat(U[-1:], min(delay, len(U)), axis=0)])[: len(U)]
    current = None
    if currents:  # from the state, by the motor's equation, with the config's own arm and first payload
        params = ArmParams(*(jnp.asarray(x, float) for x in cfg.arm.params))
        arm = Arm(params, jnp.asarray(cfg.plant.payloads[0], float))
        current = np.asarray(jax.vmap(lambda x: jnp.stack(arm.init(x).current))(jnp.asarray(X)))
    log = identification.check_log(identification.Log(t, theta, u, current))
    if path is not None:
        identification.write_log(log, path)
    return log
