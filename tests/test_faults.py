"""A fault campaign (issue 34, items 1, 3, 6): bad inputs, unwritable outputs, a reader that goes
away and Ctrl-C, each met as docs/troubleshooting.md's table "What is refused, and how" says.

From the command line every bad input is refused with exactly one line on stderr, ``fosmc:
error: <key or option>: <what is wrong>``, exit status 2, before any work: no progress line (a
command's first progress line comes before it compiles), nothing written. From Python each is
one ``ValueError`` or ``TypeError`` whose one-line message starts with the argument's name.
The default tier compiles nothing here; the runs that must compile (a pipe closed on a
simulation, Ctrl-C during ``tune`` and ``front``) are in the slow tier.
"""

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import fosmc_jax as fj
from fosmc_jax import _problems as _config
from fosmc_jax._app import commands, study
from fosmc_jax._app import reproduce as reproduction
from fosmc_jax._app.cli import main
from fosmc_jax._io import check_writable, write_text
from fosmc_jax._problems import memory
from fosmc_jax._simulator.checks import check_inputs
from fosmc_jax._simulator.rollout import option_names

ROOT = Path(__file__).resolve().parents[1]
FRONT = ROOT / "tuning" / "results" / "front_budget_300" / "front.json"
SHORT = "[sim]\nt_final = 0.05\ndt = 1e-3\n"
ONE_LINE = re.compile(r"fosmc: error: (\S+): \S.*")


def _unwritable() -> Path:
    """A folder no file can be made in, even as root: /sys (sysfs refuses new files); skips
    where that is not so (another OS, a container that lets root write there)."""
    try:
        check_writable("/sys/fosmc-probe", folder=False)
    except ValueError:
        return Path("/sys")
    pytest.skip("no folder here refuses a new file to this user")


def cli(capsys, *argv) -> tuple[int, str, str]:
    """``fosmc argv`` in this process: (exit status, stdout, stderr); argparse's own errors exit."""
    try:
        code = main([str(a) for a in argv])
    except SystemExit as e:
        code = e.code
    out, err = capsys.readouterr()
    return code, out, err


def assert_refused(code: int, err: str, option: str) -> str:
    """Exit status 2 and exactly one stderr line ``fosmc: error: <option>: ...``; the line."""
    lines = err.splitlines()
    assert code == 2 and len(lines) == 1, (code, err)
    match = ONE_LINE.fullmatch(lines[0])
    assert match and match.group(1) == option, lines[0]
    return lines[0]


# ---------------------------------------------------------------------------- the config file


def test_config_file_not_utf8_is_one_line(capsys, tmp_path):
    """UTF-16 (a BOM) and Latin-1 files: read as UTF-8 whatever the locale, refused in one line
    that names the file and the first bad byte."""
    utf16, latin1 = tmp_path / "utf16.toml", tmp_path / "latin1.toml"
    utf16.write_bytes(SHORT.encode("utf-16"))
    latin1.write_bytes(SHORT.encode() + "# caf\u00e9\n".encode("latin-1"))
    for path, byte in ((utf16, "byte 0 is 0xff"), (latin1, f"byte {len(SHORT) + 5} is 0xe9")):
        line = assert_refused(*cli(capsys, "simulate", "--config", path)[::2], option=str(path))
        assert "not UTF-8" in line and byte in line
    # the same text as UTF-8 is read (the check is on the encoding, not on what it says)
    assert _config.load(_write(tmp_path / "ok.toml", SHORT + "# caf\u00e9\n"))["sim"]["t_final"] == 0.05


def _write(path: Path, text: str) -> Path:
    path.write_text(text, encoding="utf-8")
    return path


# ---------------------------------------------------------------------------- the digital loop's ranges


LOOP = {"controller": {"sample_period": 1e-3}, "sim": {"t_final": 0.01, "dt": 1e-4}}


def _loop(**controller) -> dict:
    return {**LOOP, "controller": {**LOOP["controller"], **controller}}


