"""The command line: JSON shapes, config handling, one-line errors with exit status 2."""

import json

import numpy as np
import pytest

from fosmc_jax import _problems as _config
from fosmc_jax._app.cli import main
from fosmc_jax._design import paper as _paper
from fosmc_jax._simulator.metrics import METRIC_NAMES

SHORT = """
[sim]
t_final = 0.05
dt = 1e-3
"""


def run(capsys, tmp_path, text, *args):
    path = tmp_path / "c.toml"
    path.write_text(text)
    code = main([args[0], "--config", str(path), *args[1:]])
    out, err = capsys.readouterr()
    return code, out, err


def test_simulate_json_has_one_entry_per_rollout(capsys, tmp_path):
    text = (
        SHORT
        + """
initial_offset = [[0, 0, 0, 0, 0, 0, 0, 0, 0], [0.01, 0, 0, 0, 0, 0, 0, 0, 0]]
[plant]
uncertainty = "sample"
samples = 3
seed = 7
"""
    )
    code, out, _ = run(capsys, tmp_path, text, "simulate", "--json")
    assert code == 0
    d = json.loads(out)
    assert len(d["rollouts"]) == 6
    for r in d["rollouts"]:
        assert set(r["metrics"]) == set(METRIC_NAMES)
        assert all(len(v) == 3 and all(np.isfinite(v)) for v in r["metrics"].values())
        assert r["diverged"] is False
    assert d["config"]["plant"]["samples"] == 3
    assert d["config"]["controller"]["gamma"] == _paper.GAMMA.tolist()  # defaults filled in
    # rollouts with the zero offset start on the reference: error 0 at t = 0, offset 1 does not
    assert d["rollouts"][0]["metrics"]["max_abs_error"][0] < d["rollouts"][1]["metrics"]["max_abs_error"][0]


@pytest.mark.slow  # 3 s: the default tier keeps to 4 minutes on 2 cores
def test_simulate_npz_holds_the_json_values(capsys, tmp_path):
    text = SHORT + 'precision = "float32"\n[plant]\nuncertainty = "sample"\nsamples = 4\n'
    both, alone = tmp_path / "both.npz", tmp_path / "alone.npz"
    code, out, _ = run(capsys, tmp_path, text, "simulate", "--json", "--npz", str(both))
    assert code == 0
    records = json.loads(out)["rollouts"]
    code, out, _ = run(capsys, tmp_path, text, "simulate", "--npz", str(alone))
    assert code == 0 and "batch of 4" in out and "rollout" not in out.splitlines()[0]  # the summary only
    a, b = np.load(both), np.load(alone)
    assert sorted(a) == sorted(b) == sorted([*METRIC_NAMES, "diverged", "diverged_at", "plant_index",
                                             "offset_index", "realization_index", "fosmc_jax"])  # fmt: skip
    for k in a:
        assert a[k].dtype == b[k].dtype and np.array_equal(a[k], b[k]), k
    assert a["rms_error"].dtype == np.float32 and a["rms_error"].shape == (4, 3)
    for name in METRIC_NAMES:
        np.testing.assert_array_equal(a[name], np.asarray([r["metrics"][name] for r in records], np.float32))
    assert a["plant_index"].tolist() == [r["plant_index"] for r in records] == [0, 1, 2, 3]


def test_simulate_json_writes_non_finite_numbers_as_null():
    from fosmc_jax._app.cli import _simulate_json

    arrays = {name: np.ones((1, 3)) for name in METRIC_NAMES}
    arrays["rms_error"] = np.array([[np.nan, 1.0, -np.inf]])
    arrays.update(diverged=np.array([True]), diverged_at=np.array([np.inf]), plant_index=np.array([0]),
                  offset_index=np.array([0]), realization_index=np.array([0]))  # fmt: skip
    d = json.loads(_simulate_json({"arrays": arrays, "summary": {"mean": float("nan")}, "config": {}}))
    (record,) = d["rollouts"]
    assert record["metrics"]["rms_error"] == [None, 1.0, None] and record["metrics"]["chattering"] == [1.0] * 3
    assert record["diverged"] is True and record["diverged_at"] is None and record["plant_index"] == 0
    assert d["summary"] == {"mean": None} and d["config"] == {}


@pytest.mark.slow  # 4 s: the default tier keeps to 4 minutes on 2 cores
def test_simulate_plot_is_written(capsys, tmp_path):
    png = tmp_path / "fig.png"
    code, _, err = run(capsys, tmp_path, SHORT, "simulate", "--plot", str(png))
    assert code == 0 and png.stat().st_size > 10_000, err


def test_bounds_json(capsys, tmp_path):
    # a small box keeps the vertex enumeration quick
    A = _paper.A_ROWS
    text = f"""
[plant.box]
A_lower = {(A - 0.5 * (np.abs(A) > 20)).tolist()}
A_upper = {(A + 0.5 * (np.abs(A) > 20)).tolist()}
"""
    code, out, _ = run(capsys, tmp_path, text, "bounds", "--json")
    assert code == 0
    d = json.loads(out)
    assert np.asarray(d["K"]).shape == (3, 9) and np.asarray(d["CB"]).shape == (3, 3)
    poles = np.sort(np.asarray(d["closed_loop_poles"])[:, 0])
    np.testing.assert_allclose(poles, np.sort(_paper.POLES.ravel()), rtol=1e-6)
    assert set(d["gamma_min"]) == {"spectral", "paper"}
    assert all(len(v) == 3 for v in d["gamma_min"].values())
    assert np.all(np.asarray(d["gamma_min"]["spectral"]) >= np.asarray(d["gamma_min"]["paper"]))
    assert 0 < d["alpha"] and 0 < d["beta"]


