"""Every controller kind is tunable with its own parameters: ``fosmc tune`` and ``fosmc front``
on SMC's (k, phi) and super-twisting's (k1, k2), their results put back into the config's keys
by ``fosmc simulate --params``, the tune loss's gradient in the log gains against central
differences, and one-line errors for mixing kinds or FOSMC-only options."""

import dataclasses
import functools
import json
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fosmc_jax as fj
from fosmc_jax import _problems as _config
from fosmc_jax import search as fs
from fosmc_jax._app.cli import main
from fosmc_jax._search import front as front_module
from fosmc_jax._search import tune as tuner
from fosmc_jax.search import nondominated

#: (kind, [controller] extras, [tune] params): SMC in the ideal loop with all its parameters,
#: super-twisting in a digital loop (sampled at 2 steps, one sample of delay) with k2 alone free.
CASES = [("smc", {}, None), ("super_twisting", {"sample_period": 4e-3, "delay_samples": 1}, ["k2"])]
#: The fixtures' cases: SMC's runs in the slow tier (10 s; the default tier keeps to 4 minutes on 2
#: cores), which still tunes SMC through its gradient test below
PARAMS = [pytest.param(CASES[0], marks=pytest.mark.slow), CASES[1]]
SIM = {"t_final": 0.25, "dt": 2e-3, "integrator": "euler"}
PLANT = {"uncertainty": "sample", "samples": 2}


def toml(path, kind, controller=None, tune=None):
    """A short config: the linear model at 2 box samples, 0.25 s of Euler at 2 ms."""
    value = lambda v: json.dumps(v) if not isinstance(v, bool) else str(v).lower()
    table = lambda name, keys: [f"[{name}]", *(f"{k} = {value(v)}" for k, v in keys.items())]
    lines = [
        *table("controller", {"kind": kind, **(controller or {})}),
        *table("plant", PLANT),
        *table("sim", SIM),
        *table("tune", {"global_candidates": 0, "mode": "reverse", "remat_steps": 0, **(tune or {})}),
    ]
    path.write_text("\n".join(lines) + "\n")
    return str(path)


def mean_metrics(capsys) -> dict:
    return json.loads(capsys.readouterr()[0])["summary"]["mean"]


@pytest.fixture(scope="module", params=PARAMS, ids=[c[0] for c in CASES])
def tuned(request, tmp_path_factory):
    kind, controller, params = request.param
    tmp = tmp_path_factory.mktemp(f"tune_{kind}")
    path = toml(tmp / "c.toml", kind, controller, {"params": params} if params else None)
    assert main(["tune", "--config", path, "--steps", "4", "--out", str(tmp / "out")]) == 0
    return kind, path, tmp / "out" / "result.json"


def test_tune_lowers_the_objective_and_its_result_resimulates(tuned, capsys):
    kind, path, result = tuned
    res = json.loads(result.read_text())
    space = tuner.SPACES[kind]
    free = res["config"]["tune"]["params"]
    assert set(res["final"]["params"]) == set(space.names) and free == (["k", "phi"] if kind == "smc" else ["k2"])
    assert res["history"]["loss"][-1] < res["history"]["loss"][0]
    for p in space.params:  # free parameters moved, frozen ones kept (to exp(log(x)) rounding), signs kept
        moved = not np.allclose(res["final"]["params"][p.name], res["initial"]["params"][p.name], rtol=1e-12, atol=0)
        assert moved == (p.name in free) and np.all(np.asarray(res["final"]["params"][p.name]) > 0)
    cfg = _config.with_params(_config.load(path), result)
    for p in space.params:
        np.testing.assert_array_equal(cfg["controller"][p.key], res["final"]["params"][p.name])
    assert main(["simulate", "--config", path, "--params", str(result), "--json", "--devices", "1"]) == 0
    mean = mean_metrics(capsys)
    for name, value in res["final"]["metrics"].items():
        np.testing.assert_allclose(mean[name], value, rtol=1e-9, atol=1e-15, err_msg=name)
    assert (result.parent / "tuning.png").stat().st_size > 0  # the loss and the kind's parameters


