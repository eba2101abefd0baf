"""Configs for research scripts: a TOML file or a dict, checked and completed with the
defaults (every key is documented in docs/configuration.md), turned into the objects the
simulator and the tuner take. Errors are one-line :class:`ConfigError`\\ s naming the key.

    import fosmc_jax.config as fc
    cfg = fc.load("tuning/configs/realistic_arm.toml")  # or fc.resolve({"plant": {...}})
    sim = fc.build(cfg)  # a Problem: plants, base parameters, reference, initial states, dt, ...
    result = sim.simulate()  # the batch with the config's parameters
    plain, train, p0 = fc.tuning_problems(cfg)  # what fosmc tune and fosmc front search on
    fc.design_model(cfg)  # the rows and box the controller is designed on ([model] from)
"""

from ._app.config import (
    GRADIENT_WINDOW,
    PRESETS,
    ConfigError,
    DesignModel,
    arm_params_of,
    arm_samples,
    as_config,
    box_of,
    build,
    defaults,
    design_model,
    design_summary,
    draws,
    load,
    resolve,
    sample_steps,
    tuning_problems,
    with_params,
)
from ._app.study import held_out_config, references, study
from ._simulator.problem import Problem

__all__ = [
    "GRADIENT_WINDOW",
    "PRESETS",
    "ConfigError",
    "DesignModel",
    "arm_params_of",
    "arm_samples",
    "as_config",
    "Problem",
    "box_of",
    "build",
    "defaults",
    "design_model",
    "design_summary",
    "draws",
    "held_out_config",
    "load",
    "references",
    "resolve",
    "sample_steps",
    "study",
    "tuning_problems",
    "with_params",
]
