"""``fosmc simulate`` as a function: the config's batch, in chunks where it does not fit, resumable."""

from __future__ import annotations

import functools
import json
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import jax
import numpy as np

from .. import _problems as problems
from .._io import jsonable, stamped, write_text
from .._problems import ConfigError, memory
from .._simulator import sharding
from .._simulator.metrics import METRIC_NAMES, Metrics, batch_summary
from .._simulator.rollout import simulate_batch
from . import chunks
from .distributed import JOIN_TIMEOUT_S, Processes, agreeing, digest, join
from .shared import (
    ConfigInput,
    Log,
    _is_integer,
    _quiet,
    _with_x64,
    config_of,
    writable,
)


@_with_x64
def run_simulate(
    config: ConfigInput = None,
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
    distributed: bool = False,
    coordinator: str | None = None,
    num_processes: int | None = None,
    process_id: int | None = None,
    join_timeout: float = JOIN_TIMEOUT_S,
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
    as many rollouts as fit beside what the whole run holds (:func:`fosmc_jax._problems.memory.plan`;
    ``chunk``: at most that many), with the same results; a ``log`` line after the first chunk
    and then every 10 s says how far it is. One whose draws and outputs cannot fit, chunked or
    not, is refused (:class:`ConfigError` naming the key to lower, with the estimate and the
    limit) before anything is drawn.

    ``checkpoint``: a folder (empty or new) where each finished chunk is written as it ends
    (chunks of at most :data:`fosmc_jax._app.chunks.CHECKPOINT_CHUNK` rollouts then, whatever
    the memory), so that ``resume`` continues a killed run from its last finished chunk, with
    the same results as a run not killed; the folder's ``plan.json`` (config, chunk size,
    devices, versions) must be the run's.

    Across processes (``distributed`` or ``coordinator``, ``num_processes``, ``process_id``,
    ``join_timeout``: as :func:`fosmc_jax._app.front.run_front`'s), the batch is split over every
    process's devices (``devices``: None, all of them) and every process returns the whole
    result; process 0 alone logs. Not with ``checkpoint`` (its chunk files would be written by
    every process).

    (Long for its options and this page on them; the body is the stages below, in order.)
    """
    across = join(Processes(distributed, coordinator, num_processes, process_id, join_timeout))
    log = log if not across or sharding.leads() else _quiet
    with agreeing(across) as agree:
        if across and checkpoint is not None:
            raise ConfigError("--checkpoint: not in a run across processes (each would write the chunks)")
        if across and devices not in (None, jax.device_count()):
            raise ConfigError(f"--devices: a run across processes splits the batch over every process's devices "
                              f"({jax.device_count()}); set each process's count with JAX_NUM_CPU_DEVICES")  # fmt: skip
        cfg = config_of(config)
        options = {"command": "simulate", "config": cfg.as_dict(), "params": params, "point": point,
                   "keep_trace": keep_trace, "records": records, "draws": draws, "chunk": chunk}  # fmt: skip
        agree(digest(options, (params,)))
    checkpoint = _checkpoint_folder(checkpoint, resume)
    devices = (jax.device_count() if across else jax.local_device_count()) if devices is None else devices
    cfg = _run_config(cfg, params, point, keep_trace, chunk, checkpoint)
    size, too_large = memory.plan(cfg, records=records, draws=draws)  # before anything is drawn
    if too_large is not None:
        raise ConfigError(too_large)
    if checkpoint is not None:
        size = _checkpoint_chunk(checkpoint, cfg, devices, size, chunk, resume)
    size = size if chunk is None else min(size, chunk)
    problem = problems.problem_of(cfg)
    arrays, trace = _batch_arrays(cfg, problem, _runner(across, devices), devices, size, checkpoint, log)
    # result.summary() of the arrays, whether or not they came in chunks
    summary = batch_summary(Metrics(*(arrays[name] for name in METRIC_NAMES)), arrays["diverged"])
    arrays.update(_rollout_indices(cfg, problem))
    body = {"rollouts": list(rollout_records(arrays))} if records else {"arrays": arrays}
    out = stamped({**body, "summary": summary, **(_draw_records(cfg) if draws else {}), "config": cfg.as_dict()})
    return dict(out, trace=trace) if keep_trace else out


def _checkpoint_folder(checkpoint: str | Path | None, resume: bool) -> Path | None:
    """``--checkpoint``'s folder, checked: writable, and empty unless the run resumes there."""
    if resume and checkpoint is None:
        raise ConfigError("--resume: needs --checkpoint DIR, the folder of the run's chunks")
    if checkpoint is not None:
        checkpoint = writable(checkpoint, "--checkpoint", folder=True)
        if not resume and checkpoint.exists() and any(checkpoint.iterdir()):
            raise ConfigError(f"--checkpoint: {checkpoint} exists and is not empty (--resume continues the run "
                              "there; or give another folder)")  # fmt: skip
    return checkpoint


def _run_config(cfg: problems.Config, params, point, keep_trace: bool, chunk, checkpoint) -> problems.Config:
    """The config the run simulates: the tuned ``params`` in it, a trace's decimation where
    ``keep_trace`` asks for one; ``chunk`` checked, and refused beside a trace."""
    if params:
        cfg = problems.with_params(cfg, params, point)
    elif point is not None:
        raise ConfigError("--point: needs --params FRONT.json")
    if keep_trace and not cfg.sim.save_every:
        m = problems.sample_steps(cfg)
        cfg = problems.replace(cfg, sim={"save_every": max(1, problems.n_steps(cfg) // 4000 // m) * m})
    if chunk is not None and not (_is_integer(chunk) and chunk >= 1):
        raise ConfigError(f"--chunk: expected a positive integer (rollouts), got {chunk!r}")
    if cfg.sim.save_every and (chunk is not None or checkpoint is not None):
        option = "--checkpoint" if checkpoint is not None else "--chunk"
        raise ConfigError(f"{option}: a batch that keeps a trace ([sim] save_every, or --plot without a [sample] "
                          "table) runs whole, not in chunks")  # fmt: skip
    return cfg


def _runner(across: bool, devices: int):
    """The batch simulation: over every process's devices (each process gets the whole
    batch's results), split over ``devices`` local devices, or unsharded."""
    if across:
        return lambda *args, **kw: sharding.gathered(sharding.simulate_sharded(*args, devices=None, **kw))
    if devices > 1:
        return functools.partial(sharding.simulate_sharded, devices=devices)
    return simulate_batch


def _batch_arrays(cfg, problem, run, devices: int, size: int, checkpoint: Path | None, log: Log):
    """(every rollout's metrics, ``diverged`` and ``diverged_at`` as NumPy arrays, the trace or
    None) of ``problem`` run by ``run``: whole, or in chunks of at most ``size`` rollouts."""
    n_rollouts, paired = problem.rollouts, cfg.sim.pairing == "paired"
    in_chunks = size < n_rollouts or checkpoint is not None
    log(f"fosmc: {n_rollouts} rollout(s) x {problems.n_steps(cfg)} steps ({cfg.sim.integrator}, "
        f"dt = {cfg.sim.dt} s, {cfg.sim.precision}) on {devices} device(s)"
        f"{f' in chunks of at most {size} rollouts' if in_chunks else ''}: compiling and running ...")  # fmt: skip
    start, trace = time.perf_counter(), None
    if in_chunks:
        plants, ctrl, reference, X0s, dt = problem.args
        simulate = lambda plants, X0s, keys: run(plants, ctrl, reference, X0s, dt, keys=keys, **problem.options)
        try:
            arrays = chunks.run(simulate, plants, X0s, problem.keys, paired, size, log, checkpoint=checkpoint)
        except ValueError as e:  # a chunk file that is not this run's
            raise ConfigError(f"--resume: {e}") from None
    else:
        result = jax.block_until_ready(run(*problem.args, keys=problem.keys, **problem.options))
        # one transfer per array: indexing a device array per rollout costs a transfer each
        # (BENCHMARKS.md, "Figures behind the code")
        arrays = {name: np.asarray(getattr(result.metrics, name)) for name in METRIC_NAMES}
        arrays.update(diverged=np.asarray(result.diverged), diverged_at=np.asarray(result.diverged_at))
        trace = result.trace
    log(f"fosmc: done in {time.perf_counter() - start:.2f} s (compilation included)")
    return arrays, trace


def _rollout_indices(cfg: problems.Config, problem) -> dict[str, np.ndarray]:
    """Each rollout's ``plant_index``, ``realization_index``, ``offset_index`` (and
    ``arm_index`` with ``[arm.uncertainty]``), in the batch's order."""
    paired = cfg.sim.pairing == "paired"
    n_real = 1 if problem.keys is None else problem.keys.shape[0]
    per_plant = 1 if paired else problem.X0s.shape[0]  # initial states per plant
    r = np.arange(problem.rollouts)
    indices = dict(plant_index=r // (per_plant * n_real), realization_index=r % n_real,
                   offset_index=r // n_real if paired else r // n_real % per_plant)  # fmt: skip
    if problems.arm_varies(cfg):  # [arm.uncertainty]: which sampled arm each rollout ran (arm-major, then payload)
        payloads = cfg.sample.count if cfg.sample.payloads else len(cfg.plant.payloads)
        indices["arm_index"] = indices["plant_index"] // (1 if paired else payloads)
    return indices


def _draw_records(cfg: problems.Config) -> dict[str, Any]:
    """The config's draws as lists: ``"sampled"`` (a ``[sample]`` table's payloads, offsets)
    and ``"arms"`` (each sampled arm's parameters by ``[arm]`` key), where there are any."""
    drawn, extra = problems.draws(cfg), {}
    if cfg.sample.count:
        extra["sampled"] = {k: v.tolist() for k, v in drawn.items() if k != "arms"}
    if "arms" in drawn:  # each sampled arm's parameters
        n_arms = len(drawn["arms"]["F"])
        extra["arms"] = [{k: v[i].tolist() for k, v in drawn["arms"].items()} for i in range(n_arms)]
    return extra


def _checkpoint_chunk(
    folder: Path, cfg: problems.Config, devices: int, size: int, chunk: int | None, resume: bool
) -> int:
    """The rollouts per chunk of a run with a checkpoint ``folder``: a new run's (at most
    :data:`fosmc_jax._app.chunks.CHECKPOINT_CHUNK`, ``size`` where memory holds fewer, ``chunk``
    where given), recorded in the folder's ``plan.json`` with the config, the devices and the
    versions; a resumed run's, read from it, which must record this run (a :class:`ConfigError`
    naming what differs otherwise: another config's chunks, or another device count's, which
    differ to rounding, would not be this run's results)."""
    plan_path = folder / "plan.json"
    meta = stamped({"config": json.loads(json.dumps(jsonable(cfg.as_dict()))), "devices": devices})
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
