"""The problems a config describes: its batch of plants, initial states and controller as a
:class:`fosmc_jax.Problem` (:func:`build`), and the problems ``fosmc tune`` and ``fosmc front``
search on (:func:`tuning_problems`)."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .._controllers import KINDS, SPACES
from .._controllers.fosmc import FOSMCParams
from .._loop.digital import DigitalLoop, Sensors
from .._plants.arm import Arm, ArmParams, tracking_voltage
from .._plants.linear import uncertain_plants
from .._plants.reference import Cycloid, desired_state
from .._simulator.problem import Problem
from . import memory
from .design import box_of, cycloid, design_model
from .draws import draws
from .resolve import as_config, replace
from .schema import ConfigError
from .tables import Config, Gains


def _cast(x: Any, dtype) -> jax.Array:
    """A config's numbers (Python, nested tuples) as an array of ``dtype``, through float64."""
    return jnp.asarray(np.asarray(x, dtype=np.float64), dtype)


def reference_of(cfg: Config, dtype) -> Cycloid:
    """The reference (30) a config describes."""
    return cycloid(cfg.trajectory, dtype)


def n_steps(cfg: Config) -> int:
    """n = round(t_final / dt)."""
    return max(1, round(cfg.sim.t_final / cfg.sim.dt))


def sample_steps(config: Config | dict) -> int:
    """m = controller.sample_period / sim.dt (1 for the ideal loop)."""
    cfg = as_config(config)
    T = cfg.controller.sample_period
    return max(1, round(T / cfg.sim.dt)) if T else 1


def arm_params_of(config: Config | dict, dtype) -> ArmParams:
    """The ``[arm]`` table's :class:`fosmc_jax.ArmParams`, as arrays of ``dtype``."""
    return ArmParams(*(_cast(x, dtype) for x in as_config(config).arm.params))


def controller_of(cfg: Config, dtype, gamma=None) -> FOSMCParams:
    """The :class:`FOSMCParams` a config describes (``gamma`` overrides ``controller.gamma``),
    on the nominal rows of its design model (:func:`design_model`)."""
    ctl, design = cfg.controller, design_model(cfg)
    gamma = ctl.gamma if gamma is None else gamma
    return FOSMCParams(*(_cast(x, dtype) for x in (ctl.C, ctl.poles, gamma, ctl.delta, design.A_rows, design.B_rows)))


def _law_and_loop(cfg: Config, dtype) -> tuple[Callable[[FOSMCParams], Any], Callable[[Any], Any]]:
    """(law, loop): FOSMC parameters -> the config's kind of law with the config's gains,
    sampled with period T (T = 0: the ideal loop's); a law -> the controller of the config's
    loop (the ideal loop: the law itself, super-twisting's v integrated with the plant)."""
    ctl, sens = cfg.controller, cfg.sensors
    T = _cast(ctl.sample_period, dtype)
    kind = KINDS[ctl.kind]
    # the kind's law reads the typed [controller] table, its own gains as arrays of the run's dtype
    gains = Gains(tuple((key, _cast(value, dtype) if key in kind.gains else value) for key, value in ctl.gains.pairs))
    table = dataclasses.replace(ctl, gains=gains)
    law = lambda params: kind.law(params, table, T)
    if not ctl.sample_period:
        return law, kind.ideal or (lambda law: law)
    noise_std = _cast(sens.noise_std, dtype) if any(sens.noise_std) else None  # all zero: nothing to draw
    sensors = Sensors(_cast(sens.encoder_counts, dtype), noise_std, sens.derivatives)
    u_max = _cast(cfg.actuator.u_max if cfg.actuator.u_max is not None else [np.inf] * 3, dtype)
    m, d = sample_steps(cfg), ctl.delay_samples
    return law, lambda law: DigitalLoop(law, sensors, u_max, T, m, d)


def keys_of(cfg: Config) -> Any:
    """One PRNG key per noise realization (``sensors.seed``, ``sensors.realizations``); None for
    the ideal loop."""
    if not cfg.controller.sample_period:
        return None
    return jax.random.split(jax.random.PRNGKey(cfg.sensors.seed), cfg.sensors.realizations)


def _paired_length(lengths: dict[str, int]) -> int:
    """The common length of what ``sim.pairing = "paired"`` pairs (a length of 1 is repeated)."""
    longer = {n for n in lengths.values() if n > 1}
    if len(longer) > 1:
        named = ", ".join(f"{name} ({n})" for name, n in lengths.items())
        raise ConfigError(f"sim.pairing: 'paired' needs as many of each, or one: got {named}")
    return longer.pop() if longer else 1