def test_delay_at_the_horizon_is_refused_one_sample_less_runs():
    """10 controller samples in 0.01 s at 1 ms: a delay of 9 applies the first sample's voltage
    at the last; 10 (or the issue's 1e9, which allocated 51 GB) never acts, and is refused."""
    assert _config.resolve(_loop(delay_samples=9))["controller"]["delay_samples"] == 9
    for delay in (10, 10**9):
        with pytest.raises(_config.ConfigError, match=r"^controller\.delay_samples: expected fewer than the 10 "):
            _config.resolve(_loop(delay_samples=delay))


def test_delay_as_long_as_the_training_horizon_is_refused():
    """tune trains on tune.train_t_final: a delay of 2 samples in 2 ms of it never acts."""
    assert _config.resolve({**_loop(delay_samples=2), "tune": {"train_t_final": 0.003}})
    with pytest.raises(_config.ConfigError, match=r"^tune\.train_t_final: expected more than controller\.delay_"):
        _config.resolve({**_loop(delay_samples=2), "tune": {"train_t_final": 0.002}})


def test_sample_period_past_the_horizon_is_refused():
    """1e300 s overflowed the step count; a period up to the horizon is a loop that samples."""
    assert _config.resolve(_loop(sample_period=0.01))["controller"]["sample_period"] == 0.01
    for period in (0.011, 1e300):
        with pytest.raises(_config.ConfigError, match=r"^controller\.sample_period: expected at most sim\.t_final"):
            _config.resolve(_loop(sample_period=period))


# ---------------------------------------------------------------------------- options out of range


# (argv after the command's name, the option named); each is refused before any work
OPTIONS = [
    (["front", "--budget", "inf"], "--budget"),
    (["front", "--budget", "nan"], "--budget"),
    (["front", "--budget", "0"], "--budget"),
    (["front", "--seed", "-1"], "--seed"),
    (["front", "--seed", str(commands.MAX_FRONT_SEED + 1)], "--seed"),  # CMA-ES's seeds would pass 2^32
    (["front", "--points", "0"], "--points"),
    (["certify", "--seed", "-1"], "--seed"),
    (["reproduce", "--t-final", "-1"], "--t-final"),
    (["reproduce", "--t-final", "inf"], "--t-final"),
    (["reproduce", "--dt", "0"], "--dt"),
    (["reproduce", "--dt", "1", "--t-final", "0.5"], "--dt"),
    (["reproduce", "--dt", "1e-12"], "--dt"),  # 4e12 steps
    (["reproduce", "--t-final", "1e-3"], "--t-final"),  # the realistic loop's 1 ms sample, one of delay
    (["simulate", "--devices", "0"], "--devices"),
    (["simulate", "--devices", "1000"], "--devices"),  # aborted the process (LLVM pthread_create)
    (["simulate", "--plot", "x.xyz"], "--plot"),  # matplotlib refused it after the simulation
    (["simulate", "--plot", "x"], "--plot"),
    # argparse's errors, in the same form (no usage block)
    (["front", "--budget", "soon"], "--budget"),
    (["simulate", "--bogus"], "--bogus"),
    (["tune", "--steps", "2.5"], "--steps"),
    (["frobnicate"], "command"),
]


@pytest.mark.parametrize("argv, option", OPTIONS, ids=[" ".join(a) for a, _ in OPTIONS])
def test_option_out_of_range_is_one_line_before_the_work(capsys, tmp_path, argv, option):
    out = tmp_path / "out"
    extra = ["--out", out] if argv[0] in ("front", "reproduce", "tune") else []
    code, stdout, err = cli(capsys, *argv, *extra)
    assert_refused(code, err, option)
    assert stdout == "" and not out.exists()  # nothing made, not even the folder


NUMBERS = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-(10**6), 10**6))


class _Reached(Exception):
    """Raised by a stub in place of the work: the options were accepted."""


@pytest.mark.filterwarnings("ignore::UserWarning")  # the default config's one plant
@settings(max_examples=60, derandomize=True, deadline=None)
@given(budget=NUMBERS, seed=st.integers(-(10**6), 10**6))
def test_front_budget_and_seed_are_accepted_exactly_when_in_range(budget, seed):
    """Any number for --budget and --seed: refused in one line naming it, or the work starts
    (a stub here) exactly when the budget is positive and finite and the seed in [0, 4294]."""

    def stub(*args, **kwargs):
        raise _Reached

    valid = np.isfinite(budget) and budget > 0 and 0 <= seed <= commands.MAX_FRONT_SEED
    original, study.study = study.study, stub
    try:
        commands.run_front(budget=budget, seed=seed)
        raise AssertionError("neither refused nor started")
    except _Reached:
        assert valid
    except _config.ConfigError as e:
        assert not valid and str(e).split(":")[0] in ("--budget", "--seed") and "\n" not in str(e)
    finally:
        study.study = original


