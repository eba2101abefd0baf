"""A config resolved once: a TOML file, a preset's name or a user dict checked key by key
against :data:`fosmc_jax._problems.schema.SCHEMA`, completed with the defaults, checked across
keys, and returned as a typed :class:`fosmc_jax._problems.tables.Config`; its variants
(:func:`replace`, :func:`with_params`: a kind's parameters from a result file) resolved again.
Errors are one-line :class:`ConfigError`\\ s naming the first offending key and the expected form.
"""

from __future__ import annotations

import copy
import math
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import jax
import numpy as np

from .._controllers import SPACES
from .._controllers.kind import load as load_kind
from .._controllers.kind import space_of
from .._design.gains import DesignError, check_design, stable_step
from .._io import read_json
from .._plants.arm import ArmParams, centre_error
from .design import design_model, not_an_arm
from .schema import BOX_KEYS, ConfigError, check_horizon, defaults, full_schema, short
from .tables import Config

try:  # Python >= 3.11
    import tomllib
except ModuleNotFoundError:  # pragma: no cover - Python 3.10
    import tomli as tomllib

#: The configs that ship with the package, by name (``build("realistic_arm")``).
PRESETS = {path.stem: path for path in sorted((Path(__file__).parent / "presets").glob("*.toml"))}


def _merge(schema: dict, base: dict, user: Any, prefix: str) -> dict:
    if not isinstance(user, Mapping):
        raise ConfigError(f"{prefix or 'config'}: expected a table, got {short(user)}")
    out = dict(base)
    for key, value in user.items():
        shown = key if str(key).isidentifier() else repr(key)
        name = f"{prefix}.{shown}" if prefix else shown
        if key not in schema:
            known = ", ".join(sorted(schema))
            raise ConfigError(f"{name}: unknown key (known here: {known})")
        rule = schema[key]
        out[key] = _merge(rule, base[key], value, name) if isinstance(rule, dict) else rule(name, _python(name, value))
    return out


