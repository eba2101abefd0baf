"""``fosmc front``: the front is non-dominated and sorted, its points re-simulate to their stored
metrics, a resumed run ends where an uninterrupted one does, and bad arguments are refused."""

import json

import numpy as np
import pytest

from fosmc_jax import _problems as _config
from fosmc_jax._app import study as front_study
from fosmc_jax._app.cli import main
from fosmc_jax._search import front as search_front
from fosmc_jax._search import tune as tuner
from fosmc_jax.search import epsilon, nondominated

TINY = {
    "plant": {"uncertainty": "sample", "samples": 3},
    "sim": {"t_final": 0.3, "dt": 2e-3, "integrator": "euler"},
}
SETTINGS = search_front.Settings(search="staged", points=3, candidates=16, steps=3, chunk=8, checkpoint_every=1)


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    out = tmp_path_factory.mktemp("front")
    cfg = _config.resolve(TINY)
    lines = []
    result = front_study.study(cfg, SETTINGS, out=out, log=lines.append)
    result["log"] = lines
    return out, result


def test_nondominated_by_hand():
    x = np.array([1.0, 2.0, 3.0, 2.0, np.nan, 0.5])
    y = np.array([3.0, 2.0, 1.0, 3.0, 0.1, 5.0])
    np.testing.assert_array_equal(nondominated(x, y), [True, True, True, False, False, True])


def test_front_is_nondominated_sorted_and_written(study):
    out, res = study
    pts = res["points"]
    assert res["axes"] == ["rms_error", "chattering_hf"] and len(pts) >= 2
    e = np.array([np.mean(p["metrics"]["rms_error"]) for p in pts])
    c = np.array([np.mean(p["metrics"]["chattering_hf"]) for p in pts])
    assert np.all(np.diff(c) > 0) and np.all(np.diff(e) < 0)  # sorted by chattering, hence error falls
    assert nondominated(e, c).all()
    for p in pts:
        assert set(p["params"]) == {"delta", "gamma", "poles"} and len(p["metrics"]["rms_error"]) == 3
        assert len(p["held_out"]["rms_error"]) == 3 and p["held_out_diverged"] == 0
    ratio = [np.mean(p["held_out"]["rms_error"]) / np.mean(p["metrics"]["rms_error"]) for p in pts]
    holds = sum(abs(r - 1) <= 0.25 for r in ratio)
    assert f"front: held out: {holds} of {len(pts)} points within 25% of their training rms_error, the worst " \
           f"{max(ratio):.3g}x (point {int(np.argmax(ratio))})" in "\n".join(res["log"])  # fmt: skip
    assert {"Table 1 set 1", "Table 1 set 2", "Table 1 set 3", "SGN"} <= set(res["references"])
    on_disk = json.loads((out / "front.json").read_text())
    assert len(on_disk["points"]) == len(pts) and (out / "front.png").stat().st_size > 10_000


def test_point_resimulates_to_the_stored_metrics(study, tmp_path, capsys):
    out, res = study
    config = tmp_path / "c.toml"
    config.write_text(
        '[plant]\nuncertainty = "sample"\nsamples = 3\n[sim]\nt_final = 0.3\ndt = 2e-3\nintegrator = "euler"\n'
    )
    i = len(res["points"]) - 1
    assert main(["simulate", "--config", str(config), "--params", str(out / "front.json"), "--point", str(i),
                 "--json"]) == 0  # fmt: skip
    summary = json.loads(capsys.readouterr()[0])["summary"]
    for name, value in res["points"][i]["metrics"].items():
        np.testing.assert_allclose(summary["mean"][name], value, rtol=1e-9, atol=1e-15, err_msg=name)
    assert main(["simulate", "--config", str(config), "--params", str(out / "front.json"), "--point", "99"]) == 2
    assert "--point" in capsys.readouterr()[1]


