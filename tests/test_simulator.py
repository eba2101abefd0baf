"""The simulator against an independent plain-NumPy closed loop, integrator convergence orders,
batching, compilation caching, float32, divergence handling, metric definitions, gradients."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

import fosmc_jax as fj
from fosmc_jax import paper

BOX = (paper.A_LOWER, paper.A_UPPER, paper.B_LOWER, paper.B_UPPER)
OFFSET = np.array([0.05, 0.0, 0.0, -0.03, 0.1, 0.0, 0.02, 0.0, -0.2])
SET1 = paper.DELTA_SETS[0]


# ------------------------------------------------------------------ independent NumPy loop


def np_cycloid(start, end, tau, t):
    """(30) and its derivatives, rows theta, theta', theta'', theta''' (per joint)."""
    delta, w = end - start, 2 * np.pi / tau
    if t < 0:
        return np.stack([start, 0 * start, 0 * start, 0 * start])
    if t >= tau:
        return np.stack([end, 0 * start, 0 * start, 0 * start])
    return np.stack(
        [
            start + delta * (t / tau - np.sin(w * t) / (2 * np.pi)),
            delta / tau * (1 - np.cos(w * t)),
            delta / tau * w * np.sin(w * t),
            delta / tau * w**2 * np.cos(w * t),
        ]
    )


def np_gain(a_rows, b_rows, poles):
    target = np.zeros((3, 9))
    for j in range(3):
        target[j, 3 * j : 3 * j + 3] = -np.real(np.poly(poles[j]))[::-1][:3]
    return np.linalg.solve(b_rows, target - a_rows)


def np_simulate(plant_a, plant_b, ctrl, ref, X0, dt, n, integrator, switching, law, bound=1e6):
    """The closed loop of the paper in plain NumPy: s = C Z - w, w' = (CA + CBK) Z, U from (23)
    (+ K Z for ``equivalent``) held over each step, Euler or classic RK4 on (X, w), the
    reference at the stage times. Returns the samples (X, X_d, U, s) up to the first bad one,
    the index of that one (None if none) and the metrics."""
    C, poles, gamma, delta, a_rows, b_rows = (np.asarray(x, np.float64) for x in ctrl)
    A, B = paper.full_A(a_rows), paper.full_B(b_rows)
    Ap, Bp = paper.full_A(np.asarray(plant_a, float)), paper.full_B(np.asarray(plant_b, float))
    K = np_gain(a_rows, b_rows, poles)
    S = C @ (A + B @ K)
    CB_inv = np.linalg.inv(C @ B)
    f = {
        "sign": np.sign,
        "ratio": lambda s: s / (np.abs(s) + delta),
        "sat": lambda s: np.clip(s / delta, -1, 1),
        "tanh": lambda s: np.tanh(s / delta),
    }[switching]

    def X_d_of(t):
        d = ref(t)
        return d[:3].T.ravel(), d

    def control(t, X, w):
        X_d, d = X_d_of(t)
        Omega = np.linalg.solve(b_rows, d[3] - a_rows @ X_d)
        Z = X - X_d
        s = C @ Z - w
        rho = gamma[0] * np.linalg.norm(Z) + gamma[1] * np.linalg.norm(X_d) + gamma[2] * np.linalg.norm(Omega)
        U = Omega - CB_inv @ (rho * f(s))
        if law == "equivalent":
            U = U + K @ Z
        return U, s, X_d

    def rhs(t, y, U):
        X = y[:9]
        return np.concatenate([Ap @ X + Bp @ U, S @ (X - X_d_of(t)[0])])

    y = np.concatenate([np.asarray(X0, float), np.zeros(3)])
    Xs, Xds, Us, ss = [], [], [], []
    bad = None
    for k in range(n + 1):
        t = k * dt
        U, s, X_d = control(t, y[:9], y[9:])
        if not (np.all(np.isfinite(y)) and np.all(np.isfinite(U)) and np.all(np.abs(y[:9]) <= bound)):
            bad = k
            break
        Xs.append(y[:9]), Xds.append(X_d), Us.append(U), ss.append(s)
        if integrator == "euler":
            y = y + dt * rhs(t, y, U)
        else:
            k1 = rhs(t, y, U)
            k2 = rhs(t + dt / 2, y + dt / 2 * k1, U)
            k3 = rhs(t + dt / 2, y + dt / 2 * k2, U)
            k4 = rhs(t + dt, y + dt * k3, U)
            y = y + dt * (k1 + 2 * k2 + 2 * k3 + k4) / 6
    X, X_d, U, s = (np.array(v) for v in (Xs, Xds, Us, ss))
    return X, X_d, U, s, bad, np_metrics(X, X_d, U, n * dt)


def np_metrics(X, X_d, U, t_final, dt=None):
    """The metrics of samples k = 0..n (fewer for a rollout frozen early: pass its ``dt``)."""
    dt = t_final / (len(U) - 1) if dt is None else dt
    e = X[:, ::3] - X_d[:, ::3]
    return {
        "rms_error": np.sqrt(np.mean(e**2, axis=0)),
        "max_abs_error": np.max(np.abs(e), axis=0),
        "final_abs_error": np.abs(e[-1]),
        "chattering": np.sum(np.abs(np.diff(U, axis=0)), axis=0) / t_final,
        "control_rms": np.sqrt(np.mean(U**2, axis=0)),
        "max_abs_control": np.max(np.abs(U), axis=0),
        "chattering_hf": np_chattering_hf(U, dt, t_final),
        "saturation_fraction": np.zeros(U.shape[1]),
    }


def np_chattering_hf(U, dt, t_final, cutoff=10.0):
    """sqrt(1/t_final int (u - ubar)^2 dt) for u held at U[k] over [k dt, (k + 1) dt), k < len(U) - 1,
    and its first-order low-pass from ubar(0) = U[0], integrated in closed form step by step
    (tests/test_metrics.py checks the closed form against numerical integration)."""
    w = 2 * np.pi * cutoff
    decay, weight = np.exp(-w * dt), (1 - np.exp(-2 * w * dt)) / (2 * w)
    low, total = U[0].copy(), np.zeros(U.shape[1])
    for u in U[:-1]:
        r = u - low
        total, low = total + r * r * weight, u - r * decay
    return np.sqrt(total / t_final)


# ------------------------------------------------------------------ helpers


def controller(gamma=paper.GAMMA, delta=SET1, poles=paper.POLES, dtype=np.float64):
    c = lambda x: jnp.asarray(np.asarray(x, np.float64), dtype)
    return fj.FOSMCParams(c(paper.C), c(poles), c(gamma), c(delta), c(paper.A_ROWS), c(paper.B_ROWS))


def cycloid(start=paper.THETA_START, end=paper.THETA_END, tau=paper.TAU, dtype=np.float64):
    c = lambda x: jnp.asarray(np.asarray(x, np.float64), dtype)
    return fj.Cycloid(c(start), c(end), c(tau))


def np_ref(start=paper.THETA_START, end=paper.THETA_END, tau=paper.TAU):
    return functools.partial(np_cycloid, np.asarray(start, float), np.asarray(end, float), float(tau))


def nominal_plant(dtype=np.float64):
    return fj.LinearPlant(jnp.asarray(paper.A_ROWS, dtype), jnp.asarray(paper.B_ROWS, dtype))


def sampled_plants(n=2, seed=4, dtype=np.float64):
    p = fj.uncertain_plants(paper.A_ROWS, paper.B_ROWS, "sample", box=BOX, samples=n, seed=seed)
    return fj.LinearPlant(jnp.asarray(p.a_rows, dtype), jnp.asarray(p.b_rows, dtype))


def X_start(offset=OFFSET):
    return np_cycloid(paper.THETA_START, paper.THETA_END, paper.TAU, 0.0)[:3].T.ravel() + offset


def unbatch(plants, i):
    return fj.LinearPlant(*(jnp.asarray(np.asarray(x)[i]) for x in (plants.a_rows, plants.b_rows)))


def assert_metrics_close(got, want, rtol, atol=0.0):
    for name in fj.METRIC_NAMES:
        np.testing.assert_allclose(np.asarray(getattr(got, name)), want[name], rtol=rtol, atol=atol, err_msg=name)


def take(tree, i):
    """Rollout i of a batched result, in NumPy (indexing the device arrays compiles a program per shape)."""
    return jax.tree.map(lambda x: np.asarray(x)[i], tree)


def assert_results_equal(a, b, rtol=1e-12, atol=1e-14):
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=rtol, atol=atol)


# ------------------------------------------------------------------ (1) against NumPy

CONFIGS = [
    # plant, switching, law, integrator, n_steps; each a program of its own (3-4 s of compilation):
    # the default tier has each plant kind, switching function, law and integrator at least once
    ("nominal", "ratio", "paper", "euler", 300),
    pytest.param("nominal", "ratio", "equivalent", "rk4", 300, marks=pytest.mark.slow),
    ("sampled", "tanh", "equivalent", "rk4", 300),
    ("sampled", "sat", "paper", "euler", 300),
    ("sampled", "ratio", "paper", "rk4", 400),  # 400 steps: test_simulate_batch_equals_one_by_one's (slow)
]


@pytest.mark.parametrize("plant_kind,switching,law,integrator,n", CONFIGS)
def test_matches_numpy_closed_loop(plant_kind, switching, law, integrator, n):
    dt, save_every = 1e-3, 7
    plant = nominal_plant() if plant_kind == "nominal" else unbatch(sampled_plants(), 1)
    ctrl = controller()
    res = fj.simulate(
        plant,
        ctrl,
        cycloid(),
        jnp.asarray(X_start()),
        dt,
        n_steps=n,
        integrator=integrator,
        switching=switching,
        law=law,
        save_every=save_every,
        divergence_bound=1e6,  # the default, passed (an argument, not a constant): huge-step test's program
    )
    X, X_d, U, s, bad, metrics = np_simulate(
        plant.a_rows, plant.b_rows, ctrl, np_ref(), X_start(), dt, n, integrator, switching, law
    )
    assert bad is None and not bool(res.diverged) and np.isinf(float(res.diverged_at))
    assert_metrics_close(res.metrics, metrics, rtol=1e-9, atol=1e-13)
    idx = np.r_[np.arange(0, n + 1, save_every), n]
    tr = res.trace
    assert tr.X.shape == (idx.size, 9) and tr.U.shape == (idx.size, 3)
    np.testing.assert_allclose(np.asarray(tr.t), idx * dt, rtol=1e-14)
    for got, want in ((tr.X, X), (tr.X_d, X_d), (tr.U, U), (tr.s, s)):
        np.testing.assert_allclose(np.asarray(got), want[idx], rtol=1e-9, atol=1e-12)


def test_sign_matches_numpy_while_s_is_far_from_zero():
    # SGN(s) is discontinuous: once s sits at 0 the rollouts' bits decide the sign and no two
    # implementations agree. From a large offset, s stays far from 0 for the first 25 steps
    # (checked below), where the comparison is exact up to rounding.
    dt, n = 1e-3, 25
    X0 = X_start(10 * OFFSET)
    ctrl = controller()
    res = fj.simulate(
        nominal_plant(),
        ctrl,
        cycloid(),
        jnp.asarray(X0),
        dt,
        n_steps=n,
        integrator="euler",
        switching="sign",
        save_every=1,
    )
    X, X_d, U, s, _, metrics = np_simulate(
        paper.A_ROWS, paper.B_ROWS, ctrl, np_ref(), X0, dt, n, "euler", "sign", "paper"
    )
    assert np.min(np.abs(s)) > 1e-3
    assert_metrics_close(res.metrics, metrics, rtol=1e-9, atol=1e-13)
    np.testing.assert_allclose(np.asarray(res.trace.U), U, rtol=1e-9)


# ------------------------------------------------------------------ (2) convergence orders


def exact_final(plant, U, X0, X_d, S, C, T):
    """X(T) and s(T) for X' = A_p X + B_p U, w' = S (X - X_d), constant U and X_d: expm of
    the augmented system [X; w; 1]."""
    Ap, Bp = paper.full_A(np.asarray(plant.a_rows)), paper.full_B(np.asarray(plant.b_rows))
    M = np.zeros((13, 13))
    M[:9, :9], M[:9, 12] = Ap, Bp @ U
    M[9:12, :9], M[9:12, 12] = S, -S @ X_d
    y = scipy.linalg.expm(M * T) @ np.concatenate([X0, np.zeros(3), [1.0]])
    return y[:9], C @ (y[:9] - X_d) - y[9:12]


@pytest.mark.parametrize(
    "integrator,dts,order",
    [
        ("rk4", [0.02, 0.01, 0.005, 0.0025], 4.0),
        ("euler", [2e-3, 1e-3, 5e-4, 2.5e-4], 1.0),
    ],
)
def test_convergence_order(integrator, dts, order):
    # gamma = 0 makes U = Omega; with a constant reference (start == end) Omega is constant,
    # so the zero-order hold is exact and the only error is the integrator's.
    T = 0.4
    rest = np.array([0.3, -0.2, 0.5])
    plant = unbatch(sampled_plants(seed=9), 0)
    ctrl = controller(gamma=np.zeros(3))
    X_d = np.repeat(rest, 3) * np.tile([1.0, 0, 0], 3)
    X0 = X_d + OFFSET
    U = np.linalg.solve(paper.B_ROWS, -paper.A_ROWS @ X_d)
    S = paper.C @ (
        paper.full_A(paper.A_ROWS) + paper.full_B(paper.B_ROWS) @ np_gain(paper.A_ROWS, paper.B_ROWS, paper.POLES)
    )
    X_T, s_T = exact_final(plant, U, X0, X_d, S, paper.C, T)
    # One compilation for all steps: n_steps is static, dt is not, so every run takes the
    # finest grid's step count and is read at sample T / dt (what follows T is ignored; the
    # open-loop plant grows there, hence the raised divergence bound).
    n_max = round(T / min(dts))
    errs = []
    for dt in dts:
        k = round(T / dt)
        res = fj.simulate(
            plant,
            ctrl,
            cycloid(rest, rest),
            jnp.asarray(X0),
            dt,
            n_steps=n_max,
            integrator=integrator,
            save_every=1,
            divergence_bound=1e300,
        )
        assert float(res.trace.t[k]) == pytest.approx(T, rel=1e-12)
        np.testing.assert_allclose(np.asarray(res.trace.U[: k + 1]), np.broadcast_to(U, (k + 1, 3)), rtol=1e-12)
        errs.append(
            max(
                np.max(np.abs(np.asarray(res.trace.X[k]) - X_T)) / np.max(np.abs(X_T)),
                np.max(np.abs(np.asarray(res.trace.s[k]) - s_T)) / np.max(np.abs(s_T)),
            )
        )
    slope = np.polyfit(np.log(dts), np.log(errs), 1)[0]
    assert abs(slope - order) < 0.3, (slope, errs)
    assert errs[-1] > 1e-13  # still above rounding, so the slope means something


# ------------------------------------------------------------------ (3) batching

# 400 steps: the divergence test below diverges after 205 and shares these tests' programs
OPTS = dict(n_steps=400, integrator="rk4", switching="ratio", law="paper")


@pytest.mark.slow  # 4 s: the default tier keeps to 4 minutes on 2 cores
def test_simulate_batch_equals_one_by_one():
    plants = sampled_plants(n=2)
    X0s = jnp.asarray(np.stack([X_start(), X_start(-OFFSET)]))
    ctrl, ref = controller(), cycloid()
    batch = fj.simulate_batch(plants, ctrl, ref, X0s, 1e-3, **OPTS, save_every=7)
    assert batch.metrics.rms_error.shape == (4, 3) and batch.diverged.shape == (4,)
    assert batch.trace.X.shape == (4, 59, 9)  # samples 0, 7, ..., 399 and the last, 400
    for p in range(2):
        for o in range(2):
            # the static options of test_matches_numpy_closed_loop's last case: its program
            solo = fj.simulate(unbatch(plants, p), ctrl, ref, X0s[o], 1e-3, **OPTS, save_every=7, divergence_bound=1e6)
            assert_results_equal(take(batch, 2 * p + o), solo)  # plant-major


def run_gains(gamma, delta, divergence_bound=1e6):
    """A rollout of the nominal plant with these gains (OPTS): the programs of the vmap test and
    of the divergence test (section 6) are the same ones."""
    return fj.simulate(
        nominal_plant(),
        controller()._replace(gamma=gamma, delta=delta),
        cycloid(),
        jnp.asarray(X_start()),
        1e-3,
        **OPTS,
        divergence_bound=divergence_bound,
    )


@pytest.mark.slow  # 4 s: the default tier keeps to 4 minutes on 2 cores
def test_vmap_of_simulate_equals_one_by_one():
    gammas = jnp.asarray(np.stack([paper.GAMMA, 0.5 * paper.GAMMA, 2 * paper.GAMMA]))
    deltas = jnp.asarray(paper.DELTA_SETS)
    batch = jax.vmap(run_gains)(gammas, deltas)
    for i in range(3):
        assert_results_equal(take(batch, i), run_gains(gammas[i], deltas[i]))


# ------------------------------------------------------------------ (4) no recompilation


@pytest.mark.slow  # moved from the default tier (4-min budget): 4-8 s
def test_second_call_with_new_values_does_not_recompile():
    opts = dict(n_steps=37, integrator="euler", switching="tanh", law="equivalent")  # a config no other test uses
    before = fj.simulate._cache_size()
    fj.simulate(
        unbatch(sampled_plants(seed=1), 0),
        controller(),
        cycloid(),
        jnp.asarray(X_start()),
        1e-3,
        **opts,
    )
    first = fj.simulate._cache_size()
    assert first == before + 1  # the counter does see a new compilation
    # new values everywhere (plant, gains, poles, reference, X0, dt), same shapes and dtypes
    fj.simulate(
        unbatch(sampled_plants(seed=2), 1),
        controller(gamma=2 * paper.GAMMA, delta=paper.DELTA_SETS[2], poles=2 * paper.POLES),
        cycloid(paper.THETA_END, paper.THETA_START, 3.0),
        jnp.asarray(X_start(-OFFSET)),
        2e-3,
        **opts,
    )
    assert fj.simulate._cache_size() == first
    # a new static argument does compile again (so the check above can fail)
    fj.simulate(
        nominal_plant(),
        controller(),
        cycloid(),
        jnp.asarray(X_start()),
        1e-3,
        **{**opts, "n_steps": 38},
    )
    assert fj.simulate._cache_size() == first + 1

    b0 = fj.simulate_batch._cache_size()
    fj.simulate_batch(sampled_plants(seed=1), controller(), cycloid(), jnp.asarray(X_start()[None]), 1e-3, **opts)
    b1 = fj.simulate_batch._cache_size()
    fj.simulate_batch(
        sampled_plants(seed=3),
        controller(gamma=paper.GAMMA / 2),
        cycloid(),
        jnp.asarray(X_start(OFFSET / 3)[None]),
        5e-4,
        **opts,
    )
    assert b1 == b0 + 1 and fj.simulate_batch._cache_size() == b1


def test_second_call_does_not_recompile_by_compile_events():
    # Independent of jit's cache: count XLA backend compilations through jax.monitoring.
    events = []
    listener = lambda name, *a, **k: events.append(name) if "backend_compile" in name else None
    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        opts = dict(n_steps=41, integrator="rk4", switching="sat", law="paper")
        args = lambda s: (
            unbatch(sampled_plants(seed=s), 0),
            controller(gamma=paper.GAMMA * (1 + s)),
            cycloid(),
            jnp.asarray(X_start(OFFSET * s)),
        )
        jax.block_until_ready(fj.simulate(*args(1), 1e-3, **opts))
        n1 = len(events)
        jax.block_until_ready(fj.simulate(*args(2), 3e-3, **opts))
        n2 = len(events)
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)
    assert n1 >= 1 and n2 == n1


# ------------------------------------------------------------------ (5) float32


@pytest.mark.slow  # moved from the default tier (4-min budget): 4-8 s
def test_float32_run_stays_float32_and_agrees_with_float64():
    n, dt = 300, 1e-3
    res = {}
    for dtype in (np.float32, np.float64):
        res[dtype] = fj.simulate(
            unbatch(sampled_plants(dtype=dtype), 0),
            controller(dtype=dtype),
            cycloid(dtype=dtype),
            jnp.asarray(X_start(), dtype),
            jnp.asarray(dt, dtype),
            n_steps=n,
            integrator="rk4",
            save_every=100,
        )
    r32, r64 = res[np.float32], res[np.float64]
    for leaf in jax.tree.leaves((r32.metrics, r32.trace, r32.diverged_at)):
        assert leaf.dtype == np.float32
    assert r32.diverged.dtype == np.bool_
    # float32 rounding (eps = 1.2e-7) accumulated over 300 steps, on angles of order 1 rad
    # (observed: 4e-7 rad on the errors, 6e-6 rad on X, 4e-6 relative on the controls):
    # errors agree to 4e-6 rad, controls (volts) to 3e-5 relative, the state to 2e-5 rad.
    for name in ("rms_error", "max_abs_error", "final_abs_error"):
        np.testing.assert_allclose(
            getattr(r32.metrics, name), getattr(r64.metrics, name), rtol=0, atol=4e-6, err_msg=name
        )
    for name in ("control_rms", "max_abs_control", "chattering"):
        np.testing.assert_allclose(getattr(r32.metrics, name), getattr(r64.metrics, name), rtol=3e-5, err_msg=name)
    np.testing.assert_allclose(r32.trace.X, r64.trace.X, rtol=0, atol=2e-5)


# ------------------------------------------------------------------ (6) divergence


def test_divergence_is_flagged_frozen_and_isolated():
    n, dt, bound = OPTS["n_steps"], 1e-3, 1e3
    # the middle rollout's negative gains push away from s = 0; its neighbours are good
    gammas = jnp.asarray(np.stack([paper.GAMMA, -paper.GAMMA, 2 * paper.GAMMA]))
    deltas = jnp.asarray(np.stack([paper.DELTA_SETS[1], SET1, paper.DELTA_SETS[2]]))
    run = lambda g, d: run_gains(g, d, bound)
    batch = jax.vmap(run)(gammas, deltas)
    good, bad, good2 = (take(batch, i) for i in range(3))
    for g in (good, good2):
        assert not bool(g.diverged) and np.isinf(float(g.diverged_at))
    assert bool(bad.diverged) and np.isfinite(float(bad.diverged_at))
    for leaf in jax.tree.leaves(bad.metrics):  # a diverged rollout's metrics cannot pass for a good one's
        assert np.all(np.isnan(leaf))
    for i, g in ((0, good), (2, good2)):  # the good rollouts are unaffected by their neighbour
        assert_results_equal(g, run(gammas[i], deltas[i]))

    # the flag time matches the NumPy loop stopped at the first bad sample
    X, X_d, U, s, k_bad, _ = np_simulate(
        paper.A_ROWS,
        paper.B_ROWS,
        controller()._replace(gamma=gammas[1], delta=deltas[1]),
        np_ref(),
        X_start(),
        dt,
        n,
        "rk4",
        "ratio",
        "paper",
        bound=bound,
    )
    assert k_bad is not None and 0 < k_bad < n
    assert float(bad.diverged_at) == pytest.approx(k_bad * dt, rel=1e-12)


def test_huge_step_diverges_to_nonfinite_and_is_flagged():
    # the static options of test_matches_numpy_closed_loop's first case: its program, compiled once
    res = fj.simulate(
        nominal_plant(),
        controller(),
        cycloid(),
        jnp.asarray(X_start()),
        0.5,
        n_steps=300,
        integrator="euler",
        switching="ratio",
        law="paper",
        save_every=7,
        divergence_bound=np.inf,
    )
    assert bool(res.diverged) and np.isfinite(float(res.diverged_at)) and float(res.diverged_at) > 0
    for leaf in jax.tree.leaves(res.metrics):
        assert np.all(np.isnan(leaf))
    assert np.all(np.isfinite(np.asarray(res.trace.X)))  # frozen at the last finite state


# ------------------------------------------------------------------ (7) metric definitions


@pytest.mark.parametrize("switching", ["ratio", "sign"])
def test_metrics_recomputed_from_full_trace(switching):
    n, dt = 1600, 1e-3  # the Euler case of test_convergence_order takes 1600 steps too: its program
    res = fj.simulate(
        unbatch(sampled_plants(), 0),
        controller(),
        cycloid(),
        jnp.asarray(X_start()),
        dt,
        n_steps=n,
        integrator="euler",
        switching=switching,
        save_every=1,
        divergence_bound=1e6,  # the default, passed (an argument, not a constant), as there
    )
    tr = res.trace
    assert tr.X.shape == (n + 1, 9)
    np.testing.assert_allclose(np.asarray(tr.t), np.arange(n + 1) * dt, rtol=1e-14)
    want = np_metrics(np.asarray(tr.X), np.asarray(tr.X_d), np.asarray(tr.U), n * dt)
    assert_metrics_close(res.metrics, want, rtol=1e-12, atol=1e-15)


# ------------------------------------------------------------------ (8) gradients


@jax.jit
def fd_loss(delta, gamma, poles, X0):
    """200 RK4 steps on the nominal plant along the paper's cycloid from ``X0``: one compilation
    (and one of its gradient) for every X0."""
    res = fj.simulate(
        nominal_plant(),
        controller()._replace(delta=delta, gamma=gamma, poles=poles),
        cycloid(),
        X0,
        1e-3,
        n_steps=200,
        integrator="rk4",
        switching="ratio",
    )
    return jnp.sum(res.metrics.rms_error) + 1e-3 * jnp.sum(res.metrics.chattering)


def central_differences(f, args, rel=1e-4):
    grads = []
    for i, a in enumerate(args):
        a = np.asarray(a, float)
        g = np.zeros_like(a)
        for j in range(a.size):
            h = rel * np.max(np.abs(a))  # the group's scale (poles: 3e-4), above the rounding noise
            up, dn = a.copy(), a.copy()
            up.flat[j] += h
            dn.flat[j] -= h
            f_up = f(*args[:i], jnp.asarray(up), *args[i + 1 :])
            f_dn = f(*args[:i], jnp.asarray(dn), *args[i + 1 :])
            g.flat[j] = (float(f_up) - float(f_dn)) / (2 * h)
        grads.append(g)
    return grads


# in the slow tier (7 s each): the default tier keeps to 4 minutes on 2 cores, and checks the
# whole tuning loss's gradient against central differences (test_tuning.py)
@pytest.mark.parametrize("offset", [pytest.param("offset", marks=pytest.mark.slow),
                                    pytest.param("on_reference", marks=pytest.mark.slow)])  # fmt: skip
def test_gradients_match_finite_differences(offset):
    # "on_reference": X0 = X_d(0), so Z = 0 at t = 0 (the safe-norm case).
    # Steps of 1e-4 relative: truncation ~1e-8 relative; the loss (~1e-3) carries ~1e-16
    # absolute rounding from the 200 steps, so components far below the largest one of their
    # group are noise-limited: tolerance rtol 1e-4 plus 1e-4 of the group's largest entry.
    X0 = jnp.asarray(X_start(OFFSET if offset == "offset" else 0 * OFFSET))
    loss = functools.partial(fd_loss, X0=X0)
    args = (jnp.asarray(SET1), jnp.asarray(paper.GAMMA), jnp.asarray(paper.POLES))
    grads = jax.grad(loss, argnums=(0, 1, 2))(*args)
    for g, fd in zip(grads, central_differences(loss, args), strict=True):
        g = np.asarray(g)
        assert np.all(np.isfinite(g))
        np.testing.assert_allclose(g, fd, rtol=1e-4, atol=1e-4 * np.max(np.abs(fd)))


@pytest.fixture(scope="module")
def at_rest():
    """Every metric's sum at rest at the origin, and its gradient in (delta, gamma, poles): one
    compiled program (jax.jacrev, a row per metric) for all metrics."""
    zero = np.zeros(3)
    base = controller()

    def sums(delta, gamma, poles):
        res = fj.simulate(
            nominal_plant(),
            base._replace(delta=delta, gamma=gamma, poles=poles),
            cycloid(zero, zero),
            jnp.zeros(9),
            1e-3,
            n_steps=50,
            integrator="rk4",
            switching="ratio",
        )
        return jnp.stack([jnp.sum(getattr(res.metrics, name)) for name in fj.METRIC_NAMES])

    args = (jnp.asarray(SET1), jnp.asarray(paper.GAMMA), jnp.asarray(paper.POLES))
    return np.asarray(sums(*args)), jax.jacrev(sums, argnums=(0, 1, 2))(*args)


@pytest.mark.parametrize("metric", fj.METRIC_NAMES)
def test_gradient_is_finite_when_everything_is_zero(metric, at_rest):
    # Rest at the origin, X0 = 0: Z, X_d, Omega, s and U are exactly 0 at every step, so all
    # three norms in (23) sit at 0, and so do the errors and controls the metrics summarise.
    # Every metric is identically 0 in (delta, gamma, poles): its gradient must be exactly 0.
    # (rms_error and control_rms take sqrt(0) in _metrics.finish: NaN gradient.) The rows of
    # jax.jacrev are reverse passes with a cotangent of 1 on this metric and 0 on the others,
    # so a NaN in any metric's reverse pass (0 * inf) shows in every row.
    values, jacobians = at_rest
    i = fj.METRIC_NAMES.index(metric)
    assert values[i] == 0.0
    for g in jacobians:
        np.testing.assert_array_equal(np.asarray(g)[i], 0.0)
