"""Resume and budgets that keep their word (issue 34, items 4 and 5): a front stopped after any
checkpoint resumes without redoing a finished unit of work and ends at the uninterrupted front;
a budgeted front records its work and a replay redoes it bit for bit; a finished run is left as
it is by ``--resume``; a budget that compilation alone exceeds says so. The slow tier kills
``fosmc front`` processes with SIGKILL at several moments."""

import json
import os
import random
import shutil
import signal
import subprocess
import sys
import time

import pytest

import fosmc_jax as fj
from fosmc_jax import _problems as _config
from fosmc_jax._app.cli import main
from fosmc_jax._io import jsonable
from fosmc_jax._search import front as search_front
from fosmc_jax._search import tune as tuner

TINY = {
    "plant": {"uncertainty": "sample", "samples": 3},
    "sim": {"t_final": 0.3, "dt": 2e-3, "integrator": "euler"},
    "tune": {"train_dt": 4e-3},  # a training surrogate: every stage runs, the plain rounds too
}
TINY_TOML = """
[plant]
uncertainty = "sample"
samples = 3
[sim]
t_final = 0.3
dt = 2e-3
integrator = "euler"
[tune]
train_dt = 4e-3
"""
#: Given sizes with every stage: 4 chunks of global candidates, 2 CMA-ES generations, 3 local and 2 plain rounds.
SIZES = search_front.Settings(search="staged", points=3, candidates=32, steps=3, chunk=8, cma=2, polish=2,
                              checkpoint_every=1)  # fmt: skip


class Crash(Exception):
    pass


class Counted:
    """An evaluator whose compiled chunk counts its calls (the units of work done)."""

    def __init__(self, problem):
        self.evaluator = search_front.Evaluator(problem)
        run = self.evaluator.compiled()
        self.calls = 0

        def counted(p):
            self.calls += 1
            return run(p)

        self.evaluator._run = counted


@pytest.fixture(scope="module")
def problems():
    plain, train, p0 = _config.tuning_problems(_config.resolve(TINY))
    return Counted(train), Counted(plain), p0


def _strip(result):
    """A front without its wall time (the only number a clock may change)."""
    return json.dumps({**result, "stages": {**result["stages"], "wall_time_s": 0}})


def _run(problems, settings, **kw):
    train, plain, p0 = problems
    train.calls = plain.calls = 0
    r = search_front.front_search(train.evaluator, plain.evaluator, p0, settings, **kw)
    return r, train.calls + plain.calls


@pytest.fixture(scope="module")
def whole(problems):
    """The uninterrupted front of :data:`SIZES` and its units of work (evaluated chunks)."""
    return _run(problems, SIZES, log=lambda _: None)


# after the k-th checkpoint: 2 and 4 inside the global stage (4: its last chunk), 5 at its end,
# 6 after the first CMA-ES generation, 9 after the first local round, 12 after the plain
# evaluation, 13 after the first plain round; two in the default tier, all in the slow one
SLOW_STOPS = [(4, "global"), (5, "cma"), (9, "local"), (12, "polish"), (13, "polish")]


@pytest.mark.parametrize("k, stage", [(2, "global"), (6, "cma"),
                                      *(pytest.param(*c, marks=pytest.mark.slow) for c in SLOW_STOPS)])  # fmt: skip
def test_a_front_stopped_after_any_checkpoint_resumes_to_the_uninterrupted_front(problems, whole, tmp_path,
                                                                                 monkeypatch, k, stage):  # fmt: skip
    _stop_and_resume(problems, SIZES, whole, tmp_path / "checkpoint.npz", monkeypatch, k, stage)