@pytest.mark.parametrize("kill_at", ["front: CMA-ES generation 2/", "front: local round 2/"])
def test_resume_ends_where_an_uninterrupted_run_does(tmp_path, kill_at):
    """Killed inside the CMA-ES stage (which resumes at its start) or in the local rounds."""
    cfg = _config.resolve(TINY)
    plain, train, p0 = _config.tuning_problems(cfg)
    settings = SETTINGS._replace(cma=2)
    whole = search_front.front_search(train, plain, p0, settings, log=lambda _: None)
    st = whole["stages"]
    cma_evaluations = st["evaluations"] - 16 - 3 * 8  # but the global stage's and the local rounds'
    assert st["cma_generations"] == 2 and cma_evaluations in (2 * 8 * k for k in range(1, 5))  # 1-4 runs

    class Crash(Exception):
        pass

    def crash(msg):
        if msg.startswith(kill_at):
            raise Crash

    checkpoint = tmp_path / "checkpoint.npz"
    with pytest.raises(Crash):
        search_front.front_search(train, plain, p0, settings, checkpoint=checkpoint, log=crash)
    resumed = search_front.front_search(
        train, plain, p0, settings, checkpoint=checkpoint, resume=True, log=lambda _: None
    )
    assert resumed["stages"] | {"wall_time_s": 0} == st | {"wall_time_s": 0}
    assert len(resumed["points"]) == len(whole["points"])
    for a, b in zip(resumed["points"], whole["points"]):
        for k in a["params"]:
            np.testing.assert_allclose(a["params"][k], b["params"][k], rtol=1e-12)
        np.testing.assert_allclose(a["metrics"]["rms_error"], b["metrics"]["rms_error"], rtol=1e-12)


@pytest.mark.parametrize(
    "args, key",
    [(["--budget", "0"], "--budget"), (["--points", "0"], "--points"), (["--steps", "-1"], "--steps"),
     (["--compare", "/nonexistent.json"], "--compare"), (["--search", "nsga2", "--steps", "2"], "--steps"),
     (["--search", "staged", "--generations", "2"], "--generations"), (["--generations", "0"], "--generations"),
     (["--population", "2"], "--population"), (["--plain-share", "1"], "--plain-share")],
)  # fmt: skip
def test_bad_front_arguments_are_refused(tmp_path, capsys, args, key):
    out = tmp_path / "out"
    assert main(["front", "--out", str(out), *args]) == 2
    assert capsys.readouterr()[1].startswith(f"fosmc: error: {key}")
    assert not out.exists()


def test_cma_es_wrapper_reaches_the_minimum_of_a_quadratic():
    from fosmc_jax._search.peers import cma_es

    a = np.array([0.3, -1.2, 2.0, 0.5])
    f = lambda X: np.sum((X - a) ** 2, axis=1)
    best, value, X, F_ = cma_es(f, np.zeros(4), 1.0, budget=30.0, popsize=12, log=lambda _: None)
    np.testing.assert_allclose(best, a, atol=1e-4)
    assert value < 1e-8 and len(X) == len(F_) and F_.min() == value


def test_cma_es_keeps_to_its_generations_and_to_a_random_stream_of_its_own():
    """``generations`` caps the run, a spent budget still runs one generation, the same seed gives
    the same draws, and NumPy's global stream (the caller's) is left as it was."""
    from fosmc_jax._search.peers import cma_es

    f = lambda X: np.sum(X**2, axis=1)
    np.random.seed(7)
    expected = np.random.rand()
    np.random.seed(7)
    _, _, X, _ = cma_es(f, np.ones(3), 0.3, budget=60.0, popsize=8, generations=4, log=lambda _: None)
    assert len(X) == 32 and np.random.rand() == expected
    np.testing.assert_array_equal(cma_es(f, np.ones(3), 0.3, 60.0, 8, generations=4, log=lambda _: None)[2], X)
    assert len(cma_es(f, np.ones(3), 0.3, budget=0.0, popsize=8, log=lambda _: None)[2]) == 8


def test_factors_map_and_random_search_cover_the_box():
    from fosmc_jax._search import peers

    cfg = _config.resolve(TINY)
    plain, train, p0 = _config.tuning_problems(cfg)
    z = np.array([[1.0, 0, 0, -1, 0, 0, 0, 0, 2.0]])
    p = peers.from_factors(p0, z)
    np.testing.assert_allclose(p.delta[0], np.asarray(p0.delta) * [10, 1, 1])
    np.testing.assert_allclose(p.gamma[0], np.asarray(p0.gamma) * [0.1, 1, 1])
    np.testing.assert_allclose(p.poles[0], np.asarray(p0.poles) * np.array([1, 1, 100])[:, None])
    r = peers.random_search(train, p0, budget=1e-9, chunk=8, log=lambda _: None)  # one chunk at least
    lo, hi = peers.bounds()
    assert r["z"].shape == (8, 9) and np.all((r["z"] >= lo) & (r["z"] <= hi))
    assert r["metrics"]["rms_error"].shape == (8, 3)


