"""Tuning: constraint maps, gradients against finite differences, NaN guard, frozen
parameters, and a resumed run ending exactly where an uninterrupted one does."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fosmc_jax as fj
from fosmc_jax._search import tune as tuner

P = fj.paper


def problem(n_steps=200, dt=2e-3, samples=3):
    ref = fj.Cycloid(jnp.array(P.THETA_START), jnp.array(P.THETA_END), jnp.array(0.5))
    base = fj.FOSMCParams(*(jnp.asarray(x) for x in (P.C, P.POLES, P.GAMMA, P.DELTA_SETS[1], P.A_ROWS, P.B_ROWS)))
    box = (P.A_LOWER, P.A_UPPER, P.B_LOWER, P.B_UPPER)
    plants = fj.uncertain_plants(P.A_ROWS, P.B_ROWS, "sample", box=box, samples=samples, seed=3)
    plants = fj.LinearPlant(*(jnp.asarray(x) for x in plants))
    X0s = fj.desired_state(ref(0.0))[None] + jnp.array([[0.02] + [0.0] * 8])
    opts = dict(n_steps=n_steps, integrator="rk4", switching="ratio", checkpoint_every=50)
    return tuner.Problem(plants, base, ref, X0s, jnp.asarray(dt), opts)


def test_constraint_maps_round_trip_and_respect_bounds():
    prob = problem()
    p = tuner.Tunable(jnp.array([200.0, 100.0, 60.0]), jnp.array([350.0, 300.0, 30.0]), jnp.array(P.POLES))
    u = tuner.to_internal(p, prob.base)
    back = tuner.to_physical(u, prob.base)
    for a, b in zip(back, p):
        np.testing.assert_allclose(a, b, rtol=1e-12)
    # any unconstrained point maps to positive delta, gamma and negative poles
    rand = tuner.Tunable(*(jax.random.normal(jax.random.PRNGKey(i), np.shape(x)) * 5 for i, x in enumerate(p)))
    q = tuner.to_physical(rand, prob.base)
    assert np.all(q.delta > 0) and np.all(q.gamma > 0) and np.all(q.poles < 0)
    # with the floor, gamma stays above the (pole-dependent) bound (24)-(26)
    floor = tuner.GammaFloor(5.987, 0.62, "paper")
    q = tuner.to_physical(rand, prob.base, floor)
    K = fj.gain_from_poles(prob.base.a_rows, prob.base.b_rows, q.poles)
    bound = fj.gamma_bounds(5.987, 0.62, prob.base.C, prob.base.b_rows, K, "paper")
    assert np.all(q.gamma > bound)
    with pytest.raises(ValueError, match="gamma"):
        tuner.to_internal(p._replace(gamma=jnp.array([1.0, 1.0, 1.0])), prob.base, floor)


# both modes in the slow tier (12-22 s of the default tier's 4 minutes on 2 cores); the default tier
# checks gradients against central differences in tests/test_tuning_kinds.py (SMC's log gains) and
# tests/test_digital_loop.py, and the kernel's against the vmap path in tests/test_generated.py
@pytest.mark.slow
@pytest.mark.parametrize("mode", ["reverse", "forward"])
def test_gradient_matches_central_differences(mode):
    prob = problem()
    obj = tuner.Objective(error_ref=0.05, chattering_ref=5.0, worst_case="cvar", worst_weight=0.5, cvar_alpha=0.5)
    loss = tuner.make_loss(prob, obj, None)
    p0 = tuner.Tunable(prob.base.delta, prob.base.gamma, prob.base.poles)
    u0 = tuner.to_internal(p0, prob.base)
    (_, _), grad = tuner.value_and_grad(loss, mode)(u0)
    flat, unravel = jax.flatten_util.ravel_pytree(u0)
    g = jax.flatten_util.ravel_pytree(grad)[0]
    f = jax.jit(lambda x: loss(unravel(x))[0])
    h = 1e-5
    for i in range(flat.size):
        e = jnp.zeros_like(flat).at[i].set(h)
        fd = (f(flat + e) - f(flat - e)) / (2 * h)
        np.testing.assert_allclose(g[i], fd, rtol=2e-4, atol=1e-8, err_msg=f"parameter {i}")


def quadratic(target):
    def loss(u):
        parts = [jnp.sum((a - b) ** 2) for a, b in zip(u, target)]
        return sum(parts), (parts[0], parts[1])

    return loss


def start_point():
    return tuner.Tunable(jnp.zeros(3), jnp.zeros(3), jnp.zeros((3, 3)))


def test_frozen_parameters_do_not_move_and_free_ones_converge():
    target = tuner.Tunable(jnp.ones(3), 2 * jnp.ones(3), -jnp.ones((3, 3)))
    s = tuner.Settings(
        steps=300, learning_rate=0.1, schedule="constant", mode="reverse", free=("delta", "poles"), checkpoint_every=0
    )
    u, hist = tuner.run(quadratic(target), start_point(), s, log=lambda _: None)
    np.testing.assert_array_equal(u.gamma, 0.0)
    np.testing.assert_allclose(u.delta, 1.0, atol=1e-2)
    np.testing.assert_allclose(u.poles, -1.0, atol=1e-2)
    assert hist["loss"][-1] < hist["loss"][0]


def test_a_gradient_above_the_guard_at_the_start_falls_back_and_a_resumed_run_keeps_it(tmp_path):
    """fosmc tune's fallback (a rough loop's truncated gradient where the whole horizon's
    explodes): a loss whose gradient at the start is above ``guard`` is replaced by ``fallback``
    for the whole run, as if the run had been given the fallback; below the guard it is kept."""
    target = tuner.Tunable(jnp.ones(3), 2 * jnp.ones(3), -jnp.ones((3, 3)))
    base = quadratic(target)
    steep = lambda u: (lambda v: (1e6 * v[0], v[1]))(base(u))  # the same minimum, a gradient ~1e7
    s = tuner.Settings(steps=4, learning_rate=0.1, schedule="constant", mode="reverse", checkpoint_every=2)
    lines = []
    _, hist = tuner.run(steep, start_point(), s, fallback=base, guard=1e3, log=lines.append)
    _, plain = tuner.run(base, start_point(), s, log=lambda _: None)
    assert any("fallback" in line for line in lines)
    np.testing.assert_allclose(hist["loss"], plain["loss"], rtol=1e-12)  # the fallback's run, from the start
    _, kept = tuner.run(steep, start_point(), s, fallback=base, guard=1e8, log=lambda _: None)
    assert kept["loss"][0] == pytest.approx(1e6 * plain["loss"][0])  # below the guard: the loss itself

    # killed after step 3 (the checkpoint of step 2), resumed where no guard would switch: the fallback still
    def killer(msg):
        if msg.startswith("tune: step    3/"):
            raise Killed

    with pytest.raises(Killed):
        tuner.run(steep, start_point(), s, fallback=base, guard=1e3, checkpoint=tmp_path / "ck.npz", log=killer)
    _, resumed = tuner.run(steep, start_point(), s, fallback=base, guard=np.inf, checkpoint=tmp_path / "ck.npz",
                       resume=True, log=lambda _: None)  # fmt: skip
    np.testing.assert_allclose(resumed["loss"], plain["loss"], rtol=1e-12)


def test_nan_guard_skips_the_step():
    target = tuner.Tunable(jnp.ones(3), jnp.ones(3), jnp.ones((3, 3)))
    base = quadratic(target)

    def loss(u):
        v, aux = base(u)
        # the loss is NaN wherever delta's first coordinate is exactly 0: the start point
        return jnp.where(u.delta[0] == 0, jnp.nan, v), aux

    messages = []
    s = tuner.Settings(steps=3, mode="reverse", checkpoint_every=0)
    u, hist = tuner.run(loss, start_point(), s, log=messages.append)
    assert hist["skipped"] == [True, True, True]
    assert any("skipped" in m for m in messages)
    for a, b in zip(u, start_point()):
        np.testing.assert_array_equal(a, b)  # nothing applied


def test_the_best_iterate_is_returned_when_a_step_lands_on_a_flat_penalty():
    """Past delta[0] = 0.5 the loss is a flat penalty with zero gradient (what diverged
    rollouts give); large steps jump there and Adam's momentum keeps going: the run returns
    the step of lowest loss, not the last one."""
    target = tuner.Tunable(jnp.ones(3), jnp.zeros(3), jnp.zeros((3, 3)))
    base = quadratic(target)

    def loss(u):
        v, aux = base(u)
        return jnp.where(u.delta[0] > 0.5, 100.0, v), aux

    s = tuner.Settings(steps=6, learning_rate=0.3, schedule="constant", mode="reverse", checkpoint_every=0)
    u, hist = tuner.run(loss, start_point(), s, log=lambda _: None)
    assert hist["loss"][-1] == 100.0  # the run ended on the penalty
    assert hist["best_step"] == int(np.argmin(hist["loss"])) < 6
    assert np.isclose(float(loss(u)[0]), min(hist["loss"]), rtol=1e-12) and min(hist["loss"]) < hist["loss"][0]
    np.testing.assert_array_equal(u.delta, hist["params"][hist["best_step"]][0])


@pytest.mark.slow  # two tuning runs: ~10 s
def test_resume_equals_uninterrupted(tmp_path):
    prob = problem(n_steps=100)
    obj = tuner.Objective(error_ref=0.05, chattering_ref=5.0)
    loss = tuner.make_loss(prob, obj, None)
    u0 = tuner.to_internal(tuner.Tunable(prob.base.delta, prob.base.gamma, prob.base.poles), prob.base)
    s = tuner.Settings(steps=6, learning_rate=0.05, mode="reverse", checkpoint_every=2)
    full, hist_full = tuner.run(loss, u0, s, checkpoint=tmp_path / "a.npz", log=lambda _: None)

    # dies after step 5 is logged: the last checkpoint is at step 4
    assert_resumes_to(loss, u0, s, tmp_path / "b.npz", 5, full, hist_full)


class Killed(Exception):
    pass


def assert_resumes_to(loss, u0, s, checkpoint, step, full, hist_full):
    """A run killed after ``step`` is logged, then resumed, ends at ``full`` with its history."""

    def killer(msg):
        if msg.startswith(f"tune: step {step:4d}/"):
            raise Killed

    with pytest.raises(Killed):
        tuner.run(loss, u0, s, checkpoint=checkpoint, log=killer)
    resumed, hist = tuner.run(loss, u0, s, checkpoint=checkpoint, resume=True, log=lambda _: None)
    for a, b in zip(full, resumed):
        np.testing.assert_array_equal(a, b)
    assert hist["loss"] == hist_full["loss"]


@pytest.mark.slow  # three reverse-mode compilations (~17 s on 2 cores)
def test_truncated_gradient_keeps_values_and_is_exact_beyond_the_horizon():
    """``truncate_every``: the rollout's values are unchanged; a window at least as long as the
    horizon gives the whole horizon's gradient (to rounding); a shorter one another, finite one
    (on this smooth loop the two differ, which is why the ideal loop is not truncated)."""
    prob = problem(n_steps=100)
    u = tuner.to_internal(tuner.Tunable(prob.base.delta, prob.base.gamma, prob.base.poles), prob.base)
    obj = tuner.Objective(error_ref=0.01)

    def grad(window):
        p = prob._replace(options=dict(prob.options, truncate_every=window))
        return jax.jit(jax.value_and_grad(tuner.make_loss(p, obj, None), has_aux=True))(u)

    (v0, _), g0 = grad(0)
    (v1, _), g1 = grad(100)
    (v2, _), g2 = grad(10)
    assert float(v0) == float(v1) == float(v2)
    flat = lambda g: np.concatenate([np.ravel(x) for x in g])
    np.testing.assert_allclose(flat(g1), flat(g0), rtol=1e-12, atol=1e-14)
    assert np.isfinite(flat(g2)).all() and not np.allclose(flat(g2), flat(g0), rtol=1e-3)


def test_norm_does_not_overflow():
    big = tuner.Tunable(jnp.array([3e200, 4e200]), jnp.zeros(1), jnp.zeros(1))
    assert np.isclose(tuner._norm(big), 5e200, rtol=1e-12)
    assert tuner._norm(big._replace(gamma=jnp.array([jnp.inf]))) == np.inf
    assert tuner._norm(tuner.Tunable(jnp.zeros(2), jnp.zeros(1), jnp.zeros(1))) == 0.0


CONFIGS = sorted((__import__("pathlib").Path(__file__).parent.parent / "tuning" / "configs").glob("*.toml"))


@pytest.mark.slow  # a reverse-mode compilation per committed config
@pytest.mark.parametrize("path", CONFIGS, ids=[p.stem for p in CONFIGS])
def test_tune_gradient_is_finite_sane_and_its_steps_lower_the_loss(path):
    """At ``fosmc tune``'s start on every committed config (the best of 16 global candidates, a
    shortened 1 s horizon), with the config's own [tune] (the automatic gradient window, and tune's
    fallback to a truncated one where the whole horizon's explodes): the gradient tune uses is
    finite and below 1e5 in norm (no exponential growth: the whole horizon's reached 1e226 on the
    realistic preset from a poorer start; the sign law's ideal loop gives 5.5e3 in gamma), and
    five Adam steps reach a lower training loss."""
    from fosmc_jax import _problems as _config
    from fosmc_jax._search.front import global_stage

    cfg = _config.load(path)
    cfg = _config.replace(
        cfg, sim={"t_final": min(cfg.sim.t_final, 1.0)}, tune={"train_t_final": min(cfg.tune.train_t_final, 1.0)}
    )
    _, train, p0 = _config.tuning_problems(cfg)
    obj = tuner.objective_of(cfg["tune"], tuner.evaluate(train, p0)["metrics"])
    start, _ = global_stage(train, obj, p0, 16, free=tuple(cfg["tune"]["params"]), log=lambda _: None)
    u0 = tuner.to_internal(start, train.base)
    truncated = _config.fallback_problem(cfg, train)  # as fosmc tune: its fallback where the gradient explodes
    fallback = None if truncated is None else tuner.make_loss(truncated, obj, None)
    rate = tuner.learning_rate(cfg["tune"]["learning_rate"], _config.rough_loop(cfg))
    settings = tuner.Settings(steps=5, learning_rate=rate, mode="reverse", free=tuple(cfg["tune"]["params"]),
                              checkpoint_every=0)  # fmt: skip
    _, hist = tuner.run(tuner.make_loss(train, obj, None), u0, settings, fallback=fallback,
                        guard=_config.GRADIENT_GUARD, log=lambda _: None)  # fmt: skip
    assert np.isfinite(hist["loss"][0]) and np.isfinite(hist["grad_norm"][0]) and hist["grad_norm"][0] < 1e5
    assert not any(hist["skipped"])
    if path.stem in NO_DESCENT and not min(hist["loss"][1:]) < hist["loss"][0]:
        pytest.xfail(NO_DESCENT[path.stem])
    assert min(hist["loss"][1:]) < hist["loss"][0]


#: Committed configs whose first five Adam steps from tune's start were seen not to lower the loss.
NO_DESCENT = {
    "arm_sign_dt": "the sign law: only gamma acts, and the loss is rough in it",
}


# ---------------------------------------------------------------------------- L-BFGS


def rosenbrock(u):
    """Rosenbrock's valley in delta[0], delta[1] (minimum 0 at (1, 1)), a quadratic bowl in the
    other free entries: Adam's small steps crawl along the valley, a line search does not."""
    x, y = u.delta[0], u.delta[1]
    v = (1 - x) ** 2 + 100 * (y - x**2) ** 2 + jnp.sum((u.delta[2] - 0.5) ** 2) + jnp.sum((u.poles + 1) ** 2)
    return v, (v, v)


def lbfgs(steps, **kw):
    return tuner.Settings(steps=steps, mode="reverse", checkpoint_every=0, optimizer="lbfgs", **kw)


def test_lbfgs_reaches_the_rosenbrock_minimum_and_keeps_frozen_parameters():
    start = start_point()._replace(delta=jnp.array([-1.2, 1.0, 0.0]), gamma=jnp.array([3.0, 3.0, 3.0]))
    u, hist = tuner.run(rosenbrock, start, lbfgs(80, free=("delta", "poles")), log=lambda _: None)
    np.testing.assert_allclose(u.delta, [1.0, 1.0, 0.5], atol=1e-4)
    np.testing.assert_allclose(u.poles, -1.0, atol=1e-4)
    np.testing.assert_array_equal(u.gamma, 3.0)  # frozen
    assert all(b <= a for a, b in zip(hist["loss"], hist["loss"][1:]))  # no accepted step ascends
    # Adam from the same start with as many gradients as L-BFGS's line search took stays far off
    adam = tuner.Settings(steps=80, learning_rate=0.05, schedule="constant", mode="reverse", free=("delta", "poles"),
                      checkpoint_every=0)  # fmt: skip
    v, _ = tuner.run(rosenbrock, start, adam, log=lambda _: None)
    assert float(rosenbrock(v)[0]) > 1e3 * float(rosenbrock(u)[0])


def test_lbfgs_backs_off_a_flat_penalty_and_a_nan():
    """Past delta[0] = 0.5 the loss is the diverged rollouts' flat penalty, past 0.8 NaN: the line
    search rejects both trials, ends below 0.5 and every step it accepts descends."""
    target = tuner.Tunable(jnp.ones(3), jnp.zeros(3), jnp.zeros((3, 3)))
    base = quadratic(target)

    def loss(u):
        v, aux = base(u)
        v = jnp.where(u.delta[0] > 0.5, 100.0, v)
        return jnp.where(u.delta[0] > 0.8, jnp.nan, v), aux

    messages = []
    u, hist = tuner.run(loss, start_point(), lbfgs(20), log=messages.append)
    assert 0.4 < float(u.delta[0]) <= 0.5 and float(loss(u)[0]) < hist["loss"][0]
    assert all(b <= a for a, b in zip(hist["loss"], hist["loss"][1:]))


def test_lbfgs_resumes_to_the_uninterrupted_run_and_refuses_adams_checkpoint(tmp_path):
    start = start_point()._replace(delta=jnp.array([-1.2, 1.0, 0.0]))
    s = lbfgs(12)._replace(checkpoint_every=2)
    full, hist_full = tuner.run(rosenbrock, start, s, checkpoint=tmp_path / "a.npz", log=lambda _: None)

    assert_resumes_to(rosenbrock, start, s, tmp_path / "b.npz", 7, full, hist_full)  # last checkpoint: step 6
    with pytest.raises(ValueError, match="of the lbfgs optimizer, not of adam"):
        tuner.run(rosenbrock, start, s._replace(optimizer="adam"), checkpoint=tmp_path / "b.npz", resume=True)


def test_the_config_names_the_optimizer_and_refuses_others():
    from fosmc_jax import _problems as _config

    assert _config.resolve({"tune": {"optimizer": "lbfgs"}})["tune"]["optimizer"] == "lbfgs"
    with pytest.raises(fj.ConfigError, match="tune.optimizer"):
        _config.resolve({"tune": {"optimizer": "bfgs"}})


def stack(*points):
    return jax.tree.map(lambda *x: jnp.stack(x), *points)


def test_starts_each_follow_their_own_adam_and_equal_single_runs():
    """run_starts: K starts in one vmapped call, each as run's Adam with its own rate; the point
    returned is the lowest loss of all; the starts' rates span rate / spread .. rate * spread."""
    target = tuner.Tunable(jnp.ones(3), 2 * jnp.ones(3), -jnp.ones((3, 3)))
    loss = quadratic(target)
    far = start_point()._replace(delta=jnp.full(3, -3.0))
    s = tuner.Settings(steps=5, learning_rate=0.1, schedule="cosine", mode="reverse", free=("delta", "poles"),
                       checkpoint_every=0)  # fmt: skip
    rates = tuner.rates_of(0.1, 2, 2.0)
    np.testing.assert_allclose(rates, [0.05, 0.2])
    np.testing.assert_allclose(tuner.rates_of(0.1, 3, 1.0), 0.1)
    u, hist = tuner.run_starts(loss, stack(start_point(), far), s, rates=rates, log=lambda _: None)
    _, one = tuner.run(loss, start_point(), s._replace(learning_rate=0.05), log=lambda _: None)
    _, two = tuner.run(loss, far, s._replace(learning_rate=0.2), log=lambda _: None)
    np.testing.assert_allclose(hist["loss"], np.minimum(one["loss"], two["loss"]), rtol=1e-10)
    np.testing.assert_array_equal(u.gamma, 0.0)  # frozen
    best = min(one["loss"] + two["loss"] + [hist["last"]])
    assert float(loss(u)[0]) == pytest.approx(best, rel=1e-10)


def test_a_start_on_the_flat_penalty_goes_back_to_its_best_at_half_its_rate():
    """Past delta[0] = 0.5 the loss is the diverged rollouts' flat penalty (zero gradient): a
    start that steps there is sent back to its best point with a fresh Adam state, the other
    start goes on untouched."""
    target = tuner.Tunable(jnp.ones(3), jnp.zeros(3), jnp.zeros((3, 3)))
    base = quadratic(target)

    def loss(u):
        v, aux = base(u)
        return jnp.where(u.delta[0] > 0.5, 100.0, v), aux

    s = tuner.Settings(steps=8, learning_rate=0.3, schedule="constant", mode="reverse", checkpoint_every=0)
    slow = start_point()._replace(delta=jnp.array([-2.0, 0.0, 0.0]))
    u, hist = tuner.run_starts(loss, stack(start_point(), slow), s, rates=np.array([0.3, 0.01]), log=lambda _: None)
    assert sum(hist["restarts"]) >= 1
    assert all(x < 100.0 for x in hist["loss"])
    assert float(u.delta[0]) <= 0.5 and float(loss(u)[0]) < hist["loss"][0]


def test_the_config_names_the_starts():
    from fosmc_jax import _problems as _config

    assert _config.resolve({})["tune"]["starts"] == 1
    assert _config.resolve({"tune": {"starts": 8}})["tune"]["starts"] == 8
    with pytest.raises(fj.ConfigError, match="tune.starts"):
        _config.resolve({"tune": {"starts": 0}})


@pytest.mark.slow  # a global stage and a batched gradient's compilation (~15 s on 2 cores)
def test_fosmc_tune_with_starts_tunes_the_global_stages_best_at_once(tmp_path):
    """``[tune] starts = 2``: the global stage's best two candidates start the gradient steps,
    each step one batched call; the result is at least as good as the global stage's best."""
    from fosmc_jax._app.tune import run_tune

    cfg = {"plant": {"uncertainty": "sample", "samples": 2},
           "sim": {"t_final": 0.25, "dt": 2e-3, "integrator": "euler"},
           "tune": {"global_candidates": 16, "starts": 2, "steps": 3, "mode": "reverse", "remat_steps": 0}}  # fmt: skip
    lines = []
    res = run_tune(cfg, log=lines.append)
    assert any("the best 2 start the gradient steps" in line for line in lines)
    assert any("best of 2 starts" in line for line in lines)
    assert res["start"]["global_candidates"] == 16 and len(res["history"]["loss"]) == 3
    assert min(res["history"]["loss"] + [res["history"]["last"]]) <= res["history"]["loss"][0]


def test_the_config_names_the_cma_stage():
    from fosmc_jax import _problems as _config

    assert _config.resolve({})["tune"]["cma_generations"] == 100
    assert _config.resolve({"tune": {"cma_generations": 50}})["tune"]["cma_generations"] == 50
    with pytest.raises(fj.ConfigError, match="tune.cma_generations: expected a non-negative integer"):
        _config.resolve({"tune": {"cma_generations": -1}})


@pytest.mark.slow  # a global stage, a batched loss and a batched gradient compiled (~20 s on 2 cores)
def test_fosmc_tune_with_a_cma_stage_starts_the_gradient_steps_at_its_best():
    """``[tune] cma_generations``: CMA-ES runs from the global stage's best on the training loss
    and the gradient steps (here two starts at once) begin at its best point: their first loss is
    the stage's, which is at most the global stage's best's."""
    from fosmc_jax._app.tune import run_tune

    cfg = {"plant": {"uncertainty": "sample", "samples": 2},
           "sim": {"t_final": 0.25, "dt": 2e-3, "integrator": "euler"},
           "tune": {"global_candidates": 16, "starts": 2, "cma_generations": 3, "steps": 2, "mode": "reverse",
                    "remat_steps": 0}}  # fmt: skip
    lines = []
    res = run_tune(cfg, log=lines.append)
    cma = res["start"]["cma"]
    assert cma["generations"] == 3 and cma["loss"] <= cma["start_loss"]
    assert any(line.startswith("tune: CMA-ES stage: 3 generations") for line in lines)
    assert res["history"]["loss"][0] == pytest.approx(cma["loss"], rel=1e-9, abs=1e-9)


def test_a_budget_gives_the_global_stage_what_the_steps_do_not_need():
    """``fosmc tune --budget``'s plan, made once the gradient is compiled: the steps end at the
    budget's end; the global stage takes the time ``tune.steps`` steps and a possible second
    compilation (the fallback's) leave, ``GLOBAL_SHARE`` of it at least, nothing past the end."""
    from fosmc_jax._app import tune as app

    assert app.plan(None, 0.01, 100, 0.0, now=0.0) == app.Plan(None, None)
    cheap = app.plan(100.0, 0.01, 100, 0.0, now=0.0)  # 100 steps need 1.03 s
    assert cheap.steps == 100.0 and cheap.global_stage == pytest.approx(100.0 - 103 * 0.01)
    fallback = app.plan(100.0, 0.01, 100, 10.0, now=0.0)  # a second compilation kept back
    assert fallback.steps == 100.0 and fallback.global_stage == pytest.approx(90.0 - 103 * 0.01)
    dear = app.plan(100.0, 1.0, 100, 0.0, now=0.0)  # the steps would take it all: the least share
    assert dear.global_stage == pytest.approx(app.GLOBAL_SHARE * 100.0)
    late = app.plan(10.0, 0.01, 100, 0.0, now=12.0)  # already past the end: one chunk, then the steps
    assert late.global_stage == 12.0 and late.steps == 10.0


def test_run_steps_with_the_prepared_gradient():
    """``prepare`` compiles and times a loss's value and gradient at a point of the starts' shape;
    ``run`` and ``run_starts`` step with it instead of compiling their own: the same steps as
    without; a run that falls back compiles the fallback's."""
    target = tuner.Tunable(jnp.ones(3), 2 * jnp.ones(3), -jnp.ones((3, 3)))
    base = quadratic(target)
    steep = lambda u: (lambda v: (1e6 * v[0], v[1]))(base(u))
    s = tuner.Settings(steps=3, learning_rate=0.1, schedule="constant", mode="reverse", checkpoint_every=0)
    quiet = lambda _: None
    calls = []

    def counted(stepper, name):
        return stepper._replace(fn=lambda u: (calls.append(name), stepper.fn(u))[1])

    st = tuner.prepare(base, start_point(), "reverse", log=quiet)
    assert st.mode == "reverse" and st.compile_seconds > 0 and st.step_seconds > 0
    _, alone = tuner.run(base, start_point(), s, log=quiet)
    _, hist = tuner.run(base, start_point(), s, stepper=counted(st, "loss"), log=quiet)
    np.testing.assert_allclose(hist["loss"], alone["loss"], rtol=1e-12)
    assert calls and set(calls) == {"loss"}
    calls.clear()
    steep_st = counted(tuner.prepare(steep, start_point(), "reverse", log=quiet), "steep")
    _, fell = tuner.run(steep, start_point(), s, fallback=base, guard=1e3, stepper=steep_st, log=quiet)
    np.testing.assert_allclose(fell["loss"], alone["loss"], rtol=1e-12)
    assert calls == ["steep"]  # the start's gradient only: the fallback's steps are its own program
    calls.clear()
    two = jax.tree.map(lambda x: jnp.stack([x, x]), start_point())
    batched = tuner.prepare(base, two, starts=True, log=quiet)
    _, starts = tuner.run_starts(base, two, s, stepper=counted(batched, "starts"), log=quiet)
    assert calls and set(calls) == {"starts"}
    np.testing.assert_allclose(starts["loss"], alone["loss"], rtol=1e-12)


@pytest.mark.slow  # real time: a 30 s budget filled with steps
def test_a_budget_holds_from_the_start_within_its_margin():
    """``fosmc tune --budget S`` ends within 1.05 S + 2 s of its start (issue 33's margin), its
    compilations included, on a tiny config given more steps than fit: the steps fill the budget
    and stop at its deadline."""
    import time

    started = time.perf_counter()
    cfg = {"plant": {"uncertainty": "sample", "samples": 2}, "sim": {"t_final": 0.2, "dt": 2e-3, "integrator": "euler"},
           "tune": {"train_dt": 4e-3, "global_candidates": 64}}  # fmt: skip
    res = fj.run_tune(cfg, steps=10**6, budget=30.0, started=started, log=lambda _: None)
    assert time.perf_counter() - started <= 1.05 * 30.0 + 2.0
    assert 1 < len(res["history"]["loss"]) < 10**6
