"""The second arm preset, end to end (issue 25, item 6): ``fosmc bounds``, ``fosmc front
--budget 120`` and ``fosmc simulate --point`` on ``small_arm``, as a user would run them, and
its front's held-out arms (fresh sampled arms and payloads) within 25% of the training error."""

import json

import numpy as np
import pytest

import fosmc_jax as fj
from fosmc_jax._app.cli import main


@pytest.mark.slow  # resolving [model] from = "arm" compiles the arm's rows: ~10 s
def test_the_small_arm_preset_is_a_different_arm_with_uncertain_friction_and_motors():
    cfg = fj.config.resolve(fj.config.load("small_arm"))
    paper = fj.ARM_PARAMS
    assert cfg["arm"]["m2"] < paper.m2 / 4 and cfg["arm"]["payload_range"] == [0.0, 2.0]
    assert np.all(np.asarray(cfg["arm"]["Kt"]) < np.asarray(paper.Kt) / 2)
    unc = cfg["arm"]["uncertainty"]
    assert {k for k in fj.ArmParams._fields if np.any(np.asarray(unc[k]) > 0)} == {"F", "Kt", "Kb"}
    assert cfg["controller"]["sample_period"] > 0  # a digital loop
    # its training arms are corners of those ranges: the extreme arms (the preset says why)
    kt = fj.config.arm_samples(cfg)["Kt"] / np.asarray(cfg["arm"]["Kt"])
    np.testing.assert_allclose(np.abs(kt - 1), 0.2, rtol=1e-12)


@pytest.mark.slow  # a two-minute front, as the issue asks: ~3 min in all
def test_bounds_front_and_simulate_point_run_on_the_small_arm(tmp_path, capsys):
    assert main(["bounds", "--config", "small_arm", "--json"]) == 0
    bounds = json.loads(capsys.readouterr().out)
    assert bounds["beta"] < 1  # the paper's matching condition holds on this arm's own box
    out = tmp_path / "front"
    assert main(["front", "--config", "small_arm", "--budget", "120", "--out", str(out)]) == 0
    front = json.loads((out / "front.json").read_text())
    assert front["held_out_batch"]["arm_samples"] == 4 and front["held_out_batch"]["arm_seed"] == 1
    ratio = lambda k: np.array([np.mean(p["held_out"][k]) / np.mean(p["metrics"][k]) for p in front["points"]])
    error, chattering = ratio("rms_error"), ratio("chattering_hf")
    # the same parameters chatter alike on held-out arms (median within 5%, every point within
    # 25%), and their error stays within 25% of the training error for nine points in ten and
    # the median (measured at 60 s: 100% and 94% of 290 points, medians 1.000 and 0.964; trained
    # on uniform draws instead: 85% and 43%, joint 3 lost on held-out arms, the preset says why)
    assert abs(np.median(chattering) - 1) < 0.05 and np.all(np.abs(chattering - 1) < 0.25), chattering
    assert np.mean(np.abs(error - 1) <= 0.25) >= 0.9 and abs(np.median(error) - 1) <= 0.25, error
    capsys.readouterr()
    point = len(front["points"]) // 2
    assert main(["simulate", "--config", "small_arm", "--params", str(out / "front.json"),
                 "--point", str(point), "--json"]) == 0  # fmt: skip
    sim = json.loads(capsys.readouterr().out)
    rms = np.mean([r["metrics"]["rms_error"] for r in sim["rollouts"]])
    np.testing.assert_allclose(rms, np.mean(front["points"][point]["metrics"]["rms_error"]), rtol=1e-6)
