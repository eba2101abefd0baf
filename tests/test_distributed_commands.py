"""``fosmc front``, ``simulate`` and ``tune`` as several processes (issue 36): two processes on
127.0.0.1, one CPU device each (gloo collectives, as tests/test_distributed.py), against one
process with two devices; a process killed mid-run, one that never joins, one started with other
options. Each process runs in a folder of its own with the same relative paths, so that what
process 1 writes (nothing) shows.
"""

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from fosmc_jax._app import commands
from fosmc_jax._problems import ConfigError

FRONT = '[plant]\nuncertainty = "sample"\nsamples = 3\n[sim]\nt_final = 0.3\ndt = 2e-3\nintegrator = "euler"\n'
#: Four plants: the tuner's loss splits them over the two processes' devices (and sums across them);
#: the gradient's mode fixed, since "auto" picks it by timing, which differs between the two runs.
TUNE = FRONT.replace("samples = 3", "samples = 4") + '[tune]\nmode = "reverse"\n'
SAMPLED = ('[sim]\nt_final = 0.2\ndt = 2e-3\nintegrator = "euler"\n[sample]\ncount = 7\n'
           "offsets = [0.01, 0, 0, 0.01, 0, 0, 0.01, 0, 0]\n")  # fmt: skip


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def environment(devices: int) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "JAX_PLATFORMS")}
    return dict(env, JAX_NUM_CPU_DEVICES=str(devices), JAX_PLATFORMS="cpu")


def folders(tmp_path: Path, n: int) -> list[Path]:
    """n working folders, each with the same configs (the processes' own copies)."""
    out = []
    for i in range(n):
        d = tmp_path / f"p{i}"
        d.mkdir()
        (d / "front.toml").write_text(FRONT)
        (d / "sampled.toml").write_text(SAMPLED)
        (d / "tune.toml").write_text(TUNE)
        out.append(d)
    return out


def start(args: list[str], cwd: Path, devices: int = 1, tag: str = "") -> subprocess.Popen:
    log = open(cwd / f"stderr{tag}.txt", "w")
    return subprocess.Popen([sys.executable, "-m", "fosmc_jax._app.cli", *args], cwd=cwd, env=environment(devices),
                            stdout=open(cwd / f"stdout{tag}.txt", "w"), stderr=log)  # fmt: skip


