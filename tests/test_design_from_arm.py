"""The design model from the arm (issue 25, item 3): ``[model] from = "arm"`` derives the
controller's nominal rows and uncertainty box from the configured ``[arm]`` along the
configured reference, and every command designs on them; ``from = "paper"`` (the default)
changes nothing."""

import copy
import itertools
import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fosmc_jax as fj
from fosmc_jax import _problems as problems
from fosmc_jax._app import cli
from fosmc_jax._design import paper
from fosmc_jax._plants.arm import ArmParams, rows_over
from fosmc_jax._plants.reference import desired_state
from fosmc_jax._problems import design as design_of_config

# not the paper's reference nor its payload range, and a relative range on the friction: the
# design must follow all three (8 corners of F's range)
ARM = {
    "plant": {"kind": "arm", "payloads": [0.0, 6.0]},
    "model": {"from": "arm"},
    "trajectory": {"start": [-0.5, -1.2, -0.3], "end": [0.8, 0.4, 1.0], "duration": 1.5},
    "arm": {"payload_range": [0.0, 6.0], "uncertainty": {"F": 0.3, "samples": 3}},
    "sim": {"t_final": 0.05, "dt": 1e-3},
}


@pytest.fixture(scope="module")
def arm_cfg():
    """The resolved config, its design model derived once (a compilation of the arm's rows,
    ~7 s on 2 cores, ~15 s under load; shared by the module)."""
    return problems.resolve(ARM)


def rows_at(cfg: dict, params: ArmParams, rng) -> np.ndarray:
    """The arm's instantaneous rows [a | b] (11, 81, 3, 12) at 11 random payloads in
    arm.payload_range x 81 random instants of the configured reference (the shapes of the design
    grid, so nothing is compiled again)."""
    reference = problems.reference_of(cfg, jnp.float64)
    times = jnp.asarray(rng.uniform(0.0, cfg["trajectory"]["duration"], design_of_config.ARM_MODEL_TIMES))
    states = jax.vmap(lambda t: desired_state(reference(t)))(times)
    payloads = jnp.asarray(rng.uniform(*cfg["arm"]["payload_range"], design_of_config.ARM_MODEL_PAYLOADS))
    a, b = rows_over(params, payloads, states)
    return np.concatenate([np.asarray(a), np.asarray(b)], axis=-1)


def test_from_arm_needs_an_arm_and_replaces_the_papers_rows_refusing_them_in_one_line():
    for user, message in [
        ({"model": {"from": "arm"}}, r"^model\.from: 'arm' derives the design model from \[arm\], for plant\.kind "
                                     r"= 'arm' only; got plant\.kind = 'linear'$"),
        ({"model": {"from": "both"}}, r"^model\.from: expected one of paper, arm; got 'both'$"),
        ({**ARM, "model": {"from": "arm", "B_rows": np.eye(3).tolist()}}, r"^model\.B_rows: not used with model\."
                                                                          r"from = 'arm'"),
        ({**ARM, "plant": {**ARM["plant"], "box": {"A_lower": (paper.A_LOWER - 1).tolist()}}},
         r"^plant\.box\.A_lower: not used with model\.from = 'arm'"),
    ]:  # fmt: skip
        with pytest.raises(fj.ConfigError, match=message) as e:
            problems.resolve(user)
        assert "\n" not in str(e.value)


