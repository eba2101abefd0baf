"""What each ``fosmc`` command computes, as one Python function per command.

``run_simulate``, ``run_bounds``, ``run_reproduce``, ``run_certify``, ``run_tune`` and
``run_front`` take a config (a TOML path, a user dict, an already resolved config, or
``None`` for the paper's defaults) and the command's options as keyword arguments, and return
the data the command writes: the dict that ``--json`` prints (``simulate``, ``bounds``,
``certify``), that ``result.json`` / ``front.json`` hold (``tune``, ``front``), or the tables
that ``reproduce`` writes. The dicts hold NumPy arrays where the JSON has lists;
``fosmc_jax._io.jsonable`` of a result is exactly the command's JSON. The ``fosmc`` command
line (``fosmc_jax._app.cli``) only parses arguments, prints and maps errors to exit codes.

Naming: ``run_<command>`` says "what ``fosmc <command>`` does" and keeps these config-level
entry points apart from the library functions they call (``simulate``, ``certify`` take
plants, controllers and arrays, not configs). Errors are :class:`ConfigError` with the
command line's one-line message; an option is named as the command line spells it
(``--steps: expected a positive integer, got 0``), so both surfaces say the same thing.

Every function runs with float64 available (``jax.enable_x64`` inside the call, as the
command line enables it globally); the config's ``[sim] precision`` picks the dtype. ``log``
receives the progress lines the command prints on stderr (default: silent). ``tune``,
``front`` and ``reproduce`` write their files only when given ``out``, refusing a non-empty
folder without ``force`` (or ``resume``) as the command does.
"""

from __future__ import annotations

import functools
import json
import math
import numbers
import time
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import jax
import numpy as np

from .._design import paper as _paper
from .._io import check_writable, jsonable, stamped, write_text
from .._simulator.metrics import METRIC_NAMES, UNITS, Metrics, batch_summary
from .._simulator.rollout import simulate_batch
from . import chunks, memory
from . import config as _config
from .config import ConfigError

Config = str | Path | dict | None
Log = Callable[[str], None]

__all__ = ["run_simulate", "run_bounds", "run_reproduce", "run_certify", "run_tune", "run_front", "run_export",
           "run_identify"]  # fmt: skip


def _quiet(_: str) -> None:
    pass


def _with_x64(f):
    @functools.wraps(f)
    def wrapped(*args, **kwargs):
        with jax.enable_x64(True):
            return f(*args, **kwargs)

    return wrapped


def config_of(config: Config) -> dict[str, Any]:
    """The resolved config (:func:`fosmc_jax._app.config.as_config`: a TOML path, a preset's
    name, a user dict, a resolved config, or ``None`` for the paper's defaults)."""
    return _config.as_config(config)


def _fresh_out(out: str | Path, flags: bool, hint: str) -> Path:
    """``out``, a folder that can be made and written (:func:`writable`), empty unless ``flags``
    (``--force``, ``--resume``); else a :class:`ConfigError` naming ``--out``, before any work."""
    out = writable(out, "--out", folder=True)
    if out.exists() and any(out.iterdir()) and not flags:
        raise ConfigError(f"--out: {out} exists and is not empty ({hint})")
    return out


def writable(path: str | Path, option: str, *, folder: bool = False) -> Path:
    """``path`` (:func:`fosmc_jax._io.check_writable`: a file or folder that can be made and
    written there, probed now), or a one-line :class:`ConfigError` naming ``option``."""
    try:
        return check_writable(path, folder=folder)
    except ValueError as e:
        raise ConfigError(f"{option}: {e}") from None


def _is_integer(value: Any) -> bool:
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def _is_real(value: Any) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


#: The largest ``fosmc front --seed``: its CMA-ES runs seed NumPy's legacy generator with
#: ``seed * 1_000_003 + 700_000 + run`` (``fosmc_jax._search.front``), which must stay below 2^32.
MAX_FRONT_SEED = (2**32 - 1 - 700_000 - 1_000) // 1_000_003


# ---------------------------------------------------------------------------- simulate


