"""A batch larger than memory holds at once (issue 34, item 2): ``fosmc simulate`` runs it in
chunks of one shape (``fosmc_jax/_app/chunks.py``) sized from the memory estimate
(:func:`fosmc_jax._problems.memory.plan`), with the unchunked run's results, or refuses in one line,
before anything is drawn, a batch whose draws and outputs cannot fit however it is chunked.

The default tier checks the chunks' order without compiling (a stand-in simulator), the plan
against given limits, one small compiled batch chunked and whole, and the issue's five
oversized batches refused under ``ulimit -v 12000000``; the slow tier runs a batch that the
whole-batch run could not fit under an address-space limit, and compares chunked and whole
runs on every simulator path.
"""

import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace
from typing import NamedTuple

import numpy as np
import pytest

from fosmc_jax import _problems as _config
from fosmc_jax._app import chunks, commands
from fosmc_jax._app import simulate as simulate_command
from fosmc_jax._app.cli import main
from fosmc_jax._problems import memory
from fosmc_jax._simulator.metrics import METRIC_NAMES, Metrics

ROOT = Path(__file__).resolve().parents[1]
ENV = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
SHORT = {"sim": {"t_final": 0.01, "dt": 1e-3}}
#: The issue's five batches that passed validation and died in NumPy or XLA (as tests/test_faults.py has them)
OVERSIZED = {
    "plant.samples": {"plant": {"uncertainty": "sample", "samples": 10**8}},
    "sample.count": {"sample": {"count": 10**8, "offsets": [0.01] + [0.0] * 8}},
    "sensors.realizations": {"controller": {"sample_period": 1e-3}, "sensors": {"realizations": 10**8}},
    "arm.uncertainty.samples": {"plant": {"kind": "arm"}, "arm": {"uncertainty": {"samples": 10**7, "F": 0.2}}},
    "arm.uncertainty.sampling": {  # 2^24 corners of 24 varying entries
        "plant": {"kind": "arm"},
        "arm": {
            "uncertainty": {"sampling": "vertices", **{k: 0.1 for k in ("F", "R", "Kt", "Kb", "Jm", "L", "I2", "I3")}}
        },
    },
}


# ---------------------------------------------------------------------------- the chunks, without compiling


