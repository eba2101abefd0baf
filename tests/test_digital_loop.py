"""The digital loop (fosmc_jax._loop.digital): sampled FOSMC, sensors, delay, actuator limit.

Checked against the ideal loop (equality where the semantics coincide), against values
computed by hand on short runs, against central finite differences (gradients), and through
the config and the command line (one-line errors, exit status 2)."""

import dataclasses
import json
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fosmc_jax as fj
from fosmc_jax import _problems as _config
from fosmc_jax._app.cli import main
from fosmc_jax._loop.digital import SensorMemory, measure, quantize

P = fj.paper
REF = fj.Cycloid(jnp.array(P.THETA_START), jnp.array(P.THETA_END), jnp.array(P.TAU))
PARAMS = fj.FOSMCParams(jnp.array(P.C), jnp.array(P.POLES), jnp.array(P.GAMMA), jnp.array(P.DELTA_SETS[0]),
                       jnp.array(P.A_ROWS), jnp.array(P.B_ROWS))  # fmt: skip
PLANTS = fj.uncertain_plants(P.A_ROWS, P.B_ROWS, "sample", box=(P.A_LOWER, P.A_UPPER, P.B_LOWER, P.B_UPPER),
                             samples=3, seed=1)  # fmt: skip
X0S = fj.desired_state(REF(0.0))[None] + jnp.array([[0.0] * 9, [0.02, 0, 0, -0.01, 0, 0, 0.01, 0, 0]])
DT = 1e-4


def loop(period_steps=1, delay=0, counts=(0, 0, 0), noise=(0.0,) * 9, u_max=(np.inf,) * 3, derivatives="measured",
         params=PARAMS, law=None):  # fmt: skip
    T = jnp.asarray(period_steps * DT)
    law = fj.DiscreteFOSMC(params, T) if law is None else law
    sensors = fj.Sensors(jnp.asarray(counts, float), jnp.asarray(noise), derivatives)
    return fj.DigitalLoop(law, sensors, jnp.asarray(u_max), T, period_steps, delay)


def batch(controller, n=600, keys=None, integrator="euler", **kw):
    return fj.simulate_batch(PLANTS, controller, REF, X0S, DT, n_steps=n, integrator=integrator, keys=keys, **kw)


def assert_results_close(a, b, rtol=1e-10, atol=1e-12):
    for name in fj.METRIC_NAMES:
        np.testing.assert_allclose(getattr(a.metrics, name), getattr(b.metrics, name), rtol=rtol, atol=atol,
                                   err_msg=name)  # fmt: skip


# ---------------------------------------------------------------------------- equality with the ideal loop


@pytest.mark.slow  # four compilations (~13 s); the config-level test below checks the same in the default tier
def test_sample_period_dt_equals_the_ideal_loop_with_euler():
    """T = dt, d = 0, no noise, no quantization, no limit, Euler: the discrete integral
    w_{j+1} = w_j + T S Z_j is Euler's step for (14), so the results equal the ideal loop."""
    ideal = batch(PARAMS, fast=False)
    fast = batch(PARAMS, fast=True)
    for digital in (batch(fj.DiscreteFOSMC(PARAMS, jnp.asarray(DT))), batch(loop())):
        assert_results_close(digital, ideal)
        assert_results_close(digital, fast, rtol=1e-9)
    assert float(np.max(ideal.metrics.rms_error)) > 1e-4  # a non-trivial run


@pytest.mark.slow  # moved from the default tier (4-min budget): 4-8 s
def test_config_with_sample_period_dt_equals_the_ideal_loop(capsys, tmp_path):
    base = {"sim": {"t_final": 0.05, "dt": 1e-3, "integrator": "euler"}}
    digital = {**base, "controller": {"sample_period": 1e-3}}
    outs = []
    for cfg in (base, digital):
        path = tmp_path / "c.toml"
        path.write_text(_toml(cfg))
        assert main(["simulate", "--config", str(path), "--json"]) == 0
        outs.append(json.loads(capsys.readouterr()[0])["rollouts"][0]["metrics"])
    for name in fj.METRIC_NAMES:
        np.testing.assert_allclose(outs[1][name], outs[0][name], rtol=1e-10, atol=1e-14, err_msg=name)


