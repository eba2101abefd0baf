"""``fosmc export`` as a function: the digital loop's controller as C99 for a drive."""

from __future__ import annotations

import re
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from .. import _problems as problems
from .._problems import ConfigError
from .shared import (
    ConfigInput,
    Log,
    _quiet,
    _with_x64,
    config_of,
    writable,
)


@_with_x64
def run_export(
    config: ConfigInput = None,
    *,
    out: str | Path | None = None,
    params: str | Path | dict | None = None,
    point: int | None = None,
    precision: str = "float64",
    name: str = "fosmc",
    check: bool = True,
    log: Log = _quiet,
) -> dict[str, Any]:
    """``fosmc export``: the config's digital-loop controller as C99 (``fosmc_jax._firmware.export``):
    ``<name>.h`` and ``<name>.c`` with the constants of the config's point, or of the tuned
    parameters ``params``: a ``fosmc tune`` result.json, or point ``point`` of a ``fosmc front``
    front.json, as ``run_simulate`` takes them, or a dict of the kind's parameters by name, as
    ``fosmc_jax.build(config).simulate(params)`` takes it (a subset: the others stay the
    config's; e.g. ``run_tune(...)["final"]["params"]``), checked as the simulator checks it;
    in ``precision`` (``float32`` or ``float64``).

    The constants are computed in float64 whatever ``[sim] precision`` says and rounded to
    ``precision`` when written; the files say which design model (``[model] from``) their rows
    are. A config without a digital loop (``controller.sample_period`` = 0) is refused: its
    ideal loop reads the exact state at every integration step and integrates the law's state
    with the plant, which no drive does, and the package has no simulation of that law at
    another rate to check the code against. With ``out``, a folder (created), the files are
    written there (existing files of those names replaced; both targets checked before either
    is written) and, with ``check``, compiled with the host's C compiler under ``-std=c99 -Wall
    -Wextra -Werror -pedantic`` (skipped, and said so, without one); ``log`` gets the line of a
    clean compile (the command line prints the paths). Returns ``{"files":
    {filename: text}, "paths": [written paths], "kind", "precision", "model": the design model
    in words, "check": the compile command that passed, or why none ran}``.
    """
    from .._firmware import export as _export

    given = _checked_arguments(params, point, precision, name)
    if out is not None:
        try:
            out = _export.check_targets(out, (f"{name}.h", f"{name}.c"))
        except ValueError as e:
            raise ConfigError(f"--out: {e} (nothing written)") from None
        writable(out, "--out", folder=True)  # a probe: what permission bits do not tell (root, read-only mounts)
    cfg = _export_config(config_of(config), params, point, given)
    problem = problems.build(cfg)
    loop = _checked_loop(problem, params) if given else problem.controller()
    design = problems.design_model(cfg)
    if design.source == "arm":
        model = "the model derived from the configured [arm] along the reference"
    elif all(cfg.model.as_dict()[k] == problems.defaults()["model"][k] for k in ("A_rows", "B_rows")):
        model = _export.PAPER_MODEL
    else:
        model = "the config's nominal model ([model] A_rows, B_rows)"
    try:
        files = _export.export_c(loop, problem.reference, precision=precision, name=name,
                                 source=_origin(config, params, point, given, design), model=model)  # fmt: skip
    except ValueError as e:
        raise ConfigError(str(e)) from None
    paths, checked = _written(files, out, check, log) if out is not None else ([], "not written")
    return {"files": files, "paths": paths, "kind": cfg.controller.kind, "precision": precision,
            "model": model, "check": checked}  # fmt: skip