def _stop_and_resume(problems, settings, whole, checkpoint, monkeypatch, k, stage):
    """Stop a front of ``settings`` after its k-th checkpoint (written in ``stage``), resume it:
    it ends bit for bit at the uninterrupted front ``whole`` (its result and units of work)
    without doing a finished unit of work twice."""
    front, work = whole
    save, saved = tuner._save, []

    def crash_after_k(path, header, arrays):
        save(path, header, arrays)
        saved.append(header["stage"])
        if len(saved) == k:
            raise Crash

    monkeypatch.setattr(tuner, "_save", crash_after_k)
    train, plain, _ = problems
    with pytest.raises(Crash):
        _run(problems, settings, checkpoint=checkpoint, log=lambda _: None)
    before = train.calls + plain.calls
    assert saved[-1] == stage
    monkeypatch.setattr(tuner, "_save", save)
    lines = []
    resumed, after = _run(problems, settings, checkpoint=checkpoint, resume=True, log=lines.append)
    assert lines[0].startswith(f"front: resumed from {checkpoint} at ")
    assert _strip(resumed) == _strip(front)  # bit for bit
    assert before + after == work  # no finished unit of work done twice


#: NSGA-II's given sizes (``--search nsga2``): 3 generations of 16 (one call each), then 2 plain rounds.
NSGA2 = search_front.Settings(search="nsga2", population=16, generations=3, points=3, chunk=8, polish=2,
                              checkpoint_every=1)  # fmt: skip


@pytest.mark.parametrize("k, stage", [(2, "nsga2"), pytest.param(4, "polish", marks=pytest.mark.slow)])
def test_an_nsga2_front_stopped_after_a_checkpoint_resumes_bit_for_bit(problems, tmp_path, monkeypatch, k, stage):
    """Stopped after its second generation (pymoo's algorithm pickled whole) or after the plain
    evaluation: resumed, it asks for the same generations, ends at the same front and redoes no
    finished chunk."""
    whole = _run(problems, NSGA2, log=lambda _: None)
    st = whole[0]["stages"]
    assert st["search"] == "nsga2" and st["nsga2_generations"] == 3 and st["evaluations"] == 3 * 16
    assert st["from_nsga2"] + st["from_plain_rounds"] == len(whole[0]["points"]) and st["from_nsga2"] > 0
    _stop_and_resume(problems, NSGA2, whole, tmp_path / "c.npz", monkeypatch, k, stage)
    with pytest.raises(ValueError, match="is of the nsga2 search, not of staged: resume with that search"):
        _run(problems, SIZES, checkpoint=tmp_path / "c.npz", resume=True, log=lambda _: None)


# on the training surrogate, the plain evaluation of the steps' points is sized by the clock too
@pytest.mark.parametrize("gradient_on", ["plain", pytest.param("train", marks=pytest.mark.slow)])
def test_a_budgeted_nsga2_front_replays_bit_for_bit(problems, gradient_on):
    """NSGA-II's generations from the budget, then gradient steps (their share of it): the work
    is recorded and its replay, without a clock, ends at the same front."""
    lines = []
    settings = search_front.Settings(search="nsga2", population=16, points=3, chunk=8, budget=3.0,
                                     gradient_on=gradient_on)  # fmt: skip
    budgeted, _ = _run(problems, settings, log=lines.append)
    rec = budgeted["stages"]["replay"]
    assert rec["search"] == "nsga2" and rec["population"] == 16 and rec["nsga2_generations"] >= 1
    assert rec["local_rounds"] == rec["cma_generations"] == 0 and rec["gradient_steps"] >= 1
    assert rec["gradient_on"] == gradient_on and (rec["gradient_plain"] >= 1) == (gradient_on == "train")
    replayed, _ = _run(problems, search_front.replay_settings(budgeted["stages"]), log=lines.append)
    assert _strip(replayed) == _strip(budgeted)
    assert not [line for line in lines if "s left)" in line and "(-" in line]


@pytest.mark.slow  # a budgeted run and its replay (6-20 s): the default tier keeps its 4 minutes
def test_a_budgeted_front_replays_bit_for_bit(problems):
    lines = []
    budgeted, _ = _run(
        problems,
        search_front.Settings(search="staged", points=3, chunk=8, budget=3.0, checkpoint_every=1),
        log=lines.append,
    )
    rec = budgeted["stages"]["replay"]
    assert rec["probe"] and rec["evaluated"] + 8 == budgeted["stages"]["candidates"]
    assert rec["local_rounds"] == budgeted["stages"]["local_rounds"]  # how many: the load decides
    replayed, _ = _run(problems, search_front.replay_settings(budgeted["stages"]), log=lines.append)
    assert _strip(replayed) == _strip(budgeted)
    # no time left below zero, whatever the load
    assert not [line for line in lines if "s left)" in line and "(-" in line]
    assert not [line for line in lines if "search ends -" in line]


