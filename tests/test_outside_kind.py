"""A controller kind from outside the package: a module of its own (written here into tmp_path),
named by a config (``[controller] kind = "module:KIND"``) or declared in the ``fosmc_jax.kinds``
entry-point group of an installed distribution, known to every command as the package's own
kinds are."""

import dataclasses
import json
import textwrap

import jax.numpy as jnp
import numpy as np
import pytest

import fosmc_jax as fj
from fosmc_jax import _problems as problems
from fosmc_jax._app import commands
from fosmc_jax._app.certify import certify
from fosmc_jax._app.cli import main
from fosmc_jax._controllers import KINDS
from fosmc_jax._controllers.kind import ENTRY_POINTS, load_entry_points

#: The kind's module: a law on the FOSMC's surface, U = -k tanh(s / eps), with a state of its own
#: (the last s) and two tunable gains per joint.
MODULE = """
import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp

import fosmc_jax as fj
from fosmc_jax import search


@functools.partial(jax.tree_util.register_dataclass, data_fields=["C", "k", "eps"], meta_fields=[])
@dataclasses.dataclass(frozen=True)
class TanhSurface:
    C: jax.Array
    k: jax.Array
    eps: jax.Array

    def init(self, X0, r0, key=None):
        return jnp.zeros(3, X0.dtype)

    def update(self, state, Y, r, t):
        s = self.C @ (Y - fj.desired_state(r))
        return -self.k * jnp.tanh(s / self.eps), s

    def sliding_variable(self, state):
        return state


class Gains(NamedTuple):
    k: jax.Array
    eps: jax.Array


KIND = search.Kind(
    search.Space("NAME", Gains, (search.Param("k", "NAME_k", 1, (-1.0, 1.0)),
                                 search.Param("eps", "NAME_eps", 1, (-1.0, 1.0)))),
    {"NAME_k": (20.0, 20.0, 20.0), "NAME_eps": (1.0, 1.0, 1.0)},
    lambda params, controller, T: TanhSurface(params.C, controller.gains["NAME_k"], controller.gains["NAME_eps"]),
    rules={TanhSurface: {"C": search.rules.MATRIX_3x9, "k": search.rules.GAINS, "eps": search.rules.GAINS}},
)
"""


@pytest.fixture
def outside(tmp_path, monkeypatch):
    """A function writing the kind's module ``name`` into tmp_path (on sys.path); every kind it
    registers is gone again after the test."""
    monkeypatch.syspath_prepend(str(tmp_path))
    before = set(KINDS)

    def write(name: str) -> str:
        (tmp_path / f"{name}.py").write_text(textwrap.dedent(MODULE).replace("NAME", name))
        return f"{name}:KIND"

    yield write
    for name in set(KINDS) - before:
        KINDS.pop(name)


def _config(spec: str, **sim) -> dict:
    return {"controller": {"kind": spec}, "sim": {"t_final": 0.02, "dt": 1e-3, **sim}}


def test_a_config_naming_a_modules_kind_loads_it_and_simulates(outside):
    spec = outside("outside_a")
    cfg = problems.resolve(_config(spec))
    assert cfg.controller.kind == "outside_a" and cfg.tune.params == ("k", "eps")
    res = commands.run_simulate(_config(spec), devices=1)
    assert res["config"]["controller"]["kind"] == "outside_a"
    assert np.isfinite(res["summary"]["mean"]["rms_error"]).all()
    with pytest.raises(problems.ConfigError, match=r"^controller\.kind: certify checks the FOSMC's hitting"):
        certify(cfg)


def test_a_kinds_input_rules_are_checked_at_the_simulators_edge(outside):
    """The kind's own rules (``Kind.rules``) refuse a wrong shape or value in one line naming the
    field, as the package's kinds' do."""
    p = fj.build(_config(outside("outside_d")))
    law = p.controller()
    for bad, message in [
        (dataclasses.replace(law, k=jnp.ones(2)), r"^controller\.k: expected shape \(3,\), got \(2,\)$"),
        (
            dataclasses.replace(law, eps=-law.eps),
            r"^controller\.eps: expected 3 positive numbers, got -1\.0 at index 0$",
        ),
    ]:
        with pytest.raises(ValueError, match=message):
            fj.simulate_batch(p.plants, bad, p.reference, p.X0s, p.dt, **p.options)


def test_keep_gamma_bound_is_refused_for_a_kind_without_the_gamma_bounds(outside):
    spec = outside("outside_e")
    with pytest.raises(problems.ConfigError, match=r"^tune\.keep_gamma_bound: .* got kind = 'outside_e'$"):
        commands.run_tune({**_config(spec), "tune": {"keep_gamma_bound": True}}, steps=1)


@pytest.mark.parametrize(
    "spec, message",
    [
        ("no_such_module_here:KIND", r"^controller\.kind: cannot load the controller kind 'no_such_module_here:KIND' "),
        ("json:dumps", r"^controller\.kind: 'json:dumps' is a function, not a controller kind"),
    ],
)
def test_a_kind_that_does_not_load_is_refused_in_one_line(spec, message):
    with pytest.raises(problems.ConfigError, match=message) as e:
        problems.resolve({"controller": {"kind": spec}})
    assert "\n" not in str(e.value)


def test_an_installed_distributions_entry_point_registers_its_kind(outside, tmp_path):
    outside("outside_b")
    info = tmp_path / "outside_b-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: outside-b\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text(f"[{ENTRY_POINTS}]\noutside_b = outside_b:KIND\n")
    assert "outside_b" not in KINDS
    assert [k.name for k in load_entry_points()] == ["outside_b"]
    assert problems.resolve({"controller": {"kind": "outside_b"}}).controller.kind == "outside_b"


@pytest.mark.slow  # a tune, a front, an export of their own (~30-60 s on 2 cores)
def test_every_command_runs_a_kind_from_outside_the_package(outside, tmp_path, capsys):
    spec = outside("outside_c")
    path = tmp_path / "c.toml"
    path.write_text(f'[controller]\nkind = "{spec}"\n[sim]\nt_final = 0.05\ndt = 1e-3\n')
    assert main(["simulate", "--config", str(path), "--json"]) == 0
    assert json.loads(capsys.readouterr()[0])["config"]["controller"]["kind"] == "outside_c"
    out = tmp_path / "tune"
    assert main(["tune", "--config", str(path), "--steps", "2", "--out", str(out)]) == 0
    assert set(json.loads((out / "result.json").read_text())["final"]["params"]) == {"k", "eps"}
    assert main(["simulate", "--config", str(path), "--params", str(out / "result.json")]) == 0
    front = tmp_path / "front"
    assert main(["front", "--config", str(path), "--candidates", "16", "--steps", "1", "--out", str(front)]) == 0
    points = json.loads((front / "front.json").read_text())["points"]
    assert points and all(set(p["params"]) == {"k", "eps"} for p in points)
    capsys.readouterr()
    assert main(["select", "--front", str(front / "front.json"), "--max-error", "1e9", "--json"]) == 0
    assert json.loads(capsys.readouterr()[0])
    digital = tmp_path / "digital.toml"
    digital.write_text(path.read_text().replace("[sim]", "sample_period = 1e-3\n[sim]"))
    assert main(["export", "--config", str(digital), "--out", str(tmp_path / "c99")]) == 0
    assert "TanhSurface" in (tmp_path / "c99" / "fosmc.c").read_text()
    assert main(["certify", "--config", str(path)]) == 2  # the hitting condition (20) is the FOSMC's
