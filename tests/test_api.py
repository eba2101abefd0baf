"""One function per command (fosmc_jax.run_*): the command line's JSON (or files) equals the
function's result, configs may be paths, dicts or resolved configs, and bad input raises the
command line's one-line error as a ConfigError."""

import json

import numpy as np
import pytest

import fosmc_jax as fj
from fosmc_jax import _problems as _config
from fosmc_jax._app.cli import main
from fosmc_jax._design import paper as _paper
from fosmc_jax._io import jsonable

SHORT = {"sim": {"t_final": 0.05, "dt": 1e-3, "initial_offset": [[0.0] * 9, [0.01] + [0.0] * 8]}}
SHORT_TOML = """
[sim]
t_final = 0.05
dt = 1e-3
initial_offset = [[0, 0, 0, 0, 0, 0, 0, 0, 0], [0.01, 0, 0, 0, 0, 0, 0, 0, 0]]
"""
# a few optimizer steps on 3 sampled plants, 0.3 s: tune and front share these compilations
TINY = {"plant": {"uncertainty": "sample", "samples": 3}, "sim": {"t_final": 0.3, "dt": 2e-3, "integrator": "euler"}}
TINY_TOML = """
[plant]
uncertainty = "sample"
samples = 3
[sim]
t_final = 0.3
dt = 2e-3
integrator = "euler"
[tune]
mode = "reverse"
global_candidates = 4
"""


def as_json(result) -> dict:
    return json.loads(json.dumps(jsonable(result)))