def _repeat(x, n: int):
    """``x`` (leading length 1 or n) with leading length n."""
    return x if len(x) == n else (jnp if isinstance(x, jax.Array) else np).repeat(x, n, axis=0)


def build(config: str | Path | dict | Config | None = None) -> Problem:
    """The simulation a config describes (a TOML path, a preset's name such as
    ``"realistic_arm"``, a dict, a resolved :class:`Config`, or ``None``: the paper's defaults;
    see :func:`fosmc_jax.config.as_config`), as a :class:`fosmc_jax.Problem` in the config's
    ``sim.precision``: ``problem.simulate(params)`` runs its batch.

    The plants are the linear model's uncertainty realizations (``kind = "linear"``) or one arm
    per payload (``kind = "arm"``). The initial states are X_d(0) + each ``sim.initial_offset``;
    the batch is every plant crossed with every initial state, crossed with every noise
    realization of a digital loop (in that order); with ``sim.pairing = "paired"`` the i-th plant
    runs from the i-th initial state only (one plant or one initial state: repeated). A
    ``[sample]`` table's draws (:func:`fosmc_jax.config.draws`) replace ``plant.payloads`` and
    ``sim.initial_offset``. The problem's ``base`` holds the kind's
    parameters: the FOSMC's :class:`FOSMCParams`, or the SMC's or super-twisting's law with
    the config's gains.

    A batch that cannot fit in the memory this process may use (:mod:`fosmc_jax._problems.memory`:
    a lower bound of its memory above the smaller of the available memory and ``ulimit -v``) is
    refused before anything is drawn, naming the key to change.

    ``sim.precision = "float64"`` (the default) needs JAX's 64-bit mode, which only the user
    may switch on (it changes every array of the process):
    ``jax.config.update("jax_enable_x64", True)`` first, or ``with jax.enable_x64(True):``
    around the script, or ``[sim] precision = "float32"``.
    """
    cfg = as_config(config)
    too_large = memory.refusal(cfg)  # before anything is drawn
    if too_large is not None:
        raise ConfigError(too_large)
    return problem_of(cfg)


def tracking_voltages(config: str | Path | dict | Config) -> np.ndarray:
    """The exact tracking voltage (:func:`fosmc_jax.tracking_voltage`) of each arm of the
    config's batch on the controller's sampling grid (every ``sim.dt``, or every
    ``controller.sample_period``, over [0, t_final]), (arms, samples, 3), V. Arm plants only
    (``plant.kind = "arm"``): a one-line :class:`ConfigError` otherwise."""
    cfg = as_config(config)
    if cfg.plant.kind != "arm":
        raise ConfigError(f"plant.kind: the tracking voltage is an arm's; got {cfg.plant.kind!r}")
    problem = build(cfg)
    t = jnp.arange(0, n_steps(cfg) + 1, sample_steps(cfg)) * problem.dt  # the controller's samples
    voltage = lambda arm: jax.vmap(lambda s: tracking_voltage(arm, problem.reference(s), s))(t)
    return np.asarray(jax.jit(jax.vmap(voltage))(problem.plants))


def chattering_floor(config: str | Path | dict | Config) -> np.ndarray:
    """The ``chattering`` metric (sum_k |u_k+1 - u_k| / t_final, V/s) of a perfect tracker: the
    total variation rate of :func:`tracking_voltages`, per arm of the config's batch and joint,
    (arms, 3). A controller that tracks closely puts out about this voltage, so no tuning takes
    the mean ``chattering`` far below the mean of this floor at a small error (``[tune]
    chattering_bound``); the switching part is what lies above it. Arm plants only."""
    cfg = as_config(config)
    if cfg.plant.kind != "arm":
        raise ConfigError(f"plant.kind: the chattering floor is the arm's tracking voltage's; got {cfg.plant.kind!r}")
    return np.abs(np.diff(tracking_voltages(cfg), axis=1)).sum(axis=1) / cfg.sim.t_final