@pytest.mark.parametrize("sizes", [(5, 3, 1), (1, 10, 1), (1, 1, 7), (3, 4, 5), (2, 7), (7, 1), (1, 1, 1)])
@pytest.mark.parametrize("chunk", [1, 2, 3, 6, 20, 1000])
def test_blocks_cover_the_batch_once_in_order(sizes, chunk):
    """The chunks cover every rollout once, in the batch's order, each at most ``chunk``
    rollouts (two where the innermost axis is chunked), all of one padded shape."""
    todo = chunks.blocks(sizes, chunk)
    assert [b.start for b in todo] == list(np.cumsum([0] + [b.size for b in todo[:-1]]))
    assert sum(b.size for b in todo) == math.prod(sizes)
    assert len({(b.axis, b.length) for b in todo}) == 1
    for b in todo:
        padded = math.prod((b.length if i == b.axis else hi - lo) for i, (lo, hi) in enumerate(b.ranges))
        assert b.size <= padded <= max(chunk, 2 * math.prod(sizes[b.axis + 1 :]))
    if chunk >= math.prod(sizes):
        assert len(todo) == 1
    # as few chunks as at most chunk rollouts take, evened out: the last padded by fewer elements than there are chunks
    whole = max(chunk // math.prod(sizes[todo[0].axis + 1 :]), 2 if todo[0].axis == len(sizes) - 1 else 1)
    n = sizes[todo[0].axis]
    assert len(todo) == math.prod(sizes[: todo[0].axis]) * -(-n // whole)
    assert todo[0].length * -(-n // todo[0].length) - n < -(-n // todo[0].length)


class Plants(NamedTuple):
    """Stand-in plants: an id each (a NamedTuple is a pytree, as the plants are)."""

    id: np.ndarray


def _fake(plants, X0s, keys, paired):
    """A stand-in for the simulator: each rollout's ``rms_error`` is (plant, initial state,
    key) as it would pair them, so the order of the reassembled batch can be read off."""
    p, o = np.asarray(plants.id), np.asarray(X0s[:, 0])
    k = np.zeros(1) if keys is None else np.asarray(keys[:, 0], float)
    ids = np.stack(np.broadcast_arrays(p[:, None], o[:, None], k[None]) if paired else
                   np.broadcast_arrays(p[:, None, None], o[None, :, None], k[None, None]), -1)  # fmt: skip
    ids = ids.reshape(-1, 3)
    zeros = np.zeros_like(ids)
    return SimpleNamespace(metrics=Metrics(ids, *[zeros] * (len(METRIC_NAMES) - 1)),
                           diverged=ids[:, 0] < 0, diverged_at=ids[:, 1])  # fmt: skip


@pytest.mark.parametrize("paired", [False, True])
@pytest.mark.parametrize("keys", [None, 3])
@pytest.mark.parametrize("chunk", [1, 2, 4, 5, 100])
def test_chunks_reassemble_the_batch_in_its_order(paired, keys, chunk):
    """Every rollout's outputs land where the whole batch has them, padding dropped."""
    P = 5
    plants = Plants(np.arange(P) + 100.0)
    X0s = np.repeat((np.arange(P if paired else 3) + 10.0)[:, None], 9, axis=1)
    K = None if keys is None else np.stack([np.arange(keys), np.zeros(keys)], 1).astype(np.uint32)
    whole = _fake(plants, X0s, K, paired)
    got = chunks.run(lambda p, x, k: _fake(p, x, k, paired), plants, X0s, K, paired, chunk, log=lambda _: None)
    np.testing.assert_array_equal(got["rms_error"], whole.metrics.rms_error)
    np.testing.assert_array_equal(got["diverged_at"], whole.diverged_at)
    assert got["diverged"].dtype == bool and not got["diverged"].any()


# ---------------------------------------------------------------------------- the plan


def _room(cfg: dict, rollouts: float, draws: bool = False) -> int:
    """The limit at which ``cfg``'s batch runs in chunks of ``rollouts`` (memory.plan's terms;
    ``draws``: with the draws as lists, as ``--json`` has them)."""
    b = memory.batch(cfg)
    work = memory.WORK_FACTOR * (memory.WORK_FLOATS + b.entries) * b.item
    return int(memory.RESERVE + memory.held(cfg, draws=draws) + rollouts * work) + 1


def test_a_batch_that_fits_runs_whole_one_too_large_in_chunks_one_that_cannot_fit_is_refused():
    """The plan against given limits: the whole batch where it fits; chunks of as many
    rollouts as fit beside what the run holds; a one-line refusal with the estimate, the
    limit and the key where not even the fewest rollouts fit; no limit known: whole."""
    cfg = _config.resolve({"sample": {"count": 10_000, "offsets": 0.01}, **SHORT})
    assert memory.plan(cfg, available=(_room(cfg, 10_000), "x")) == (10_000, None)
    assert memory.plan(cfg, available=(_room(cfg, 2_500), "x")) == (2_500, None)
    assert memory.plan(cfg, available=(None, "unknown")) == (10_000, None)
    # the reserve, an estimate, makes chunks smaller but refuses nothing: only what cannot fit is refused
    least = _room(cfg, memory.MIN_CHUNK) - memory.RESERVE
    assert memory.plan(cfg, available=(least, "x")) == (memory.MIN_CHUNK, None)
    size, line = memory.plan(cfg, available=(least - 2, "a test's limit"))
    assert size == 0 and line.startswith("sample.count: the batch needs at least ")
    assert "(1e+04 rollout(s) of 1 plant(s); its draws and outputs" in line
    assert line.endswith("this process may use (a test's limit): lower sample.count") and "\n" not in line
    # the records and the draws as lists are held too
    assert memory.held(cfg, records=True) > memory.held(cfg, draws=True) > memory.held(cfg)


def test_a_batch_with_a_trace_is_not_chunked():
    """A trace is an output of every rollout: the whole batch or the whole-batch refusal."""
    traced = {"sim": {"t_final": 0.01, "dt": 1e-3, "save_every": 1}, "sample": {"count": 100, "offsets": 0.01}}
    cfg = _config.resolve(traced)
    need = memory.estimate(cfg).bytes
    assert memory.plan(cfg, available=(need, "x")) == (100, None)
    size, line = memory.plan(cfg, available=(need - 1, "x"))
    assert size == 0 and line == memory.refusal(cfg, (need - 1, "x"))


@pytest.mark.parametrize("key", OVERSIZED)
def test_the_five_oversized_batches_are_refused_by_the_plan_at_12_gb(key):
    """At the 12 GB of the issue's campaign, each of the five cannot fit even in chunks (its
    outputs alone: 25 GB for 10^8 rollouts' metrics in float64), so each is refused naming its
    key; nothing drawn."""
    size, line = memory.plan(_config.resolve(OVERSIZED[key]), available=(12 * 10**9, "ulimit"))
    assert size == 0 and line.startswith(f"{key}: the batch needs at least "), line


# ---------------------------------------------------------------------------- compiled: chunked equals whole


def test_cli_runs_a_batch_too_large_for_its_memory_in_chunks(capsys, tmp_path, monkeypatch):
    """``fosmc simulate --json`` with a limit that holds 70 of its 150 rollouts at once: three
    chunks of one shape (one compilation), a progress line after the first and at the end on
    stderr, every rollout printed in the batch's order. (Equal to the unchunked run's output
    byte for byte: the slow test below.)"""
    config = tmp_path / "mc.toml"
    config.write_text(_toml(MC))
    monkeypatch.setattr(memory, "limit", lambda: (_room(_config.load(str(config)), 70, draws=True), "a test's"))
    assert main(["simulate", "--config", str(config), "--json"]) == 0
    out, err = capsys.readouterr()
    lines = err.splitlines()
    assert "in chunks of at most 70 rollouts" in lines[0] and len(lines) == 4, err
    assert lines[1].startswith("fosmc: chunk 1 of 3: 50 of 150 rollouts in ")  # three chunks, evened out
    assert lines[1].endswith("(compilation included)")
    assert lines[2].startswith("fosmc: chunk 3 of 3: 150 of 150 rollouts in ")
    rollouts = json.loads(out)["rollouts"]
    assert [r["offset_index"] for r in rollouts] == list(range(150))
    assert not any(r["diverged"] for r in rollouts)


#: A small Monte-Carlo batch on the linear plant's kernel: one plant, 150 drawn offsets
MC = {"sample": {"count": 150, "offsets": 0.01}, **SHORT}
#: A batch down each path of the simulator, and whether its chunks equal the whole batch bit for
#: bit: the generated kernel runs each rollout alike whatever the batch, but what it takes per
#: rollout and its first sample come from XLA programs of the batch's size, as the vmap path's
#: do, whose code differs with the size, to rounding (measured: relative 2.3e-14 at most on the
#: vmap path, 8.5e-15 on the linear plant's kernel since kernel.cc retired in 712f2e0; the
#: sampled arms' chunks happen to come out bit for bit, and are held to it)
PATHS = {
    "linear native, [sample] offsets": (MC, False),
    "linear vmap, paired": ({"plant": {"uncertainty": "sample", "samples": 7}, "sample": {"count": 7, "offsets": 0.01},
                             "sim": {**SHORT["sim"], "pairing": "paired"}}, False),
    "linear digital loop, noise": ({"controller": {"sample_period": 1e-3}, "plant": {"uncertainty": "sample",
                                    "samples": 2}, "sensors": {"realizations": 9, "noise_std": [1e-3, 0, 0] * 3},
                                    **SHORT}, False),
    "arm native, sampled arms": ({"plant": {"kind": "arm"}, "arm": {"uncertainty": {"samples": 5, "F": 0.2}},
                                  **SHORT}, True),
    "arm digital loop, noise": ({"plant": {"kind": "arm"}, "controller": {"sample_period": 1e-3},
                                 "sensors": {"realizations": 5, "noise_std": [1e-3, 0, 0] * 3}, **SHORT}, False),
}  # fmt: skip


@pytest.mark.slow
@pytest.mark.parametrize("path", PATHS)
def test_chunks_equal_the_whole_batch_on_every_path(path):
    """``run_simulate(chunk=...)`` with chunks of 2, 3 and 4 rollouts (the last padded) against
    the whole batch: the same arrays, bit for bit on the native kernels and to rounding on the
    vmap path, and the summary of the same arrays."""
    cfg, exact = PATHS[path]
    whole = commands.run_simulate(cfg, devices=1, records=False)
    for chunk in (2, 3, 4):
        parts = commands.run_simulate(cfg, devices=1, records=False, chunk=chunk)
        assert set(parts["arrays"]) == set(whole["arrays"])
        for name, x in whole["arrays"].items():
            y = parts["arrays"][name]
            assert x.dtype == y.dtype, name
            if exact or x.dtype.kind != "f":
                assert np.array_equal(x, y), (name, chunk)
            else:
                np.testing.assert_allclose(y, x, rtol=1e-12, atol=0, err_msg=f"{name}, chunk {chunk}")
        if exact:
            assert json.dumps(parts["summary"]) == json.dumps(whole["summary"])


@pytest.mark.slow
def test_cli_output_in_chunks_is_the_unchunked_output_byte_for_byte(capsys, tmp_path, monkeypatch):
    """The default-tier run above against the same command unchunked: stdout byte for byte."""
    config = tmp_path / "mc.toml"
    config.write_text(_toml(MC))
    assert main(["simulate", "--config", str(config), "--json"]) == 0
    whole, err = capsys.readouterr()
    assert "chunk" not in err
    monkeypatch.setattr(memory, "limit", lambda: (_room(_config.load(str(config)), 70, draws=True), "a test's"))
    assert main(["simulate", "--config", str(config), "--json"]) == 0
    out, err = capsys.readouterr()
    assert "in chunks of at most 70 rollouts" in err and out == whole


#: Compares run_simulate of MC over two devices whole and in chunks of 70; prints the arrays that differ
SHARDED = """
import json, sys
import jax
jax.config.update("jax_enable_x64", True)
import numpy as np
from fosmc_jax._app import commands
cfg = json.loads(sys.argv[1])
whole = commands.run_simulate(cfg, devices=2, records=False)
parts = commands.run_simulate(cfg, devices=2, records=False, chunk=70)
print(json.dumps([k for k, x in whole["arrays"].items() if not np.array_equal(x, parts["arrays"][k])]))
"""


@pytest.mark.slow
def test_chunks_split_over_two_devices_equal_the_whole_batch_split_alike():
    """Chunks each split over two devices (``simulate_sharded``, as the command line runs on a
    machine of two cores) equal the whole batch split over them, bit for bit (the native
    kernel), in a process of its own with two CPU devices."""
    env = dict(ENV, XLA_FLAGS="--xla_force_host_platform_device_count=2")
    done = subprocess.run([sys.executable, "-c", SHARDED, json.dumps(MC)], env=env, capture_output=True, text=True,
                          timeout=600)  # fmt: skip
    assert done.returncode == 0 and done.stdout.strip() == "[]", done.stderr[-3000:] + done.stdout


# ---------------------------------------------------------------------------- under ulimit -v


def _under_ulimit(kib: int, script: str, *args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    """``python -c script args`` in a shell that set ``ulimit -v kib`` first."""
    cmd = f'ulimit -v {kib}; exec {sys.executable} -c "$0" "$@"'
    return subprocess.run(["bash", "-c", cmd, script, *args], env=ENV, capture_output=True, text=True,
                          timeout=timeout)  # fmt: skip


#: Runs ``fosmc simulate --config C`` for each config C of its arguments in this process, and
#: prints one JSON line per run: its exit status and its stderr.
CLI = """
import io, json, sys
from contextlib import redirect_stderr
from fosmc_jax._app.cli import main
for config in sys.argv[1:]:
    err = io.StringIO()
    with redirect_stderr(err):
        code = main(["simulate", "--config", config])
    print(json.dumps([code, err.getvalue()]), flush=True)
"""


def test_the_five_oversized_batches_are_refused_in_one_line_under_ulimit_v_12_gb(tmp_path):
    """The issue's five through the command line under ``ulimit -v 12000000``: each refused
    with one line naming its key, the estimate and the limit (the address space), exit status
    2, and nothing killed."""
    paths = []
    for key, cfg in OVERSIZED.items():
        paths.append(tmp_path / f"{key}.toml")
        paths[-1].write_text(_toml(cfg))
    done = _under_ulimit(12_000_000, CLI, *map(str, paths))
    runs = [json.loads(line) for line in done.stdout.splitlines()]
    assert done.returncode == 0 and len(runs) == len(OVERSIZED), done.stderr[-3000:]
    for key, (code, err) in zip(OVERSIZED, runs):
        assert code == 2 and len(err.splitlines()) == 1, err
        assert err.startswith(f"fosmc: error: {key}: the batch needs at least "), err
        # the smaller limit is named: the address space left, or the machine's available memory where a
        # loaded machine has less than that left
        assert "more than the" in err and ("(the address-space limit (ulimit -v) less what this process maps)" in err
                                           or "(the machine's available memory)" in err), err  # fmt: skip


def _toml(cfg: dict, prefix: str = "") -> str:
    """A nested dict of tables as TOML (numbers, strings and lists of numbers only)."""
    scalars = {k: v for k, v in cfg.items() if not isinstance(v, dict)}
    text = f"[{prefix}]\n" if prefix and scalars else ""
    text += "".join(f"{k} = {json.dumps(v)}\n" for k, v in scalars.items())
    return text + "".join(_toml(v, f"{prefix}.{k}" if prefix else k) for k, v in cfg.items() if isinstance(v, dict))


@pytest.mark.slow
def test_a_batch_the_whole_run_could_not_fit_runs_in_chunks_under_an_address_space_limit(tmp_path):
    """2,000,000 rollouts (drawn offsets, two steps) under ``ulimit -v 4000000``: run whole, the
    batch died there (``jax.errors.JaxRuntimeError: ... Out of memory allocating 1040000984
    bytes``, before chunks); in chunks it ends cleanly with every rollout in its --npz (bit
    for bit the whole run's without the limit, measured once: 35 s; 4 GB, not the issue's 12 GB,
    so that the batch takes half a minute rather than several)."""
    config, npz = tmp_path / "big.toml", tmp_path / "big.npz"
    config.write_text(_toml({"sim": {"t_final": 0.002, "dt": 1e-3}, "sample": {"count": 2_000_000, "offsets": 0.01}}))
    cmd = f"ulimit -v 4000000; exec {sys.executable} -m fosmc_jax simulate --config {config} --npz {npz}"
    done = subprocess.run(["bash", "-c", cmd], env=ENV, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "in chunks of at most" in done.stderr and "Traceback" not in done.stderr
    with np.load(npz) as a:
        assert a["rms_error"].shape == (2_000_000, 3) and np.isfinite(a["rms_error"]).all()
        assert (a["offset_index"] == np.arange(2_000_000)).all()


# ---------------------------------------------------------------------------- resume (item 4: a chunk is the unit)


def test_a_run_cut_short_resumes_from_its_last_finished_chunk(tmp_path):
    """With a checkpoint folder each finished chunk is a file; a run stopped in its fifth chunk
    and run again there runs only the chunks not in the folder, and ends with the arrays of a
    run not stopped (the stand-in simulator: no compiling)."""
    plants, X0s = Plants(np.arange(7) + 100.0), np.repeat((np.arange(3) + 10.0)[:, None], 9, axis=1)
    whole = chunks.run(lambda p, x, k: _fake(p, x, k, False), plants, X0s, None, False, 3, log=lambda _: None)
    calls = []

    def stopped(p, x, k):
        if len(calls) == 4:
            raise KeyboardInterrupt  # in the fifth chunk, as a kill would
        calls.append(p.id[0])
        return _fake(p, x, k, False)

    with pytest.raises(KeyboardInterrupt):
        chunks.run(stopped, plants, X0s, None, False, 3, log=lambda _: None, checkpoint=tmp_path)
    assert sorted(f.name for f in tmp_path.iterdir()) == [f"chunk_{i:06d}.npz" for i in range(4)]
    calls.clear()
    lines = []
    again = chunks.run(lambda p, x, k: calls.append(p.id[0]) or _fake(p, x, k, False), plants, X0s, None, False, 3,
                       log=lines.append, checkpoint=tmp_path)  # fmt: skip
    assert calls == [104.0, 105.0, 106.0]  # the plants of chunks 5 to 7 only
    assert lines[0] == f"fosmc: 4 of 7 chunks are in {tmp_path}: running the other 3"
    for name, x in whole.items():
        assert np.array_equal(again[name], x), name
    calls.clear()
    chunks.run(lambda p, x, k: calls.append(p.id[0]), plants, X0s, None, False, 3, log=lines.append,
               checkpoint=tmp_path)  # fmt: skip
    assert calls == [] and lines[-1] == f"fosmc: 7 of 7 chunks are in {tmp_path}: nothing to run"


def test_resume_refuses_a_checkpoint_of_another_run_before_the_work(capsys, tmp_path):
    """``--resume`` needs ``--checkpoint``; a new run needs an empty folder; a folder of another
    config's run, another device count's or another chunk size's is refused, in one line
    naming the option, before anything is drawn or compiled."""
    config, folder = tmp_path / "mc.toml", tmp_path / "ck"
    config.write_text(_toml(MC))
    cfg = _config.load(str(config))
    run = lambda *argv: (main(["simulate", "--config", str(config), *map(str, argv)]), capsys.readouterr()[1])
    code, err = run("--resume")
    assert code == 2 and err == "fosmc: error: --resume: needs --checkpoint DIR, the folder of the run's chunks\n"
    folder.mkdir()
    (folder / "x").write_text("")
    code, err = run("--checkpoint", folder)
    assert code == 2 and err.startswith(f"fosmc: error: --checkpoint: {folder} exists and is not empty (--resume")
    simulate_command._checkpoint_chunk(
        folder, cfg, 1, 1000, 70, resume=False
    )  # the plan.json a run of chunks of 70 writes
    code, err = run("--checkpoint", folder, "--resume", "--devices", 1, "--chunk", 50)
    assert code == 2 and err.startswith(f"fosmc: error: --chunk: {folder} holds chunks of 70 rollouts") and err.count(
        "\n") == 1  # fmt: skip
    code, err = run("--checkpoint", folder, "--resume", "--devices", 1, "--chunk", 0)
    assert code == 2 and err.startswith("fosmc: error: --chunk: expected a positive integer (rollouts), got 0")
    other = _config.replace(cfg, sim={"t_final": 0.02})
    with pytest.raises(_config.ConfigError, match=rf"^--resume: {folder} holds chunks of another config's run"):
        simulate_command._checkpoint_chunk(folder, other, 1, 1000, None, resume=True)
    with pytest.raises(_config.ConfigError, match=r"run on 1 device\(s\) .*: give --devices 1, or give another"):
        simulate_command._checkpoint_chunk(folder, cfg, 2, 1000, None, resume=True)
    with pytest.raises(_config.ConfigError, match=r"chunks of 70 rollouts, more than the 60 this process may hold"):
        simulate_command._checkpoint_chunk(folder, cfg, 1, 60, None, resume=True)
    assert simulate_command._checkpoint_chunk(folder, cfg, 1, 1000, None, resume=True) == 70


@pytest.mark.parametrize("option", ["--chunk", "--checkpoint"])
def test_a_batch_that_keeps_a_trace_is_not_run_in_chunks(capsys, tmp_path, option):
    """``--chunk`` or ``--checkpoint`` with a trace (``--plot`` of a batch without a
    ``[sample]`` table) is refused in one line before the work: a trace is kept whole."""
    value = tmp_path / "ck" if option == "--checkpoint" else 10
    code = main(["simulate", "--plot", str(tmp_path / "x.png"), option, str(value)])
    err = capsys.readouterr()[1]
    assert code == 2 and err == (f"fosmc: error: {option}: a batch that keeps a trace ([sim] save_every, or --plot "
                                 "without a [sample] table) runs whole, not in chunks\n")  # fmt: skip


def test_ctrl_c_with_a_checkpoint_says_how_to_resume(capsys, tmp_path, monkeypatch):
    """Ctrl-C in a run with ``--checkpoint`` whose folder holds chunks: exit status 130 and one
    line with the command that resumes (the same arguments and ``--resume``)."""
    folder = tmp_path / "ck"

    def interrupted(*args, **kwargs):
        folder.mkdir()
        (folder / "chunk_000000.npz").write_bytes(b"")
        raise KeyboardInterrupt

    monkeypatch.setattr(commands, "run_simulate", interrupted)
    assert main(["simulate", "--checkpoint", str(folder), "--chunk", "10"]) == 130
    assert capsys.readouterr()[1] == (f"fosmc: interrupted; {folder} keeps the chunks done so far: resume with "
                                      f"`fosmc simulate --checkpoint {folder} --chunk 10 --resume`\n")  # fmt: skip


#: Runs MC's batch with a checkpoint, in chunks of 10 (15 chunks)
RESUMED = ["--chunk", "10", "--devices", "1"]


@pytest.mark.slow
def test_a_run_killed_at_random_moments_resumes_to_the_run_not_killed(tmp_path):
    """``fosmc simulate --checkpoint DIR`` killed (SIGKILL) at three random moments after its
    n-th chunk file, each time resumed with ``--resume``, ends with the --npz of a run not
    killed, bit for bit; ``--resume`` on the finished folder runs nothing and writes the same.
    Where the rest of a run takes less than the pause before its kill (a quiet machine: the last
    chunks take milliseconds), its --npz is whole and equal to the run not killed, never partial."""
    config = tmp_path / "mc.toml"
    config.write_text(_toml({**MC, "sim": {"t_final": 0.3, "dt": 1e-3}}))
    fosmc = [sys.executable, "-m", "fosmc_jax", "simulate", "--config", str(config), *RESUMED]
    whole = tmp_path / "whole.npz"
    subprocess.run([*fosmc, "--npz", whole], env=ENV, check=True, capture_output=True, timeout=600)
    rng = np.random.default_rng(0)
    folder, out = tmp_path / "ck", tmp_path / "resumed.npz"
    cmd = [*fosmc, "--checkpoint", folder, "--npz", out]
    for after in sorted(rng.choice(np.arange(1, 14), 3, replace=False)):
        proc = subprocess.Popen(cmd + (["--resume"] if folder.exists() else []), env=ENV,
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
        while len(list(folder.glob("chunk_*.npz"))) < after and proc.poll() is None:
            time.sleep(0.005)
        time.sleep(rng.uniform(0, 0.02))
        proc.kill()  # SIGKILL: no handler runs
        proc.wait()
        if out.exists():  # the rest of the run took less than the pause (a quiet machine): whole, never partial
            with np.load(whole) as a, np.load(out) as b:
                assert all(np.array_equal(a[k], b[k]) for k in a.files if k != "fosmc_jax")
            break
    done = subprocess.run(cmd + ["--resume"], env=ENV, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0 and " chunks are in " in done.stderr, done.stderr
    with np.load(whole) as a, np.load(out) as b:
        assert all(np.array_equal(a[k], b[k]) for k in a.files if k != "fosmc_jax")
    again = subprocess.run(cmd + ["--resume"], env=ENV, capture_output=True, text=True, timeout=600)
    assert "15 of 15 chunks are in" in again.stderr and ": nothing to run" in again.stderr
    with np.load(whole) as a, np.load(out) as b:
        assert all(np.array_equal(a[k], b[k]) for k in a.files if k != "fosmc_jax")
