"""``fosmc tune --budget`` (issue 33, item 3): the global stage and the gradient steps share a
wall-time budget counted from the process's start; a budget too short for anything still runs
one step and says so; bad budgets are refused in one line before any work."""

import math

import pytest

import fosmc_jax as fj
from fosmc_jax._app.cli import main

TINY = {
    "plant": {"uncertainty": "sample", "samples": 2},
    "sim": {"t_final": 0.2, "dt": 2e-3, "integrator": "euler"},
    "tune": {"train_dt": 4e-3, "global_candidates": 16},
}


def _cfg():
    return {k: dict(v) for k, v in TINY.items()}


@pytest.mark.slow  # two tuning runs (15 s): the default tier keeps to 4 minutes on 2 cores
def test_a_budget_sizes_the_steps_between_one_and_tune_steps():
    """A budget already spent runs one step (and says the deadline passed before the steps); an
    ample one runs every step of ``tune.steps``: the budget only ever shortens the run."""
    lines = []
    spent = fj.run_tune(_cfg(), steps=4, budget=1e-3, log=lines.append)
    assert len(spent["history"]["loss"]) == 1
    assert any("passed before the gradient steps" in line for line in lines)
    assert any(line.startswith("tune: budget: 1 gradient steps") for line in lines)
    ample = fj.run_tune(_cfg(), steps=3, budget=1e6, log=lambda _: None)
    assert len(ample["history"]["loss"]) == 3
    assert math.isfinite(ample["final"]["metrics"]["rms_error"][0])


@pytest.mark.parametrize("budget", [0.0, -1.0, math.inf, math.nan])
def test_a_budget_that_is_not_a_positive_finite_time_is_refused_before_any_work(budget):
    with pytest.raises(fj.ConfigError, match="--budget: expected a positive, finite number of seconds"):
        fj.run_tune(_cfg(), steps=1, budget=budget)


def test_the_cli_refuses_a_bad_budget_in_one_line(tmp_path, capsys):
    assert main(["tune", "--budget", "inf", "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["fosmc: error: --budget: expected a positive, finite number of seconds, got inf"]
    assert not (tmp_path / "out").exists()