def _plants(cfg: Config, offsets: np.ndarray, drawn: dict, dtype) -> tuple[Any, np.ndarray]:
    """The batch's plants (every arm sample x payload, or the linear model's realizations) and
    the initial offsets, paired one to one with ``sim.pairing = "paired"``."""
    cast = lambda x: _cast(x, dtype)
    paired = cfg.sim.pairing == "paired"
    plant = cfg.plant
    if plant.kind == "arm":
        payloads = np.asarray(drawn.get("payloads", plant.payloads), dtype=float)
        arms = drawn.get("arms") or {k: np.asarray(v, float)[None] for k, v in cfg.arm.params._asdict().items()}
        n_arms = len(arms["F"])
        if paired:  # the i-th arm sample with the i-th payload and the i-th initial state
            n = _paired_length({"arm samples": n_arms, "payloads": len(payloads), "initial offsets": len(offsets)})
            arms, payloads, offsets = ({k: _repeat(v, n) for k, v in arms.items()}, _repeat(payloads, n),
                                       _repeat(offsets, n))  # fmt: skip
        else:  # every arm sample with every payload, the arm sample first
            arms = {k: np.repeat(v, len(payloads), axis=0) for k, v in arms.items()}
            payloads = np.tile(payloads, n_arms)
        return Arm(ArmParams(**{k: cast(v) for k, v in arms.items()}), cast(payloads)), offsets
    plants = uncertain_plants(
        cfg.model.A_rows, cfg.model.B_rows, plant.uncertainty, box=box_of(cfg),
        dA_rows=plant.dA_rows, dB_rows=plant.dB_rows, samples=plant.samples, seed=plant.seed,
    )  # fmt: skip
    plants = type(plants)(*(cast(x) for x in plants))
    if paired:
        n = _paired_length({"plants": len(plants.a_rows), "initial offsets": len(offsets)})
        plants, offsets = jax.tree.map(lambda x: _repeat(x, n), plants), _repeat(offsets, n)
    return plants, offsets


def problem_of(cfg: Config) -> Problem:
    """:func:`build` of a resolved config without its memory check, for a caller that holds
    the batch against memory itself (``fosmc simulate`` runs it in chunks:
    :func:`fosmc_jax._problems.memory.plan`)."""
    sim, ctl = cfg.sim, cfg.controller
    if sim.precision == "float64" and not jax.config.jax_enable_x64:
        raise ConfigError('sim.precision: "float64" needs JAX\'s 64-bit mode: call jax.config.update('
                          '"jax_enable_x64", True) before building, or set [sim] precision = "float32"')  # fmt: skip
    dtype = jnp.dtype(sim.precision)
    reference = reference_of(cfg, dtype)
    drawn = draws(cfg)
    offsets = np.atleast_2d(np.asarray(drawn.get("offsets", sim.initial_offset), dtype=float))
    plants, offsets = _plants(cfg, offsets, drawn, dtype)
    X0s = desired_state(reference(jnp.zeros((), dtype)))[None] + _cast(offsets, dtype)
    options = {
        "n_steps": n_steps(cfg),
        "integrator": sim.integrator,
        "switching": ctl.switching,
        "law": ctl.law,
        "save_every": sim.save_every,
        "divergence_bound": sim.divergence_bound,
        "pairing": sim.pairing,
    }
    dt = jnp.asarray(sim.dt, dtype)
    params = controller_of(cfg, dtype)
    law, loop = _law_and_loop(cfg, dtype)
    if KINDS[ctl.kind].tunes_params:  # the kind's parameters are fields of the FOSMC parameters
        base, controller_from = params, lambda params: loop(law(params))
    else:  # the kind's parameters are fields of its law
        base, controller_from = law(params), loop
    arm = arm_params_of(cfg, dtype) if cfg.plant.kind == "arm" else None  # the nominal, sampled arms around it
    return Problem(plants, base, reference, X0s, dt, options, keys_of(cfg), controller_from, ctl.kind, arm)


#: The ``[tune] gradient_window`` (s) of the sign law, and of a rough loop where the whole horizon's
#: gradient explodes: shorter than where its growth starts (docs/configuration.md, the [tune] table).
GRADIENT_WINDOW = 0.02
#: The largest norm of the whole horizon's gradient (internal coordinates) at ``fosmc tune``'s start
#: on a rough loop that tune keeps: an exploding one lies orders of magnitude above it, a finite one
#: orders below (tuning/results/tune_vs_cma_window.md); above it tune falls back to :data:`GRADIENT_WINDOW`.
GRADIENT_GUARD = 1e3