@pytest.fixture(scope="module", params=PARAMS, ids=[c[0] for c in CASES])
def front(request, tmp_path_factory):
    """The front's search (fosmc_jax._search.front.front_search) on the kind's problem, written as a front.json."""
    kind, controller, _ = request.param
    tmp = tmp_path_factory.mktemp(f"front_{kind}")
    path = toml(tmp / "c.toml", kind, controller)
    cfg = _config.load(path)
    plain, train, p0 = _config.tuning_problems(cfg)
    res = front_module.front_search(
        train,
        plain,
        p0,
        front_module.Settings(search="staged", points=3, candidates=16, steps=2, chunk=8),
        log=lambda _: None,
    )
    (tmp / "front.json").write_text(json.dumps({**res, "config": cfg.as_dict()}))
    return kind, path, tmp / "front.json", res, (train, p0, cfg)


def test_front_is_nondominated_sorted_with_the_kinds_params(front, capsys):
    kind, path, front_json, res, _ = front
    pts = res["points"]
    assert len(pts) >= 2 and res["stages"]["evaluations"] == 16 + 2 * 8
    assert res["stages"]["grid_per_axis"] == 3  # 1 + 3^2 of 16 on the grid of two parameters (three: 1 + 2^3)
    e = np.array([np.mean(p["metrics"]["rms_error"]) for p in pts])
    c = np.array([np.mean(p["metrics"]["chattering_hf"]) for p in pts])
    assert np.all(np.diff(c) > 0) and np.all(np.diff(e) < 0) and nondominated(e, c).all()
    space = tuner.SPACES[kind]
    base = _config.load(path)["controller"]
    lo, hi = space.bounds()
    for pt in pts:
        assert list(pt["params"]) == list(space.names)
        z = np.concatenate([np.log10(np.asarray(pt["params"][p.name]) / base[p.key]) for p in space.params])
        assert np.all((z >= lo - 1e-12) & (z <= hi + 1e-12))  # within the kind's box
    i = len(pts) - 1
    assert main(["simulate", "--config", path, "--params", str(front_json), "--point", str(i), "--json",
                 "--devices", "1"]) == 0  # fmt: skip
    mean = mean_metrics(capsys)
    for name, value in pts[i]["metrics"].items():
        np.testing.assert_allclose(mean[name], value, rtol=1e-9, atol=1e-15, err_msg=name)


def test_global_stage_keeps_the_kinds_frozen_parameters(front):
    kind, _, _, _, (train, p0, cfg) = front
    obj = tuner.objective_of(cfg["tune"], tuner.evaluate(train, p0)["metrics"])
    first, second = tuner.SPACES[kind].names
    best, score = front_module.global_stage(train, obj, p0, 16, free=(first,), chunk=8, log=lambda _: None)
    np.testing.assert_array_equal(getattr(best, second), getattr(p0, second))
    assert type(best) is type(p0) and score <= 1e-9  # the start (score about 0) is among the candidates