def _toml(cfg: dict) -> str:
    lines = []
    for table, items in cfg.items():
        lines.append(f"[{table}]")
        lines += [f"{k} = {json.dumps(v)}" for k, v in items.items()]
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------------- pieces by hand


def test_quantize_rounds_to_the_encoder_grid_and_passes_gradients_straight_through():
    counts = jnp.array([4096.0, 0.0, 100.0])
    theta = jnp.array([0.30001, -1.234567, 0.05])
    q = 2 * np.pi / np.array([4096.0, 1.0, 100.0])
    want = np.array([q[0] * np.round(0.30001 / q[0]), -1.234567, q[2] * np.round(0.05 / q[2])])
    np.testing.assert_allclose(quantize(theta, counts), want, rtol=1e-15)
    np.testing.assert_allclose(jax.jacfwd(quantize)(theta, counts), np.eye(3))


def test_difference_estimator_by_hand():
    """Backward differences of the quantized, noisy angles at the sample period."""
    T = 1e-3
    sensors = fj.Sensors(jnp.array([1000.0, 0.0, 0.0]), jnp.array([1e-3, 0, 0, 0, 0, 0, 2e-3, 0, 0]), "difference")
    X = jnp.arange(9.0) / 10
    memory = SensorMemory(jnp.array([0.05, 0.25, 0.55]), jnp.array([1.0, 2.0, 3.0]))
    noise = jnp.array([-1.0, 0.5, 0.25])  # the angles' draws only, with differences
    assert sensors.noise_size() == 3
    Y, new = measure(sensors, X, memory, noise, jnp.asarray(T))
    q = 2 * np.pi / 1000
    theta = np.array([q * np.round((0.0 + 1e-3 * -1.0) / q), 0.3, 0.6 + 2e-3 * 0.25])
    dtheta = (theta - np.array([0.05, 0.25, 0.55])) / T
    ddtheta = (dtheta - np.array([1.0, 2.0, 3.0])) / T
    np.testing.assert_allclose(Y, np.stack([theta, dtheta, ddtheta], axis=1).reshape(9), rtol=1e-12)
    np.testing.assert_allclose(new.theta, theta, rtol=1e-14)
    np.testing.assert_allclose(new.dtheta, dtheta, rtol=1e-12)


class _Recorder(NamedTuple):
    """A law that applies U_j = (j + 1) * gains and keeps the measurements it was given."""

    gains: jax.Array

    def init(self, X0, r0, key=None):
        return (jnp.zeros((), X0.dtype), jnp.zeros(9, X0.dtype))

    def update(self, state, Y, r, t):
        j = state[0]
        return (j + 1) * self.gains, (j + 1, Y)


def test_delay_and_saturation_by_hand():
    """V_j = clip(U_{j-d}, -u_max, u_max) for j >= d, 0 before; held over m steps; the
    saturation fraction counts the simulation samples at the limit."""
    m, d, n = 3, 2, 20  # 20 steps: samples j = 0..6 at k = 0, 3, ..., 18; k = 19, 20 hold V_6
    gains = jnp.array([1.0, -2.0, 3.0])
    u_max = jnp.array([2.5, 7.0, 100.0])
    ctrl = loop(period_steps=m, delay=d, u_max=u_max, law=_Recorder(gains))
    plant = fj.LinearPlant(jnp.array(P.A_ROWS), jnp.array(P.B_ROWS))
    res = fj.simulate(plant, ctrl, REF, X0S[0], DT, n_steps=n, integrator="euler", save_every=m)
    js = np.arange(7)
    U = (js[:, None] + 1) * np.asarray(gains)
    V = np.where(js[:, None] >= d, np.clip(np.roll(U, d, axis=0), -u_max, u_max), 0.0)
    np.testing.assert_allclose(res.trace.U[:7], V)
    np.testing.assert_allclose(res.trace.U[7], V[6])  # the last sample, k = 20, still holds V_6
    per_k = np.repeat(V, m, axis=0)[: n + 1]
    per_k = np.concatenate([per_k, np.repeat(V[-1:], n + 1 - len(per_k), axis=0)])
    want_sat = np.mean(np.abs(per_k) >= np.asarray(u_max), axis=0)
    np.testing.assert_allclose(res.metrics.saturation_fraction, want_sat)
    assert want_sat[0] > 0 and want_sat[1] > 0 and want_sat[2] == 0
    np.testing.assert_allclose(res.metrics.max_abs_control, np.abs(per_k).max(axis=0))
    np.testing.assert_allclose(res.metrics.chattering, np.abs(np.diff(per_k, axis=0)).sum(axis=0) / (n * DT))