@pytest.mark.filterwarnings("ignore::UserWarning")  # steps beyond the stability limit
@settings(max_examples=60, derandomize=True, deadline=None)
@given(t_final=NUMBERS, dt=NUMBERS)
def test_reproduce_horizon_follows_the_config_rules(t_final, dt):
    """--t-final and --dt of reproduce are refused exactly when [sim] t_final and dt would be
    (:func:`fosmc_jax._problems.check_horizon`), named as the options; the linear plant, so
    that the realistic loop's own rule does not enter."""

    def stub(*thunks):
        raise _Reached

    try:
        _config.resolve({"sim": {"t_final": t_final, "dt": dt}})
        valid = True
    except _config.ConfigError:
        valid = False
    original, reproduction.run_groups = reproduction.run_groups, stub
    try:
        commands.run_reproduce(plant="linear", t_final=t_final, dt=dt)
        raise AssertionError("neither refused nor started")
    except _Reached:
        assert valid
    except _config.ConfigError as e:
        assert not valid and str(e).split(":")[0] in ("--t-final", "--dt") and "\n" not in str(e)
    finally:
        reproduction.run_groups = original


# ---------------------------------------------------------------------------- unwritable outputs


def _outputs(base: Path) -> list[tuple[list, str]]:
    """Every output option of every command, at ``base`` (a place no file can be made)."""
    return [
        (["simulate", "--npz", base / "m.npz"], "--npz"),
        (["simulate", "--plot", base / "m.png"], "--plot"),
        (["tune", "--out", base / "tune"], "--out"),
        (["front", "--out", base / "front"], "--out"),
        (["reproduce", "--out", base / "rep"], "--out"),
        (["identify", "--data", FRONT, "--params", "R", "--payload", "0", "--out", base / "id"], "--out"),
        (["export", "--config", "realistic_arm", "--out", base / "fw"], "--out"),
    ]


@pytest.mark.parametrize("where", ["below a file", "a read-only file system"])
def test_unwritable_output_is_refused_before_the_work(capsys, tmp_path, where):
    """--out, --npz, --plot where nothing can be written: below a file, or in /sys (which
    refuses root too: permission bits do not). Each refused in one line naming the option,
    within seconds; the six lost runs of the issue wrote there after their work."""
    if where == "below a file":
        blocker = tmp_path / "afile"
        blocker.write_text("keep")
        base = blocker / "sub"
    else:
        base = _unwritable() / "fosmc-out"
    for argv, option in _outputs(base):
        start = time.perf_counter()
        code, stdout, err = cli(capsys, *argv)
        line = assert_refused(code, err, option)
        assert stdout == "" and time.perf_counter() - start < 30, (argv, line)
        below = "is a file" in line or "is not a folder" in line  # export's own words
        assert below if where == "below a file" else ("cannot write in" in line), line
    if where == "below a file":
        assert blocker.read_text() == "keep"


def test_report_that_cannot_be_read_is_refused_before_the_work(capsys, tmp_path):
    """reproduce --report read the report after every case had run."""
    code, _, err = cli(capsys, "reproduce", "--plant", "linear", "--report", tmp_path / "missing.md")
    assert "cannot read" in assert_refused(code, err, "--report")


def test_check_writable_leaves_nothing_and_makes_no_folder(tmp_path):
    """The probe file is removed; the folders still to be made are not made by the check."""
    target = tmp_path / "a" / "b" / "c.npz"
    assert check_writable(target, folder=False) == target
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "d").mkdir()
    with pytest.raises(ValueError, match="is a folder, not a file"):
        check_writable(tmp_path / "d", folder=False)
    assert check_writable(tmp_path / "d", folder=True) == tmp_path / "d"
    assert list((tmp_path / "d").iterdir()) == []