def _checked_arguments(params, point, precision, name) -> bool:
    """``precision``, ``name``, ``point`` and ``params`` checked (one-line errors naming the
    option); whether ``params`` are given as parameters (a dict), not as a file."""
    from .._firmware import export as _export

    if not isinstance(precision, str) or precision not in _export.PRECISIONS:
        raise ConfigError(f"--precision: expected one of {', '.join(_export.PRECISIONS)}, got {precision!r}")
    if not (isinstance(name, str) and name.isidentifier() and name.isascii()):
        raise ConfigError(f"--name: expected a C identifier (letters, digits, _; not first a digit), got {name!r}")
    if point is not None and (isinstance(point, bool) or not isinstance(point, (int, np.integer))):
        raise ConfigError(f"--point: expected an integer (the index of a front's point), got {point!r}")
    given = isinstance(params, Mapping) or hasattr(params, "_asdict")  # parameters, not a file
    if not (params is None or given or isinstance(params, (str, Path))):
        raise ConfigError(f"--params: expected a fosmc tune result.json or fosmc front front.json (a path), or a "
                          f"dict of the controller kind's parameters by name, got {type(params).__name__}")  # fmt: skip
    if point is not None and (params is None or given):
        raise ConfigError("--point: needs --params FRONT.json" + (" (not a dict of parameters)" if given else ""))
    return given


def _export_config(cfg: problems.Config, params, point, given: bool) -> problems.Config:
    """The config whose controller is exported: a file's tuned ``params`` in it (a front's
    point named), a digital loop required, in float64 (the constants in full precision,
    rounded to the export's precision when written)."""
    from .._io import read_json

    if params is not None and not given:
        if point is None:
            try:
                data = read_json(params)
            except ValueError:
                data = None  # with_params says why
            if isinstance(data, dict) and isinstance(data.get("points"), list):
                raise ConfigError(f"--point: {params} is a front of {len(data['points'])} points: name the one to "
                                  "export with --point I (e.g. the one `fosmc select` names)")  # fmt: skip
        cfg = problems.with_params(cfg, params, point)
    if not cfg.controller.sample_period:
        raise ConfigError("controller.sample_period: fosmc export needs a digital loop (sample_period > 0, the "
                          "drive's period, e.g. 1e-3): the ideal loop reads the exact state at every step and "
                          "integrates the law with the plant, which no drive does")  # fmt: skip
    return problems.replace(cfg, sim={"precision": "float64"})


def _checked_loop(problem, params):
    """The problem's controller at the given ``params``, checked as ``Problem.simulate`` checks
    them: names and shapes (``Problem.controller``), then signs and ranges."""
    from .._simulator.checks import check_inputs
    from .._simulator.rollout import option_names

    try:
        loop = problem.controller(params)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the step-size warning is the simulation's, not the drive's
            args = (problem.plants, loop, problem.reference, problem.X0s, problem.dt)
            check_inputs(*args, True, problem.options, option_names(True))
    except ValueError as e:  # named as the option: params.delta, not controller.law.params.delta
        message = re.sub(r"^controller\.law\.(params\.)?(?=\w+:)", "params.", str(e))
        raise ConfigError(message if message.startswith("params") else f"params: {message}") from None
    return loop


def _origin(config, params, point, given: bool, design) -> str:
    """The files' note of where their numbers come from: the config, the parameters, the design model."""
    origin = ["config: " + (str(config) if isinstance(config, (str, Path)) else "the paper's defaults"
                            if config is None else "a config dict")]  # fmt: skip
    if given:
        names = list(params if isinstance(params, Mapping) else params._asdict())
        origin.append(f"params: a dict of {', '.join(names) or 'none'} (the config's for the rest)")
    elif params is not None:
        origin.append(f"params: {params}" + (f", point {point}" if point is not None else " (final)"))
    origin.append(f"design model: [model] from = '{design.source}'" + (
        f", the midpoint of the rows' box over {design.sampled}" if design.source == "arm" else ""))  # fmt: skip
    return "\n".join(origin)


def _written(files: dict[str, str], out: Path, check: bool, log: Log) -> tuple[list, str]:
    """(the paths of ``files`` written into ``out``, what the compile check said: the command
    that passed, or why none ran or why it failed)."""
    from .._firmware import export as _export

    try:
        paths = _export.write(files, out)
    except (ValueError, OSError) as e:
        raise ConfigError(f"--out: {e}") from None
    checked = "not checked"
    if check:
        if _export.c_compiler() is None:
            checked = "not compiled: no C compiler found ($CC, cc, gcc, clang)"
        else:
            try:
                checked = "compiled cleanly: " + _export.check_compiles(paths[1])
            except RuntimeError as e:
                checked = f"did NOT compile: {e}"
        if checked.startswith("compiled cleanly"):  # otherwise "check" says why (the command line warns)
            log(f"fosmc export: {checked}")
    return paths, checked
