"""Every result file carries the package's version and the metric definitions' version under
``"fosmc_jax"`` (issue 24, item 7), written by one helper; readers still take files without it.
tune's result.json and front.json are checked on real runs in tests/test_tune_defaults.py."""

import json

import numpy as np
import pytest

import fosmc_jax as fj
from fosmc_jax import _problems as _config
from fosmc_jax._app.cli import main
from fosmc_jax._io import METRICS_VERSION, VERSIONS_KEY, stamped, stamped_arrays, versions

SHORT = "[sim]\nt_final = 0.05\ndt = 1e-3\n"


def test_versions_name_the_package_and_the_metric_definitions():
    assert VERSIONS_KEY == "fosmc_jax"
    assert versions() == {"version": fj.__version__, "metrics_version": METRICS_VERSION}
    assert isinstance(METRICS_VERSION, int) and METRICS_VERSION >= 3  # issue 24: diverged rollouts' metrics NaN


def test_stamped_puts_the_versions_first_and_keeps_the_rest():
    d = stamped({"points": [1], "fosmc_jax": {"version": "old"}, "config": {}})
    assert list(d) == ["fosmc_jax", "points", "config"] and d["fosmc_jax"] == versions()
    a = stamped_arrays({"rms_error": np.ones((2, 3))})
    assert list(a) == ["fosmc_jax", "rms_error"] and json.loads(a["fosmc_jax"].item()) == versions()


def test_simulate_json_and_npz_carry_the_versions(capsys, tmp_path):
    config, npz = tmp_path / "c.toml", tmp_path / "m.npz"
    config.write_text(SHORT)
    assert main(["simulate", "--config", str(config), "--json", "--npz", str(npz)]) == 0
    d = json.loads(capsys.readouterr()[0])
    assert list(d)[:2] == ["fosmc_jax", "rollouts"] and d["fosmc_jax"] == versions()
    with np.load(npz) as z:  # no pickle needed: a string array
        assert json.loads(z["fosmc_jax"].item()) == versions() and z["rms_error"].shape == (1, 3)
    assert fj.run_simulate(str(config))["fosmc_jax"] == versions()  # the function returns what --json prints


@pytest.mark.parametrize("stamp", [False, True])
def test_params_files_with_and_without_the_versions_are_read(tmp_path, stamp):
    """Files written before versioning have no "fosmc_jax" key: --params still reads them."""
    cfg = _config.resolve({})
    delta = [0.5, 0.6, 0.7]
    params = {"delta": delta, "gamma": cfg["controller"]["gamma"], "poles": cfg["controller"]["poles"]}
    tune, front = {"final": {"params": params}}, {"axes": [], "points": [{"params": params}]}
    if stamp:
        tune, front = stamped(tune), stamped(front)
    (tmp_path / "result.json").write_text(json.dumps(tune))
    (tmp_path / "front.json").write_text(json.dumps(front))
    assert _config.with_params(cfg, tmp_path / "result.json")["controller"]["delta"] == delta
    assert _config.with_params(cfg, tmp_path / "front.json", 0)["controller"]["delta"] == delta