def test_global_stage_keeps_frozen_parameters_and_never_scores_worse_than_the_start():
    from fosmc_jax._search import tune as tuner

    cfg = _config.resolve(TINY)
    plain, train, p0 = _config.tuning_problems(cfg)
    m = tuner.evaluate(train, p0)["metrics"]
    obj = tuner.objective_of(cfg["tune"], m)
    best, score = search_front.global_stage(train, obj, p0, 16, free=("delta",), chunk=8, log=lambda _: None)
    np.testing.assert_array_equal(best.gamma, p0.gamma)
    np.testing.assert_array_equal(best.poles, p0.poles)
    start = float(tuner.rollout_costs(type("M", (), {k: np.asarray(v)[None] for k, v in m.items()}),
                                  np.array([False]), obj)[0][0])  # fmt: skip
    assert abs(start) < 1e-9  # log scale, scales from the start itself
    assert score <= start


def test_global_stage_holds_the_start_and_the_whole_grid_of_common_factors():
    z = search_front.global_factors(300, seed=0, grid_share=1.0)
    g = search_front.grid_size(300, 1.0)
    assert g == 6 and z.shape == (300, 9)
    np.testing.assert_array_equal(z[0], 0.0)  # the start itself
    grid = search_front.grid_factors(g)
    np.testing.assert_array_equal(z[1 : 1 + g**3], grid)
    assert np.all(grid[:, 0:3] == grid[:, [0]]) and np.all(grid[:, 6:9] == grid[:, [6]])  # common to the joints
    lo, hi = search_front.bounds()
    for k in range(3):  # ends of each range included
        np.testing.assert_array_equal(np.unique(grid[:, 3 * k])[[0, -1]], [lo[3 * k], hi[3 * k]])
    draws = z[1 + g**3 :]
    assert np.all((draws >= lo) & (draws <= hi)) and np.ptp(draws[:, 0:3], axis=1).min() > 0  # per joint
    assert (
        search_front.grid_size(300, 0.5) == 5
        and search_front.grid_size(8, 1.0) == 0
        and search_front.grid_size(28, 1.0) == 3
    )


@pytest.mark.slow  # 5 s: the default tier keeps to 4 minutes on 2 cores
def test_stages_from_the_budget_run_until_their_deadlines(tmp_path):
    """Sizes from the budget: the probe's chunk joins the global stage, and the checkpoint
    holds the stage deadlines in order (offsets from the run's start, which a
    resumed run keeps). A training surrogate (train_dt), so that every stage runs."""
    import cma  # noqa: F401  (imported and compiled before: the budget then goes to the stages)

    plain, train, p0 = _config.tuning_problems(_config.resolve({**TINY, "tune": {"train_dt": 4e-3}}))
    search_front.evaluate_many(train, search_front.sample_candidates(p0, 8, 0), 8, log=lambda _: None)
    settings = search_front.Settings(search="staged", points=3, chunk=8, budget=3.0, checkpoint_every=1)
    r = search_front.front_search(train, plain, p0, settings, checkpoint=tmp_path / "c.npz", log=lambda _: None)
    st = r["stages"]
    assert st["candidates"] % 8 == 0 and st["candidates"] >= 16  # the global stage and the probe's chunk
    # how many generations and rounds fit depends on the machine's load: only their bookkeeping is checked
    assert st["evaluations"] >= st["candidates"] + 8 * st["local_rounds"]
    header, _ = tuner._load(tmp_path / "c.npz")
    ends = header["ends"]
    # in order; not held against the budget: a stage that overruns its deadline (a loaded machine:
    # 3.66 s of a 3 s budget once) moves the later ones, and timings belong to the benchmarks
    assert 0 < ends["global"] <= ends["cma"] <= ends["local"] <= ends["end"]
    assert header["steps"] == st["local_rounds"] and header["cma_generations"] == st["cma_generations"]


