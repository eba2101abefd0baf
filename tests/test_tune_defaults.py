"""``fosmc tune`` and ``fosmc front`` on their defaults (issue 24, item 5): a batch of one plant
draws a warning that the optimum holds for that plant only, their log lines name their own
command, and tune reports the metrics its objective uses, with their units."""

import json
import warnings

import pytest

import fosmc_jax as fj
from fosmc_jax import _problems as _config
from fosmc_jax._app import commands
from fosmc_jax._app.cli import main
from fosmc_jax._io import versions

SHORT = {"sim": {"t_final": 0.1, "dt": 2e-3, "integrator": "euler"}}
# the default config's one nominal plant, a short horizon: a global stage of 16, two steps
NOMINAL = dict(SHORT, tune={"mode": "reverse", "global_candidates": 16, "steps": 2})
UNCERTAIN = dict(NOMINAL, plant={"uncertainty": "sample", "samples": 3})


@pytest.mark.parametrize(
    "plant, one",
    [
        ({}, "the nominal linear model"),  # the default config's
        ({"uncertainty": "fixed", "dA_rows": [[0.1] * 9] * 3}, "plus plant.dA_rows"),
        ({"uncertainty": "sample", "samples": 1}, "one plant of the box"),
        ({"uncertainty": "sample", "samples": 3}, None),
        ({"uncertainty": "vertices", "samples": 4}, None),
        ({"kind": "arm", "payloads": [5.0]}, "the arm with a 5 kg payload"),
        ({"kind": "arm", "payloads": [5.0, 5.0]}, "the arm with a 5 kg payload"),
        ({"kind": "arm"}, None),  # 0 and 10 kg
    ],
)
def test_one_plant_rule(plant, one):
    cfg = _config.resolve({"plant": plant})
    assert (commands.one_plant(cfg) is None) if one is None else (one in commands.one_plant(cfg))


def test_a_box_of_zero_width_is_one_plant():
    box = _config.resolve({})["plant"]["box"]
    flat = {"A_lower": box["A_lower"], "A_upper": box["A_lower"], "B_lower": box["B_lower"], "B_upper": box["B_lower"]}
    cfg = _config.resolve({"plant": {"uncertainty": "vertices", "samples": 8, "box": flat}})
    assert commands.one_plant(cfg) == "one plant of the box"


def test_offsets_and_noise_do_not_make_a_plant_uncertain():
    cfg = _config.resolve({"sim": {"initial_offset": [[0.0] * 9, [0.01] + [0.0] * 8]},
                           "controller": {"sample_period": 1e-3},
                           "sensors": {"noise_std": [1e-4] + [0.0] * 8, "realizations": 4}})  # fmt: skip
    assert commands.one_plant(cfg) == "the nominal linear model"


class _Stop(Exception):
    pass


def _stop(*args, **kwargs):
    raise _Stop


@pytest.mark.parametrize("config, warned", [(NOMINAL, True), (UNCERTAIN, False)])
def test_the_warning_is_for_one_plant_only(monkeypatch, config, warned):
    """Both commands warn before any simulation: stopped where their problems would be built."""
    from fosmc_jax._app import study

    monkeypatch.setattr(_config, "tuning_problems", _stop)
    monkeypatch.setattr(study, "study", _stop)
    for command, run in (("tune", fj.run_tune), ("front", fj.run_front)):
        with warnings.catch_warnings(record=True) as caught, pytest.raises(_Stop):
            warnings.simplefilter("always")
            run(config)
        ours = [w for w in caught if issubclass(w.category, UserWarning) and "one plant" in str(w.message)]
        assert len(ours) == int(warned), command
        if warned:
            message = str(ours[0].message)
            assert message.startswith(f"{command}: ") and "the nominal linear model" in message
            assert "uncertainty = 'sample'" in message and "payloads" in message  # how to add uncertainty
            assert ours[0].filename == __file__  # points at the caller