def across(args: list[str], dirs: list[Path], tag: str = "", timeout: float = 300,
           extra: list[list[str]] | None = None) -> list[subprocess.Popen]:  # fmt: skip
    """``fosmc args`` (and each process's ``extra`` arguments) as len(dirs) processes joined on a
    free port, waited for."""
    address = f"127.0.0.1:{free_port()}"
    extra = extra or [[] for _ in dirs]
    procs = [start([*args, "--coordinator", address, "--num-processes", str(len(dirs)), "--process-id", str(i),
                    *extra[i]], d, tag=tag) for i, d in enumerate(dirs)]  # fmt: skip
    deadline = time.monotonic() + timeout
    for p in procs:
        try:
            p.wait(timeout=max(1.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            for q in procs:
                q.kill()
            pytest.fail(f"fosmc {' '.join(args)}: the processes did not end within {timeout} s")
    return procs


def read(d: Path, name: str) -> str:
    return (d / name).read_text()


def front_equal(a: dict, b: dict) -> None:
    for r in (a, b):
        r["stages"].pop("wall_time_s")
    assert a == b


@pytest.mark.slow  # two processes start, join and compile, and the same runs in one process (~60-90 s)
def test_front_and_simulate_across_two_processes_equal_one_process(tmp_path):
    """Two processes of one CPU device each give the front and the metrics one process of two
    devices gives, bit for bit (the candidates and rollouts are split alike: 8 per device);
    process 0 alone prints and writes."""
    dirs = folders(tmp_path, 3)  # two processes, then the one-process reference
    front = ["front", "--config", "front.toml", "--candidates", "16", "--steps", "2", "--out", "out"]
    procs = across(front, dirs[:2])
    assert [p.returncode for p in procs] == [0, 0], read(dirs[0], "stderr.txt") + read(dirs[1], "stderr.txt")
    assert sorted(x.name for x in (dirs[0] / "out").iterdir()) == ["checkpoint.npz", "front.json", "front.png"]
    assert not (dirs[1] / "out").exists()  # process 1 wrote nothing
    assert read(dirs[1], "stdout.txt") == "" and read(dirs[1], "stderr.txt") == ""  # and printed nothing
    one = subprocess.run([sys.executable, "-m", "fosmc_jax._app.cli", *front], cwd=dirs[2], env=environment(2),
                         capture_output=True, text=True, timeout=300)  # fmt: skip
    assert one.returncode == 0, one.stderr
    a, b = (json.loads((d / "out" / "front.json").read_text()) for d in (dirs[0], dirs[2]))
    assert len(a["points"]) > 5
    front_equal(a, b)
    assert read(dirs[0], "stdout.txt") == one.stdout  # the points printed

    simulate = ["simulate", "--config", "sampled.toml", "--json"]
    procs = across(simulate, dirs[:2], tag="-simulate")
    assert [p.returncode for p in procs] == [0, 0], read(dirs[0], "stderr-simulate.txt")
    assert read(dirs[1], "stdout-simulate.txt") == ""
    one = subprocess.run([sys.executable, "-m", "fosmc_jax._app.cli", *simulate], cwd=dirs[2], env=environment(2),
                         capture_output=True, text=True, timeout=300)  # fmt: skip
    assert one.returncode == 0, one.stderr
    got = json.loads(read(dirs[0], "stdout-simulate.txt"))
    assert len(got["rollouts"]) == 7 and got == json.loads(one.stdout)


@pytest.mark.slow  # two processes joined, then one tune run each way (~60 s)
def test_tune_across_two_processes_equal_one_process(tmp_path):
    """``fosmc tune`` (its global stage over both processes' devices, then gradient steps whose
    loss splits the plants over them): the same result.json as one process of two devices, bit
    for bit, written by process 0 alone."""
    dirs = folders(tmp_path, 3)
    tune = ["tune", "--config", "tune.toml", "--steps", "3", "--out", "out"]
    procs = across(tune, dirs[:2])
    assert [p.returncode for p in procs] == [0, 0], read(dirs[0], "stderr.txt") + read(dirs[1], "stderr.txt")
    assert not (dirs[1] / "out").exists() and read(dirs[1], "stdout.txt") == ""
    one = subprocess.run([sys.executable, "-m", "fosmc_jax._app.cli", *tune], cwd=dirs[2], env=environment(2),
                         capture_output=True, text=True, timeout=300)  # fmt: skip
    assert one.returncode == 0, one.stderr
    a, b = (json.loads((d / "out" / "result.json").read_text()) for d in (dirs[0], dirs[2]))
    assert a["final"] == b["final"] and a["history"] == b["history"] and a["start"] == b["start"]
    assert read(dirs[0], "stdout.txt") == one.stdout


def wait_for(path: Path, text: str, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if path.exists() and text in path.read_text():
            return
        time.sleep(0.2)
    pytest.fail(f"{text!r} not in {path} within {timeout} s:\n{path.read_text() if path.exists() else ''}")


@pytest.mark.slow  # two processes run until the local stage, one is killed, the checkpoint is resumed (~60-90 s)
@pytest.mark.parametrize("victim", [1, 0])
def test_a_process_killed_mid_run(tmp_path, victim):
    """The other process ends non-zero within 120 s of the death with one line naming it; no
    front.json, no temporary is left, and the checkpoint written so far is resumed by one
    process (victim 1: process 0 wrote it)."""
    dirs = folders(tmp_path, 2)
    front = ["front", "--config", "front.toml", "--candidates", "32", "--steps", "300", "--out", "out"]
    address = f"127.0.0.1:{free_port()}"
    procs = [start([*front, "--coordinator", address, "--num-processes", "2", "--process-id", str(i)], d)
             for i, d in enumerate(dirs)]  # fmt: skip
    try:
        wait_for(dirs[0] / "stderr.txt", "local round 20/300", timeout=240)
        procs[victim].send_signal(signal.SIGKILL)
        killed = time.monotonic()
        other = procs[1 - victim]
        code = other.wait(timeout=150)
        assert time.monotonic() - killed < 120
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
    err = read(dirs[1 - victim], "stderr.txt").strip().splitlines()
    assert code != 0
    assert err[-1].startswith(f"fosmc: error: process {victim} of 2") and "stopped mid-run" in err[-1], err[-5:]
    assert not any("Check failure" in line or line.startswith(("E1", "F1")) for line in err)  # no JAX C++ log
    out = dirs[0] / "out"
    assert not (out / "front.json").exists()
    assert not list(out.glob(".*")) if out.exists() else True  # no temporary of an atomic write
    assert not (dirs[1] / "out").exists()
    if victim == 1:  # a later run, in one process, resumes from process 0's checkpoint and ends
        assert (out / "checkpoint.npz").exists()
        one = subprocess.run([sys.executable, "-m", "fosmc_jax._app.cli", *front, "--resume"], cwd=dirs[0],
                             env=environment(2), capture_output=True, text=True, timeout=600)  # fmt: skip
        assert one.returncode == 0, one.stderr
        assert "resumed from" in one.stderr and (out / "front.json").exists()


# the coordinator's case in the slow tier (5 s of waiting for --join-timeout: the default tier keeps to 4 minutes)
@pytest.mark.parametrize("me", [pytest.param(0, marks=pytest.mark.slow), 1])
def test_a_process_that_never_joins(tmp_path, me):
    """One process of two alone ends non-zero after --join-timeout (well within 120 s), with one
    line naming the missing process."""
    (d,) = folders(tmp_path, 1)
    t = time.monotonic()
    p = subprocess.run([sys.executable, "-m", "fosmc_jax._app.cli", "front", "--config", "front.toml", "--out", "out",
                        "--coordinator", f"127.0.0.1:{free_port()}", "--num-processes", "2", "--process-id", str(me),
                        "--join-timeout", "4"], cwd=d, env=environment(1), capture_output=True, text=True,
                       timeout=120)  # fmt: skip
    assert time.monotonic() - t < 120
    assert p.returncode == 1 and p.stdout == ""
    missing = "process 1 of 2 did not join" if me == 0 else "process 0 (the coordinator, 127.0.0.1:"
    assert p.stderr.count("\n") == 1 and p.stderr.startswith(f"fosmc: error: --join-timeout: {missing}"), p.stderr
    assert not (d / "out").exists()


def test_processes_with_other_options_are_refused(tmp_path):
    """Process 1 started with another --seed than process 0: both end with status 2 and one
    line each, before any work (no output folder)."""
    dirs = folders(tmp_path, 2)
    front = ["front", "--config", "front.toml", "--candidates", "16", "--steps", "2", "--out", "out"]
    procs = across(front, dirs, timeout=120, extra=[[], ["--seed", "1"]])
    assert [p.returncode for p in procs] == [2, 2]
    err = [read(d, "stderr.txt") for d in dirs]
    assert err[0] == ("fosmc: error: process 1 was started with another config, options or input files than "
                      "process 0: refused, every process ends\n")  # fmt: skip
    assert err[1].startswith("fosmc: error: process 1: its config, options or input files differ from process 0's")
    assert err[1].count("\n") == 1
    assert not any((d / "out").exists() for d in dirs)


def test_an_output_refused_on_process_0_ends_both_in_one_line(tmp_path):
    """simulate --npz that process 0 cannot write (a file's path as its folder): refused before
    any work, every process ends with status 2 and one line, at once (not after JAX's heartbeat)."""
    dirs = folders(tmp_path, 2)
    t = time.monotonic()
    procs = across(["simulate", "--config", "sampled.toml", "--npz", "sampled.toml/x.npz"], dirs, timeout=120)
    assert time.monotonic() - t < 60
    assert [p.returncode for p in procs] == [2, 2]
    err = [read(d, "stderr.txt") for d in dirs]
    assert err[0].startswith("fosmc: error: --npz: ") and err[0].count("\n") == 1, err[0]
    assert err[1] == "fosmc: error: process 0 refused the run (its error says why): every process ends\n", err[1]


def test_joining_options_checked_in_one_line(tmp_path, capsys):
    """Incomplete or contradictory joining options, and joining after JAX has computed (as it
    has in this test process), are refused in one line naming the option."""
    from fosmc_jax._app.cli import main

    cases = [
        (["--coordinator", "127.0.0.1:1234"], "--coordinator: needs --num-processes and --process-id too"),
        (["--coordinator", "nohost", "--num-processes", "2", "--process-id", "0"], "--coordinator: expected HOST:PORT"),
        (["--coordinator", "h:1", "--num-processes", "2", "--process-id", "2"], "--process-id: expected an integer"),
        (["--distributed", "--process-id", "0"], "--distributed: finds the processes by itself"),
        (["--distributed", "--join-timeout", "0"], "--join-timeout: expected a positive number"),
    ]
    for extra, message in cases:
        assert main(["front", "--out", str(tmp_path / "o"), *extra]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"fosmc: error: {message}") and err.count("\n") == 1, err
    import jax

    jax.numpy.zeros(1).block_until_ready()  # JAX has computed in this process
    with pytest.raises(ConfigError, match=r"^--coordinator: JAX has already computed in this process"):
        commands.run_front(coordinator="127.0.0.1:1234", num_processes=2, process_id=0)
    assert not (tmp_path / "o").exists()