def test_a_plain_share_of_zero_runs_no_plain_rounds(tmp_path):
    """With a training surrogate and ``polish_share = 0`` the training front is re-evaluated on
    the plain problem and no plain round runs: the search's time goes to NSGA-II."""
    plain, train, p0 = _config.tuning_problems(_config.resolve(dict(TINY, tune={"train_t_final": 0.1})))
    n = SETTINGS.chunk  # the population in one call of the other tests' chunk: their compilations
    settings = search_front.Settings(population=n, chunk=n, budget=1.0, polish_share=0.0, gradient_share=0.0)
    st = search_front.front_search(train, plain, p0, settings, log=lambda _: None)["stages"]
    assert st["plain_rounds"] == 0 and st["from_plain_rounds"] == 0
    assert st["plain_evaluations"] > 0 and st["nsga2_generations"] >= 1


def test_local_round_perturbs_only_non_dominated_points_within_the_box():
    z = np.array([[0.0] * 9, [0.2] * 9, [-0.2] * 9, [0.4] * 9])
    m = {"rms_error": np.array([[1.0] * 3, [2.0] * 3, [3.0] * 3, [0.5] * 3]),
         "chattering_hf": np.array([[1.0] * 3, [0.5] * 3, [2.0] * 3, [4.0] * 3])}  # fmt: skip
    front = {0, 1, 3}  # point 2 is dominated by point 0
    children = search_front.local_factors(z, m, 12, points=2, sigma=0.0, seed=1)
    parents = {int(np.flatnonzero((z == c).all(1))[0]) for c in children}
    assert len(parents) == 2 and parents <= front
    lo, hi = search_front.bounds()
    moved = search_front.local_factors(z, m, 64, points=8, sigma=0.5, seed=2)
    assert np.all((moved >= lo) & (moved <= hi)) and np.any(moved == hi) and not np.any((moved[:, None] == z).all(-1))
    small = search_front.local_factors(z, m, 64, points=1, sigma=0.01, seed=3)  # one parent, no clipping
    step = small - z[np.argmin(np.abs(z - small[0]).sum(1))]  # from the parent, the nearest row
    moved_coords = np.abs(step) > 0
    assert moved_coords[0::2].all() and moved_coords[1::2].any(1).all()  # per joint: all; common: a subset
    assert not moved_coords[1::2].all(1).all()
    common = step[1::2].reshape(-1, 3, 3)  # parameter, joint: the same step for the three joints
    np.testing.assert_allclose(common, np.repeat(common[:, :, :1], 3, axis=2), atol=1e-15)
    assert np.ptp(step[0::2].reshape(-1, 3, 3), axis=2).max() > 0  # per joint
    # a point with a diverged rollout (its metrics: means over the survivors) is no parent
    children = search_front.local_factors(z, dict(m, diverged=np.array([0, 1, 0, 0])), 12, points=3, sigma=0.0, seed=1)
    assert {int(np.flatnonzero((z == c).all(1))[0]) for c in children} == {0, 3}


def _killed_and_resumed(train, plain, p0, settings, checkpoint, line: str) -> dict:
    """A front search killed (an exception) at its first log line starting with ``line``, then
    resumed from its checkpoint: the resumed run's result."""

    class Crash(Exception):
        pass

    def crash(msg):
        if msg.startswith(line):
            raise Crash

    with pytest.raises(Crash):
        search_front.front_search(train, plain, p0, settings, checkpoint=checkpoint, log=crash)
    return search_front.front_search(train, plain, p0, settings, checkpoint=checkpoint, resume=True, log=lambda _: None)