def cli(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture
def toml(tmp_path):
    def write(text: str):
        path = tmp_path / "c.toml"
        path.write_text(text)
        return str(path)

    return write


def test_public_names():
    for name in ("run_simulate", "run_bounds", "run_reproduce", "run_certify", "run_tune", "run_front"):
        assert name in fj.__all__ and callable(getattr(fj, name))


@pytest.mark.slow  # 6 s: the default tier keeps to 4 minutes on 2 cores
def test_simulate_equals_cli_json_for_path_dict_and_resolved_config(capsys, toml):
    path = toml(SHORT_TOML)
    code, out, _ = cli(capsys, "simulate", "--config", path, "--json")
    assert code == 0
    expected = json.loads(out)
    assert as_json(fj.run_simulate(path)) == expected
    assert as_json(fj.run_simulate(SHORT)) == expected
    resolved = _config.resolve(SHORT)
    assert as_json(fj.run_simulate(resolved)) == expected
    assert resolved == _config.resolve(SHORT)  # the caller's config is not changed
    r = fj.run_simulate(SHORT, keep_trace=True)
    assert r["trace"].X.shape[0] == 2 and r["config"]["sim"]["save_every"] >= 1


def test_bounds_equals_cli_json(capsys, toml):
    A = _paper.A_ROWS
    text = f"""
[plant.box]
A_lower = {(A - 0.5 * (np.abs(A) > 20)).tolist()}
A_upper = {(A + 0.5 * (np.abs(A) > 20)).tolist()}
"""
    path = toml(text)
    code, out, _ = cli(capsys, "bounds", "--config", path, "--json")
    assert code == 0
    assert as_json(fj.run_bounds(path)) == json.loads(out)


@pytest.mark.slow  # the exact certificate over the box, twice (~8 s)
def test_certify_equals_cli_json(capsys):
    code, out, _ = cli(capsys, "certify", "--json", "--vertices", "4", "--seed", "3")
    assert code == 0
    assert as_json(fj.run_certify(None, vertices=4, seed=3)) == json.loads(out)


@pytest.mark.slow  # two tuning runs with a global stage (~25 s on 2 cores)
def test_tune_equals_cli_result_json(capsys, toml, tmp_path):
    path, out_dir = toml(TINY_TOML), tmp_path / "tune"
    code, out, _ = cli(capsys, "tune", "--config", path, "--steps", "2", "--out", str(out_dir))
    assert code == 0 and (out_dir / "tuning.png").exists() and (out_dir / "checkpoint.npz").exists()
    written = json.loads((out_dir / "result.json").read_text())
    r = fj.run_tune(path, steps=2)
    assert as_json(r) == written
    assert r["start"]["global_candidates"] == 4 and len(r["history"]["loss"]) == 2
    # the printed lines come from the same result
    first = out.splitlines()[0]
    assert first.startswith("rms_error (rad)") and f"initial {r['initial']['metrics']['rms_error'][0]:.4e}" in first


@pytest.mark.slow  # two front studies (~20 s on 2 cores)
def test_front_equals_cli_front_json(capsys, tmp_path):
    path, out_dir = tmp_path / "c.toml", tmp_path / "front"
    path.write_text(TINY_TOML.split("[tune]")[0])
    opts = ("--points", "3", "--candidates", "16", "--steps", "2", "--budget", "60")
    code, _, err = cli(capsys, "front", "--config", str(path), "--out", str(out_dir), *opts)
    assert code == 0, err
    written = json.loads((out_dir / "front.json").read_text())
    r = as_json(fj.run_front(TINY, points=3, candidates=16, steps=2, budget=60))
    for d in (written, r):
        d["stages"].pop("wall_time_s")  # the only field that is not a function of the inputs
    assert r == written


@pytest.mark.slow  # every reproduction case group compiled twice, figures drawn (~45 s)
def test_reproduce_equals_cli_files(capsys, tmp_path):
    out_dir = tmp_path / "rep"
    opts = ("--plant", "linear", "--t-final", "0.05", "--dt", "1e-3", "--integrator", "euler")
    code, out, _ = cli(capsys, "reproduce", "--out", str(out_dir), *opts)
    assert code == 0
    r = fj.run_reproduce(plant="linear", t_final=0.05, dt=1e-3, integrator="euler")
    assert set(r["files"]) == {"metrics.csv", "metrics.md", "design.md", "metrics_short.csv"}
    for name, text in r["files"].items():
        assert (out_dir / name).read_text() == text
    assert out.strip() == r["files"]["metrics.md"].strip() and r["figures"] == []
    assert len(r["rows"]["metrics"]) == len(r["files"]["metrics.csv"].splitlines()) - 1


BAD_CONFIG = "[controller]\ndelta = [1, -2, 3]"


@pytest.mark.parametrize(
    "argv, call",
    [
        (["simulate", "--config", "{bad}"], lambda c, d: fj.run_simulate(c)),
        (["simulate", "--config", "/nonexistent/c.toml"], lambda c, d: fj.run_simulate("/nonexistent/c.toml")),
        (["simulate", "--point", "1"], lambda c, d: fj.run_simulate(point=1)),
        (["bounds", "--config", "{bad}"], lambda c, d: fj.run_bounds({"controller": {"delta": [1, -2, 3]}})),
        (["certify", "--vertices", "0"], lambda c, d: fj.run_certify(vertices="0")),
        (["certify", "--vertices", "some"], lambda c, d: fj.run_certify(vertices="some")),
        (["tune", "--steps", "0", "--out", "{out}"], lambda c, d: fj.run_tune(steps=0, out=d / "out")),
        (["tune", "--out", "{full}"], lambda c, d: fj.run_tune(out=d / "full")),
        (["front", "--budget", "0", "--out", "{out}"], lambda c, d: fj.run_front(budget=0.0, out=d / "out")),
        (["front", "--points", "0", "--out", "{out}"], lambda c, d: fj.run_front(points=0, out=d / "out")),
        (["front", "--config", "{bad}", "--out", "{out}"], lambda c, d: fj.run_front(c, out=d / "out")),
        (["reproduce", "--out", "{full}"], lambda c, d: fj.run_reproduce(d / "full")),
    ],
)  # fmt: skip
def test_bad_input_raises_the_clis_one_line_error(capsys, tmp_path, argv, call):
    bad = tmp_path / "bad.toml"
    bad.write_text(BAD_CONFIG)
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("")
    subs = {"{bad}": str(bad), "{out}": str(tmp_path / "out"), "{full}": str(tmp_path / "full")}
    code, out, err = cli(capsys, *(subs.get(a, a) for a in argv))
    assert code == 2 and out == ""
    with pytest.raises(fj.ConfigError) as e:
        call(str(bad), tmp_path)
    assert err.strip() == f"fosmc: error: {e.value}"
    assert "\n" not in str(e.value)
    assert not (tmp_path / "out").exists()


def test_config_of_refuses_other_types():
    with pytest.raises(fj.ConfigError, match="config: expected a TOML path, a preset name .*, a dict or None, got int"):
        fj.run_bounds(42)