@_with_x64
def run_simulate(
    config: Config = None,
    *,
    params: str | Path | None = None,
    point: int | None = None,
    devices: int | None = None,
    keep_trace: bool = False,
    records: bool = True,
    draws: bool = True,
    chunk: int | None = None,
    checkpoint: str | Path | None = None,
    resume: bool = False,
    log: Log = _quiet,
) -> dict[str, Any]:
    """``fosmc simulate``: every plant x initial offset (x noise realization) of the config.

    ``params``: a ``fosmc tune`` result.json or ``fosmc front`` front.json whose parameters
    replace the config's (``point``: the front's point): the FOSMC's delta, gamma, poles, or
    SMC's k, phi (``smc_k``, ``smc_phi``) or super-twisting's k1, k2 (``st_k1``, ``st_k2``),
    of the config's ``controller.kind`` only. The batch is split over ``devices`` devices
    (``simulate_sharded``; default: every local device, one per core on CPU after
    ``use_all_cores()`` or ``use_host_devices(n)`` before the first JAX operation, as the
    command line does; 1: unsharded).
    ``keep_trace`` stores a decimated trace (``[sim] save_every``, or about 4,000 samples when
    it is 0) and adds it as ``"trace"`` (a :class:`Trace` with a batch axis).

    Returns ``{"fosmc_jax": {"version", "metrics_version"}, "rollouts": [{"plant_index",
    "offset_index", "realization_index", "metrics": {name: (3,)}, "diverged", "diverged_at"},
    ...], "summary": batch_summary, "config": resolved config}``: what ``--json`` prints; with
    a ``[sample]`` table also ``"sampled"``: its draws (``payloads``, ``offsets``), indexed by
    ``plant_index`` and ``offset_index``; with ``[arm.uncertainty]`` each rollout's
    ``arm_index`` and ``"arms"``: each sampled arm's parameters by ``[arm]`` key. With
    ``records=False``, ``"arrays"`` instead of ``"rollouts"``: the same fields as NumPy arrays
    over the rollouts (what ``--npz`` writes, with the versions, and ``--json`` prints as
    records; no Python object per rollout). With ``draws=False``, no ``"sampled"`` or
    ``"arms"`` (the draws as lists, which the command line prints only with ``--json``: 3 KB per
    sampled arm).

    A batch larger than memory holds at once runs in chunks of one shape (the last padded), of
    as many rollouts as fit beside what the whole run holds (:func:`fosmc_jax._app.memory.plan`;
    ``chunk``: at most that many), with the same results; a ``log`` line after the first chunk
    and then every 10 s says how far it is. One whose draws and outputs cannot fit, chunked or
    not, is refused (:class:`ConfigError` naming the key to lower, with the estimate and the
    limit) before anything is drawn.

    ``checkpoint``: a folder (empty or new) where each finished chunk is written as it ends
    (chunks of at most :data:`fosmc_jax._app.chunks.CHECKPOINT_CHUNK` rollouts then, whatever
    the memory), so that ``resume`` continues a killed run from its last finished chunk, with
    the same results as a run not killed; the folder's ``plan.json`` (config, chunk size,
    devices, versions) must be the run's.
    """
    if resume and checkpoint is None:
        raise ConfigError("--resume: needs --checkpoint DIR, the folder of the run's chunks")
    if checkpoint is not None:
        checkpoint = writable(checkpoint, "--checkpoint", folder=True)
        if not resume and checkpoint.exists() and any(checkpoint.iterdir()):
            raise ConfigError(f"--checkpoint: {checkpoint} exists and is not empty (--resume continues the run "
                              "there; or give another folder)")  # fmt: skip
    cfg = config_of(config)
    devices = jax.local_device_count() if devices is None else devices
    if params:
        cfg = _config.with_params(cfg, params, point)
    elif point is not None:
        raise ConfigError("--point: needs --params FRONT.json")
    n = _config.n_steps(cfg)
    if keep_trace and not cfg["sim"]["save_every"]:
        m = _config.sample_steps(cfg)
        cfg["sim"]["save_every"] = max(1, n // 4000 // m) * m
    if chunk is not None and not (_is_integer(chunk) and chunk >= 1):
        raise ConfigError(f"--chunk: expected a positive integer (rollouts), got {chunk!r}")
    if cfg["sim"]["save_every"] and (chunk is not None or checkpoint is not None):
        option = "--checkpoint" if checkpoint is not None else "--chunk"
        raise ConfigError(f"{option}: a batch that keeps a trace ([sim] save_every, or --plot without a [sample] "
                          "table) runs whole, not in chunks")  # fmt: skip
    size, too_large = memory.plan(cfg, records=records, draws=draws)  # before anything is drawn
    if too_large is not None:
        raise ConfigError(too_large)
    if checkpoint is not None:
        size = _checkpoint_chunk(checkpoint, cfg, devices, size, chunk, resume)
    size = size if chunk is None else min(size, chunk)
    problem = _config.problem_of(cfg)
    n_rollouts, n_real = problem.rollouts, 1 if problem.keys is None else problem.keys.shape[0]
    paired = cfg["sim"]["pairing"] == "paired"
    per_plant = 1 if paired else problem.X0s.shape[0]  # initial states per plant
    in_chunks = size < n_rollouts or checkpoint is not None
    log(f"fosmc: {n_rollouts} rollout(s) x {n} steps ({cfg['sim']['integrator']}, "
        f"dt = {cfg['sim']['dt']} s, {cfg['sim']['precision']}) on {devices} device(s)"
        f"{f' in chunks of at most {size} rollouts' if in_chunks else ''}: compiling and running ...")  # fmt: skip
    start = time.perf_counter()
    if devices > 1:
        from .._simulator.sharding import simulate_sharded

        run = functools.partial(simulate_sharded, devices=devices)
    else:
        run = simulate_batch
    if in_chunks:
        plants, ctrl, reference, X0s, dt = problem.args
        simulate = lambda plants, X0s, keys: run(plants, ctrl, reference, X0s, dt, keys=keys, **problem.options)
        try:
            arrays = chunks.run(simulate, plants, X0s, problem.keys, paired, size, log, checkpoint=checkpoint)
        except ValueError as e:  # a chunk file that is not this run's
            raise ConfigError(f"--resume: {e}") from None
    else:
        result = jax.block_until_ready(run(*problem.args, keys=problem.keys, **problem.options))
        # one transfer per array (indexing a device array per rollout cost 27 of 45 s at 16,384
        # rollouts: BENCHMARKS.md)
        arrays = {name: np.asarray(getattr(result.metrics, name)) for name in METRIC_NAMES}
        arrays.update(diverged=np.asarray(result.diverged), diverged_at=np.asarray(result.diverged_at))
    log(f"fosmc: done in {time.perf_counter() - start:.2f} s (compilation included)")
    # result.summary() of the arrays, whether or not they came in chunks
    summary = batch_summary(Metrics(*(arrays[name] for name in METRIC_NAMES)), arrays["diverged"])

    r = np.arange(n_rollouts)
    arrays.update(plant_index=r // (per_plant * n_real), realization_index=r % n_real,
                  offset_index=r // n_real if paired else r // n_real % per_plant)  # fmt: skip
    if _config.arm_varies(cfg):  # [arm.uncertainty]: which sampled arm each rollout ran (arm-major, then payload)
        payloads = cfg["sample"]["count"] if cfg["sample"]["payloads"] else len(cfg["plant"]["payloads"])
        arrays["arm_index"] = arrays["plant_index"] // (1 if paired else payloads)
    drawn, extra = _config.draws(cfg) if draws else {}, {}
    if cfg["sample"]["count"] and draws:
        extra["sampled"] = {k: v.tolist() for k, v in drawn.items() if k != "arms"}
    if "arms" in drawn:  # each sampled arm's parameters
        n_arms = len(drawn["arms"]["F"])
        extra["arms"] = [{k: v[i].tolist() for k, v in drawn["arms"].items()} for i in range(n_arms)]
    body = {"rollouts": list(rollout_records(arrays))} if records else {"arrays": arrays}
    out = stamped({**body, "summary": summary, **extra, "config": cfg})
    return dict(out, trace=result.trace) if keep_trace else out


def _checkpoint_chunk(folder: Path, cfg: dict, devices: int, size: int, chunk: int | None, resume: bool) -> int:
    """The rollouts per chunk of a run with a checkpoint ``folder``: a new run's (at most
    :data:`fosmc_jax._app.chunks.CHECKPOINT_CHUNK`, ``size`` where memory holds fewer, ``chunk``
    where given), recorded in the folder's ``plan.json`` with the config, the devices and the
    versions; a resumed run's, read from it, which must record this run (a :class:`ConfigError`
    naming what differs otherwise: another config's chunks, or another device count's, which
    differ to rounding, would not be this run's results)."""
    plan_path = folder / "plan.json"
    meta = stamped({"config": json.loads(json.dumps(jsonable(cfg))), "devices": devices})
    if not (resume and plan_path.exists()):
        chunk = min(size, chunks.CHECKPOINT_CHUNK, chunk or size)
        write_text(plan_path, json.dumps(jsonable({**meta, "chunk": chunk}), indent=1))
        return chunk
    try:
        kept = json.loads(plan_path.read_text())
    except (OSError, ValueError) as e:
        raise ConfigError(f"--resume: cannot read {plan_path}: {e}") from None
    differs = {
        "config": "of another config's run: give its config",
        "devices": f"run on {kept.get('devices')} device(s) (results that differ from {devices}'s to rounding): "
        f"give --devices {kept.get('devices')}",
        "fosmc_jax": f"run by fosmc_jax {kept.get('fosmc_jax')}: resume with that version",
    }
    for key, what in differs.items():
        if kept.get(key) != meta[key]:
            raise ConfigError(f"--resume: {folder} holds chunks {what}, or give another folder")
    if chunk is not None and chunk != kept["chunk"]:
        raise ConfigError(f"--chunk: {folder} holds chunks of {kept['chunk']} rollouts: give that, or leave it out")
    if kept["chunk"] > size:
        raise ConfigError(f"--resume: {folder} holds chunks of {kept['chunk']} rollouts, more than the {size} this "
                          "process may hold at once now")  # fmt: skip
    return kept["chunk"]


def rollout_records(arrays: dict) -> Iterator[dict[str, Any]]:
    """``run_simulate``'s records, one per rollout, from its ``arrays`` (NumPy arrays, or their
    ``tolist()``, as ``--json`` passes them to json's encoder): indices (``arm_index`` too with
    sampled arms), ``metrics`` rows, ``diverged`` and ``diverged_at``."""
    arms = "arm_index" in arrays
    for i in range(len(arrays["diverged"])):
        yield {
            **({"arm_index": int(arrays["arm_index"][i])} if arms else {}),
            "plant_index": int(arrays["plant_index"][i]),
            "offset_index": int(arrays["offset_index"][i]),
            "realization_index": int(arrays["realization_index"][i]),
            "metrics": {name: arrays[name][i] for name in METRIC_NAMES},
            "diverged": bool(arrays["diverged"][i]),
            "diverged_at": float(arrays["diverged_at"][i]),
        }


# ---------------------------------------------------------------------------- bounds


@_with_x64
def run_bounds(config: Config = None, *, log: Log = _quiet) -> dict[str, Any]:
    """``fosmc bounds``: for the config's design model (``[model] from``, ``config.design_model``:
    the paper's rows and ``[plant.box]``, or the rows derived from ``[arm]``), alpha, beta (31)
    by exact vertex enumeration of its box, K placing the poles (16) (the K the simulated
    controller uses), eig(A + BK), CB, and the gamma lower bounds (24)-(26) in both
    conventions, beside the paper's printed numbers.

    Returns ``{"model": "paper" | "arm", "model_detail": where its rows come from, "alpha",
    "beta", "vertices_checked": {"A", "B"}, "K": (3, 9), "closed_loop_poles": [[re, im]] x 9,
    "CB": (3, 3), "gamma_min": {convention: (3,)}, "gamma", "paper_printed": {"alpha", "beta",
    "gamma_min"}}``; for ``kind = "arm"`` also ``"models"``: ``{"paper": ..., "arm": ...}``, the
    same quantities (alpha to gamma_min) for both models whichever is in use, ``"box"`` and
    ``"nominal_A_rows"``, ``"nominal_B_rows"``: the arm's box and nominal rows, and
    ``"arm_model"``: where they come from.
    """
    cfg = config_of(config)
    used = cfg["model"]["from"]
    sources = ("paper", "arm") if cfg["plant"]["kind"] == "arm" else (used,)
    designs, summaries = {}, {}
    for source in sources:
        designs[source] = _config.design_model(cfg, source)
        log(f"fosmc bounds: the {source} model ({designs[source].sampled}): alpha, beta by vertex enumeration ...")
        summaries[source] = _config.design_summary(cfg, source)

    def quantities(d) -> dict[str, Any]:
        return {
            "alpha": d.alpha.value,
            "beta": d.beta.value,
            "vertices_checked": {"A": d.alpha.vertices_checked, "B": d.beta.vertices_checked},
            "K": d.K,
            "closed_loop_poles": [[z.real, z.imag] for z in d.closed_loop_poles],
            "CB": d.CB,
            "gamma_min": d.gamma_min,
        }

    out = {
        "model": used,
        "model_detail": designs[used].sampled,
        **quantities(summaries[used]),
        "gamma": cfg["controller"]["gamma"],
        "paper_printed": {
            "alpha": _paper.ALPHA_PRINTED,
            "beta": _paper.BETA_PRINTED,
            "gamma_min": _paper.GAMMA_MIN_PRINTED,
        },
    }
    if "arm" in designs:
        arm = designs["arm"]
        out["models"] = {source: quantities(d) for source, d in summaries.items()}
        out["box"] = dict(zip(_config.BOX_KEYS, arm.box))
        out["nominal_A_rows"], out["nominal_B_rows"] = arm.A_rows, arm.B_rows
        out["arm_model"] = arm.sampled
    return out


# ---------------------------------------------------------------------------- reproduce


@_with_x64
def run_reproduce(
    out: str | Path | None = None,
    *,
    plant: str = "arm",
    t_final: float = 4.0,
    dt: float = 1e-4,
    integrator: str = "rk4",
    force: bool = False,
    report: str | Path | None = None,
    log: Log = _quiet,
) -> dict[str, Any]:
    """``fosmc reproduce``: the paper's cases (Table 1's sets and SGN, nominal and box
    vertices or the arm at 0 and 10 kg) at ``t_final``, ``dt``, ``integrator``; the shortened
    check table; for ``plant = "arm"`` the realistic loop beside the ideal one and the
    trade-off sweeps. It takes no config: the cases are the paper's.

    ``out``: folder for the tables and figures (None: nothing written, no figures).
    ``report``: a Markdown file whose generated blocks are refreshed.
    Returns ``{"files": {file name: text}, "figures": [file names], "rows": {"metrics",
    "metrics_short"[, "realistic"]: metric rows}}``; ``files`` holds ``metrics.csv``,
    ``metrics.md``, ``design.md``, ``metrics_short.csv`` (and ``realistic.md``,
    ``tradeoff.md`` for the arm), exactly as written to ``out``.
    """
    from . import reproduce as reproduction

    if plant not in ("arm", "linear"):
        raise ConfigError(f"--plant: expected 'arm' or 'linear', got {plant!r}")
    if integrator not in ("euler", "rk4"):
        raise ConfigError(f"--integrator: expected 'euler' or 'rk4', got {integrator!r}")
    _config.check_horizon(t_final, dt, ("--t-final", "--dt"))  # as the config's [sim] t_final and dt
    if plant == "arm":  # the realistic loop's horizon too (its period, its delay), before any case runs
        try:
            _config.resolve(reproduction.realistic_config(t_final))
        except ConfigError as e:
            raise ConfigError(f"--t-final: too short for the realistic loop ({e})") from None
    if report:
        report = writable(report, "--report")
        try:
            report.read_text()
        except (OSError, ValueError) as e:
            raise ConfigError(f"--report: cannot read {report}: {getattr(e, 'strerror', None) or e}") from None
    if out is not None:
        out = _fresh_out(out, force, "use --force to overwrite")
        out.mkdir(parents=True, exist_ok=True)
    settings = reproduction.Settings(t_final=t_final, dt=dt, integrator=integrator)
    log(f"fosmc reproduce: {plant} plant, {settings.integrator}, dt = {settings.dt} s, "
        f"{settings.t_final} s; compiling and running the cases ...")  # fmt: skip
    log(
        f"fosmc reproduce: the shortened check table ({reproduction.SHORT.t_final} s)"
        f"{', the realistic loop and the trade-off sweeps' if plant == 'arm' else ''}, beside ..."
    )
    # every group at once, a thread per core: their time is mostly compilation, one core each
    jobs = [
        lambda: reproduction.run_cases(plant, settings, log=log),
        lambda: reproduction.run_cases(plant, reproduction.SHORT, log=log),
    ]
    if plant == "arm":
        jobs += [
            lambda: reproduction.run_realistic_cases(t_final, log=log),
            lambda: reproduction.tradeoff_sweeps(t_final, log=log),
        ]
    cases, short_cases, *arm_only = reproduction.parallel(*jobs)
    rows, short = reproduction.metric_rows(cases), reproduction.metric_rows(short_cases)
    files = {"metrics.csv": reproduction.to_csv(rows), "metrics.md": reproduction.to_markdown(rows),
             "design.md": reproduction.design_facts(), "metrics_short.csv": reproduction.to_csv(short)}  # fmt: skip
    tables = {"metrics": rows, "metrics_short": short}
    figures: list[str] = []
    if out is not None:
        for name, text in files.items():
            write_text(out / name, text)
        log("fosmc reproduce: drawing figures ...")
        figures = reproduction.write_figures(cases, out, plant)
    if plant == "arm":
        realistic, sweeps = arm_only
        tables["realistic"] = reproduction.metric_rows(realistic, reproduction.METRIC_NAMES)
        files.update({"realistic.md": reproduction.to_markdown(tables["realistic"], reproduction.METRIC_NAMES),
                      "tradeoff.md": reproduction.sweep_markdown(sweeps)})  # fmt: skip
        if out is not None:
            for name in ("realistic.md", "tradeoff.md"):
                write_text(out / name, files[name])
            figures += reproduction.write_realistic_figures(cases + realistic, sweeps, out)
    if report:
        text = report.read_text()
        text = reproduction.replace_block(text, "metrics", files["metrics.md"])
        text = reproduction.replace_block(text, "design", files["design.md"])
        for name in ("realistic", "tradeoff"):
            if f"{name}.md" in files:
                text = reproduction.replace_block(text, name, files[f"{name}.md"])
        write_text(report, text)
        log(f"fosmc reproduce: updated {report}")
    return {"files": files, "figures": figures, "rows": tables}


# ---------------------------------------------------------------------------- certify


@_with_x64
def run_certify(
    config: Config = None,
    *,
    vertices: int | str = "all",
    configured_switching: bool = False,
    seed: int = 0,
    log: Log = _quiet,
) -> dict[str, Any]:
    """``fosmc certify``: the hitting condition (20), s^T ds/dt < 0, checked numerically
    along the reference over sampled errors and sliding directions, over the whole box
    (``vertices = "all"``, exact) or ``vertices`` sampled vertices, or over the payload range
    for the arm; and the verdicts on the gamma bounds (24)-(26) of each convention.

    SGN switching unless ``configured_switching`` (then ``controller.switching``).
    Returns ``fosmc_jax._app.certify.report``'s dict (``max_hitting``, ``holds``,
    ``points_checked``, ``evaluations``, ``where``, ``vertices``, ``plant``, ``envelope``,
    ``gamma_bounds``): what ``--json`` prints.
    """
    from . import certify as _certify

    if not (_is_integer(seed) and seed >= 0):
        raise ConfigError(f"--seed: expected a non-negative integer, got {seed}")
    cfg = config_of(config)
    switching = cfg["controller"]["switching"] if configured_switching else "sign"
    opts = {"switching": switching, "seed": seed}
    if vertices != "all":
        count = vertices if isinstance(vertices, int) and not isinstance(vertices, bool) else None
        if isinstance(vertices, str) and vertices.isdigit():
            count = int(vertices)
        if count is None or count < 1:
            raise ConfigError(f"--vertices: expected 'all' or a positive integer, got {vertices!r}")
        opts["vertices"] = count
    log(f"fosmc certify: {cfg['plant']['kind']} plant, {switching} switching ...")
    start = time.perf_counter()
    r = _certify.report(cfg, **opts)
    log(f"fosmc certify: done in {time.perf_counter() - start:.1f} s")
    return r


# ---------------------------------------------------------------------------- tune


def one_plant(cfg: dict) -> str | None:
    """What the one plant of a resolved config's batch is, or None where the batch holds several.

    One plant: ``plant.kind = "linear"`` with ``plant.uncertainty = "none"`` (the nominal model,
    the default config's) or ``"fixed"`` (the model plus ``plant.dA_rows``, ``plant.dB_rows``),
    or ``"sample"`` / ``"vertices"`` with ``plant.samples = 1`` or a box of zero width;
    ``plant.kind = "arm"`` with one distinct payload (drawn by ``[sample]`` or listed) and no
    sampled arms (``[arm.uncertainty]``). Initial offsets (``sim.initial_offset``)
    and noise realizations (``sensors.realizations``) vary the start and the measurements, not
    the plant, so they do not count."""
    plant = cfg["plant"]
    if plant["kind"] == "arm":
        payloads = sorted(set(plant["payloads"]))
        varied = (cfg["sample"]["count"] > 1 and cfg["sample"]["payloads"]) or _config.arm_varies(cfg)
        return f"the arm with a {payloads[0]:g} kg payload" if len(payloads) == 1 and not varied else None
    if plant["uncertainty"] == "none":
        return "the nominal linear model"
    if plant["uncertainty"] == "fixed":
        return "the linear model plus plant.dA_rows, plant.dB_rows"
    box = plant["box"]
    flat = all(np.array_equal(box[f"{m}_lower"], box[f"{m}_upper"]) for m in ("A", "B"))
    return "one plant of the box" if plant["samples"] == 1 or flat else None


def metric_label(name: str) -> str:
    """A metric's name with its unit, and what it is where its name does not say it."""
    return f"{name} ({UNITS[name]}{', total variation' if name == 'chattering' else ''})"


def _warn_one_plant(cfg: dict, command: str) -> None:
    """``tune`` and ``front`` on a batch of :func:`one_plant`: a UserWarning that what they find
    holds for that plant only, and which keys add plant uncertainty."""
    what = one_plant(cfg)
    if what is not None:
        warnings.warn(
            f"{command}: the config's batch holds one plant ({what}) and no plant uncertainty: what {command} "
            "finds is optimal for that plant only. For an uncertain plant set [plant] uncertainty = 'sample' or "
            "'vertices' with samples > 1 (plants from [plant.box]) for kind = 'linear', or several [plant] "
            "payloads for kind = 'arm' (as tuning/configs/realistic_arm.toml does)",
            UserWarning,
            stacklevel=4,  # the caller of run_tune / run_front (through _with_x64)
        )


@_with_x64
def run_tune(
    config: Config = None,
    *,
    steps: int | None = None,
    out: str | Path | None = None,
    resume: bool = False,
    force: bool = False,
    budget: float | None = None,
    started: float | None = None,
    log: Log = _quiet,
) -> dict[str, Any]:
    """``fosmc tune``: gradient-based tuning (optax) of the ``[tune] params`` of the config's
    ``controller.kind`` (every kind is tunable, each with its own parameters: the FOSMC's
    delta, gamma, poles; SMC's k, phi; super-twisting's k1, k2; default: all of them) on the
    training simulation (``tune.train_dt``, ``tune.train_t_final``), with the objective's
    scales taken at the config's parameters, the optional global stage
    (``tune.global_candidates``) and, for the FOSMC only, gamma floor (24)-(26)
    (``tune.keep_gamma_bound``); initial and final parameters evaluated on the plain
    ``[sim]`` simulation.

    ``steps`` overrides ``tune.steps``. ``budget``: seconds of wall time from ``started`` (a
    ``time.perf_counter()`` value; the CLI passes its process's start; None: this call's), which
    the global stage (30% of what is left after the start's evaluations) and the gradient steps
    (as many as fit, ``tune.steps`` at most) share, the final and held-out evaluations' time kept
    back (estimated from the first evaluation's). ``out``: folder for ``result.json``, ``tuning.png``
    and ``checkpoint.npz`` (None: nothing written; ``tuning.png`` draws the kind's
    parameters); ``resume`` continues from its checkpoint. Returns what
    ``result.json`` holds: ``{"fosmc_jax": {"version", "metrics_version"}, "initial":
    {"params", "metrics", ...}, "start": {"params", "global_candidates"}, "final": {...},
    "held_out": {"metrics", ...}, "held_out_batch", "objective", "history", "config"}``
    (``held_out``: the final parameters on :func:`fosmc_jax._app.study.held_out_config`'s
    batch, fresh payloads, sampled arms and draws, as ``fosmc front`` evaluates its points),
    ``params`` by the kind's names (e.g. ``{"k": [...], "phi": [...]}``). On a batch of one
    plant (:func:`one_plant`: the default config's nominal model) it warns (``UserWarning``)
    that the optimum holds for that plant only. Its ``log`` lines start with ``tune:``; its
    step lines name the objective's metrics.
    """
    from .._search import tune as tuner
    from . import study

    started = time.perf_counter() if started is None else started
    if resume and force:
        raise ConfigError("--resume: continues the run in --out, --force starts it afresh: give one of them")
    if budget is not None and not (_is_real(budget) and math.isfinite(budget) and budget > 0):
        raise ConfigError(f"--budget: expected a positive, finite number of seconds, got {budget}")
    cfg = config_of(config)
    tcfg = cfg["tune"]
    if steps is not None:
        if steps < 1:
            raise ConfigError(f"--steps: expected a positive integer, got {steps}")
        tcfg["steps"] = steps
    kind = cfg["controller"]["kind"]
    names = tuner.SPACES[kind].names
    if not set(tcfg["params"]) <= set(names):
        raise ConfigError(f"tune.params: expected names drawn from {', '.join(names)} (the parameters of "
                          f"controller.kind = '{kind}'), got {tcfg['params']}")  # fmt: skip
    if tcfg["keep_gamma_bound"] and kind != "fosmc":
        raise ConfigError(f"tune.keep_gamma_bound: applies to controller.kind = 'fosmc' only (the gamma bounds "
                          f"(24)-(26)), got kind = '{kind}'")  # fmt: skip
    if out is not None:
        out = _fresh_out(out, force or resume, "use --resume or --force")
        if resume and (done := study.finished(out, "result.json", cfg, "tune", log)) is not None:
            return done
        if not resume:
            study.start_afresh(out, "result.json", "checkpoint.npz")
    _warn_one_plant(cfg, "tune")
    plain, problem, p0 = _config.tuning_problems(cfg)
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
    floor = None
    if tcfg["keep_gamma_bound"]:  # alpha, beta of the design model the controller is built on
        d = _config.design_summary(cfg)
        floor = tuner.GammaFloor(d.alpha.value, d.beta.value, tcfg["gamma_bound_convention"])
    log(f"tune: {problem.rollouts} rollouts x {problem.options['n_steps']} steps (dt = {float(problem.dt)} s) "
        f"per training evaluation; free parameters: {', '.join(tcfg['params'])}")  # fmt: skip
    m = tuner.evaluate(problem, p0)["metrics"]  # the objective's scales, on the training simulation
    t0 = time.perf_counter()
    initial = tuner.evaluate(plain, p0)
    # kept back for the final evaluation (compiled) and the held-out one (a program like this one)
    deadline = None if budget is None else started + budget - 1.5 * (time.perf_counter() - t0) - 2.0
    obj = tuner.objective_of(tcfg, m)
    log(f"tune: objective {obj.form} ({obj.scale} scale) of {metric_label(obj.error_metric)} and "
        f"{metric_label(obj.chattering_metric)}, each relative to its value at the config's parameters on the training "
        f"simulation ({obj.error_ref:.4e} {UNITS[obj.error_metric]}, {obj.chattering_ref:.4e} "
        f"{UNITS[obj.chattering_metric]}): the terms below are unit-free")  # fmt: skip
    start_params = p0
    checkpoint = None if out is None else out / "checkpoint.npz"
    resuming = resume and checkpoint is not None and checkpoint.exists()
    kept = tuner.checkpoint_extra(checkpoint) if resuming else None  # the first run's start, found by its global stage
    if kept and "start" in kept:
        start_params = type(p0)(*(jax.numpy.asarray(kept["start"][k], x.dtype) for k, x in zip(p0._fields, p0)))
    if tcfg["global_candidates"] and floor is None and not resuming:
        from .._search.front import global_stage

        share = None if deadline is None else time.perf_counter() + 0.3 * max(0.0, deadline - time.perf_counter())
        start_params, score = global_stage(problem, obj, p0, tcfg["global_candidates"], free=tuple(tcfg["params"]),
                                           log=log, command="tune", deadline=share)  # fmt: skip
        which = "the best candidate" if share else f"the best of {tcfg['global_candidates']} candidates"
        log(f"tune: global stage: {which} scores {score:.4f} (the config's parameters score about 0 with the log "
            "scale)")  # fmt: skip
    try:
        u0 = tuner.to_internal(start_params, plain.base, floor)
    except ValueError as e:
        raise ConfigError(str(e)) from None
    lr = tuner.learning_rate(tcfg["learning_rate"], problem)
    settings = tuner.Settings(tcfg["steps"], lr, tcfg["schedule"], tcfg["clip"], tcfg["mode"],
                              tuple(tcfg["params"]), tcfg["checkpoint_every"], tcfg["optimizer"])  # fmt: skip
    start = time.perf_counter()
    terms = (f"{obj.error_metric} term", f"{obj.chattering_metric} term")
    found = {k: np.asarray(v).tolist() for k, v in zip(p0._fields, start_params)}
    keep = None if start_params is p0 else {"start": found}  # a resumed run's start: its global stage's best
    if deadline is not None and time.perf_counter() > deadline:
        log(f"tune: --budget {budget:g} s: passed before the gradient steps (compilation included); one step runs")
    u, history = tuner.run(tuner.make_loss(problem, obj, floor), u0, settings, checkpoint=checkpoint, resume=resume,
                           terms=terms, extra=keep, deadline=deadline, log=log)  # fmt: skip
    final_params = tuner.to_physical(u, plain.base, floor)
    final = tuner.evaluate(plain, final_params)
    # the final parameters on what training did not see (fresh payloads, sampled arms, draws)
    held = study.held_out_config(cfg)
    held_out = tuner.evaluate(_config.tuning_problems(held)[0], final_params)
    log(f"tune: held out ({held_out['rollouts']} rollouts, {held_out['diverged']} diverged): "
        f"{obj.error_metric} {np.mean(held_out['metrics'][obj.error_metric]):.4g}, "
        f"{obj.chattering_metric} {np.mean(held_out['metrics'][obj.chattering_metric]):.4g}")  # fmt: skip
    as_dict = lambda p: {k: np.asarray(v).tolist() for k, v in p._asdict().items()}
    result = stamped({
        "initial": {"params": as_dict(p0), **initial},
        "start": {
            "params": as_dict(start_params),
            "global_candidates": 0 if start_params is p0 else tcfg["global_candidates"],
        },  # fmt: skip
        "final": {"params": as_dict(final_params), **final},
        "held_out": held_out,
        "held_out_batch": study.held_out_batch(held),
        "objective": obj._asdict(),
        "history": {k: v for k, v in history.items() if k != "params"},
        "config": cfg,
    })  # fmt: skip
    if out is not None:
        from .plots import plot_tuning

        write_text(out / "result.json", json.dumps(jsonable(result), indent=1))
        params_history = [as_dict(tuner.to_physical(type(p0)(*map(jax.numpy.asarray, p)), plain.base, floor))
                          for p in history["params"]]  # fmt: skip
        plot_tuning(history, params_history, out / "tuning.png")
        log(f"tune: wrote {out}/result.json and {out}/tuning.png in {time.perf_counter() - start:.1f} s")
    return result


# ---------------------------------------------------------------------------- front


@_with_x64
def run_front(
    config: Config = None,
    *,
    out: str | Path | None = None,
    points: int | None = None,
    budget: float = 300.0,
    candidates: int | None = None,
    steps: int | None = None,
    seed: int = 0,
    compare: tuple[str | Path, ...] | list[str | Path] = (),
    force: bool = False,
    resume: bool = False,
    replay: str | Path | None = None,
    started: float | None = None,
    log: Log = _quiet,
) -> dict[str, Any]:
    """``fosmc front``: the Pareto front of mean ``rms_error`` against mean
    ``chattering_hf`` over the config's batch within ``budget`` seconds of wall time, over the
    parameters of the config's ``controller.kind`` (every kind is tunable: the FOSMC's delta,
    gamma, poles; SMC's k, phi; super-twisting's k1, k2; per-joint log scale factors in the
    kind's box, ``fosmc_jax._search.tune.SPACES``), by ``fosmc_jax._app.study.study``: ``points``
    parents per local round, default 8; ``candidates``, ``steps``: the global stage's size and
    the local rounds, default from the budget; ``seed``: of the search's draws. ``out``: folder for ``front.json``,
    ``front.png`` (with the ``compare`` files' points drawn beside) and the checkpoint (None:
    nothing written); ``resume`` continues from its checkpoint. The budget counts from
    ``started`` (a ``time.perf_counter()`` value; the CLI passes its process's start; None:
    this call). ``replay``: a front.json whose recorded work (``stages.replay``) is redone with
    its config, seed and sizes, without a clock: bit for bit the same front on the same machine
    and device count (``config``, ``points``, ``candidates``, ``steps`` not given).

    Returns what ``front.json`` holds: ``{"fosmc_jax": {"version", "metrics_version"},
    "axes", "points": [{params, metrics, held_out, diverged}], "stages", "references",
    "held_out_batch", "config"}``, ``params`` by the kind's names, ``references`` the paper's
    FOSMC (Table 1's sets, SGN) whatever the kind. With ``candidates`` and ``steps`` given the
    result is deterministic except ``stages.wall_time_s``. On a batch of one plant
    (:func:`one_plant`) it warns as ``run_tune`` does. Its ``log`` lines start with ``front:``.
    """
    from .._search import front as search_front
    from . import study

    if resume and force:
        raise ConfigError("--resume: continues the run in --out, --force starts it afresh: give one of them")
    if replay is not None:
        given = [n for n, v in (("--config", config), ("--points", points), ("--candidates", candidates),
                                ("--steps", steps)) if v is not None]  # fmt: skip
        if given:
            raise ConfigError(f"--replay: takes the config and sizes from its front.json: leave out {', '.join(given)}")
        cfg, replayed = study.replayed(replay)
    else:
        cfg = config_of(config)
    if out is not None:
        out = _fresh_out(out, force or resume, "use --resume or --force")
    for name, value in (("--points", points), ("--candidates", candidates), ("--steps", steps)):
        if value is not None and not (_is_integer(value) and value >= (1 if name == "--points" else 0)):
            raise ConfigError(f"{name}: expected a {'positive' if name == '--points' else 'non-negative'} "
                              f"integer, got {value}")  # fmt: skip
    if not (_is_real(budget) and math.isfinite(budget) and budget > 0):
        raise ConfigError(f"--budget: expected a positive, finite number of seconds, got {budget}")
    if not (_is_integer(seed) and 0 <= seed <= MAX_FRONT_SEED):
        raise ConfigError(f"--seed: expected an integer in [0, {MAX_FRONT_SEED}], got {seed}")
    for path in compare:
        try:
            json.loads(Path(path).read_text())
        except (OSError, ValueError) as e:
            raise ConfigError(f"--compare: cannot read {path}: {e}") from None
    _warn_one_plant(cfg, "front")
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
    settings = search_front.Settings(
        points=points or 8, budget=budget, candidates=candidates or 0, steps=steps or 0, seed=seed
    )
    if replay is not None:
        settings = replayed._replace(budget=budget)
    return study.study(cfg, settings, out=out, resume=resume, compare=tuple(compare), started=started, log=log)


# ---------------------------------------------------------------------------- export


@_with_x64
def run_export(
    config: Config = None,
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
    import re
    from collections.abc import Mapping

    from .._firmware import export as _export
    from .._io import read_json
    from .._simulator.checks import check_inputs

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
    if out is not None:
        try:
            out = _export.check_targets(out, (f"{name}.h", f"{name}.c"))
        except ValueError as e:
            raise ConfigError(f"--out: {e} (nothing written)") from None
        writable(out, "--out", folder=True)  # a probe: what permission bits do not tell (root, read-only mounts)
    cfg = config_of(config)
    if params is not None and not given:
        if point is None:
            try:
                data = read_json(params)
            except ValueError:
                data = None  # with_params says why
            if isinstance(data, dict) and isinstance(data.get("points"), list):
                raise ConfigError(f"--point: {params} is a front of {len(data['points'])} points: name the one to "
                                  "export with --point I (e.g. the one `fosmc select` names)")  # fmt: skip
        cfg = _config.with_params(cfg, params, point)
    if cfg["controller"]["kind"] not in _export.EXPORTED_KINDS:
        raise ConfigError(f"controller.kind: fosmc export writes {', '.join(_export.EXPORTED_KINDS)}, got "
                          f"{cfg['controller']['kind']!r}")  # fmt: skip
    if not cfg["controller"]["sample_period"]:
        raise ConfigError("controller.sample_period: fosmc export needs a digital loop (sample_period > 0, the "
                          "drive's period, e.g. 1e-3): the ideal loop reads the exact state at every step and "
                          "integrates the law with the plant, which no drive does")  # fmt: skip
    cfg["sim"]["precision"] = "float64"  # the constants in full precision; rounded to `precision` when written
    problem = _config.build(cfg)
    loop = problem.controller()
    if given:  # as Problem.simulate takes them: names and shapes (Problem.controller), then signs and ranges
        try:
            loop = problem.controller(params)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # the step-size warning is the simulation's, not the drive's
                check_inputs(problem.plants, loop, problem.reference, problem.X0s, problem.dt, True, problem.options)
        except ValueError as e:  # named as the option: params.delta, not controller.law.params.delta
            message = re.sub(r"^controller\.law\.(params\.)?(?=\w+:)", "params.", str(e))
            raise ConfigError(message if message.startswith("params") else f"params: {message}") from None
    design = _config.design_model(cfg)
    if design.source == "arm":
        model = "the model derived from the configured [arm] along the reference"
    elif all(cfg["model"][k] == _config.defaults()["model"][k] for k in ("A_rows", "B_rows")):
        model = _export.PAPER_MODEL
    else:
        model = "the config's nominal model ([model] A_rows, B_rows)"
    origin = ["config: " + (str(config) if isinstance(config, (str, Path)) else "the paper's defaults"
                            if config is None else "a config dict")]  # fmt: skip
    if given:
        names = list(params if isinstance(params, Mapping) else params._asdict())
        origin.append(f"params: a dict of {', '.join(names) or 'none'} (the config's for the rest)")
    elif params is not None:
        origin.append(f"params: {params}" + (f", point {point}" if point is not None else " (final)"))
    origin.append(f"design model: [model] from = '{design.source}'" + (
        f", the midpoint of the rows' box over {design.sampled}" if design.source == "arm" else ""))  # fmt: skip
    try:
        files = _export.export_c(loop, problem.reference, precision=precision, name=name,
                                 source="\n".join(origin), model=model)  # fmt: skip
    except ValueError as e:
        raise ConfigError(str(e)) from None
    paths, checked = [], "not written"
    if out is not None:
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
    return {"files": files, "paths": paths, "kind": cfg["controller"]["kind"], "precision": precision,
            "model": model, "check": checked}  # fmt: skip


# ---------------------------------------------------------------------------- identify


@_with_x64
def run_identify(
    config: Config = None,
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
        names = [n.strip() for n in params.split(",") if n.strip()]
    elif isinstance(params, (list, tuple)) and all(isinstance(n, str) for n in params):
        names = list(params)
    else:
        raise ConfigError(f"--params: expected names, comma-separated or a list of strings, got {params!r}")
    cfg = config_of(config)
    if payload is None:
        if len(cfg["plant"]["payloads"]) != 1:
            raise ConfigError(f"--payload: the config lists {len(cfg['plant']['payloads'])} payloads "
                              f"({cfg['plant']['payloads']}); give the experiment's (kg)")  # fmt: skip
        payload = cfg["plant"]["payloads"][0]
    if out is not None:
        out = _fresh_out(out, force, "use --force to overwrite")
    counts = np.asarray(cfg["sensors"]["encoder_counts"], float)
    try:
        record = identification.read_log(data)
        period = identification.sample_period(record.t)
        samples = round(window / period)
        if samples < 2:
            raise ValueError(f"--window: expected at least 2 of the log's sample periods ({2 * period:g} s), "
                             f"got {window:g} s")  # fmt: skip
        settings = identification.Settings(
            window=samples,
            delay=cfg["controller"]["delay_samples"] if delay is None else int(delay),
            integrator=cfg["sim"]["integrator"],
            dt=None if dt is None else float(dt),
            threshold=float(threshold),
            iterations=int(iterations),
            bootstrap=int(bootstrap),
            seed=int(seed),
            resolution=tuple(np.where(counts > 0, 2 * np.pi / np.maximum(counts, 1), 0.0)),
        )
        arm = _config.arm_params_of(cfg, np.float64)
        result = identification.identify(arm, float(payload), record, names, settings, progress=log)
    except ValueError as e:
        raise ConfigError(str(e)) from None
    fitted = {k: np.asarray(v).tolist() for k, v in result["params"].items()}
    check = {**cfg, "arm": {**cfg["arm"], **fitted}, "plant": {**cfg["plant"], "kind": "arm",
                                                              "payloads": [result["payload"]]}}  # fmt: skip
    try:
        _config.resolve(check)
        config_check = "ok"
    except ConfigError as e:
        config_check = str(e)
        log(f"identify: warning: the identified arm is not a valid config: {e}")
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
    toml = identification.arm_toml(result, {"payload_range": cfg["arm"]["payload_range"]}, header)
    report = stamped({"data": str(data), "names": names, **result, "toml": toml, "config_check": config_check,
                      "config": cfg})  # fmt: skip
    if out is not None:
        try:
            out.mkdir(parents=True, exist_ok=True)
            write_text(out / "identified.toml", toml)
            write_text(out / "identify.json", json.dumps(jsonable(report), indent=1))
        except OSError as e:
            raise ConfigError(f"--out: cannot write in {out}: {e.strerror or e}") from None
    return report