@pytest.mark.slow  # a second front study with its own compilations (~8 s), run three times
def test_with_a_training_surrogate_the_front_holds_plain_metrics_only(tmp_path):
    """The training front's points re-evaluated, then plain rounds from them: every point
    holds its plain metrics, and a run killed in the plain rounds resumes to the same front."""
    cfg = _config.resolve(dict(TINY, tune={"train_t_final": 0.1}))
    plain, train, p0 = _config.tuning_problems(cfg)
    assert train.options["n_steps"] < plain.options["n_steps"]
    settings = SETTINGS._replace(polish=3)
    res = search_front.front_search(train, plain, p0, settings, log=lambda _: None)
    st = res["stages"]
    assert st["plain_rounds"] == 3 and st["plain_evaluations"] > 3 * settings.chunk
    from fosmc_jax._search import tune as tuner

    for pt in res["points"]:
        p = tuner.Tunable(*(np.asarray(pt["params"][k]) for k in tuner.PARAM_NAMES))
        np.testing.assert_allclose(
            tuner.evaluate(plain, p)["metrics"]["rms_error"], pt["metrics"]["rms_error"], rtol=1e-9
        )
        assert not np.allclose(tuner.evaluate(train, p)["metrics"]["rms_error"], pt["metrics"]["rms_error"], rtol=1e-3)

    resumed = _killed_and_resumed(train, plain, p0, settings, tmp_path / "c.npz", "front: plain round 2/")
    assert resumed["stages"] | {"wall_time_s": 0} == st | {"wall_time_s": 0}
    for a, b in zip(resumed["points"], res["points"], strict=True):
        np.testing.assert_allclose(a["metrics"]["rms_error"], b["metrics"]["rms_error"], rtol=1e-12)
        np.testing.assert_allclose(a["params"]["delta"], b["params"]["delta"], rtol=1e-12)


def test_epsilon_indicator_by_hand():
    """I(A, B): the factor by which A must shrink, in both metrics, to weakly dominate B."""
    a = (np.array([1.0, 4.0]), np.array([4.0, 1.0]))
    assert epsilon(a, a) == 1.0
    assert epsilon(a, (np.array([2.0, 8.0]), np.array([8.0, 2.0]))) == 0.5  # B is A doubled
    # a point in A's gap: (2, 2) needs A's (1, 4) shrunk by 2 (or (4, 1) by 2)
    assert epsilon(a, (np.array([2.0]), np.array([2.0]))) == 2.0
    # B beats A's second point by 10% in error only: A's best cover of it is 4 / 3.6
    assert np.isclose(epsilon(a, (np.array([3.6]), np.array([1.0]))), 4 / 3.6)
    assert epsilon((np.array([3.6]), np.array([1.0])), a) == 3.6  # covering (1, 4) takes (3.6, 1) / 3.6


def test_nondominated_equals_the_pairwise_definition():
    """The sort-and-sweep mask against the definition, on small integer grids (many ties and
    repeated points) with NaN and inf entries."""

    def pairwise(x, y):
        ok = np.isfinite(x) & np.isfinite(y)
        keep = ok.copy()
        for i in np.flatnonzero(ok):
            keep[i] = not (ok & (x <= x[i]) & (y <= y[i]) & ((x < x[i]) | (y < y[i]))).any()
        return keep

    rng = np.random.default_rng(0)
    for _ in range(500):
        n = int(rng.integers(0, 25))
        x, y = rng.integers(0, 5, n).astype(float), rng.integers(0, 5, n).astype(float)
        if n:
            x[rng.integers(0, n)] = np.nan
            y[rng.integers(0, n)] = np.inf
        np.testing.assert_array_equal(nondominated(x, y), pairwise(x, y))


def test_rounds_from_the_budget_stop_when_it_is_spent():
    """With sizes from the budget the local rounds end at the deadline even when the probe
    chunk made them look cheap (here: a budget already spent), and stages say how many ran."""
    plain, train, p0 = _config.tuning_problems(_config.resolve(TINY))
    r = search_front.front_search(
        train,
        plain,
        p0,
        search_front.Settings(search="staged", points=3, candidates=16, chunk=8, budget=0.0),
        log=lambda _: None,
    )
    assert r["stages"]["local_rounds"] == 0 and r["stages"]["evaluations"] == 16 + 8  # the given 16, the probe's 8
    assert r["stages"]["cma_generations"] == 0  # a spent budget leaves no stage a negative size
    assert len(r["points"]) >= 1


