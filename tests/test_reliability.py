"""Reliability: determinism, warnings, batch statistics that exclude diverged rollouts, and a
tuning run killed with SIGKILL that resumes to the same result as an uninterrupted one."""

import json
import os
import signal
import subprocess
import sys
import time
import warnings

import jax.numpy as jnp
import numpy as np
import pytest

from fosmc_jax import _problems as _config
from fosmc_jax._app.cli import main
from fosmc_jax._simulator.metrics import Metrics, batch_summary

TINY = """
[plant]
uncertainty = "sample"
samples = 2
seed = 11
[sim]
t_final = 0.2
dt = 2e-3
initial_offset = [0.01, 0, 0, 0, 0, 0, 0, 0, 0]
[tune]
steps = 8
checkpoint_every = 1
mode = "reverse"
remat_steps = 20
"""


def test_same_config_and_seed_give_the_same_numbers(tmp_path, capsys):
    path = tmp_path / "c.toml"
    path.write_text(TINY)
    outs = []
    for _ in range(2):
        assert main(["simulate", "--config", str(path), "--json"]) == 0
        outs.append(json.loads(capsys.readouterr().out))
    assert outs[0] == outs[1]
    # another seed draws other plants
    path.write_text(TINY.replace("seed = 11", "seed = 12"))
    assert main(["simulate", "--config", str(path), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["rollouts"] != outs[0]["rollouts"]


def test_step_beyond_stability_warns():
    with pytest.warns(UserWarning, match="stability limit"):
        _config.resolve({"sim": {"dt": 0.3, "integrator": "euler"}})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _config.resolve({})  # the defaults do not warn


def test_batch_summary_excludes_diverged():
    m = Metrics(*(jnp.array([[1.0, 2.0, 3.0], [100.0, 100.0, 100.0], [3.0, 4.0, 5.0]]) for _ in Metrics._fields))
    s = batch_summary(m, jnp.array([False, True, False]))
    assert s["rollouts"] == 3 and s["diverged_excluded"] == 1
    assert s["mean"]["rms_error"] == [2.0, 3.0, 4.0] and s["max"]["chattering"] == [3.0, 4.0, 5.0]
    empty = batch_summary(m, jnp.array([True, True, True]))
    assert empty["diverged_excluded"] == 3 and np.all(np.isnan(empty["mean"]["rms_error"]))


@pytest.mark.slow  # two tuning subprocesses (~20 s)
def test_tune_killed_with_sigkill_resumes_to_the_uninterrupted_result(tmp_path, capsys):
    config = tmp_path / "c.toml"
    config.write_text(TINY)
    whole, killed = tmp_path / "whole", tmp_path / "killed"
    assert main(["tune", "--config", str(config), "--out", str(whole)]) == 0
    capsys.readouterr()

    cmd = [sys.executable, "-m", "fosmc_jax", "tune", "--config", str(config), "--out", str(killed)]
    # one device, as in this process: the loss sums its rollouts split over the devices, so the
    # last bits of a step depend on their count (the CLI uses every core by default)
    env = dict(os.environ, JAX_NUM_CPU_DEVICES="1")
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env)
    deadline = time.monotonic() + 240
    try:
        for line in proc.stderr:  # progress lines; kill mid-run, after some checkpoints
            if line.startswith("tune: step    4/") or time.monotonic() > deadline:
                break
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait()
    assert proc.returncode == -signal.SIGKILL
    assert (killed / "checkpoint.npz").exists() and not (killed / "result.json").exists()

    assert main(["tune", "--config", str(config), "--out", str(killed), "--resume"]) == 0
    # a temporary a SIGKILL cut off mid-write is removed by the next run's write into the folder
    assert not [p for p in killed.iterdir() if p.name.startswith(".")]
    a = json.loads((whole / "result.json").read_text())
    b = json.loads((killed / "result.json").read_text())
    assert a["final"] == b["final"]
    assert a["history"]["loss"] == b["history"]["loss"]
