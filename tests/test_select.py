"""Choosing a front point (fosmc_jax.search.select, ``fosmc select``) on a committed front: the
point meets the bound and no other point that meets it beats it on the other axis (checked with
plain NumPy on the file), bad bounds and files are one-line errors, and its TOML puts the point's
parameters into a config as ``--params FRONT --point I`` does. File work only: nothing compiles."""

import json
from pathlib import Path

import numpy as np
import pytest

import fosmc_jax.search as fs
from fosmc_jax import _problems as _config
from fosmc_jax._app.cli import main

try:  # Python >= 3.11
    import tomllib
except ModuleNotFoundError:  # pragma: no cover - Python 3.10
    import tomli as tomllib

FRONT = Path(__file__).resolve().parents[1] / "tuning" / "results" / "front_budget_300" / "front.json"


def means(held_out: bool = True) -> tuple[np.ndarray, np.ndarray, dict]:
    """Mean rms_error and chattering_hf of every point of FRONT (over the joints of the stored
    per-joint means over rollouts), with ``held_out`` the larger of the training and held-out
    ones (the file's points all have held-out metrics, none a diverged rollout), and the file."""
    data = json.loads(FRONT.read_text())
    mean = lambda key, k: np.array([np.mean(p[key][k]) for p in data["points"]])
    e, c = mean("metrics", "rms_error"), mean("metrics", "chattering_hf")
    if held_out:
        e, c = np.maximum(e, mean("held_out", "rms_error")), np.maximum(c, mean("held_out", "chattering_hf"))
    return e, c, data


@pytest.mark.parametrize("q", [0.0, 0.1, 0.5, 0.9, 1.0])
@pytest.mark.parametrize("held_out", [True, False])
def test_the_point_meets_the_bound_and_none_that_does_beats_it(q, held_out):
    e, c, data = means(held_out)
    for bounded, other, key in ((e, c, "max_error"), (c, e, "max_chattering")):
        bound = float(np.quantile(bounded, q))
        r = fs.select(FRONT, **{key: bound}, **({} if held_out else {"held_out": False}))
        i = r["index"]
        assert bounded[i] <= bound
        meets = np.flatnonzero(bounded <= bound)
        assert other[i] == other[meets].min() and i == meets[other[meets] == other[i]].min()  # ties: lowest index
        assert r["params"] == data["points"][i]["params"] and r["metrics"] == data["points"][i]["metrics"]
        assert r["mean"] == pytest.approx({"rms_error": e[i], "chattering_hf": c[i]}, rel=1e-12)
        assert r["judged_on"] == ("training and held-out" if held_out else "training")


def test_the_held_out_batch_changes_the_pick():
    """FRONT's held-out chattering is up to 1.5x its training one: at some bound the pick differs,
    and a point whose held-out rollout diverged, or a front without held-out metrics, is judged
    as documented."""
    bounds = np.quantile(means(False)[1], np.linspace(0.05, 0.95, 19))
    picks = [(fs.select(FRONT, max_chattering=b)["index"], fs.select(FRONT, max_chattering=b, held_out=False)["index"])
             for b in bounds]  # fmt: skip
    assert any(a != b for a, b in picks)
    good = {"params": {"delta": [1.0] * 3}, "metrics": {"rms_error": [2.0] * 3, "chattering_hf": [1.0] * 3},
            "held_out": {"rms_error": [2.0] * 3, "chattering_hf": [1.0] * 3}}  # fmt: skip
    fragile = {"params": {"delta": [2.0] * 3}, "metrics": {"rms_error": [1.0] * 3, "chattering_hf": [1.0] * 3},
               "held_out": {"rms_error": [1.0] * 3, "chattering_hf": [1.0] * 3}, "held_out_diverged": 1}  # fmt: skip
    front = {"axes": ["rms_error", "chattering_hf"], "points": [good, fragile]}
    assert fs.select(front, max_chattering=1.0)["index"] == 0
    assert fs.select(front, max_chattering=1.0, held_out=False)["index"] == 1
    lost = dict(fragile, held_out_diverged=0, held_out={"rms_error": [1.0, None, 1.0], "chattering_hf": [1.0] * 3})
    assert fs.select({"points": [good, lost]}, max_chattering=1.0)["index"] == 0  # every held-out rollout diverged
    bare = {"points": [{k: v for k, v in p.items() if k != "held_out"} for p in (good, fragile)]}
    assert fs.select(bare, max_chattering=1.0)["judged_on"] == "training"
    with pytest.raises(ValueError, match="no held-out metrics for every point"):
        fs.select(bare, max_chattering=1.0, held_out=True)


def test_a_loaded_front_selects_as_its_file():
    data = json.loads(FRONT.read_text())
    assert fs.select(data, max_chattering=0.2) == fs.select(str(FRONT), max_chattering=0.2)


