"""tuning/research_example.py (a research script from the README alone: a Monte Carlo, a
gradient checked against central differences, a front point chosen by bound) runs on a short
horizon and writes sane numbers; the README's first example runs as written."""

import importlib.util
import json
import math
import re
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "tuning" / "research_example.py"


def load_script():
    spec = importlib.util.spec_from_file_location("research_example", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.slow  # ~60 s on 2 cores, most of it the reverse mode's compilation
def test_research_example_runs_on_a_short_horizon(tmp_path):
    script = load_script()
    out = tmp_path / "out"
    summary = script.main(["--t-final", "0.1", "--samples", "16", "--budget", "10", "--out", str(out)])
    for name in ("summary.json", "summary.md", "front/front.json", "front/front.png"):
        assert (out / name).is_file(), name
    assert json.loads((out / "summary.json").read_text())["samples"] == 16

    mc = summary["monte_carlo"]  # 16 paired rollouts: payloads and offsets drawn
    assert mc["rollouts"] == 16 and mc["diverged_excluded"] == 0
    for name in ("rms_error", "chattering_hf"):
        p5, p50, p95 = (np.asarray(mc[q][name]) for q in ("p5", "p50", "p95"))
        assert np.all(np.isfinite(p95)) and np.all(p5 > 0) and np.all(p5 <= p50) and np.all(p50 <= p95)
    assert np.all(np.asarray(mc["p95"]["rms_error"]) < 0.1)  # rad: the preset tracks

    g = summary["gradient"]
    for case in ("preset", "no_rounding"):
        assert np.all(np.isfinite(g[case]["grad"])) and np.any(np.asarray(g[case]["grad"]) != 0)
    # Without the encoder's rounding the loss is smooth: reverse mode equals central differences
    # at a relative step of 1e-4 to the script's tolerance (1e-3 of the largest component;
    # typically 1e-8). With the rounding, a secant over 30% of delta: same signs, same scale.
    assert g["no_rounding"]["max_relative_gap"] <= script.TOLERANCE
    grad, secant = np.asarray(g["preset"]["grad"]), np.asarray(g["preset"]["central"])
    assert np.all(np.sign(grad) == np.sign(secant)) and g["preset"]["max_relative_gap"] < 0.5

    f = summary["front"]
    sel = f["selected"]
    front = json.loads((out / "front" / "front.json").read_text())
    point = front["points"][sel["index"]]
    assert f["points"] == len(front["points"]) >= 1
    assert sel["mean"]["rms_error"] <= f["max_error"]
    held = float(np.mean(point["held_out"]["rms_error"]))  # judged on the larger of training and held-out
    assert math.isclose(
        sel["mean"]["rms_error"], max(float(np.mean(point["metrics"]["rms_error"])), held), rel_tol=1e-12
    )
    assert "delta" in f["controller_toml"]


def readme_first_example() -> str:
    """The README's first Python block (its first screen: a simulation, a tune, a gradient)."""
    text = (ROOT / "README.md").read_text()
    return re.search(r"```python\n(.*?)```", text[: text.index("## The commands")], re.S).group(1)


@pytest.mark.slow  # ~30 s on 2 cores: three compilations
def test_readme_first_example_runs(capsys):
    scope: dict = {}
    exec(compile(readme_first_example(), "README.md", "exec"), scope)
    assert scope["res"].metrics.rms_error.shape == (8, 3) and int(scope["res"].survivors) == 8
    initial = np.asarray(scope["res"].mean().rms_error)
    final = np.asarray(scope["tuned"]["final"]["metrics"]["rms_error"])
    assert np.all(np.isfinite(final)) and final.mean() < initial.mean()
    printed = capsys.readouterr().out.splitlines()
    assert len(printed) == 3 and all("nan" not in line for line in printed)
