"""Your arm in the config (issue 25, items 1 and 7): the [arm] table's keys, validated, used by
build, bounds and certify; gradients with respect to the arm's parameters."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fosmc_jax as fj

ARM = {"plant": {"kind": "arm", "payloads": [0.0, 5.0]}, "sim": {"t_final": 0.1, "dt": 1e-3}}


def test_the_arm_table_defaults_to_the_calibrated_arm_and_builds_the_configured_one():
    cfg = fj.config.resolve(ARM)
    assert set(cfg["arm"]) == set(fj.ArmParams._fields) | {"payload_range", "uncertainty"}
    assert cfg["arm"]["payload_range"] == list(fj.PAYLOAD_RANGE)
    for name, value in fj.ARM_PARAMS._asdict().items():
        np.testing.assert_array_equal(cfg["arm"][name], value)
    mine = fj.build({**ARM, "arm": {"F": [0.5, 0.4, 0.3], "m3": 20.0}})
    np.testing.assert_array_equal(np.asarray(mine.plants.params.F), [[0.5, 0.4, 0.3]] * 2)
    np.testing.assert_array_equal(np.asarray(mine.plants.params.m3), [20.0, 20.0])
    assert float(mine.arm_params()["m3"]) == 20.0


@pytest.mark.parametrize(
    "arm, message",
    [({"m2": -1.0}, "arm.m2: expected a positive mass"),
     ({"I2": [1.0, 1.0, 3.0]}, "arm.I2: expected 3 positive principal inertias"),
     ({"R": [0.1, 0.0, 0.1]}, "arm.R: expected 3 positive resistances"),
     ({"F": [0.1, np.nan, 0.1]}, "arm.F: expected 3 non-negative viscous friction coefficients"),
     ({"c2": 0.5, "l2": 0.3}, "arm.c2: expected the centre of mass of link 2 within the link"),
     ({"payload_range": [2.0, 1.0]}, r"arm.payload_range: expected \[low, high\]"),
     ({"payload_range": [0.0, 4.0]}, r"plant.payloads: expected payloads within arm.payload_range = \[0, 4\]")],
)  # fmt: skip
def test_a_bad_arm_is_refused_in_one_line_naming_the_key(arm, message):
    with pytest.raises(fj.ConfigError, match="^" + message) as e:
        fj.config.resolve({**ARM, "arm": arm})
    assert "\n" not in str(e.value)


@pytest.mark.slow  # both models' boxes (the arm's and the paper's, bounds shows both) twice: ~50 s under load
def test_bounds_and_certify_use_the_configured_arm():
    """A heavier link 3 changes the nominal rows fosmc bounds derives from the arm (it used
    the calibrated arm whatever the config said)."""
    base = fj.run_bounds(ARM)
    heavy = fj.run_bounds({**ARM, "arm": {"m3": 80.0}})
    assert not np.allclose(heavy["nominal_B_rows"], base["nominal_B_rows"])
    cfg = fj.config.resolve({**ARM, "arm": {"payload_range": [0.0, 6.0]}})
    cert = fj.certify(cfg, n_times=3, n_z=2, n_s=26, n_payloads=2)
    assert "evenly over (0.0, 6.0) kg" in cert.vertices and 0 <= cert.where["payload"] <= 6.0


@pytest.mark.slow  # the arm in reverse mode: ~40 s
def test_gradients_in_the_arms_parameters_equal_central_differences():
    """d(mean rms_error)/dF and /dKt through with_arm (one arm, 0.1 s), against central
    differences (relative steps 1e-2 for F, whose joint-1 derivative is 1e-8 and drowns in
    rounding below it, and 1e-4 for Kt): measured 3e-6 and 1e-6 apart, asserted to 1e-4 and 1e-5."""
    problem = fj.build({**ARM, "plant": {"kind": "arm", "payloads": [5.0]}})
    x0 = {name: np.asarray(problem.arm_params()[name]) for name in ("F", "Kt")}
    loss = lambda x: problem.with_arm(x).simulate(fast=False).mean().rms_error.mean()
    grad = jax.grad(loss)({k: jnp.asarray(v) for k, v in x0.items()})
    for name, step, rtol in (("F", 1e-2, 1e-4), ("Kt", 1e-4, 1e-5)):
        fd = []
        for j, e in enumerate(np.diag(step * x0[name])):
            up, down = dict(x0, **{name: x0[name] + e}), dict(x0, **{name: x0[name] - e})
            fd.append((float(loss(up)) - float(loss(down))) / (2 * e[j]))
        np.testing.assert_allclose(np.asarray(grad[name]), fd, rtol=rtol, err_msg=name)


def test_with_arm_refuses_unknown_names_wrong_shapes_and_linear_plants():
    problem = fj.build(ARM)
    with pytest.raises(ValueError, match=r"^with_arm: unknown arm parameter\(s\) 'friction'"):
        problem.with_arm({"friction": 1.0})
    with pytest.raises(ValueError, match=r"^with_arm: arm.F: expected shape \(3,\), got \(2,\)"):
        problem.with_arm({"F": [1.0, 2.0]})
    with pytest.raises(ValueError, match="^with_arm: the problem's plants are LinearPlant"):
        fj.build({"sim": {"t_final": 0.1}}).with_arm({"F": [1.0, 1.0, 1.0]})
    with pytest.raises(ValueError, match="^arm_params: the problem's plants are LinearPlant"):
        fj.build({"sim": {"t_final": 0.1}}).arm_params()


@pytest.mark.parametrize(
    "change, message",
    [({"m2": 0.0}, "arm.m2: expected a positive mass"),
     ({"I2": [10.0, 1.0, 1.0]}, "arm.I2: expected 3 positive principal inertias"),
     ({"c2": 5.0}, "arm.c2: expected the centre of mass of link 2 within the link"),
     ({"Kb": [0.0, 1.0, 1.0]}, "arm.Kb: expected 3 positive back-EMF constants"),
     ({"Kt": "big"}, r"arm.Kt: expected numbers of shape \(3,\)"),
     ({"F": [0.1, np.nan, 0.1]}, "arm.F: expected 3 non-negative")],
)  # fmt: skip
def test_with_arm_refuses_what_the_config_refuses(change, message):
    """A real arm's ranges (fosmc_jax._plants.arm.PARAM_RULES) hold for with_arm as for [arm]."""
    with pytest.raises(ValueError, match="^with_arm: " + message) as e:
        fj.build(ARM).with_arm(change)
    assert "\n" not in str(e.value)
    with pytest.raises(fj.ConfigError, match="^" + message.split(":")[0]):
        fj.config.resolve({**ARM, "arm": change})