def test_ties_go_to_the_lowest_index():
    point = {"params": {"k": [1.0, 1.0, 1.0]}, "metrics": {"rms_error": [1.0] * 3, "chattering_hf": [2.0] * 3}}
    front = {"axes": ["rms_error", "chattering_hf"], "points": [point, point, point]}
    assert fs.select(front, max_error=1.0)["index"] == 0
    assert fs.select(front, max_chattering=2.0)["index"] == 0


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({}, "exactly one of max_error, max_chattering, got neither"),
        ({"max_error": 1.0, "max_chattering": 1.0}, "exactly one"),
        ({"max_error": -1.0}, "max_error: expected a positive finite number"),
        ({"max_chattering": 0.0}, "max_chattering: expected a positive finite number"),
        ({"max_error": float("inf")}, "positive finite"),
        ({"max_error": float("nan")}, "positive finite"),
        (
            {"max_error": 1e-9},
            r"no point of .* has mean rms_error <= 1e-09 rad \(training and held-out\); the least "
            r"is .* rad \(point \d+\)",
        ),
        (
            {"max_chattering": 1e-9},
            r"mean chattering_hf <= 1e-09 V \(training and held-out\); the least is .* V "
            r"\(point \d+\)",
        ),
    ],
)
def test_bad_bounds_are_one_line_errors(kwargs, match):
    with pytest.raises(ValueError, match=match) as info:
        fs.select(FRONT, **kwargs)
    assert "\n" not in str(info.value)


def test_what_is_not_a_front_is_refused_in_one_line(tmp_path):
    (tmp_path / "text.json").write_text("not json")
    (tmp_path / "tune.json").write_text(json.dumps({"final": {"params": {}}}))
    (tmp_path / "empty.json").write_text(json.dumps({"points": []}))
    (tmp_path / "bare.json").write_text(json.dumps({"points": [{"params": {"k": [1.0]}}]}))
    (tmp_path / "other.json").write_text(json.dumps({"axes": ["a", "b"], "points": [{}]}))
    for name, match in [("missing.json", "cannot read"), ("text.json", "is not JSON"),
                        ("tune.json", "is not a fosmc front"), ("empty.json", "a front of no points"),
                        ("bare.json", "every point needs params and per-joint metrics"),
                        ("other.json", "not in")]:  # fmt: skip
        with pytest.raises(ValueError, match=match) as info:
            fs.select(tmp_path / name, max_error=1.0)
        assert "\n" not in str(info.value)


def test_the_toml_puts_the_point_into_a_config_as_params_point_does():
    i = fs.select(FRONT, max_error=0.5)["index"]
    toml = fs.controller_toml(json.loads(FRONT.read_text())["points"][i]["params"])
    assert toml.splitlines()[:2] == ["[controller]", 'kind = "fosmc"']
    pasted = _config.resolve(tomllib.loads(toml))
    assert pasted == _config.with_params(_config.resolve({}), FRONT, i)


def test_the_toml_uses_the_kinds_config_keys():
    toml = tomllib.loads(fs.controller_toml({"k": [1.0, 2.0, 3.0], "phi": [0.1, 1e-5, 2e22]}))
    assert toml == {"controller": {"kind": "smc", "smc_k": [1.0, 2.0, 3.0], "smc_phi": [0.1, 1e-5, 2e22]}}
    with pytest.raises(ValueError, match="no controller kind's parameter set"):
        fs.controller_toml({"zeta": [1.0]})


def test_the_command_prints_the_point_and_its_toml(capsys):
    r = fs.select(FRONT, max_error=0.5)
    assert main(["select", "--front", str(FRONT), "--max-error", "0.5"]) == 0
    out = capsys.readouterr().out
    assert out.startswith(
        f"point {r['index']}: the least mean chattering_hf with mean rms_error <= 0.5 rad "
        "(judged on training and held-out)\n"
    )
    assert f"mean rms_error      {r['mean']['rms_error']:.4e} rad  (training " in out
    assert main(["select", "--front", str(FRONT), "--max-error", "0.5", "--training-only"]) == 0
    r = fs.select(FRONT, max_error=0.5, held_out=False)
    out = capsys.readouterr().out
    assert f"(judged on training)\n  mean rms_error      {r['mean']['rms_error']:.4e} rad\n" in out
    toml = out[out.index("\n[controller]") :]
    assert toml.strip() == fs.controller_toml(r["params"])
    assert tomllib.loads(out[out.index("# point") :])["controller"]["delta"] == r["params"]["delta"]


def test_the_commands_json_is_the_files_point(capsys):
    assert main(["select", "--front", str(FRONT), "--max-chattering", "0.2", "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    point = json.loads(FRONT.read_text())["points"][d["index"]]
    assert d["params"] == point["params"] and d["metrics"] == point["metrics"]
    assert d == json.loads(json.dumps(fs.select(FRONT, max_chattering=0.2)))


@pytest.mark.parametrize("args", [["--max-error", "1e-9"], ["--max-chattering", "-1"]])
def test_the_commands_errors_are_one_line_with_status_2(capsys, args):
    assert main(["select", "--front", str(FRONT), *args]) == 2
    err = capsys.readouterr().err
    assert err.startswith("fosmc: error: ") and err.count("\n") == 1


def test_the_command_takes_exactly_one_bound(capsys):
    for args in ([], ["--max-error", "1", "--max-chattering", "1"]):
        with pytest.raises(SystemExit) as info:
            main(["select", "--front", str(FRONT), *args])
        assert info.value.code == 2
    capsys.readouterr()