def test_measurements_reach_the_law_by_hand():
    """Quantized encoder, exact rates at j = 0, backward differences from j = 1."""
    T = 2e-3
    counts = jnp.array([2000.0, 2000.0, 2000.0])
    ctrl = fj.DigitalLoop(_Recorder(jnp.zeros(3)), fj.Sensors(counts, jnp.zeros(9), "difference"), jnp.full(3, jnp.inf),
                       jnp.asarray(T), 1, 0)  # fmt: skip
    Xs = [jnp.asarray(np.random.default_rng(j).normal(size=9)) for j in range(3)]
    state = ctrl.init(Xs[0], REF(0.0))
    Ys = []
    for j, X in enumerate(Xs):
        _, state = ctrl.update(state, X, REF(j * T), j * T)
        Ys.append(np.asarray(state.law[1]))
    q = 2 * np.pi / 2000
    th = [q * np.round(np.asarray(X[0::3]) / q) for X in Xs]
    np.testing.assert_allclose(Ys[0][0::3], th[0], rtol=1e-15)
    np.testing.assert_allclose(Ys[0][1::3], Xs[0][1::3], rtol=1e-15)  # the true rates at j = 0
    np.testing.assert_allclose(Ys[0][2::3], Xs[0][2::3], rtol=1e-15)
    v1 = (th[1] - th[0]) / T
    np.testing.assert_allclose(Ys[1][1::3], v1, rtol=1e-12)
    np.testing.assert_allclose(Ys[1][2::3], (v1 - np.asarray(Xs[0][1::3])) / T, rtol=1e-12)
    v2 = (th[2] - th[1]) / T
    np.testing.assert_allclose(Ys[2][1::3], v2, rtol=1e-12)
    np.testing.assert_allclose(Ys[2][2::3], (v2 - v1) / T, rtol=1e-12)


# ---------------------------------------------------------------------------- noise and seeds


@pytest.mark.slow  # moved from the default tier (4-min budget): 4-8 s
def test_noise_realizations_are_reproducible_and_distinct():
    noisy = loop(period_steps=5, noise=(1e-3, 1e-2, 1.0) * 3)
    keys = jax.random.split(jax.random.PRNGKey(3), 2)
    a = batch(noisy, keys=keys)
    b = batch(noisy, keys=keys)
    c = batch(noisy, keys=jax.random.split(jax.random.PRNGKey(4), 2))
    assert a.metrics.rms_error.shape == (len(PLANTS.a_rows) * 2 * 2, 3)
    np.testing.assert_array_equal(a.metrics.rms_error, b.metrics.rms_error)
    assert not np.allclose(a.metrics.rms_error, c.metrics.rms_error)
    assert not np.allclose(a.metrics.rms_error[0::2], a.metrics.rms_error[1::2])  # realizations differ
    # rollout order: plant, offset, realization
    one = fj.simulate(jax.tree.map(lambda x: x[1], PLANTS), noisy, REF, X0S[1], DT, n_steps=600,
                      integrator="euler", key=keys[1])  # fmt: skip
    np.testing.assert_allclose(a.metrics.rms_error[1 * 4 + 1 * 2 + 1], one.metrics.rms_error, rtol=1e-12)