@pytest.mark.slow  # a budgeted run, resumed, and its replay (~10 s)
def test_a_resumed_budgeted_front_replays_to_its_front(problems, tmp_path, monkeypatch):
    """Stopped at the end of its CMA-ES stage (the stage boundaries are checkpointed whatever
    the time since the last), resumed: its recorded work, replayed, gives its front."""
    settings = search_front.Settings(search="staged", points=3, chunk=8, budget=3.0, checkpoint_every=1)
    save = tuner._save

    def crash_at_local(path, header, arrays):
        save(path, header, arrays)
        if header["stage"] == "local":
            raise Crash

    monkeypatch.setattr(tuner, "_save", crash_at_local)
    with pytest.raises(Crash):
        _run(problems, settings, checkpoint=tmp_path / "c.npz", log=lambda _: None)
    monkeypatch.setattr(tuner, "_save", save)
    lines = []
    resumed, _ = _run(problems, settings, checkpoint=tmp_path / "c.npz", resume=True, log=lines.append)
    assert lines[0].endswith("at local round 0")
    replayed, _ = _run(problems, search_front.replay_settings(resumed["stages"]), log=lambda _: None)
    assert _strip(replayed) == _strip(resumed)


def test_a_budget_compilation_alone_exceeds_says_so_in_one_line(problems):
    lines = []
    r, _ = _run(problems, search_front.Settings(search="staged", points=3, chunk=8, budget=0.0), log=lines.append)
    short = [line for line in lines if "warning: --budget" in line]
    assert len(short) == 1 and "s of search after" in short[0]
    serve = int(short[0].split("a budget of ")[1].split(" s")[0])
    assert serve >= search_front.MIN_SEARCH_S
    end = [line for line in lines if "the search ends" in line]
    assert len(end) == 1 and "after the run's deadline: the budget is shorter than compilation" in end[0]
    assert r["stages"]["replay"]["local_rounds"] == 0 and len(r["points"]) >= 1


def test_replay_settings_refuse_a_front_without_recorded_work():
    with pytest.raises(ValueError, match="stages.replay: this front.json does not record its work"):
        search_front.replay_settings({"candidates": 16, "local_rounds": 3})


@pytest.fixture
def finished(tmp_path):
    """An output folder as a finished ``fosmc front`` leaves it: front.json (its points left
    out: ``--resume`` reads the config only), front.png, checkpoint.npz."""
    config = tmp_path / "c.toml"
    config.write_text(TINY_TOML)
    out = tmp_path / "out"
    out.mkdir()
    cfg = _config.load(config)
    front = {"axes": list(search_front.AXES), "points": [], "stages": {"replay": {}}, "config": jsonable(cfg.as_dict())}
    (out / "front.json").write_text(json.dumps(front, indent=1))
    (out / "front.png").write_bytes(b"png")
    (out / "checkpoint.npz").write_bytes(b"npz")
    return config, out


def test_resume_on_a_finished_front_says_so_and_changes_nothing(finished, capsys):
    config, out = finished
    capsys.readouterr()
    before = {p.name: (p.read_bytes(), p.stat().st_mtime_ns) for p in out.iterdir()}
    t = time.perf_counter()
    assert main(["front", "--config", str(config), "--out", str(out), "--resume"]) == 0
    assert time.perf_counter() - t < 10  # nothing compiled
    err = capsys.readouterr().err
    assert f"front: {out / 'front.json'} is complete (nothing to resume)" in err
    assert {p.name: (p.read_bytes(), p.stat().st_mtime_ns) for p in out.iterdir()} == before