def _python(key: str, value: Any) -> Any:
    """NumPy and JAX arrays and scalars as the Python numbers and lists a TOML file gives."""
    if isinstance(value, (list, tuple)):
        return [_python(key, v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    if hasattr(value, "__array__") and not isinstance(value, (str, bytes)):
        if isinstance(value, jax.core.Tracer):
            raise ConfigError(f"{key}: expected concrete numbers, got a traced value (build the config outside jit)")
        return np.asarray(value).tolist()
    return value


def resolve(user: Mapping | None = None) -> Config:
    """Validate a user configuration (nested dict, e.g. parsed TOML; or a resolved
    :class:`Config`, checked again), fill in the defaults and return it typed.

    ``[tune] params`` defaults to every parameter of the config's ``controller.kind``.
    Raises :class:`ConfigError` naming the first offending key.
    """
    user = user.as_dict() if isinstance(user, Config) else copy.deepcopy(user or {})
    _load_kind(user)
    merged = _merge(full_schema(), defaults(), user, "")
    if "params" not in (user.get("tune", {}) if isinstance(user, Mapping) else {}):
        merged["tune"]["params"] = list(SPACES[merged["controller"]["kind"]].names)
    cfg = Config.of(merged)
    _check_consistency(merged, cfg)
    return cfg


def _load_kind(user: Any) -> None:
    """A ``[controller] kind`` naming a module's kind (``"mypkg.mykind:KIND"``): that kind
    imported and registered, and the table's kind its name (a one-line :class:`ConfigError`
    when it does not load)."""
    controller = user.get("controller") if isinstance(user, Mapping) else None
    kind = controller.get("kind") if isinstance(controller, dict) else None
    if isinstance(kind, str) and ":" in kind:
        try:
            controller["kind"] = load_kind(kind).name
        except ValueError as e:
            raise ConfigError(f"controller.kind: {e}") from None


def load(path: str | Path | None) -> Config:
    """Read and :func:`resolve` a TOML file, or a preset's by its name (:data:`PRESETS`, e.g.
    ``"realistic_arm"``; a file of that name in the working folder comes first); ``None``: the
    defaults."""
    if path is None:
        return resolve({})
    if isinstance(path, str) and path in PRESETS and not Path(path).exists():
        path = PRESETS[path]
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as e:
        raise ConfigError(f"cannot read config file {str(path)!r}: {e.strerror or e}") from None
    try:
        text = data.decode("utf-8")  # TOML is UTF-8 whatever the locale
    except UnicodeDecodeError as e:
        raise ConfigError(f"{path}: not UTF-8 text (a TOML file is UTF-8; byte {e.start} is {data[e.start]:#04x}); "
                          "save it as UTF-8") from None  # fmt: skip
    try:
        user = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{path}: not valid TOML: {e}") from None
    return resolve(user)


def as_config(config: str | Path | Mapping | None) -> Config:
    """The resolved config of a TOML path, a preset's name (:data:`PRESETS`), a user dict
    (validated, defaults filled in; NumPy and JAX arrays welcome where lists are), a resolved
    :class:`Config` (returned as it is: it was checked where it was made), or ``None`` (the
    paper's defaults)."""
    if config is None or isinstance(config, (str, Path)):
        return load(config)
    if isinstance(config, Config):
        return config
    if isinstance(config, Mapping):
        return resolve(config)
    raise ConfigError(f"config: expected a TOML path, a preset name ({', '.join(PRESETS)}), a dict or None, "
                      f"got {type(config).__name__}")  # fmt: skip


def replace(cfg: Config, **tables: dict[str, Any]) -> Config:
    """``cfg`` with the keys of ``tables`` changed (``replace(cfg, sim={"dt": 1e-3})``), resolved
    and checked again: a resolved config is frozen; this is how a variant of it is made."""
    user = cfg.as_dict()
    for name, values in tables.items():
        if name not in user:
            raise ConfigError(f"{name}: unknown table (known: {', '.join(user)})")
        user[name] = _merged(user[name], values)
    return resolve(user)


def _merged(base: Any, values: Any) -> Any:
    """``base`` (a table) with ``values`` (nested tables: merged key by key) set."""
    if not isinstance(base, dict) or not isinstance(values, Mapping):
        return values
    return {**base, **{k: _merged(base.get(k), v) for k, v in values.items()}}


def _check_consistency(cfg: dict, typed: Config) -> None:
    """The rules across keys, on the merged plain tables ``cfg`` (``typed``: the same, typed)."""
    sim, ctl, model, box = cfg["sim"], cfg["controller"], cfg["model"], cfg["plant"]["box"]
    if sim["dt"] > sim["t_final"]:
        raise ConfigError(f"sim.dt: expected at most sim.t_final = {sim['t_final']}, got {sim['dt']}")
    sample = cfg["sample"]
    drawn = bool(sample["payloads"]) or any(sample["offsets"])
    if sample["count"] and not drawn:
        raise ConfigError("sample.count: nothing to draw (set sample.payloads = [low, high] or sample.offsets)")
    if drawn and not sample["count"]:
        key = "payloads" if sample["payloads"] else "offsets"
        raise ConfigError(f"sample.{key}: draws nothing without sample.count, the number of draws (0 by default)")
    if sample["payloads"] and cfg["plant"]["kind"] != "arm":
        raise ConfigError("sample.payloads: applies to plant.kind = 'arm' only")
    _check_arm(cfg)
    if cfg["plant"]["kind"] == "arm" and cfg["plant"]["uncertainty"] != "none":
        raise ConfigError("plant.uncertainty: applies to kind = 'linear' only (the arm's uncertainty is its payloads)")
    tune = cfg["tune"]
    for form, key in (("error_bound", "error_bound"), ("chattering_bound", "chattering_bound")):
        if tune["objective"] == form and not tune[key] > 0:
            raise ConfigError(f"tune.{key}: expected a positive bound with tune.objective = '{form}', got {tune[key]}")
    train_t = cfg["tune"]["train_t_final"] or sim["t_final"]
    if train_t > sim["t_final"]:
        raise ConfigError(f"tune.train_t_final: expected at most sim.t_final = {sim['t_final']}, got {train_t}")
    if cfg["tune"]["train_dt"] > train_t:
        raise ConfigError(
            f"tune.train_dt: expected at most the training horizon {train_t}, got {cfg['tune']['train_dt']}"
        )
    check_horizon(sim["t_final"], sim["dt"])
    _check_loop(cfg)
    for m in ("A", "B"):
        if np.any(np.asarray(box[f"{m}_lower"]) > np.asarray(box[f"{m}_upper"])):
            raise ConfigError(f"plant.box.{m}_lower: must not exceed plant.box.{m}_upper entrywise")
    if abs(np.linalg.det(np.asarray(model["B_rows"]))) < 1e-12:
        raise ConfigError("model.B_rows: must be invertible (B_bar)")
    _check_model_from(cfg)
    design = design_model(typed)  # with from = "arm": derived here, once per arm (memoised)
    try:
        check_design(design.B_rows, np.asarray(ctl["C"]), np.asarray(ctl["poles"]))
    except DesignError as e:
        raise ConfigError(f"controller: {e}") from None
    h = stable_step(design.A_rows, design.B_rows, ctl["poles"], sim["integrator"])
    if sim["dt"] > h:
        warnings.warn(
            f"sim.dt = {sim['dt']} s exceeds the {sim['integrator']} stability limit {h:.3g} s of the "
            "nominal model's fastest mode: expect divergence",
            stacklevel=2,
        )


def _check_arm(cfg: dict) -> None:
    """The ``[arm]`` table's cross-field rules, and the payloads within its range."""
    arm = cfg["arm"]
    unc = arm["uncertainty"]
    varying = [k for k in ArmParams._fields if np.any(np.asarray(unc[k]) > 0)]
    varies = bool(varying)
    if varies and cfg["plant"]["kind"] != "arm":
        raise ConfigError(f"arm.uncertainty.{varying[0]}: applies to plant.kind = 'arm' only")
    if cfg["plant"]["kind"] != "arm":  # an [arm] table the linear model would ignore
        base = defaults()["arm"]
        for k in (*ArmParams._fields, "payload_range"):
            if not np.array_equal(np.asarray(arm[k], float), np.asarray(base[k], float)):
                raise ConfigError(f"arm.{k}: applies to plant.kind = 'arm' only")
    if varies and not unc["samples"] and unc["sampling"] == "uniform":
        raise ConfigError("arm.uncertainty.samples: expected a positive number of sampled arms with half-widths set")
    if unc["samples"] and not varies:
        raise ConfigError("arm.uncertainty.samples: nothing varies (set a half-width, e.g. arm.uncertainty.F = 0.3)")
    for k in varying:  # relative half-widths: a zero stays zero (the Coulomb and disturbance defaults)
        width, nominal = np.asarray(unc[k], float), np.asarray(arm[k])
        if np.ndim(width) and np.any((width > 0) & (nominal == 0)) or not np.any((width > 0) & (nominal != 0)):
            raise ConfigError(f"arm.uncertainty.{k}: a relative half-width of arm.{k} = {short(arm[k])} varies "
                              f"nothing where it is zero (a zero stays zero); set arm.{k}, the nominal")  # fmt: skip
    # parameters of a term that is absent in every joint: a half-width on them varies nothing either
    for k, term in (("v_coulomb", "Fc"), ("f_sin", "tau_sin"), ("t_step", "tau_step")):
        if k in varying and not np.any(np.asarray(arm[term])):
            raise ConfigError(f"arm.uncertainty.{k}: varies nothing while arm.{term} is zero; set arm.{term}")
    silent = (np.asarray(arm["tau_sin"]) != 0) & (np.asarray(arm["f_sin"]) == 0)
    if np.any(silent):
        joint = np.flatnonzero(silent)[0] + 1
        raise ConfigError(f"arm.tau_sin: a sinusoid at arm.f_sin = 0 Hz is zero (joint {joint}); set arm.f_sin")
    for j in (2, 3):
        if error := centre_error(arm[f"c{j}"], arm[f"l{j}"], j):
            raise ConfigError(error)
    lo, hi = arm["payload_range"]
    for key, values in (("plant.payloads", cfg["plant"]["payloads"]), ("sample.payloads", cfg["sample"]["payloads"])):
        if values and not lo <= min(values) <= max(values) <= hi:
            raise ConfigError(f"{key}: expected payloads within arm.payload_range = [{lo:g}, {hi:g}] kg, "
                              f"got {short(values)}")  # fmt: skip


def _check_loop(cfg: dict) -> None:
    ctl, sens, sim = cfg["controller"], cfg["sensors"], cfg["sim"]
    T, dt = ctl["sample_period"], sim["dt"]
    if T == 0:
        digital = {"controller.delay_samples": ctl["delay_samples"] != 0,
                   "sensors.encoder_counts": any(sens["encoder_counts"]),
                   "sensors.derivatives": sens["derivatives"] != "measured",
                   "sensors.noise_std": any(sens["noise_std"]),
                   "sensors.realizations": sens["realizations"] != 1,
                   "actuator.u_max": "u_max" in cfg["actuator"]}  # fmt: skip
        for key, set_ in digital.items():
            if set_:
                raise ConfigError(
                    f"{key}: needs controller.sample_period > 0 (the ideal loop reads the exact state; "
                    f"sample_period = sim.dt = {dt} gives a digital loop at the simulation's rate)"
                )
        return
    horizon = sim["t_final"]
    if T > horizon:  # a period past the horizon samples once, at t = 0 (and overflows the step count)
        raise ConfigError(f"controller.sample_period: expected at most sim.t_final = {horizon} s (the controller "
                          f"samples every period), got {T}")  # fmt: skip
    m = T / dt
    if round(m) < 1 or abs(m - round(m)) > 1e-9 * max(1.0, m):
        raise ConfigError(f"controller.sample_period: expected an integer multiple (>= 1) of sim.dt = {dt}, got {T}")
    samples = math.ceil(round(horizon / dt) / round(m))  # the controller's samples within the horizon
    if ctl["delay_samples"] >= samples:
        raise ConfigError(f"controller.delay_samples: expected fewer than the {samples} controller sample(s) within "
                          f"sim.t_final = {horizon} s (a delay of that many or more means the controller never acts "
                          f"on the plant), got {ctl['delay_samples']}")  # fmt: skip
    train_t = cfg["tune"]["train_t_final"]
    if train_t and ctl["delay_samples"] >= math.ceil(train_t / T - 1e-9):  # tune's training horizon
        raise ConfigError(f"tune.train_t_final: expected more than controller.delay_samples = "
                          f"{ctl['delay_samples']} controller samples of {T} s (within it the controller would never "
                          f"act), got {train_t}")  # fmt: skip
    if sim["save_every"] % round(m):
        raise ConfigError(
            f"sim.save_every: expected a multiple of controller.sample_period / sim.dt = {round(m)}, "
            f"got {sim['save_every']}"
        )
    train_dt = cfg["tune"]["train_dt"]
    if train_dt and (T / train_dt < 1 - 1e-9 or abs(T / train_dt - round(T / train_dt)) > 1e-9 * T / train_dt):
        raise ConfigError(f"tune.train_dt: expected a step that divides controller.sample_period = {T}, got {train_dt}")
    if sens["derivatives"] == "difference" and any(np.asarray(sens["noise_std"])[[1, 2, 4, 5, 7, 8]]):
        raise ConfigError(
            "sensors.noise_std: with sensors.derivatives = 'difference' only the theta entries (1, 4, 7) may be "
            f"non-zero (the rates are differences of the measured angles), got {sens['noise_std']}"
        )


def _check_model_from(cfg: dict) -> None:
    """``model.from = "arm"``: an arm plant, and none of the paper's rows or box it replaces set."""
    if cfg["model"]["from"] != "arm":
        return
    if cfg["plant"]["kind"] != "arm":
        raise ConfigError(not_an_arm(cfg["plant"]["kind"]))
    base = defaults()
    tables = (("model", cfg["model"], base["model"], ("A_rows", "B_rows")),
              ("plant.box", cfg["plant"]["box"], base["plant"]["box"], BOX_KEYS))  # fmt: skip
    for name, table, default, keys in tables:
        for k in keys:
            if table[k] != default[k]:  # a resolved config holds the defaults: only a user's value differs
                raise ConfigError(f"{name}.{k}: not used with model.from = 'arm' (the design model is derived from "
                                  "[arm]); remove it, or set model.from = 'paper'")  # fmt: skip


def with_params(config: str | Path | dict | Config, path: str | Path, point: int | None = None) -> Config:
    """The config with its controller kind's parameters (the FOSMC's delta, gamma, poles; SMC's
    k, phi; super-twisting's k1, k2) taken from a ``fosmc tune`` result file (its
    ``final.params``) or from point ``point`` of a ``fosmc front`` file, and put back into
    their config keys (``smc_k``, ...), validated like those keys. A file of another kind's
    parameters is refused."""
    try:
        data = read_json(path)
    except ValueError as e:
        raise ConfigError(f"--params: {e}") from None
    if isinstance(data, dict) and "points" in data:
        if point is None:
            raise ConfigError(f"--point: {path} is a front of {len(data['points'])} points: name one with --point I "
                              "(e.g. the one `fosmc select` names)")  # fmt: skip
        if not 0 <= point < len(data["points"]):
            raise ConfigError(f"--point: expected an index in [0, {len(data['points'])}) for the front {path}, "
                              f"got {point}")  # fmt: skip
        params = data["points"][point]["params"]
    else:
        if point is not None:
            raise ConfigError(f"--point: {path} is a tune result, not a front")
        try:
            params = data["final"]["params"]
        except (KeyError, TypeError):
            raise ConfigError(f"--params: {path} is not a fosmc tune result (no final.params) or front") from None
    try:
        space = space_of(params)
    except ValueError as e:
        raise ConfigError(f"--params: {path}'s {e}") from None
    cfg = as_config(config)
    kind = cfg.controller.kind
    if space.kind != kind:
        raise ConfigError(f"--params: {path} holds {space.kind} parameters ({', '.join(space.names)}), but the "
                          f"config's controller.kind is '{kind}' (set [controller] kind = '{space.kind}')")  # fmt: skip
    return replace(cfg, controller={p.key: params[p.name] for p in space.params if p.name in params})