def training_config(cfg: Config) -> Config:
    """The config ``fosmc tune`` and ``fosmc front`` train on: ``[sim]`` with ``tune.train_dt``
    and ``tune.train_t_final`` where set, and a digital loop without ``tune.train_dt`` at one
    integration step per controller sample (dt = ``controller.sample_period``): it ranks
    candidates like ``[sim]``'s step at a fraction of the cost (docs/configuration.md, the [tune] table); results are
    re-evaluated on ``[sim]``. ``cfg`` itself where nothing changes."""
    sim = {}
    if cfg.tune.train_dt:
        sim["dt"] = cfg.tune.train_dt
    if cfg.tune.train_t_final:
        sim["t_final"] = cfg.tune.train_t_final
    if not cfg.tune.train_dt and cfg.controller.sample_period > cfg.sim.dt:
        sim["dt"] = cfg.controller.sample_period
    return replace(cfg, sim=sim) if sim else cfg


def rough_loop(cfg: Config) -> bool:
    """Whether ``cfg``'s loop is digital and quantizes (``encoder_counts``) or differences
    (``derivatives = "difference"``) its measurements: its gradients may grow exponentially over a
    long horizon, and tune's automatic learning rate is smaller there."""
    sensors = cfg.sensors
    return cfg.controller.sample_period > cfg.sim.dt and (
        any(n > 0 for n in sensors.encoder_counts) or sensors.derivatives == "difference"
    )


def gradient_window(cfg: Config) -> float:
    """``tune.gradient_window`` (s), or where it is 0 (automatic): :data:`GRADIENT_WINDOW` under the
    sign law, where the gradient over any longer horizon points uphill, else 0: the whole
    horizon, finite and exact in the ideal loop and, from tune's start, on most rough loops
    (:func:`rough_loop`), where tune falls back to :data:`GRADIENT_WINDOW` if the whole horizon's
    gradient at its start is not finite or above :data:`GRADIENT_GUARD` (docs/configuration.md,
    the [tune] table)."""
    return cfg.tune.gradient_window or (GRADIENT_WINDOW if cfg.controller.switching == "sign" else 0.0)


def fallback_problem(cfg: Config, train: Problem) -> Problem | None:
    """The training problem ``train`` (of :func:`tuning_problems`) with its gradient truncated every
    :data:`GRADIENT_WINDOW`, where ``cfg``'s loop is rough (:func:`rough_loop`) and its window
    automatic: what ``fosmc tune`` falls back to where the whole horizon's gradient explodes at
    its start; None elsewhere."""
    if not rough_loop(cfg) or train.options.get("truncate_every"):
        return None
    window = int(round(GRADIENT_WINDOW / float(train.dt)))
    return train._replace(options=dict(train.options, truncate_every=window))


def plain_problem(config: str | Path | dict | Config, **options) -> Problem:
    """:func:`build` of a config without a trace (``save_every`` 0: metrics only), with
    ``options`` (the simulator's, e.g. ``checkpoint_every``) set: what a search evaluates."""
    b = build(config)
    return b._replace(options=dict(b.options, save_every=0, **options))


def tuning_problems(config: str | Path | dict | Config) -> tuple[Problem, Problem, Any]:
    """(plain, train, p0): the :class:`fosmc_jax.Problem` of ``[sim]`` (every result is
    evaluated on it), the training problem (:func:`training_config`, the scan rematerialised
    every ``tune.remat_steps``, the gradient truncated every :func:`gradient_window`), and the
    config's values of its kind's parameters (``fosmc_jax._controllers.SPACES[kind].values``:
    the FOSMC's :class:`Tunable` of delta, gamma, poles; SMC's k, phi; super-twisting's k1,
    k2). The problems' ``base`` is what those parameters are fields of: the FOSMC's
    :class:`FOSMCParams`, or the SMC or super-twisting law built with the config's gains."""
    cfg = as_config(config)
    space = SPACES[cfg.controller.kind]
    train_cfg = training_config(cfg)
    plain = plain_problem(cfg)
    window = int(round(gradient_window(cfg) / train_cfg.sim.dt))
    remat = {"checkpoint_every": cfg.tune.remat_steps, "truncate_every": window}
    # no surrogate: the same simulation (the same make and keys tell fosmc_jax._search.front so)
    train = (
        plain_problem(train_cfg, **remat) if train_cfg != cfg else plain._replace(options=dict(plain.options, **remat))
    )
    p0 = space.values(*(getattr(plain.base, name) for name in space.names))
    return plain, train, p0