def test_a_temporary_left_by_a_killed_writer_goes_with_the_next_write(tmp_path):
    """A writer SIGKILLed mid-write leaves its temporary (no handler runs); the next write of the
    same file removes it, and leaves a live writer's temporary alone."""
    target = tmp_path / "checkpoint.npz"
    child = (f"import time; from fosmc_jax._io import atomic_write\n"
             f"atomic_write({str(target)!r}, lambda tmp: (print(tmp, flush=True), time.sleep(60)))")  # fmt: skip
    proc = subprocess.Popen([sys.executable, "-c", child], stdout=subprocess.PIPE, text=True, cwd=ROOT)
    left = Path(proc.stdout.readline().strip())  # the temporary exists: its writer is mid-write
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    live = tmp_path / f".checkpoint.npz.{os.getpid()}.x.npz"  # this process's, as if mid-write
    live.write_text("")
    assert left.exists() and not target.exists()
    write_text(target, "new")
    assert target.read_text() == "new" and not left.exists() and live.exists()


# ---------------------------------------------------------------------------- the Python API's edges


@pytest.fixture(scope="module")
def problem():
    with jax.enable_x64(True):
        yield fj.build({"sim": {"t_final": 0.01, "dt": 1e-3}})


@pytest.mark.parametrize(
    "options, error, name",
    [
        ({"bogus": 1}, TypeError, "bogus"),
        ({"n_steps": 0}, ValueError, "n_steps"),
        ({"n_steps": 2.5}, ValueError, "n_steps"),
        ({"n_steps": -5}, ValueError, "n_steps"),
        ({"n_steps": True}, ValueError, "n_steps"),
        ({"save_every": -1}, ValueError, "save_every"),
        ({"divergence_bound": -1.0}, ValueError, "divergence_bound"),
        ({"switching": "bang"}, ValueError, "switching"),
        ({"fast": "yes"}, ValueError, "fast"),
    ],
)
def test_simulate_option_refused_naming_it(problem, options, error, name):
    """problem.simulate(bogus=1) was ignored on some paths; n_steps = 0 gave rms_error 0, 2.5
    ran, -5 spoke of `unroll`. Each is one error whose message starts with the option."""
    with jax.enable_x64(True), pytest.raises(error) as e:
        problem.simulate(**options)
    assert str(e.value).startswith(f"{name}: ") and "\n" not in str(e.value)


def test_simulate_single_rollout_refuses_batch_options(problem):
    """fosmc_jax.simulate takes no ``keys`` or ``pairing`` (simulate_batch's)."""
    plant = jax.tree.map(lambda x: x[0], problem.plants)
    with jax.enable_x64(True):
        for name in ("keys", "pairing", "bogus"):
            with pytest.raises(TypeError, match=rf"^{name}: not an option of simulate \(its options: n_steps"):
                fj.simulate(plant, problem.controller(), problem.reference, problem.X0s[0], problem.dt,
                            n_steps=5, **{name: None})  # fmt: skip


def test_valid_options_pass_the_check(problem):
    """NumPy integers are integers; every option of simulate_batch a config sets passes."""
    with jax.enable_x64(True):
        options = dict(problem.options, n_steps=np.int64(3), fast=False, native=True, chattering_cutoff=20.0)
        check_inputs(
            problem.plants,
            problem.controller(),
            problem.reference,
            problem.X0s,
            problem.dt,
            True,
            options,
            option_names(True),
        )


def test_params_of_a_wrong_type_named(problem):
    """problem.simulate([1, 2]) raised AttributeError: _asdict."""
    with pytest.raises(TypeError, match=r"^params: expected a dict of the parameters of controller kind 'fosmc' "
                                        r"by name \(delta, gamma, poles\) or a Tunable, got list$"):  # fmt: skip
        problem.simulate([1, 2])