def test_held_out_batch_has_the_payloads_and_seeds_training_did_not_see():
    cfg = _config.resolve({"plant": {"kind": "arm", "payloads": [0.0, 10.0]}})
    held = _config.held_out_config(cfg)
    assert held["plant"]["payloads"] == [1.0, 3.0, 5.0, 7.0, 9.0]
    assert held["sensors"]["seed"] == cfg["sensors"]["seed"] + 1
    cfg = _config.resolve({"plant": {"kind": "arm", "payloads": [1.0, 5.0]}})
    assert _config.held_out_config(cfg)["plant"]["payloads"] == [3.0, 7.0, 9.0]
    cfg = _config.resolve(TINY)  # linear, sampled box: fresh samples
    assert _config.held_out_config(cfg)["plant"]["seed"] == cfg["plant"]["seed"] + 1


def test_the_evaluators_metrics_do_not_depend_on_its_chunk():
    """The NSGA-II stage evaluates a generation in one call, the rounds in chunks: a candidate's
    metrics are the same to the bit in chunks of 3 (the last one padded) and in one of all 10."""
    _, train, p0 = _config.tuning_problems(_config.resolve(TINY))
    z = np.random.default_rng(1).uniform(*search_front.bounds(), size=(10, search_front.DIM))
    ev = search_front.Evaluator(train)
    a, b = (ev(search_front.from_factors(p0, z), chunk, log=lambda _: None) for chunk in (3, 10))
    for k in a:
        assert a[k].shape[0] == 10 and np.array_equal(a[k], b[k], equal_nan=True), k


@pytest.mark.parametrize("peer", ["nsga2", "optuna_nsga2"])
def test_peers_evaluate_whole_generations_within_the_box(peer):
    """pymoo's and optuna's NSGA-II (optuna: the optional extra ``peers``; skipped without it): whole
    generations of ``popsize`` candidates, inside the kind's box, at least one generation even
    with a spent budget, metrics for every candidate."""
    if peer == "optuna_nsga2":
        pytest.importorskip("optuna")
    from fosmc_jax._search import peers

    plain, train, p0 = _config.tuning_problems(_config.resolve(TINY))
    r = getattr(peers, peer)(train, p0, budget=0.0, popsize=8, log=lambda _: None)
    lo, hi = search_front.bounds()
    assert r["z"].shape == (8, 9) and np.all((r["z"] >= lo) & (r["z"] <= hi))
    assert r["metrics"]["rms_error"].shape == (8, 3) and r["metrics"]["diverged"].shape == (8,)


def test_a_training_problem_that_differs_only_in_its_gradient_is_no_surrogate():
    """Rematerialisation and gradient truncation change derivatives, not values: such a training
    problem is the plain one, and the front then spends no evaluation re-evaluating its points
    (tuning/results/front_ablation.md found 1,600 spent so with train_dt = [sim] dt)."""
    cfg = _config.resolve({**TINY, "tune": {"gradient_window": 0.01}})
    plain, train, _ = _config.tuning_problems(cfg)
    assert train.options["truncate_every"] > 0 and "truncate_every" not in plain.options
    assert search_front._same_simulation(train, plain)
    assert not search_front._same_simulation(train._replace(dt=2 * train.dt), plain)


def test_gradient_stage_scalarization_matches_central_differences():
    """The gradient stage's objective log E + w log C of the log factors (y = z ln 10): its
    value is the plain evaluator's axes at those factors, and its gradient equals central
    differences of itself along three random directions (h = 1e-5 in y, rtol 1e-5)."""
    import jax
    import jax.numpy as jnp

    plain, _, p0 = _config.tuning_problems(_config.resolve(TINY))
    f = search_front.scalarized(plain, p0)
    y, w = jnp.asarray(np.linspace(-0.3, 0.3, search_front.DIM)), 1.7
    (value, (E, C, bad)), g = jax.value_and_grad(f, has_aux=True)(y, w)
    m = search_front.evaluate_many(plain, search_front.from_factors(p0, np.asarray(y)[None] / np.log(10.0)), 1,
                                   log=lambda _: None)  # fmt: skip
    e, c = search_front.axes(m)
    assert not bad
    np.testing.assert_allclose([E, C], [e[0], c[0]], rtol=1e-12)
    np.testing.assert_allclose(value, np.log(e[0]) + w * np.log(c[0]), rtol=1e-12)
    h, value_of = 1e-5, jax.jit(lambda y: f(y, w)[0])
    for v in np.random.default_rng(0).normal(size=(3, search_front.DIM)):  # directional derivatives
        fd = (value_of(y + h * v) - value_of(y - h * v)) / (2 * h)
        np.testing.assert_allclose(g @ v, fd, rtol=1e-5)