def test_with_arm_moves_the_nominal_and_keeps_the_sampled_spread():
    """On sampled arms (F, Kt +-20%, 3 samples x 2 payloads): arm_params() is the configured
    [arm], with_arm(arm_params()) leaves every plant exactly as it was, and doubling F doubles
    every plant's F (the relative draws kept); an ArmParams is taken as a dict of its fields; a
    field whose nominal is 0 (never drawn) becomes the value in every plant."""
    cfg = {**ARM, "arm": {"F": [0.5, 0.4, 0.3], "uncertainty": {"F": 0.2, "Kt": 0.2, "samples": 3, "seed": 1}}}
    problem = fj.build(cfg)
    F = np.asarray(problem.plants.params.F)
    assert len(np.unique(F[:, 0])) == 3  # three sampled arms, each twice (two payloads)
    np.testing.assert_array_equal(problem.arm_params()["F"], [0.5, 0.4, 0.3])
    np.testing.assert_array_equal(problem.arm_params()["Kt"], fj.ARM_PARAMS.Kt)
    same = problem.with_arm(problem.arm_params())
    for a, b in zip(jax.tree.leaves(same.plants), jax.tree.leaves(problem.plants)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    doubled = problem.with_arm({"F": [1.0, 0.8, 0.6]})
    np.testing.assert_allclose(np.asarray(doubled.plants.params.F), 2 * F, rtol=1e-15)
    np.testing.assert_array_equal(doubled.arm_params()["F"], [1.0, 0.8, 0.6])
    np.testing.assert_array_equal(np.asarray(doubled.plants.params.Kt), np.asarray(problem.plants.params.Kt))
    coulomb = problem.with_arm({"Fc": [0.1, 0.2, 0.3]})
    np.testing.assert_array_equal(np.asarray(coulomb.plants.params.Fc), [[0.1, 0.2, 0.3]] * 6)


def test_an_arm_key_on_the_linear_plant_is_refused():
    with pytest.raises(fj.ConfigError, match=r"^arm.F: applies to plant.kind = 'arm' only$"):
        fj.config.resolve({"arm": {"F": [0.1, 0.1, 0.1]}})
    fj.config.resolve({"arm": {"F": list(fj.ARM_PARAMS.F)}})  # the default, said again: nothing to refuse


UNCERTAIN = {**ARM, "arm": {"uncertainty": {"F": 0.3, "Kt": [0.1, 0.1, 0.2], "samples": 3, "seed": 7}}}


def test_sampled_arms_draw_within_their_ranges_and_cross_with_payloads_arm_first():
    cfg = fj.config.resolve(UNCERTAIN)
    arms = fj.config.draws(cfg)["arms"]
    F, Kt = np.asarray(cfg["arm"]["F"]), np.asarray(cfg["arm"]["Kt"])
    assert arms["F"].shape == (3, 3) and np.all(np.abs(arms["F"] / F - 1) <= 0.3)
    assert np.all(np.abs(arms["Kt"] / Kt - 1) <= [0.1, 0.1, 0.2]) and not np.allclose(arms["F"], F)
    np.testing.assert_array_equal(arms["m2"], [cfg["arm"]["m2"]] * 3)  # what does not vary stays
    problem = fj.build(UNCERTAIN)
    assert problem.rollouts == 6  # 3 arms x 2 payloads, arm first
    np.testing.assert_array_equal(np.asarray(problem.plants.payload), [0.0, 5.0] * 3)
    np.testing.assert_array_equal(np.asarray(problem.plants.params.F), np.repeat(arms["F"], 2, axis=0))
    # the corners of the ranges: 2^(3 + 3) = 64 when every corner is asked for
    corners = fj.config.draws(fj.config.resolve(
        {**ARM, "arm": {"uncertainty": {"F": 0.3, "Kt": 0.1, "sampling": "vertices"}}}))["arms"]  # fmt: skip
    assert corners["F"].shape == (64, 3) and np.allclose(np.abs(corners["F"] / F - 1), 0.3)
    assert len({tuple(np.sign(row)) for row in np.concatenate([corners["F"] / F - 1, corners["Kt"] / Kt - 1], 1)}) == 64


@pytest.mark.parametrize(
    "uncertainty, message",
    [({"F": 1.2, "samples": 2}, r"arm.uncertainty.F: expected a relative half-width in \[0, 1\)"),
     ({"F": 0.3}, "arm.uncertainty.samples: expected a positive number of sampled arms"),
     ({"samples": 4}, "arm.uncertainty.samples: nothing varies"),
     ({"m2": [0.1, 0.1, 0.1], "samples": 2}, r"arm.uncertainty.m2: expected a relative half-width")],
)  # fmt: skip
def test_bad_arm_uncertainty_is_refused_naming_the_key(uncertainty, message):
    with pytest.raises(fj.ConfigError, match="^" + message):
        fj.config.resolve({**ARM, "arm": {"uncertainty": uncertainty}})
    with pytest.raises(fj.ConfigError, match="^arm.uncertainty.F: applies to plant.kind = 'arm' only"):
        fj.config.resolve({"arm": {"uncertainty": {"F": 0.3, "samples": 2}}})


@pytest.mark.slow  # the arm's kernel and one rollout at a time: ~15 s
def test_sampled_arms_paired_and_in_the_json_equal_their_rollouts_one_by_one(capsys, tmp_path):
    """Paired: arm i with payload i and offset i; each rollout equals fj.simulate of that arm;
    --json names each rollout's arm_index and lists the arms' parameters."""
    import json

    from fosmc_jax._app.cli import main

    user = {
        **UNCERTAIN,
        "plant": {"kind": "arm", "payloads": [0.0, 5.0, 2.0]},
        "sim": {**ARM["sim"], "pairing": "paired"},
    }
    problem = fj.build(user)
    assert problem.rollouts == 3
    batch = problem.simulate()
    options = {k: v for k, v in problem.options.items() if k != "pairing"}
    for i in range(3):
        plant = jax.tree.map(lambda x, i=i: x[i], problem.plants)
        one = fj.simulate(plant, problem.controller(), problem.reference, problem.X0s[i], problem.dt, **options)
        np.testing.assert_allclose(batch.metrics.rms_error[i], one.metrics.rms_error, rtol=1e-9)
    path = tmp_path / "u.toml"
    path.write_text('[plant]\nkind = "arm"\npayloads = [0.0, 5.0]\n[sim]\nt_final = 0.1\ndt = 1e-3\n'
                    '[arm.uncertainty]\nF = 0.3\nKt = [0.1, 0.1, 0.2]\nsamples = 3\nseed = 7\n')  # fmt: skip
    assert main(["simulate", "--config", str(path), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert [r["arm_index"] for r in out["rollouts"]] == [0, 0, 1, 1, 2, 2]
    drawn = fj.config.draws(fj.config.load(path))["arms"]
    assert len(out["arms"]) == 3 and np.allclose(out["arms"][2]["F"], drawn["F"][2])


def test_the_fronts_held_out_batch_has_fresh_arms_and_payloads_within_the_range():
    cfg = fj.config.resolve({**UNCERTAIN, "plant": {"kind": "arm", "payloads": [0.0, 2.0]},
                             "arm": {**UNCERTAIN["arm"], "payload_range": [0.0, 4.0]}})  # fmt: skip
    held = fj.config.held_out_config(cfg)
    assert held["plant"]["payloads"] == pytest.approx([0.4, 1.2, 2.8, 3.6])
    assert not np.allclose(fj.config.draws(held)["arms"]["F"], fj.config.draws(cfg)["arms"]["F"])
    paper = fj.config.held_out_config(fj.config.resolve({"plant": {"kind": "arm", "payloads": [0.0, 10.0]}}))
    assert paper["plant"]["payloads"] == pytest.approx([1.0, 3.0, 5.0, 7.0, 9.0])


@pytest.mark.slow  # three compilations (9 s): the default tier keeps its 4 minutes
def test_the_chattering_floor_is_the_integral_of_the_tracking_voltages_rate():
    """``fosmc_jax.config.chattering_floor``, the total variation rate of the exact tracking
    voltage on the controller's grid, against int |dU/dt| dt / t_final with dU/dt by forward-mode
    autodiff in t and trapezoids on a 10x finer grid (measured 1e-5 to 6e-5 relative, the
    trapezoids' error and the turns between samples: 2e-4); a digital loop's 5 ms samples the
    same."""
    cfg = {**ARM, "sim": {"t_final": 1.0, "dt": 1e-3}}
    floor = fj.config.chattering_floor(cfg)
    problem = fj.build(cfg)
    t = jnp.linspace(0.0, 1.0, 10001)

    def rate(arm):
        u = lambda s: fj.tracking_voltage(arm, problem.reference(s), s)
        return jax.vmap(jax.jacfwd(u))(t)  # (samples, 3), V/s

    dU = np.abs(np.asarray(jax.jit(jax.vmap(rate))(problem.plants)))  # (arms, samples, 3)
    integral = ((dU[:, 1:] + dU[:, :-1]) / 2 * np.diff(np.asarray(t))[None, :, None]).sum(axis=1)  # over t_final = 1 s
    assert floor.shape == (2, 3) and np.all(floor > 0)
    np.testing.assert_allclose(floor, integral, rtol=2e-4)
    digital = fj.config.chattering_floor({**cfg, "controller": {"sample_period": 5e-3}})
    np.testing.assert_allclose(digital, integral, rtol=2e-4)


def test_the_chattering_floor_of_a_linear_plant_is_refused_in_one_line():
    with pytest.raises(fj.ConfigError, match="^plant.kind: the chattering floor is the arm's") as e:
        fj.config.chattering_floor({"sim": {"t_final": 0.1}})
    assert "\n" not in str(e.value)


@pytest.mark.slow  # a tune of an arm (about 20 s)
def test_tune_warns_of_a_chattering_bound_below_the_floor_and_reports_the_switching_above_it():
    """A bound on the total variation below the reference's own floor is named at the start; the
    result holds the floor and the final chattering's share above it; a bound on
    ``chattering_hf`` (not the total variation) has no floor."""
    cfg = {**ARM, "sim": {"t_final": 0.2, "dt": 1e-3, "integrator": "euler"},
           "tune": {"objective": "chattering_bound", "chattering_metric": "chattering", "chattering_bound": 0.5,
                    "global_candidates": 0}}  # fmt: skip
    lines = []
    result = fj.run_tune(cfg, steps=1, log=lines.append)
    floor = fj.config.chattering_floor(cfg).mean(axis=0)
    warned = [line for line in lines if "warning: [tune] chattering_bound 0.5 V/s is at or below the floor" in line]
    assert len(warned) == 1 and f"{floor.mean():.4g} V/s" in warned[0]
    got = result["chattering_floor"]
    np.testing.assert_allclose(got["per_joint"], floor, rtol=1e-12)
    tv = np.mean(result["final"]["metrics"]["chattering"])
    np.testing.assert_allclose(got["switching"], tv - floor.mean(), rtol=1e-12)
    hf = fj.run_tune({**cfg, "tune": dict(cfg["tune"], chattering_metric="chattering_hf")}, steps=1,
                     log=lambda _: None)  # fmt: skip
    assert "chattering_floor" not in hf