@pytest.mark.parametrize("kind", ["smc", pytest.param("super_twisting", marks=pytest.mark.slow)])
def test_gradient_in_log_gains_matches_central_differences(kind):
    # 0.05 rad off the reference: s leaves 0, where |s|^1/2 and the sign flips make the loss
    # piecewise smooth; a central difference that straddles a flip is off, so the better of
    # two steps must agree
    sim = {"t_final": 0.1, "dt": 2e-3, "integrator": "euler", "initial_offset": [0.05] + [0.0] * 8}
    cfg = _config.resolve({"controller": {"kind": kind}, "plant": {"uncertainty": "sample", "samples": 2}, "sim": sim})
    _, train, p0 = _config.tuning_problems(cfg)
    loss = tuner.make_loss(train, tuner.Objective(error_ref=0.01, chattering_ref=1.0), None)
    u0 = tuner.to_internal(p0, train.base)
    assert type(u0) is tuner.SPACES[kind].values
    for a, b in zip(tuner.to_physical(u0, train.base), p0):
        np.testing.assert_allclose(a, b, rtol=1e-12)
    flat, unravel = jax.flatten_util.ravel_pytree(u0)
    f = jax.jit(lambda x: loss(unravel(x))[0])
    g = np.asarray(jax.jit(jax.grad(f))(flat))
    for i in range(flat.size):
        fd = [(f(flat.at[i].add(h)) - f(flat.at[i].add(-h))) / (2 * h) for h in (1e-5, 1e-6)]
        best = min(fd, key=lambda d: abs(d - g[i]))
        np.testing.assert_allclose(g[i], best, rtol=2e-4, atol=1e-8, err_msg=f"log parameter {i}")


def test_mixing_kinds_and_fosmc_only_options_are_refused(tuned, tmp_path, capsys):
    kind, _, result = tuned
    other = "super_twisting" if kind == "smc" else "smc"
    cases = [
        (["simulate", "--config", toml(tmp_path / "o.toml", other), "--params", str(result)], "--params"),
        (["simulate", "--params", str(result)], "--params"),  # the default config: the FOSMC
        (["tune", "--config", toml(tmp_path / "d.toml", kind, tune={"params": ["delta"]})], "tune.params"),
        (["tune", "--config", toml(tmp_path / "g.toml", kind, tune={"keep_gamma_bound": True})],
         "tune.keep_gamma_bound"),
    ]  # fmt: skip
    for args, key in cases:
        out = tmp_path / "out"
        assert main([*args, *(["--out", str(out)] if args[0] == "tune" else [])]) == 2, args
        err = capsys.readouterr()[1]
        assert err.startswith(f"fosmc: error: {key}") and err.count("\n") == 1, err
        assert not out.exists()
    fosmc_file = tmp_path / "fosmc.json"
    fosmc_file.write_text(json.dumps({"final": {"params": {"delta": [1.0] * 3}}}))
    assert main(["simulate", "--config", toml(tmp_path / "k.toml", kind), "--params", str(fosmc_file)]) == 2
    assert "holds fosmc parameters" in capsys.readouterr()[1]
    fosmc_file.write_text(json.dumps({"final": {"params": {"k": [1.0] * 3, "k1": [1.0] * 3}}}))
    assert main(["simulate", "--config", toml(tmp_path / "k.toml", kind), "--params", str(fosmc_file)]) == 2
    assert "no controller kind's parameter set" in capsys.readouterr()[1]


@pytest.mark.slow
def test_the_front_command_writes_the_kinds_front_with_held_out_and_references(tmp_path, capsys):
    """`fosmc front` end to end for SMC: the kind's params, held-out metrics, the FOSMC's
    references, the figure (about 15 s: four compilations)."""
    path = toml(tmp_path / "c.toml", "smc")
    out = tmp_path / "out"
    assert main(["front", "--config", path, "--out", str(out), "--candidates", "16", "--steps", "2",
                 "--points", "3"]) == 0  # fmt: skip
    res = json.loads((out / "front.json").read_text())
    assert res["config"]["controller"]["kind"] == "smc" and len(res["points"]) >= 2
    for pt in res["points"]:
        assert list(pt["params"]) == ["k", "phi"] and len(pt["held_out"]["rms_error"]) == 3
    assert set(res["references"]) == {"Table 1 set 1", "Table 1 set 2", "Table 1 set 3", "SGN"}
    assert set(res["references"]["SGN"]["params"]) == {"delta", "gamma", "poles"}
    assert (out / "front.png").stat().st_size > 10_000
    assert len(capsys.readouterr()[0].splitlines()) == len(res["points"])


