"""The Monte-Carlo draws a config asks for: ``[sample]``'s payloads and initial offsets and
``[arm.uncertainty]``'s sampled arms, seeded, float64 NumPy."""

from __future__ import annotations

import numpy as np

from .._plants.arm import ArmParams
from .resolve import as_config
from .schema import ConfigError
from .tables import Config


def draws(config: Config | dict) -> dict[str, np.ndarray]:
    """The ``[sample]`` table's Monte-Carlo draws, float64, seeded by ``sample.seed``: ``payloads``
    (count,) ~ U(low, high) kg when ``sample.payloads`` is set (drawn first), ``offsets``
    (count, 9) ~ N(0, diag(sample.offsets)^2) when any scale is positive (a scale of 0 leaves
    that state's offset 0); {} without sampling."""
    cfg = as_config(config)
    sample, out = cfg.sample, {}
    arms = arm_samples(cfg)
    if arms is not None:
        out["arms"] = arms
    if not sample.count:
        return out
    rng, n = np.random.default_rng(sample.seed), sample.count
    if sample.payloads:
        out["payloads"] = rng.uniform(*sample.payloads, size=n)
    if any(sample.offsets):
        out["offsets"] = rng.standard_normal((n, 9)) * np.asarray(sample.offsets)
    return out


def arm_varies(config: Config | dict) -> bool:
    """Whether ``[arm.uncertainty]`` sets a half-width, so :func:`arm_samples` draws arms (known
    without drawing them)."""
    return any(np.any(np.asarray(width, float) > 0) for width in as_config(config).arm.uncertainty.widths)


def arm_samples(config: Config | dict) -> dict[str, np.ndarray] | None:
    """``[arm.uncertainty]``'s arms, {field: (N, ...)} float64 (None: none): each field x (1 + h u),
    h its relative half-width, u ~ U(-1, 1) per entry (``sampling = "uniform"``, ``samples``
    arms, seeded), or u = +-1 at the corners of the ranges (``"vertices"``: every corner of the
    m varying entries when ``samples`` is 0 or at least 2^m, else that many distinct corners,
    seeded). The nominal arm is not one of them."""
    cfg = as_config(config)
    unc, arm = cfg.arm.uncertainty, cfg.arm.params
    widths = {k: np.broadcast_to(np.asarray(getattr(unc.widths, k), float), np.shape(getattr(arm, k)))
              for k in ArmParams._fields}  # fmt: skip
    flat = np.concatenate([w.ravel() for w in widths.values()])
    live = np.flatnonzero(flat > 0)
    if not live.size:
        return None
    rng = np.random.default_rng(unc.seed)
    if unc.sampling == "uniform":
        u = rng.uniform(-1.0, 1.0, (unc.samples, flat.size))
    else:
        m = live.size
        if m > 24:
            raise ConfigError(f"arm.uncertainty.sampling: 'vertices' of {m} varying entries is 2^{m} corners; "
                              "use 'uniform'")  # fmt: skip
        n = 2**m if not unc.samples or unc.samples >= 2**m else unc.samples
        codes = np.arange(n) if n == 2**m else rng.choice(2**m, size=n, replace=False)
        u = np.zeros((n, flat.size))
        u[:, live] = 2.0 * ((codes[:, None] >> np.arange(m)) & 1) - 1.0
    out, i = {}, 0
    for k, w in widths.items():
        size = w.size
        out[k] = np.asarray(getattr(arm, k), float) * (1.0 + w * u[:, i : i + size].reshape((-1,) + w.shape))
        i += size
    return out