def test_integer_initial_state_names_its_dtype(problem):
    """An int32 X0s said 'cannot convert float infinity to integer'."""
    with jax.enable_x64(True):
        for batch, name, X0 in ((True, "X0s", jnp.zeros((1, 9), jnp.int32)), (False, "X0", jnp.zeros(9, jnp.int32))):
            plants = problem.plants if batch else jax.tree.map(lambda x: x[0], problem.plants)
            with pytest.raises(TypeError, match=rf"^{name}: expected floating-point numbers .* got an array of int32$"):
                check_inputs(
                    plants,
                    problem.controller(),
                    problem.reference,
                    X0,
                    problem.dt,
                    batch,
                    {"n_steps": 5},
                    option_names(batch),
                )


# ---------------------------------------------------------------------------- a reader that goes away


def _fosmc(*argv) -> list[str]:
    return [sys.executable, "-m", "fosmc_jax", *map(str, argv)]


def _after(prelude: str, cmd: list[str]) -> list[str]:
    """``cmd`` run by a Python that first runs ``prelude`` (a process setting: a signal's
    handling, a resource limit) and then becomes ``cmd`` (exec), without a fork hook in this
    multithreaded (JAX) process."""
    return [sys.executable, "-c", f"import os, sys; {prelude}; os.execv(sys.argv[1], sys.argv[1:])", *cmd]


ENV = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))


def test_closed_pipe_ends_quietly():
    """stdout's reader gone before the command writes (``| head`` that has read enough): no
    traceback, nothing on stderr, exit status 141 (a process killed by SIGPIPE, in a shell);
    it was 1 and a BrokenPipeError."""
    proc = subprocess.Popen(_fosmc("select", "--front", FRONT, "--max-error", "0.1", "--json"), env=ENV,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)  # fmt: skip
    proc.stdout.close()  # before the interpreter has even imported the package
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=120) == 141 and err == "", err


@pytest.mark.slow  # compiles a simulation (~5 s in a fresh process)
def test_simulate_json_into_head_ends_quietly(tmp_path):
    """The issue's `fosmc simulate --json | head`: 2048 rollouts' JSON (about 1.5 MB, past any
    pipe's buffer, so the writer meets the closed pipe), two lines read."""
    config = _write(tmp_path / "c.toml", SHORT + '[plant]\nuncertainty = "sample"\nsamples = 2048\n')
    cmd = " ".join(_fosmc("simulate", "--config", config, "--json")) + " 2> err.txt | head -2"
    done = subprocess.run(["bash", "-o", "pipefail", "-c", cmd], cwd=tmp_path, env=ENV, capture_output=True,
                          text=True, timeout=300)  # fmt: skip
    err = (tmp_path / "err.txt").read_text()
    assert done.stdout.splitlines()[0] == "{" and len(done.stdout.splitlines()) == 2
    assert done.returncode == 141 and "Traceback" not in err and "Error" not in err, err


# ---------------------------------------------------------------------------- Ctrl-C


def _interrupt_after(writes_checkpoint: bool):
    """A stand-in for run_tune / run_front: (optionally) a checkpoint in ``out``, then Ctrl-C."""

    def run(*args, out=None, **kwargs):
        Path(out).mkdir(parents=True, exist_ok=True)
        if writes_checkpoint:
            (Path(out) / "checkpoint.npz").write_bytes(b"state")
        raise KeyboardInterrupt

    return run


@pytest.mark.parametrize("command", ["tune", "front"])
def test_ctrl_c_says_how_to_resume(capsys, tmp_path, monkeypatch, command):
    """Exit status 130 and one line that names the checkpoint and the command that resumes
    from it: the same arguments, --force dropped, --resume added once."""
    monkeypatch.setattr(commands, f"run_{command}", _interrupt_after(True))
    out = tmp_path / "out"
    code, _, err = cli(capsys, command, "--config", "my config.toml", "--out", out, "--force")
    resume = f"fosmc {command} --config 'my config.toml' --out {out} --resume"
    assert code == 130 and err.splitlines() == [
        f"fosmc: interrupted; {out / 'checkpoint.npz'} keeps the work done so far: resume with `{resume}`"
    ]
    code, _, err = cli(capsys, command, "--out", out, "--resume")
    assert code == 130 and err.count("--resume") == 1 and len(err.splitlines()) == 1