def test_from_paper_leaves_the_design_unchanged_and_derives_nothing():
    """The default config's controller, box and K are the paper's, exactly; an arm config with
    the default from = "paper" still designs on the paper's rows, and no arm rows are derived."""
    misses = design_of_config._arm_model.cache_info().misses
    cfg = problems.resolve({})
    assert cfg["model"]["from"] == "paper"
    ctrl = problems.controller_of(cfg, jnp.float64)
    np.testing.assert_array_equal(ctrl.a_rows, paper.A_ROWS)
    np.testing.assert_array_equal(ctrl.b_rows, paper.B_ROWS)
    for got, want in zip(problems.box_of(cfg), (paper.A_LOWER, paper.A_UPPER, paper.B_LOWER, paper.B_UPPER)):
        np.testing.assert_array_equal(got, want)
    K = fj.gain_from_poles(ctrl.a_rows, ctrl.b_rows, ctrl.poles)
    np.testing.assert_array_equal(K, fj.gain_from_poles(*(jnp.asarray(x) for x in (paper.A_ROWS, paper.B_ROWS,
                                                                                   paper.POLES))))  # fmt: skip
    arm = fj.build({**ARM, "model": {"from": "paper"}})
    np.testing.assert_array_equal(arm.base.a_rows, paper.A_ROWS)
    np.testing.assert_array_equal(arm.base.b_rows, paper.B_ROWS)
    assert design_of_config._arm_model.cache_info().misses == misses


def test_the_controller_is_designed_on_the_arms_rows(arm_cfg):
    """build's controller (simulate, tune, front), certify's and box_of all use the arm's model:
    the same rows, so the same K (16), exactly."""
    design = problems.design_model(arm_cfg)
    assert design.source == "arm" and "8 corners" in design.sampled and "[0, 6] kg" in design.sampled
    base = fj.build(arm_cfg).base
    np.testing.assert_array_equal(base.a_rows, design.A_rows)
    np.testing.assert_array_equal(base.b_rows, design.B_rows)
    np.testing.assert_array_equal(problems.controller_of(arm_cfg, jnp.float64).a_rows, design.A_rows)
    for got, want in zip(problems.box_of(arm_cfg), design.box):
        np.testing.assert_array_equal(got, want)
    K = fj.gain_from_poles(base.a_rows, base.b_rows, base.poles)
    np.testing.assert_array_equal(K, fj.gain_from_poles(*(jnp.asarray(x) for x in (design.A_rows, design.B_rows)),
                                                        jnp.asarray(arm_cfg["controller"]["poles"])))  # fmt: skip
    assert np.abs(design.A_rows - paper.A_ROWS).max() > 10  # the arm's rows, not the paper's


def test_the_rows_are_the_midpoint_of_a_box_that_holds_the_arms_rows(arm_cfg):
    """An independent check of the containment: the rows of the nominal arm, of the arms
    simulated ([arm.uncertainty]'s draws) and of the 8 corners of F's range, at random payloads
    in arm.payload_range x random instants of the configured reference, lie in the box (exactly:
    no tolerance), whose midpoint is the nominal. The corners' rows between the design grid's
    samples leave the grid's hull (measured: 10 of the 384,912 entries here), not the widened
    box. And the box is not loose: its width is at most 1.25 x their spread per entry
    (measured: 1.015)."""
    design = problems.design_model(arm_cfg)
    lower = np.concatenate([design.box[0], design.box[2]], axis=1)
    upper = np.concatenate([design.box[1], design.box[3]], axis=1)
    np.testing.assert_array_equal(np.concatenate([design.A_rows, design.B_rows], axis=1), (lower + upper) / 2)
    nominal, sampled = problems.arm_params_of(arm_cfg, jnp.float64), problems.arm_samples(arm_cfg)
    arms = [nominal] + [ArmParams(**{k: jnp.asarray(v[i]) for k, v in sampled.items()}) for i in range(3)]
    arms += [nominal._replace(F=nominal.F * (1 + 0.3 * jnp.asarray(s))) for s in itertools.product((-1, 1), repeat=3)]
    rng = np.random.default_rng(1)
    rows = np.stack([rows_at(arm_cfg, params, rng) for params in arms])
    assert np.all(rows >= lower) and np.all(rows <= upper)
    spread = rows.max(axis=(0, 1, 2)) - rows.min(axis=(0, 1, 2))
    width = upper - lower
    live = spread > 1e-6 * np.abs(upper).max()
    assert np.all(width[live] <= 1.25 * spread[live]), np.max(width[live] / spread[live])