@pytest.mark.parametrize(
    "text, key",
    [
        ("[controller]\ndelta = [1, -2, 3]", "controller.delta"),
        ("[controller]\ndelta = [1, 2]", "controller.delta"),
        ("[controller]\npoles = [[-1, -2, 0.5], [-1, -2, -3], [-1, -2, -3]]", "controller.poles"),
        ("[controller]\nswitching = 'sgn'", "controller.switching"),
        ("[controller]\nC = [[0,0,0,0,0,0,0,0,0],[0,0,0,30,20,1,0,0,0],[0,0,0,0,0,0,30,20,1]]", "controller"),
        ("[sim]\ndt = 0", "sim.dt"),
        ("[sim]\ndt = 'small'", "sim.dt"),
        ("[sim]\nt_final = -1", "sim.t_final"),
        ("[sim]\ninitial_offset = [1, 2, 3]", "sim.initial_offset"),
        ("[sim]\ninitial_offset = []", "sim.initial_offset"),
        ("[sim]\nfoo = 1", "sim.foo"),
        ("[nonsense]\nx = 1", "nonsense"),
        ("[plant]\nsamples = 0", "plant.samples"),
        ("[plant]\nuncertainty = 'gaussian'", "plant.uncertainty"),
        ("[plant]\nkind = 'arm'\nuncertainty = 'sample'", "plant.uncertainty"),
        ("[plant.box]\nB_lower = [[1, 2], [3, 4]]", "plant.box.B_lower"),
        ("[trajectory]\nstart = [0, 0, nan]", "trajectory.start"),
        ("this is not toml", "not valid TOML"),
    ],
)
@pytest.mark.parametrize("command", ["simulate", "bounds"])
def test_bad_config_one_line_error_exit_2(capsys, tmp_path, text, key, command):
    code, out, err = run(capsys, tmp_path, text, command)
    assert code == 2
    assert out == ""
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("fosmc: error: ") and key in lines[0], err


def test_missing_file(capsys):
    assert main(["simulate", "--config", "/nonexistent/c.toml"]) == 2
    assert "cannot read config file" in capsys.readouterr().err


def test_resolve_is_idempotent_and_api_raises_valueerror():
    cfg = _config.resolve({})
    assert _config.resolve(cfg) == cfg
    with pytest.raises(ValueError, match="sim.dt"):
        _config.resolve({"sim": {"dt": -1.0}})


def test_devices_must_be_positive(capsys):
    assert main(["simulate", "--devices", "0"]) == 2
    assert "--devices" in capsys.readouterr().err


@pytest.mark.slow  # two fresh processes (~10 s)
def test_simulate_shards_over_every_core_by_default_and_equals_one_device(tmp_path):
    """In a fresh process `fosmc simulate` shows one device per core and splits the batch
    over them; the rollouts equal `--devices 1` to rounding (5 plants: padded when split)."""
    import os
    import subprocess
    import sys

    path = tmp_path / "c.toml"
    path.write_text(SHORT + '[plant]\nuncertainty = "sample"\nsamples = 5\n')
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "JAX_NUM_CPU_DEVICES")}

    def simulate(*extra):
        cmd = [sys.executable, "-m", "fosmc_jax", "simulate", "--config", str(path), "--json", *extra]
        out = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
        assert out.returncode == 0, out.stderr[-2000:]
        return json.loads(out.stdout), out.stderr

    (default, log), (single, log1) = simulate(), simulate("--devices", "1")
    assert f"on {len(os.sched_getaffinity(0))} device(s)" in log and "on 1 device(s)" in log1
    assert len(default["rollouts"]) == len(single["rollouts"]) == 5
    for a, b in zip(default["rollouts"], single["rollouts"], strict=True):
        for name in METRIC_NAMES:
            np.testing.assert_allclose(a["metrics"][name], b["metrics"][name], rtol=1e-12, atol=1e-300)


@pytest.mark.parametrize("command", ["tune", "front"])
def test_out_that_is_a_file_is_refused_in_one_line(capsys, tmp_path, command):
    """--out naming a file, or a folder below one: one line, exit status 2, the file untouched."""
    afile = tmp_path / "afile"
    afile.write_text("keep")
    below = afile / "sub"
    for out, message in ((afile, f"--out: {afile} is a file, not a folder"),
                         (below, f"--out: cannot make the folder {below}: {afile} is a file")):  # fmt: skip
        code, _, err = run(capsys, tmp_path, SHORT, command, "--out", str(out))
        assert code == 2 and err.strip().splitlines()[-1] == f"fosmc: error: {message}"
    assert afile.read_text() == "keep"