@pytest.mark.slow  # a front with gradient steps, killed in them and resumed, then replayed (~40 s)
def test_gradient_steps_join_the_front_resume_and_replay(tmp_path):
    """Given gradient steps: the stage records them, the points they add hold plain metrics (the
    front's points re-simulate to them), a run killed in the stage resumes to the same front,
    and the recorded work replays to it bit for bit."""
    plain, _, p0 = _config.tuning_problems(_config.resolve(TINY))
    settings = SETTINGS._replace(gradient=4, gradient_rate=0.05)
    res = search_front.front_search(plain, plain, p0, settings, log=lambda _: None)
    st = res["stages"]
    assert st["gradient_steps"] == 4 and st["replay"]["gradient_steps"] == 4
    assert st["from_gradient"] > 0  # on this small problem the steps improve on the rounds' front
    for pt in res["points"]:
        p = tuner.Tunable(*(np.asarray(pt["params"][k]) for k in tuner.PARAM_NAMES))
        np.testing.assert_allclose(tuner.evaluate(plain, p)["metrics"]["rms_error"], pt["metrics"]["rms_error"],
                                   rtol=1e-9)  # fmt: skip

    resumed = _killed_and_resumed(plain, plain, p0, settings, tmp_path / "c.npz", "front: gradient step 1 ")
    replayed = search_front.front_search(plain, plain, p0, search_front.replay_settings(st), log=lambda _: None)
    for other in (resumed, replayed):
        assert other["stages"] | {"wall_time_s": 0} == st | {"wall_time_s": 0}
        assert [pt["params"] for pt in other["points"]] == [pt["params"] for pt in res["points"]]


@pytest.mark.slow  # a front on a training surrogate with gradient steps on it, then replayed (~30 s)
def test_gradient_steps_on_the_training_surrogate_add_plain_points_and_replay():
    """``gradient_on = "train"``: the steps descend the surrogate, the points they add hold
    their plain metrics (they re-simulate to them), the record says where the steps ran, and
    the recorded work replays to the same front."""
    cfg = _config.resolve(dict(TINY, tune={"train_t_final": 0.1}))
    plain, train, p0 = _config.tuning_problems(cfg)
    settings = SETTINGS._replace(polish=2, gradient=4, gradient_rate=0.05, gradient_on="train")
    res = search_front.front_search(train, plain, p0, settings, log=lambda _: None)
    st = res["stages"]
    assert st["gradient_steps"] == 4 and st["replay"]["gradient_on"] == "train" and st["from_gradient"] > 0
    for pt in res["points"]:
        p = tuner.Tunable(*(np.asarray(pt["params"][k]) for k in tuner.PARAM_NAMES))
        np.testing.assert_allclose(tuner.evaluate(plain, p)["metrics"]["rms_error"], pt["metrics"]["rms_error"],
                                   rtol=1e-9)  # fmt: skip
    replayed = search_front.front_search(train, plain, p0, search_front.replay_settings(st), log=lambda _: None)
    assert replayed["stages"] | {"wall_time_s": 0} == st | {"wall_time_s": 0}
    assert [pt["params"] for pt in replayed["points"]] == [pt["params"] for pt in res["points"]]
    with pytest.raises(ValueError, match="gradient_on: expected one of plain, train"):
        search_front.front_search(train, plain, p0, settings._replace(gradient_on="both"), log=lambda _: None)


def test_to_factors_inverts_from_factors():
    p0 = tuner.Tunable(np.array([1000.0, 550.0, 250.0]), np.array([2.0, 3.0, 4.0]), -np.arange(1.0, 10.0).reshape(3, 3))
    z = search_front.global_factors(32, seed=3)
    np.testing.assert_allclose(search_front.to_factors(p0, search_front.from_factors(p0, z)), z, atol=1e-13)