@pytest.mark.slow  # two digital-loop programs: ~9 s
def test_zero_noise_std_equals_no_noise():
    zeros = loop(period_steps=5, counts=(4096.0,) * 3)
    none = dataclasses.replace(zeros, sensors=dataclasses.replace(zeros.sensors, noise_std=None))
    keys = jax.random.split(jax.random.PRNGKey(0), 2)
    # both with two keys: the vmap path for both (one key and no noise would run the generated
    # kernel, equal to rounding only)
    a, b = batch(zeros, keys=keys), batch(none, keys=keys)
    for name in fj.METRIC_NAMES:
        np.testing.assert_array_equal(getattr(a.metrics, name), getattr(b.metrics, name), err_msg=name)
        np.testing.assert_array_equal(getattr(a.metrics, name)[0::2], getattr(a.metrics, name)[1::2], err_msg=name)


# ---------------------------------------------------------------------------- gradients


def _loss(params, ctrl_of, key, n=400):
    res = fj.simulate(fj.LinearPlant(jnp.array(P.A_ROWS), jnp.array(P.B_ROWS)), ctrl_of(params), REF,
                      X0S[1], DT, n_steps=n, integrator="rk4", key=key)  # fmt: skip
    return jnp.sum(res.metrics.rms_error) + 1e-2 * jnp.sum(res.metrics.chattering_hf)


@pytest.fixture(scope="module")
def noisy_loss():
    """The loss in (delta, gamma, poles), its point and its gradient in all three, each compiled
    once for the three parameters' tests (a gradient in all three at once is, entry by entry,
    the gradient in each alone)."""
    base = PARAMS._replace(delta=PARAMS.delta / 50)
    ctrl_of = lambda p: loop(period_steps=5, delay=1, noise=(1e-4, 1e-3, 1e-2) * 3, u_max=(3.0, 4.0, 1.0), params=p)
    key = jax.random.PRNGKey(5)
    f = jax.jit(lambda x: _loss(base._replace(**x), ctrl_of, key))
    x0 = {name: getattr(base, name) for name in ("delta", "gamma", "poles")}
    return f, x0, jax.jit(jax.grad(f))(x0)


@pytest.mark.parametrize("name", ["delta", "gamma", "poles"])
def test_gradient_matches_central_differences_without_quantization(name, noisy_loss):
    """Sampled at 5 dt, delayed one sample, noisy (fixed key), saturating: the pathwise gradient
    equals central finite differences."""
    loss, point, grads = noisy_loss
    f = lambda x: loss({**point, name: x})
    x0 = point[name]
    g = np.asarray(grads[name])
    direction = np.asarray(jax.random.normal(jax.random.PRNGKey(1), x0.shape)) * np.abs(np.asarray(x0))
    h = 1e-5  # relative: truncation ~h^2, rounding ~1e-16 / h of the loss
    fd = (float(f(x0 + h * direction)) - float(f(x0 - h * direction))) / (2 * h)
    assert np.sum(g * direction) == pytest.approx(fd, rel=1e-4)


@pytest.mark.slow
def test_straight_through_gradient_points_like_a_coarse_difference_with_quantization():
    """With 1000-count encoders (q = 6.3 mrad) the loss is piecewise constant in delta at fine
    scales, where a finite difference is zero or a jump; the straight-through gradient points
    like a finite difference whose step (+-0.3 in log delta) moves the measurements by many q."""
    ctrl_of = lambda p: loop(period_steps=10, counts=(1000.0,) * 3, params=p)
    key = jax.random.PRNGKey(0)
    for scale in (0.1, 1.0):
        base = PARAMS._replace(delta=PARAMS.delta * scale)
        f = jax.jit(lambda log_d, base=base: _loss(base._replace(delta=jnp.exp(log_d)), ctrl_of, key, n=2000))
        x0 = jnp.log(base.delta)
        g = np.asarray(jax.grad(f)(x0))
        fd = np.array([(float(f(x0 + e)) - float(f(x0 - e))) / 0.6 for e in np.eye(3) * 0.3])
        assert np.all(np.sign(g) == np.sign(fd)), (scale, g, fd)
        assert g @ fd / np.linalg.norm(g) / np.linalg.norm(fd) > 0.95, (scale, g, fd)


# ---------------------------------------------------------------------------- config and CLI


