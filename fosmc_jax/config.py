"""Configs for research scripts: a TOML file or a dict, checked and completed with the
defaults (every key is documented in docs/configuration.md), resolved once into a frozen, typed
:class:`Config` (``cfg.sim.dt``), and turned into the objects the simulator and the tuner take.
Errors are one-line :class:`ConfigError`\\ s naming the key.

    import fosmc_jax.config as fc
    cfg = fc.load("tuning/configs/realistic_arm.toml")  # or fc.resolve({"plant": {...}})
    cfg.sim.dt, cfg["sim"]["dt"]  # typed values; the mapping in the TOML's layout, read-only
    short = fc.replace(cfg, sim={"t_final": 0.5})  # a variant, checked again
    sim = fc.build(cfg)  # a Problem: plants, base parameters, reference, initial states, dt, ...
    result = sim.simulate()  # the batch with the config's parameters
    plain, train, p0 = fc.tuning_problems(cfg)  # what fosmc tune and fosmc front search on
    fc.design_model(cfg)  # the rows and box the controller is designed on ([model] from)
    fc.chattering_floor(cfg)  # an arm's: the chattering (V/s) of a perfect tracker, per arm and joint
    fc.tracking_voltages(cfg)  # the voltages (arms, samples, 3) it is the total variation of
    cfg.as_dict()  # the TOML's layout as a plain dict (what result files record)

``study`` and ``references`` (``fosmc front``'s study, :mod:`fosmc_jax._app.study`) belong to
the application and are imported on first use, so that importing this module builds problems
without the command line's layer.
"""

from ._problems import (
    GRADIENT_GUARD,
    GRADIENT_WINDOW,
    PRESETS,
    Config,
    ConfigError,
    DesignModel,
    arm_params_of,
    arm_samples,
    as_config,
    box_of,
    build,
    chattering_floor,
    defaults,
    design_model,
    design_summary,
    draws,
    fallback_problem,
    held_out_config,
    load,
    replace,
    resolve,
    rough_loop,
    sample_steps,
    tracking_voltages,
    tuning_problems,
    with_params,
)
from ._simulator.problem import Problem

__all__ = [
    "GRADIENT_GUARD",
    "GRADIENT_WINDOW",
    "PRESETS",
    "Config",
    "ConfigError",
    "DesignModel",
    "arm_params_of",
    "arm_samples",
    "as_config",
    "Problem",
    "box_of",
    "chattering_floor",
    "build",
    "defaults",
    "design_model",
    "design_summary",
    "draws",
    "fallback_problem",
    "held_out_config",
    "load",
    "references",  # noqa: F822 (imported on first use: __getattr__)
    "replace",
    "resolve",
    "rough_loop",
    "sample_steps",
    "study",  # noqa: F822
    "tracking_voltages",
    "tuning_problems",
    "with_params",
]


def __getattr__(name: str):
    if name in ("study", "references"):
        from ._app import study

        return getattr(study, name)
    raise AttributeError(f"module 'fosmc_jax.config' has no attribute {name!r}")
