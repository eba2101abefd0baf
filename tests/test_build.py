"""The research API: fosmc_jax.build(config) -> Problem, problem.simulate(params), results that
cannot hide a divergence, Monte-Carlo ([sample], pairing) batches."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fosmc_jax as fj
from fosmc_jax._app.cli import main

# one short ideal-loop linear problem: every test below that simulates it shares its compilations
SHORT = {"sim": {"t_final": 0.2, "dt": 1e-3, "integrator": "euler", "initial_offset": [[0.0] * 9, [0.02] + [0.0] * 8]}}
# a short arm problem for the Monte-Carlo batches (the arm's compiled kernel where it is built)
OFFSETS = [0.01, 0, 0, 0.01, 0, 0, 0.01, 0, 0]
ARM = {"plant": {"kind": "arm"}, "sim": {"t_final": 0.05, "dt": 1e-3, "pairing": "paired"},
       "sample": {"count": 4, "seed": 3, "payloads": [0.0, 3.0], "offsets": OFFSETS}}  # fmt: skip


def test_build_takes_a_path_a_preset_name_a_dict_a_resolved_config_or_none(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text("[sim]\nt_final = 0.2\ndt = 1e-3\n")
    from_path, from_dict = fj.build(path), fj.build({"sim": {"t_final": 0.2, "dt": 1e-3}})
    assert from_path.options == from_dict.options and from_path.options["n_steps"] == 200
    assert fj.build(fj.config.load(path)).options == from_path.options
    assert fj.build(None).options["n_steps"] == round(fj.config.defaults()["sim"]["t_final"] / 1e-4)
    preset = fj.build("realistic_arm")
    assert isinstance(preset, fj.Problem) and preset.kind == "fosmc"
    assert preset.options == fj.build(fj.config.PRESETS["realistic_arm"]).options
    with pytest.raises(fj.ConfigError, match="^config: expected a TOML path, a preset name"):
        fj.build(3)


def test_float64_without_x64_is_refused_in_one_line_and_float32_builds():
    with jax.enable_x64(False):
        with pytest.raises(fj.ConfigError, match=r'^sim.precision: "float64" needs JAX\'s 64-bit mode') as e:
            fj.build(None)
        assert "\n" not in str(e.value)
        assert fj.build({"sim": {"precision": "float32"}}).X0s.dtype == jnp.float32


def test_config_dicts_take_numpy_and_jax_arrays_where_they_take_lists():
    user = {"controller": {"delta": np.array([0.1, 0.2, 0.3]), "poles": jnp.asarray(fj.paper.POLES)},
            "sim": {"t_final": np.float64(0.5), "initial_offset": np.zeros((2, 9))}}  # fmt: skip
    cfg = fj.config.resolve(user)
    assert cfg["controller"]["delta"] == [0.1, 0.2, 0.3] and len(cfg["sim"]["initial_offset"]) == 2
    assert cfg["controller"]["poles"] == fj.paper.POLES.tolist()


def test_params_by_name_are_checked_in_one_line():
    problem = fj.build(SHORT)
    assert set(problem.params()) == {"delta", "gamma", "poles"}
    cases = {r"params: unknown name\(s\) 'dleta'": {"dleta": [1.0, 1.0, 1.0]},
             r"params.delta: expected shape \(3,\), got \(2,\)": {"delta": [1.0, 1.0]},
             r"params.delta: expected shape \(3,\), got \(1,\)": {"delta": [1.0]},
             "params.gamma: expected finite numbers": {"gamma": [np.nan, 1.0, 1.0]}}  # fmt: skip
    for message, params in cases.items():
        with pytest.raises(ValueError, match="^" + message) as e:
            problem.controller(params)
        assert "\n" not in str(e.value)


@pytest.mark.slow  # 9 s: the default tier keeps to 4 minutes on 2 cores
def test_the_builders_gradient_in_delta_equals_central_differences():
    """d/d delta of the batch's mean rms error (ideal loop, linear plant, two initial states),
    against central differences with a relative step of 1e-4 (3e-7 apart; at 1e-6 the loss's
    rounding noise shows, 4e-5): agreement to 1e-5 relative."""
    problem = fj.build(SHORT)
    delta0 = np.asarray(problem.params()["delta"])
    loss = lambda d: problem.simulate({"delta": d}, fast=False).mean().rms_error.mean()
    grad = np.asarray(jax.grad(loss)(jnp.asarray(delta0)))
    fd = np.empty(3)
    for j in range(3):
        h = 1e-4 * delta0[j]
        e = np.eye(3)[j] * h
        fd[j] = (float(loss(delta0 + e)) - float(loss(delta0 - e))) / (2 * h)
    assert np.all(np.isfinite(grad)) and np.abs(grad).max() > 0
    np.testing.assert_allclose(grad, fd, rtol=1e-5, atol=1e-6 * np.abs(fd).max())
    # the same loss under jit (the input checks run while tracing), and under jit of vmap over two deltas
    assert float(jax.jit(loss)(jnp.asarray(delta0))) == pytest.approx(float(loss(delta0)), rel=1e-12)
    both = jax.jit(jax.vmap(loss))(jnp.stack([delta0, 2 * delta0]))
    assert float(both[0]) == pytest.approx(float(loss(delta0)), rel=1e-12)


def test_a_diverged_rollout_cannot_pass_for_a_good_one():
    """A NaN initial state (traced, past the input checks, which refuse a concrete one) diverges
    at t = 0: its metrics are NaN, not the zeros its empty sums hold; means and summaries leave
    it out and count it."""
    problem = fj.build(SHORT)
    run = jax.jit(lambda X0s: problem._replace(X0s=X0s).simulate(fast=False))
    res = run(problem.X0s.at[1, 0].set(jnp.nan))
    assert list(np.asarray(res.diverged)) == [False, True] and float(res.diverged_at[1]) == 0.0
    assert all(np.isnan(np.asarray(m)[1]).all() and np.isfinite(np.asarray(m)[0]).all() for m in res.metrics)
    np.testing.assert_array_equal(np.asarray(res.mean().rms_error), np.asarray(res.metrics.rms_error[0]))
    assert int(res.survivors) == 1
    summary = res.summary()
    assert summary["diverged_excluded"] == 1 and summary["p50"]["rms_error"] == pytest.approx(
        np.asarray(res.metrics.rms_error[0]).tolist()
    )


@pytest.mark.slow  # four single rollouts of the arm compile one more program: 9 s
def test_a_paired_sampled_batch_equals_its_rollouts_one_by_one():
    """[sample] draws payloads and offsets; paired, rollout i is plant i from offset i: the batch
    (the arm's kernel where built) equals fj.simulate of each pair to rounding."""
    problem = fj.build(ARM)
    drawn = fj.config.draws(fj.config.resolve(ARM))
    assert problem.rollouts == 4 and drawn["payloads"].shape == (4,) and drawn["offsets"].shape == (4, 9)
    assert np.all((drawn["payloads"] >= 0) & (drawn["payloads"] <= 3)) and np.all(drawn["offsets"][:, 1] == 0)
    np.testing.assert_array_equal(np.asarray(problem.plants.payload), drawn["payloads"])
    batch = problem.simulate()
    controller = problem.controller()
    options = {k: v for k, v in problem.options.items() if k != "pairing"}
    for i in range(4):
        plant = jax.tree.map(lambda x, i=i: x[i], problem.plants)
        one = fj.simulate(plant, controller, problem.reference, problem.X0s[i], problem.dt, **options)
        for name in fj.METRIC_NAMES:
            np.testing.assert_allclose(getattr(batch.metrics, name)[i], getattr(one.metrics, name), rtol=1e-9,
                                       atol=1e-13, err_msg=name)  # fmt: skip
    # the same seed draws the same sample; cross pairing runs every plant from every offset
    assert fj.build(ARM).X0s.tolist() == problem.X0s.tolist()
    assert fj.build({**ARM, "sim": {**ARM["sim"], "pairing": "cross"}}).rollouts == 16


def test_sample_and_pairing_errors_name_their_key():
    cases = {"sample.count: nothing to draw": {"sample": {"count": 5}},
             "sample.payloads: applies to plant.kind = 'arm' only": {"sample": {"count": 5, "payloads": [0, 1]}},
             r"sample.payloads: expected \[low, high\]": {"plant": {"kind": "arm"},
                                                          "sample": {"count": 5, "payloads": [2, 1]}},
             "sample.offsets: draws nothing without sample.count": {"sample": {"offsets": 0.1}},
             "sim.pairing: 'paired' needs as many of each, or one":
                 {"plant": {"kind": "arm", "payloads": [1, 2]},
                  "sim": {"pairing": "paired", "initial_offset": [[0] * 9] * 3}}}  # fmt: skip
    for message, user in cases.items():
        with pytest.raises(fj.ConfigError, match="^" + message):
            fj.build(user)


@pytest.mark.slow  # 4 s: the default tier keeps to 4 minutes on 2 cores
def test_simulate_on_a_sample_prints_percentiles_and_plots_histograms(tmp_path, capsys):
    path = tmp_path / "mc.toml"
    path.write_text('[plant]\nkind = "arm"\n[sim]\nt_final = 0.05\ndt = 1e-3\npairing = "paired"\n'
                    f"[sample]\ncount = 4\nseed = 3\npayloads = [0.0, 3.0]\noffsets = {OFFSETS}\n")  # fmt: skip
    assert main(["simulate", "--config", str(path), "--plot", str(tmp_path / "h.png")]) == 0
    out = capsys.readouterr().out
    assert "batch of 4: 0 diverged" in out and "p5 " in out and "p95 " in out and "rollout plant" not in out
    assert (tmp_path / "h.png").stat().st_size > 10_000


@pytest.mark.slow  # the realistic preset's digital loop in reverse mode: ~40 s on 2 cores
def test_the_gradient_on_the_realistic_preset_equals_central_differences():
    """d/d delta of mean rms_error + 0.1 mean chattering_hf on the realistic preset (1 kHz
    digital loop, differenced rates, a sample of delay, 0.1 s), against central differences
    with a relative step of 1e-4: measured 1e-6 apart, asserted to 1e-5. The encoder's rounding
    is switched off here: its derivative is the straight-through one (taken as 1, the
    tuner's surrogate), so with it the gradient is not the difference quotient's limit
    (0.2-16% apart per joint at this horizon; docs/api.md)."""
    cfg = fj.config.replace(
        fj.config.load("realistic_arm"), sim={"t_final": 0.1}, sensors={"encoder_counts": [0, 0, 0]}
    )
    problem = fj.build(cfg)
    delta0 = np.asarray(problem.params()["delta"])

    def loss(delta):
        mean = problem.simulate({"delta": delta}, fast=False).mean()
        return mean.rms_error.mean() + 0.1 * mean.chattering_hf.mean()

    grad = np.asarray(jax.grad(loss)(jnp.asarray(delta0)))
    fd = np.array([(float(loss(delta0 + e)) - float(loss(delta0 - e))) / (2 * e[j])
                   for j, e in enumerate(np.diag(1e-4 * delta0))])  # fmt: skip
    np.testing.assert_allclose(grad, fd, rtol=1e-5)