@pytest.mark.parametrize(
    "text, key",
    [
        ("[controller]\nsample_period = 1.5e-4", "controller.sample_period"),
        ("[controller]\nsample_period = 5e-5", "controller.sample_period"),
        ("[controller]\nsample_period = -1e-3", "controller.sample_period"),
        ("[controller]\nsample_period = 1e-3\ndelay_samples = -1", "controller.delay_samples"),
        ("[controller]\ndelay_samples = 2", "controller.delay_samples"),
        ("[controller]\nsample_period = 1e-3\n[sensors]\nencoder_counts = [1, 2]", "sensors.encoder_counts"),
        ("[controller]\nsample_period = 1e-3\n[sensors]\nencoder_counts = -3", "sensors.encoder_counts"),
        ("[controller]\nsample_period = 1e-3\n[sensors]\nencoder_counts = 1.5", "sensors.encoder_counts"),
        ("[sensors]\nencoder_counts = 4096", "sensors.encoder_counts"),
        ("[controller]\nsample_period = 1e-3\n[sensors]\nderivatives = 'kalman'", "sensors.derivatives"),
        ("[controller]\nsample_period = 1e-3\n[sensors]\nnoise_std = [0, 0, 0]", "sensors.noise_std"),
        ("[controller]\nsample_period = 1e-3\n[sensors]\nnoise_std = [0, -1, 0, 0, 0, 0, 0, 0, 0]",
         "sensors.noise_std"),
        ("[controller]\nsample_period = 1e-3\n[sensors]\nderivatives = 'difference'\n"
         "noise_std = [1e-4, 1e-3, 0, 0, 0, 0, 0, 0, 0]", "sensors.noise_std"),
        ("[controller]\nsample_period = 1e-3\n[sensors]\nseed = -1", "sensors.seed"),
        ("[controller]\nsample_period = 1e-3\n[sensors]\nrealizations = 0", "sensors.realizations"),
        ("[controller]\nsample_period = 1e-3\n[sensors]\nfilter = 1", "sensors.filter"),
        ("[controller]\nsample_period = 1e-3\n[actuator]\nu_max = [1, 0, 1]", "actuator.u_max"),
        ("[controller]\nsample_period = 1e-3\n[actuator]\nu_max = 5", "actuator.u_max"),
        ("[actuator]\nu_max = [5, 5, 5]", "actuator.u_max"),
        ("[controller]\nsample_period = 1e-3\n[sim]\nsave_every = 15", "sim.save_every"),
        ("[controller]\nsample_period = 1e-3\n[tune]\ntrain_dt = 3e-4", "tune.train_dt"),
    ],
)  # fmt: skip
def test_bad_loop_keys_are_refused_in_one_line_and_nothing_is_written(capsys, tmp_path, text, key):
    path = tmp_path / "c.toml"
    path.write_text(text + "\n")
    plot = tmp_path / "p.png"
    assert main(["simulate", "--config", str(path), "--plot", str(plot)]) == 2
    err = capsys.readouterr()[1].strip()
    assert err.startswith(f"fosmc: error: {key}") and "\n" not in err
    assert not plot.exists()


@pytest.mark.slow  # 5 s: the default tier keeps to 4 minutes on 2 cores
def test_loop_keys_resolve_and_json_has_saturation_and_realizations(capsys, tmp_path):
    path = tmp_path / "c.toml"
    path.write_text(
        "[sim]\nt_final = 0.02\ndt = 1e-4\nintegrator = 'euler'\n"
        "initial_offset = [[0, 0, 0, 0, 0, 0, 0, 0, 0], [0.01, 0, 0, 0, 0, 0, 0, 0, 0]]\n"
        "[controller]\nsample_period = 5e-4\ndelay_samples = 1\n"
        "[sensors]\nencoder_counts = 4096\nderivatives = 'difference'\nnoise_std = [1e-4, 0, 0, 1e-4, 0, 0, 0, 0, 0]\n"
        "realizations = 3\nseed = 2\n"
        "[actuator]\nu_max = [1.0, 1.0, 0.2]\n"
    )
    cfg = _config.load(path)
    assert cfg["sensors"]["encoder_counts"] == [4096, 4096, 4096] and _config.sample_steps(cfg) == 5
    assert main(["simulate", "--config", str(path), "--json"]) == 0
    d = json.loads(capsys.readouterr()[0])
    rollouts = d["rollouts"]
    assert len(rollouts) == 2 * 3
    order = [(r["offset_index"], r["realization_index"]) for r in rollouts]
    assert order == [(o, r) for o in (0, 1) for r in (0, 1, 2)]
    sat = np.array([r["metrics"]["saturation_fraction"] for r in rollouts])
    assert np.all((sat >= 0) & (sat <= 1)) and sat.max() > 0
    assert np.all(np.array([r["metrics"]["max_abs_control"] for r in rollouts]) <= [1.0, 1.0, 0.2])