# ---------------------------------------------------------------------------- a kind of one's own


@functools.partial(jax.tree_util.register_dataclass, data_fields=["surface", "k", "eps"], meta_fields=[])
@dataclasses.dataclass(frozen=True)
class TanhSMC:
    """A law defined here, not in the package: U = U_eq - (CB)^-1 k tanh(s / eps) on the
    conventional surface (fosmc_jax.SurfaceParams)."""

    surface: fj.SurfaceParams
    k: jax.Array
    eps: jax.Array

    def init(self, X0, r0, key=None):
        return jnp.zeros(3, X0.dtype)

    def update(self, state, Y, r, t):
        X_d, dX_d = fj.desired_state(r), jnp.stack([r[1], r[2], r[3]], axis=1).reshape(9)
        C, a_rows, b_rows = self.surface
        s = C @ (Y - X_d)
        rates = jnp.stack([Y[1::3], Y[2::3], a_rows @ Y], axis=1).reshape(9)  # nominal X' without input
        CB = fj.input_matrix_product(C, b_rows)
        return jnp.linalg.solve(CB, C @ dX_d - C @ rates - self.k * jnp.tanh(s / self.eps)), s

    def sliding_variable(self, state):
        return state


class TanhGains(NamedTuple):
    k: jax.Array
    eps: jax.Array


TANH = fs.Kind(
    fs.Space(
        "tanh_smc", TanhGains, (fs.Param("k", "tanh_k", 1, (-2.0, 2.0)), fs.Param("eps", "tanh_eps", 1, (-3.0, 1.0)))
    ),
    {"tanh_k": (300.0, 300.0, 300.0), "tanh_eps": (1.0, 1.0, 1.0)},
    lambda params, controller, T: TanhSMC(
        fj.SurfaceParams(params.C, params.a_rows, params.b_rows),
        controller.gains["tanh_k"],
        controller.gains["tanh_eps"],
    ),
)


@pytest.mark.slow  # a tune, a simulate and a front of their own (~15 s)
def test_a_kind_defined_outside_the_package_is_one_registry_line_and_tunes(tmp_path, capsys):
    fs.register(TANH)  # the one line
    try:
        path = toml(tmp_path / "c.toml", "tanh_smc", {"tanh_eps": [0.5, 0.5, 0.5]})
        assert main(["tune", "--config", path, "--steps", "4", "--out", str(tmp_path / "out")]) == 0
        res = json.loads((tmp_path / "out" / "result.json").read_text())
        assert set(res["final"]["params"]) == {"k", "eps"} and res["config"]["tune"]["params"] == ["k", "eps"]
        assert res["initial"]["params"]["eps"] == pytest.approx([0.5] * 3)  # from its own config key
        assert res["history"]["loss"][-1] < res["history"]["loss"][0]
        capsys.readouterr()
        # its result goes back into its config keys, as a built-in kind's does
        assert main(["simulate", "--config", path, "--params", str(tmp_path / "out" / "result.json"), "--json"]) == 0
        assert np.isfinite(mean_metrics(capsys)["rms_error"]).all()
        front = tmp_path / "front"
        assert main(["front", "--config", path, "--candidates", "16", "--steps", "1", "--out", str(front)]) == 0
        points = json.loads((front / "front.json").read_text())["points"]
        assert points and all(set(pt["params"]) == {"k", "eps"} for pt in points)
        with pytest.raises(fj.ConfigError, match="controller.tanh_k: expected 3 positive numbers"):
            _config.resolve({"controller": {"kind": "tanh_smc", "tanh_k": [1.0, -1.0, 1.0]}})
    finally:
        from fosmc_jax._controllers import KINDS

        KINDS.pop("tanh_smc")
    with pytest.raises(fj.ConfigError, match="controller.kind: expected one of fosmc, smc, super_twisting"):
        _config.resolve({"controller": {"kind": "tanh_smc"}})