def test_resume_on_a_finished_tune_says_so_and_changes_nothing(finished):
    config, out = finished
    (out / "front.json").rename(out / "result.json")
    before = {p.name: (p.read_bytes(), p.stat().st_mtime_ns) for p in out.iterdir()}
    lines = []
    done = fj.run_tune(str(config), out=out, resume=True, log=lines.append)
    assert lines == [f"tune: {out / 'result.json'} is complete (nothing to resume): left as it is; --force starts "
                     "afresh"]  # fmt: skip
    assert done == json.loads((out / "result.json").read_text())
    assert {p.name: (p.read_bytes(), p.stat().st_mtime_ns) for p in out.iterdir()} == before


def test_resume_refuses_a_finished_run_of_another_config_and_resume_with_force(finished, tmp_path, capsys):
    config, out = finished
    other = tmp_path / "other.toml"
    other.write_text(TINY_TOML.replace("samples = 3", "samples = 4"))
    before = (out / "front.json").read_bytes()
    assert main(["front", "--config", str(other), "--out", str(out), "--resume"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("fosmc: error: --resume: ") and "is a complete run of another config" in err
    assert (out / "front.json").read_bytes() == before
    for command in ("front", "tune"):
        assert main([command, "--config", str(config), "--out", str(out), "--resume", "--force"]) == 2
        assert capsys.readouterr().err.startswith("fosmc: error: --resume: ")
    assert (out / "front.json").read_bytes() == before


def test_replay_refuses_a_config_beside_it_and_a_file_without_recorded_work(finished, tmp_path, capsys):
    config, out = finished
    assert (
        main(["front", "--replay", str(out / "front.json"), "--config", str(config), "--out", str(tmp_path / "a")]) == 2
    )
    assert capsys.readouterr().err.strip() == ("fosmc: error: --replay: takes the config and sizes from its "
                                               "front.json: leave out --config")  # fmt: skip
    old = json.loads((out / "front.json").read_text())
    del old["stages"]["replay"]  # as a front written before the work was recorded
    (tmp_path / "old.json").write_text(json.dumps(old))
    assert main(["front", "--replay", str(tmp_path / "old.json"), "--out", str(tmp_path / "b")]) == 2
    assert "stages.replay: this front.json does not record its work" in capsys.readouterr().err
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


# ---------------------------------------------------------------------------- SIGKILL, in the slow tier


def _run_until(cmd, env, checkpoint, after_s=None):
    """Run ``cmd``; with ``after_s``, SIGKILL it that long after ``checkpoint`` first appears
    (the search under way, compilation done). Returns (killed, seconds from the checkpoint's
    appearance to the end)."""
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
    while proc.poll() is None and not checkpoint.exists():
        time.sleep(0.01)
    seen = time.perf_counter()
    try:
        proc.wait(timeout=after_s)
        return False, time.perf_counter() - seen
    except subprocess.TimeoutExpired:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        return True, time.perf_counter() - seen


@pytest.fixture(scope="module")
def subprocess_env():
    # one device, as an uninterrupted run here and its resumed copy must share the same split
    return dict(os.environ, JAX_NUM_CPU_DEVICES="1", PYTHONPATH=os.getcwd())


@pytest.mark.slow  # 6 front processes of given sizes and 6 resumes (5 min on 2 cores at load 6)
def test_fronts_killed_with_sigkill_at_five_random_moments_resume_to_the_uninterrupted_one(tmp_path, subprocess_env):
    config = tmp_path / "c.toml"
    config.write_text(TINY_TOML)
    sizes = ["--config", str(config), "--candidates", "320", "--steps", "60", "--points", "3"]
    whole = tmp_path / "whole"
    _, work = _run_until([sys.executable, "-m", "fosmc_jax", "front", *sizes, "--out", str(whole)], subprocess_env,
                         whole / "checkpoint.npz")  # fmt: skip
    front = _strip(json.loads((whole / "front.json").read_text()))
    rng = random.Random(34)
    for i in range(5):
        out = tmp_path / f"killed{i}"
        cmd = [sys.executable, "-m", "fosmc_jax", "front", *sizes, "--out", str(out)]
        frac = rng.uniform(0.0, 0.8)
        # a run faster than the first (its programs now in the compilation cache, less load) may end,
        # or write front.json and be killed on its way out, before its kill: again, earlier
        for _ in range(4):
            killed, took = _run_until(cmd, subprocess_env, out / "checkpoint.npz", frac * work)
            if killed and not (out / "front.json").exists():
                break
            shutil.rmtree(out)
            work, frac = min(work, took), frac / 2
        assert killed and not (out / "front.json").exists(), f"kill {i}: the run ended first 4 times ({work:.1f} s)"
        subprocess.run(cmd + ["--resume"], env=subprocess_env, check=True, capture_output=True)
        assert _strip(json.loads((out / "front.json").read_text())) == front, f"kill {i}"
        # a temporary a SIGKILL cut off mid-write is removed by the next run into the folder
        assert not [p for p in out.iterdir() if p.name.startswith(".")]
    # and --resume on the finished run leaves it byte for byte
    before = (whole / "front.json").read_bytes()
    subprocess.run([sys.executable, "-m", "fosmc_jax", "front", *sizes, "--out", str(whole), "--resume"],
                   env=subprocess_env, check=True, capture_output=True)  # fmt: skip
    assert (whole / "front.json").read_bytes() == before


@pytest.mark.slow  # 2 budgeted front processes, killed, resumed and replayed (3 min on 2 cores at load 6)
def test_budgeted_fronts_killed_with_sigkill_replay_to_their_resumed_fronts(tmp_path, subprocess_env):
    config = tmp_path / "c.toml"
    config.write_text(TINY_TOML)
    args = ["--config", str(config), "--budget", "25", "--points", "3"]
    rng = random.Random(35)
    for i in range(2):
        out = tmp_path / f"killed{i}"
        cmd = [sys.executable, "-m", "fosmc_jax", "front", *args, "--out", str(out)]
        killed, _ = _run_until(cmd, subprocess_env, out / "checkpoint.npz", rng.uniform(0.0, 5.0))
        assert killed
        subprocess.run(cmd + ["--resume"], env=subprocess_env, check=True, capture_output=True)
        resumed = json.loads((out / "front.json").read_text())
        replay = tmp_path / f"replay{i}"
        subprocess.run([sys.executable, "-m", "fosmc_jax", "front", "--replay", str(out / "front.json"), "--out",
                        str(replay)], env=subprocess_env, check=True, capture_output=True)  # fmt: skip
        assert _strip(json.loads((replay / "front.json").read_text())) == _strip(resumed), f"kill {i}"


@pytest.mark.slow  # 5 tuning processes (~2 min on 2 cores)
def test_a_tune_killed_with_sigkill_resumes_to_the_uninterrupted_result_json(tmp_path, subprocess_env):
    """With a global stage: the resumed run keeps the start it found (result.json's ``start``),
    so the whole result.json is the uninterrupted run's."""
    config = tmp_path / "c.toml"
    config.write_text(TINY_TOML + 'global_candidates = 16\nsteps = 12\ncheckpoint_every = 1\nmode = "reverse"\n')
    whole = tmp_path / "whole"
    tune = [sys.executable, "-m", "fosmc_jax", "tune", "--config", str(config), "--out"]
    subprocess.run(tune + [str(whole)], env=subprocess_env, check=True, capture_output=True)
    result = json.loads((whole / "result.json").read_text())
    assert result["start"]["global_candidates"] == 16
    rng = random.Random(36)
    for i in range(2):
        out = tmp_path / f"killed{i}"
        step = rng.randint(2, 11)  # killed as it says it has done this step (its checkpoint written or not)
        proc = subprocess.Popen(tune + [str(out)], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                                env=subprocess_env)  # fmt: skip
        for line in proc.stderr:
            if line.startswith(f"tune: step {step:4d}/"):
                os.kill(proc.pid, signal.SIGKILL)
                break
        proc.wait()
        assert proc.returncode == -signal.SIGKILL and not (out / "result.json").exists()
        subprocess.run(tune + [str(out), "--resume"], env=subprocess_env, check=True, capture_output=True)
        assert json.loads((out / "result.json").read_text()) == result, f"kill at step {step}"