def test_the_rows_follow_the_configured_reference_and_are_derived_once(arm_cfg):
    """Resolving the config again, its tuning problems and its held-out batch (fosmc front:
    another arm seed, other payloads) reuse the derived model, the same arrays; the paper's
    reference gives another one."""
    misses = design_of_config._arm_model.cache_info().misses
    design = problems.design_model(arm_cfg)
    again = problems.resolve(copy.deepcopy(arm_cfg))
    assert problems.design_model(again) is design
    plain, train, _ = problems.tuning_problems(arm_cfg)
    np.testing.assert_array_equal(plain.base.a_rows, design.A_rows)
    np.testing.assert_array_equal(train.base.a_rows, design.A_rows)
    held = fj.config.held_out_config(arm_cfg)
    assert held["plant"]["payloads"] != arm_cfg["plant"]["payloads"]
    assert problems.design_model(held) is design
    assert design_of_config._arm_model.cache_info().misses == misses
    papers = problems.design_model(problems.resolve({**ARM, "trajectory": {}}))
    assert np.abs(papers.A_rows - design.A_rows).max() > 1e-3


@pytest.mark.slow  # the vertex enumeration of both models' boxes (2^24 and 2^23 vertices): ~15 s
def test_bounds_reports_both_models_and_the_K_the_simulated_controller_uses(arm_cfg, monkeypatch, capsys):
    d = fj.run_bounds(arm_cfg)
    assert d["model"] == "arm" and set(d["models"]) == {"paper", "arm"}
    base = fj.build(arm_cfg).base
    np.testing.assert_array_equal(d["K"], fj.gain_from_poles(base.a_rows, base.b_rows, base.poles))
    for key in ("alpha", "beta", "K", "CB"):
        np.testing.assert_array_equal(d["models"]["arm"][key], d[key])
    papers = fj.build({**ARM, "model": {"from": "paper"}}).base
    np.testing.assert_array_equal(d["models"]["paper"]["K"], fj.gain_from_poles(papers.a_rows, papers.b_rows,
                                                                                papers.poles))  # fmt: skip
    np.testing.assert_array_equal(d["nominal_A_rows"], problems.design_model(arm_cfg).A_rows)
    assert d["models"]["paper"]["alpha"] == pytest.approx(5.9871, abs=1e-4)
    assert 0 < d["alpha"] < d["models"]["paper"]["alpha"]  # the arm's own box is tighter around its nominal
    monkeypatch.setattr(cli.commands, "run_bounds", lambda *args, **kwargs: d)
    assert cli.cmd_bounds(types.SimpleNamespace(config=None, json=False)) == 0
    out = capsys.readouterr().out
    assert out.startswith("model: arm (K, CB and the bounds below: the nominal arm and the 8 corners")
    assert "both design models (in use: arm):" in out and "K of the paper model (3x9; not the controller's):" in out


def test_only_entries_that_move_the_rows_make_design_corners():
    """Corners over the drawn entries that enter the rows: Fc's non-zero joint (a zero stays
    zero) and F's three joints; the external torque's half-widths (outside the rows) add none."""
    widths = {"Fc": 0.3, "F": 0.2, "tau_sin": 0.5, "f_sin": 0.5, "samples": 2}
    arm = {"Fc": [1.0, 0.0, 0.0], "tau_sin": [0.5, 0.5, 0.5], "uncertainty": widths}
    cfg = fj.config.resolve({"plant": {"kind": "arm", "payloads": [0.0]}, "arm": arm})
    arms, which = design_of_config._design_arms(cfg["arm"], cfg["arm"]["uncertainty"])
    assert len(arms) == 1 + 2**4 and "the 16 corners" in which
    Fc = np.array([np.asarray(a.Fc) for a in arms])
    np.testing.assert_allclose(sorted(set(Fc[:, 0])), [0.7, 1.0, 1.3])
    assert not Fc[:, 1:].any()
    assert all(np.array_equal(np.asarray(a.tau_sin), [0.5, 0.5, 0.5]) for a in arms)