def test_the_command_line_shows_the_warning_as_one_line(monkeypatch, capsys, tmp_path):
    monkeypatch.setattr(_config, "tuning_problems", _stop)
    path = tmp_path / "c.toml"
    path.write_text("[sim]\nt_final = 0.1\n")
    with pytest.raises(_Stop):
        main(["tune", "--config", str(path), "--out", str(tmp_path / "out")])
    lines = [x for x in capsys.readouterr()[1].splitlines() if "warning" in x]
    assert len(lines) == 1 and lines[0].startswith("fosmc: warning: tune: the config's batch holds one plant")


@pytest.fixture(scope="module")
def tuned(tmp_path_factory):
    """A real tune of the nominal plant, 50 steps of 2 ms: its warning, log lines and files."""
    out = tmp_path_factory.mktemp("tune")
    lines = []
    with pytest.warns(UserWarning, match="one plant"):
        result = fj.run_tune(NOMINAL, out=out, log=lines.append)
    return result, lines, out


@pytest.mark.slow  # a real (tiny) run: 10-14 s of compilation
def test_tune_logs_name_tune_and_the_objectives_metrics(tuned):
    result, lines, _ = tuned
    assert lines and all(line.startswith("tune: ") for line in lines), [x for x in lines if not x.startswith("tune")]
    assert any(line.startswith("tune: global stage 16/16") for line in lines)  # the global stage's own lines
    steps = [line for line in lines if line.startswith("tune: step ")]
    assert len(steps) == 2 and all("rms_error term" in x and "chattering_hf term" in x for x in steps)
    (objective,) = [line for line in lines if line.startswith("tune: objective ")]
    assert "rms_error (rad)" in objective and "chattering_hf (V)" in objective
    assert result["objective"]["chattering_metric"] == "chattering_hf"


@pytest.mark.slow  # a real (tiny) run: 10-14 s of compilation
def test_tune_prints_the_metrics_it_optimises_with_their_units(tuned, monkeypatch, capsys):
    result = tuned[0]
    monkeypatch.setattr(commands, "run_tune", lambda *a, **k: result)  # the printing only
    assert main(["tune", "--steps", "2"]) == 0
    rows = capsys.readouterr()[0].splitlines()
    assert [r.split("  initial")[0].rstrip() for r in rows] == [
        "rms_error (rad)", "chattering_hf (V)", "chattering (V/s, total variation), not in the objective"]  # fmt: skip
    final = result["final"]["metrics"]["chattering_hf"]
    assert rows[1].split("final ")[1].split() == [f"{x:.4e}" for x in final]


@pytest.mark.slow  # a real (tiny) run: 10-14 s of compilation
def test_tune_result_carries_the_versions_and_resimulates(tuned, capsys):
    result, _, out = tuned
    written = json.loads((out / "result.json").read_text())
    assert list(written)[0] == "fosmc_jax" and written["fosmc_jax"] == versions() == result["fosmc_jax"]
    cfg = _config.with_params(_config.resolve(NOMINAL), out / "result.json")  # the reader takes the new key
    assert cfg["controller"]["delta"] == pytest.approx(result["final"]["params"]["delta"])


@pytest.fixture(scope="module")
def fronted(tmp_path_factory):
    """A real front of the nominal plant, given sizes (16 candidates, one local round)."""
    out = tmp_path_factory.mktemp("front")
    lines = []
    with pytest.warns(UserWarning, match="one plant"):
        result = fj.run_front(SHORT, out=out, candidates=16, steps=1, points=3, log=lines.append)
    return result, lines, out


@pytest.mark.slow  # a real (tiny) run: 10-14 s of compilation
def test_front_logs_name_front_and_its_file_carries_the_versions(fronted):
    result, lines, out = fronted
    assert lines and all(line.startswith("front: ") for line in lines), [x for x in lines if not x.startswith("front")]
    written = json.loads((out / "front.json").read_text())
    assert list(written)[0] == "fosmc_jax" and written["fosmc_jax"] == versions() == result["fosmc_jax"]
    cfg = _config.with_params(_config.resolve(SHORT), out / "front.json", 0)  # the reader takes the new key
    assert cfg["controller"]["delta"] == pytest.approx(result["points"][0]["params"]["delta"])