def test_ctrl_c_before_the_first_checkpoint_says_there_is_nothing_to_resume(capsys, tmp_path, monkeypatch):
    """No checkpoint, or an earlier run's that --force was about to replace: no resume offered."""
    monkeypatch.setattr(commands, "run_tune", _interrupt_after(False))
    out = tmp_path / "out"
    out.mkdir()
    (out / "checkpoint.npz").write_bytes(b"an earlier run's")
    os.utime(out / "checkpoint.npz", (time.time() - 3600,) * 2)
    code, _, err = cli(capsys, "tune", "--out", out, "--force")
    assert code == 130 and err.splitlines() == [
        f"fosmc: interrupted before the first checkpoint in {out}: nothing to resume, run the command again"
    ]


def test_ctrl_c_elsewhere_is_one_line(capsys, monkeypatch):
    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(commands, "run_bounds", interrupted)
    code, _, err = cli(capsys, "bounds")
    assert code == 130 and err.splitlines() == ["fosmc: interrupted"]


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


def _interrupt(cmd: list[str], ready: Path, progress: str, timeout: float = 300) -> tuple[int, list[str]]:
    """Start ``cmd``, send SIGINT once ``ready`` exists and a stderr line starts with
    ``progress``; (exit status, stderr lines)."""
    env = dict(ENV, JAX_NUM_CPU_DEVICES="1")
    # SIGINT as a terminal delivers it: a test run in the background (`pytest &`) ignores it, and
    # a child would inherit that
    default = "import signal; signal.signal(signal.SIGINT, signal.SIG_DFL)"
    proc = subprocess.Popen(_after(default, cmd), env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    lines, deadline = [], time.monotonic() + timeout
    try:
        for line in proc.stderr:
            lines.append(line.rstrip("\n"))
            if (line.startswith(progress) and ready.exists()) or time.monotonic() > deadline:
                break
        proc.send_signal(signal.SIGINT)
        lines += proc.stderr.read().splitlines()
    finally:
        proc.wait(timeout=120)
    return proc.returncode, lines


@pytest.mark.slow  # two tuning runs and a fresh process (~30 s)
def test_ctrl_c_during_tune_resumes_to_the_uninterrupted_result(tmp_path, capsys):
    config = _write(tmp_path / "c.toml", TINY)
    whole, cut = tmp_path / "whole", tmp_path / "cut"
    code, lines = _interrupt(
        _fosmc("tune", "--config", config, "--out", cut), cut / "checkpoint.npz", "tune: step    3/"
    )
    resume = f"fosmc tune --config {config} --out {cut} --resume"
    assert code == 130 and lines[-1].endswith(f"resume with `{resume}`"), lines[-3:]
    assert not any("Traceback" in line for line in lines)
    assert not (cut / "result.json").exists() and not [p for p in cut.iterdir() if p.name.startswith(".")]
    assert main(resume.split()[1:]) == 0
    assert "resumed from" in capsys.readouterr().err
    assert main(["tune", "--config", str(config), "--out", str(whole)]) == 0
    a, b = (json.loads((d / "result.json").read_text()) for d in (whole, cut))
    assert a["final"] == b["final"] and a["history"]["loss"] == b["history"]["loss"]


@pytest.mark.slow  # a front in a fresh process, up to its first checkpoint (~60 s)
def test_ctrl_c_during_front_leaves_a_checkpoint_to_resume(tmp_path):
    config = _write(tmp_path / "c.toml", TINY)
    cut = tmp_path / "cut"
    cmd = _fosmc("front", "--config", config, "--out", cut, "--budget", "300")  # interrupted long before
    code, lines = _interrupt(cmd, cut / "checkpoint.npz", "front:")
    assert code == 130 and lines[-1].startswith(f"fosmc: interrupted; {cut / 'checkpoint.npz'} keeps"), lines[-3:]
    assert lines[-1].endswith("--resume`") and not any("Traceback" in line for line in lines)
    assert not (cut / "front.json").exists()


# ---------------------------------------------------------------------------- memory (item 2: the refusal)


# The five batches that passed validation and died in NumPy or XLA, and the key each names
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
LIMIT = (16 * 10**9, "a test's 16 GB")


@pytest.mark.parametrize("key", OVERSIZED)
def test_oversized_batch_is_refused_with_the_estimate_the_limit_and_the_key(capsys, tmp_path, monkeypatch, key):
    """Refused in one line that gives the estimate, the limit it was held against and the key,
    before anything is drawn (fj.build) and through the command line; the limit is a fixed 16
    GB here, so that no machine draws these batches."""
    monkeypatch.setattr(memory, "limit", lambda: LIMIT)
    with jax.enable_x64(True), pytest.raises(_config.ConfigError) as e:
        fj.build(OVERSIZED[key])
    message = str(e.value)
    pattern = (rf"{re.escape(key)}: the batch needs at least [\d.]+ GB \(.*\), more than the 16 GB this process "
               rf"may use \(a test's 16 GB\): .*{re.escape(key.split('.')[-1])}.*")  # fmt: skip
    assert re.fullmatch(pattern, message), message
    config = tmp_path / "c.toml"
    config.write_text(_toml(OVERSIZED[key]))
    assert_refused(*cli(capsys, "simulate", "--config", config)[::2], option=key)


def _toml(cfg: dict, prefix: str = "") -> str:
    """A nested dict of tables as TOML (numbers, strings and lists of numbers only)."""
    scalars = {k: v for k, v in cfg.items() if not isinstance(v, dict)}
    text = f"[{prefix}]\n" if prefix and scalars else ""
    text += "".join(f"{k} = {json.dumps(v)}\n" for k, v in scalars.items())
    return text + "".join(_toml(v, f"{prefix}.{k}" if prefix else k) for k, v in cfg.items() if isinstance(v, dict))


def test_oversized_batches_are_refused_under_an_address_space_limit():
    """Under `ulimit -v 12000000` (12 GB of address space, as the issue's campaign ran), in a
    process of its own: each batch refused naming its key and the limit, none drawn."""
    script = (
        "import json, sys, jax\n"
        "jax.config.update('jax_enable_x64', True)\n"
        "import fosmc_jax as fj\n"
        "for cfg in json.loads(sys.argv[1]):\n"
        "    try:\n"
        "        fj.build(cfg)\n"
        "        print('built')\n"
        "    except ValueError as e:\n"
        "        print(e)\n"
    )
    limit = "import resource; resource.setrlimit(resource.RLIMIT_AS, (12 * 10**9, 12 * 10**9))"
    cmd = _after(limit, [sys.executable, "-c", script, json.dumps(list(OVERSIZED.values()))])
    done = subprocess.run(cmd, env=ENV, capture_output=True, text=True, timeout=300)
    lines = done.stdout.splitlines()
    assert done.returncode == 0 and len(lines) == len(OVERSIZED), done.stderr[-2000:]
    for key, line in zip(OVERSIZED, lines):
        # the smaller limit is named: the 12 GB address space, or the machine's available memory
        # where a loaded machine has less than that left
        assert line.startswith(f"{key}: the batch needs at least"), line
        assert "(ulimit -v)" in line or "(the machine's available memory)" in line, line


def test_the_estimate_is_a_lower_bound_of_the_arrays_drawn_and_the_limit_is_a_boundary():
    """The estimate counts at least the plants and initial states build draws (and not a
    thousand times more); a batch of exactly the room left fits, one byte less is refused."""
    cfg = _config.resolve({"plant": {"uncertainty": "sample", "samples": 500}, "sim": {"t_final": 0.01, "dt": 1e-3}})
    need = memory.estimate(cfg)
    with jax.enable_x64(True):
        problem = _config.build(cfg)
    drawn = sum(x.nbytes for x in jax.tree.leaves(problem.plants)) + problem.X0s.nbytes
    assert need.key == "plant.samples" and need.batch == "500 rollout(s) of 500 plant(s)"
    assert drawn <= need.bytes <= 1000 * drawn
    assert memory.refusal(cfg, (need.bytes, "x")) is None
    assert memory.refusal(cfg, (need.bytes - 1, "x")).startswith("plant.samples: the batch needs at least")


@pytest.mark.parametrize("preset", [None, "realistic_arm"])  # small_arm's design takes 20 s to resolve
def test_the_presets_fit(preset):
    """The package's own configs pass the check on this machine (they need a few MB)."""
    cfg = _config.load(preset)
    assert memory.refusal(cfg) is None and memory.estimate(cfg).bytes < 10**8