def test_certify_refuses_a_digital_loop(capsys, tmp_path):
    path = tmp_path / "c.toml"
    path.write_text("[controller]\nsample_period = 1e-3\n")
    assert main(["certify", "--config", str(path)]) == 2
    assert "cannot be certified" in capsys.readouterr()[1]


def test_digital_loop_refuses_a_continuous_law():
    with pytest.raises(TypeError, match="sampled controller"):
        dataclasses.replace(loop(), law=fj.FOSMC(PARAMS))


@pytest.mark.slow  # 256 rollouts of the README's example (~9 s)
def test_readme_digital_loop_example_runs():
    """docs/api.md's digital loop (its section "A digital loop") runs after the README's Python
    API example, whose names it uses, as written."""
    import re
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    readme, api = (root / "README.md").read_text(), (root / "docs" / "api.md").read_text()
    section = readme[readme.index("## Python API") : readme.index("## Where things live")]
    blocks = re.findall(r"```python\n(.*?)```", section, re.S)
    loop = re.findall(r"```python\n(.*?)```", api[api.index("### A digital loop") :], re.S)[0]
    assert len(blocks) == 1 and "DigitalLoop" in loop
    scope: dict = {}
    for name, code in (("README.md", blocks[0]), ("docs/api.md", loop)):
        exec(compile(code, name, "exec"), scope)
    res = scope["res"]
    assert res.metrics.chattering_hf.shape == (256, 3)
    ok = ~np.asarray(res.diverged)  # 4 of the box's plants diverge: their metrics NaN, as the README says
    assert int(res.survivors) == ok.sum() == 252 and np.isnan(np.asarray(res.metrics.max_abs_control)[~ok]).all()
    assert np.all(np.asarray(res.metrics.max_abs_control)[ok] <= 24.0)


def test_report_realistic_blocks_equal_committed_tables():
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    report = (root / "REPRODUCTION.md").read_text()
    for name in ("realistic", "tradeoff"):
        begin, end = f"<!-- begin:{name} -->\n", f"<!-- end:{name} -->"
        block = report[report.index(begin) + len(begin) : report.index(end)]
        assert block == (root / "tuning/results/reproduction" / f"{name}.md").read_text(), name
    preset = root / "tuning/configs/realistic_arm.toml"
    assert _config.load(preset) == _config.load(root / "fosmc_jax/_problems/presets/realistic_arm.toml")


@pytest.mark.slow
def test_tradeoff_exists_in_the_realistic_loop_and_not_in_the_ideal_one():
    """Shortened sweep (0.2 s): lowering delta 3000-fold raises the realistic loop's
    chattering_hf more than tenfold, while the ideal loop's stays below 0.2 V until the
    smallest delta."""
    from fosmc_jax._app import reproduce as reproduction

    sweeps = reproduction.tradeoff_sweeps(t_final=0.2, log=lambda _: None)
    delta = sweeps[0]
    real = np.mean(delta.realistic.chattering_hf, axis=-1)
    ideal = np.mean(delta.ideal.chattering_hf, axis=-1)
    assert delta.values[0] == 3.0 and delta.values[-1] == 0.001
    assert real[-1] > 10 * real[0]
    assert np.all(ideal[:-1] < 0.2) and np.all(real > 5 * ideal)
