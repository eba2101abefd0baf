"""Reproduction of the paper's simulation study: the cases, their rollouts and metric tables.

The cases are the paper's (Figs. 2-5): SGN control (23) and the continuous function (28) with
Table 1's three delta sets, on the plant at payloads 0 and 10 kg (the arm) or the nominal
linear model (29); plus the linear model at random vertices of the Appendix box, which the
paper does not show. Figures are drawn by :mod:`fosmc_jax._reproduce_plots`.
"""

from __future__ import annotations

import concurrent.futures
import csv
import functools
import io
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import _problems as problems
from .._controllers.fosmc import FOSMC, FOSMCParams
from .._design import paper
from .._design.gains import summarize
from .._io import write_text
from .._plants.linear import LinearPlant, uncertain_plants
from .._plants.reference import Cycloid, desired_state
from .._problems import ConfigError
from .._simulator.metrics import METRIC_NAMES, UNITS
from .._simulator.rollout import simulate_batch
from .shared import Log, _fresh_out, _quiet, _with_x64, writable

SWITCHINGS = ("sign", "set 1", "set 2", "set 3")


class Case(NamedTuple):
    """One simulated case: labels and the batch of rollouts it holds."""

    plant: str  # "arm" or "linear"
    payload: str  # "0 kg", "10 kg", "nominal" or "box vertices (N)"
    switching: str  # one of SWITCHINGS
    result: Any  # Result with a leading batch axis (1 rollout, or N vertices)


class Settings(NamedTuple):
    t_final: float = paper.T_FINAL
    dt: float = 1e-4
    integrator: str = "rk4"
    vertices: int = 64
    save_every: int = 10  # 0: metrics only, through simulate_batch's fast paths (no figures)
    seed: int = 0


#: The shortened run whose table ``tuning/results/reproduction/metrics_short.csv`` the tests recompute, so
#: the committed report cannot drift from the code (a table only: no trace).
SHORT = Settings(t_final=0.1, vertices=8, save_every=0)


class Jobs(NamedTuple):
    """A group of cases as independent runs (``thunks``, each compiling its own programs) and
    how their results make the group's (``combine``)."""

    thunks: list[Callable[[], Any]]
    combine: Callable[[list], Any]

    def run(self) -> Any:
        return self.combine(parallel(*self.thunks))


def _in_context(thunk: Callable[[], Any]) -> Callable[[], Any]:
    """``thunk`` run in its caller's precision: JAX's configuration contexts are the thread's
    own (a thread starts from the global setting), so ``run_reproduce``'s ``jax.enable_x64`` is
    passed on to the threads explicitly."""
    x64 = jax.config.jax_enable_x64

    def run():
        with jax.enable_x64(x64):
            return thunk()

    return run


def parallel(*thunks: Callable[[], Any], workers: int | None = None) -> list[Any]:
    """Each thunk's result, in order, the thunks run in ``workers`` threads (default: one per
    core): XLA compiles and runs a program without holding the GIL, so independent case
    groups, whose time is mostly compilation, overlap."""
    workers = workers or max(1, min(len(thunks), os.cpu_count() or 1))
    with concurrent.futures.ThreadPoolExecutor(max_workers=workers) as pool:
        return [f.result() for f in [pool.submit(_in_context(t)) for t in thunks]]


#: Threads of :func:`run_groups`' pool: one per core (XLA's compilation of a program uses more
#: than one core; more threads measured no faster, with more CPU time in all).
WORKERS = os.cpu_count() or 1


def run_groups(groups: list[Jobs], done: Callable[[int, list], None] = lambda i, results: None) -> list[Any]:
    """Every group's result, the groups' thunks run in one pool of :data:`WORKERS` threads in
    order (the first group's first); ``done(i, results)`` is called, in a thread of its own, as
    soon as group i and every group before it are done (results: theirs), so that the figures
    of the first groups are drawn while later groups still compile."""
    with (concurrent.futures.ThreadPoolExecutor(max_workers=WORKERS) as pool,
          concurrent.futures.ThreadPoolExecutor(max_workers=1) as drawing):  # fmt: skip
        futures = [[pool.submit(_in_context(t)) for t in g.thunks] for g in groups]

        def collect() -> list[Any]:
            results = []
            for i, (g, fs) in enumerate(zip(groups, futures)):
                results.append(g.combine([f.result() for f in fs]))
                done(i, results)
            return results

        return drawing.submit(_in_context(collect)).result()


def _batched(plants, ctrls, reference, X0, dt, **options):
    """Rollout i of ``plants`` under controller set i // P (``ctrls`` with a leading axis of
    sets, ``plants`` a batch of P), through :func:`simulate_batch`'s fast paths (the native
    kernels, traces too); results (NumPy) with a leading axis sets x P, set-major."""
    one = lambda c: simulate_batch(plants, c, reference, X0[None], dt, **options)
    r = jax.vmap(one)(ctrls)
    return jax.tree.map(lambda x: np.asarray(x).reshape((-1,) + x.shape[2:]), r)


def _controller(delta, dtype) -> FOSMCParams:
    c = lambda x: jnp.asarray(x, dtype)
    return FOSMCParams(c(paper.C), c(paper.POLES), c(paper.GAMMA), c(delta), c(paper.A_ROWS), c(paper.B_ROWS))


def _stack(trees):
    """The trees stacked on a new leading axis, in NumPy (an eager ``jnp.stack`` compiles a
    program per shape: 27 of them in a cold ``fosmc reproduce``)."""
    return jax.tree.map(lambda *xs: jnp.asarray(np.stack([np.asarray(x) for x in xs])), *trees)


def plants_under_test(kind: str, dtype) -> list[tuple[str, Any]]:
    """(label, plant batch of one) pairs for ``kind`` = "arm" (0 and 10 kg) or "linear" (nominal)."""
    if kind == "arm":
        from .._plants.arm import ARM_PARAMS, Arm

        params = jax.tree.map(lambda x: jnp.asarray(x, dtype), ARM_PARAMS)
        return [(f"{p:g} kg", _stack([Arm(params, jnp.asarray(p, dtype))])) for p in paper.PAYLOADS]
    if kind == "linear":
        nominal = LinearPlant(jnp.asarray(paper.A_ROWS, dtype), jnp.asarray(paper.B_ROWS, dtype))
        return [("nominal", _stack([nominal]))]
    raise ValueError(f"plant must be 'arm' or 'linear', got {kind!r}")


def run_cases(
    kind: str, settings: Settings | None = None, dtype=jnp.float64, log: Callable[[str], None] = print
) -> list[Case]:
    """Simulate every case (:func:`case_jobs`, run in :func:`parallel`)."""
    return case_jobs(kind, settings, dtype, log).run()


def case_jobs(kind: str, settings: Settings, dtype=jnp.float64, log: Callable[[str], None] = print) -> Jobs:
    """The cases of :func:`run_cases`: per plant group, SGN is one vmapped call over the group's
    plants and the three Table 1 sets are one call over (set x plant), four runs in all."""
    reference = Cycloid(*(jnp.asarray(x, dtype) for x in (paper.THETA_START, paper.THETA_END, paper.TAU)))
    X0 = desired_state(reference(jnp.zeros((), dtype)))
    n_steps = round(settings.t_final / settings.dt)
    box = (paper.A_LOWER, paper.A_UPPER, paper.B_LOWER, paper.B_UPPER)
    vertices = uncertain_plants(paper.A_ROWS, paper.B_ROWS, "vertices", box=box,
                                samples=settings.vertices, seed=settings.seed)  # fmt: skip
    vertices = LinearPlant(*(jnp.asarray(x, dtype) for x in vertices))
    groups = [(kind, plants_under_test(kind, dtype))]
    groups.append(("linear", [(f"box vertices ({vertices.a_rows.shape[0]})", vertices)]))

    def run(g: int, plant_kind: str, labelled: list, switching: str, sets: list[int]) -> list[Case]:
        plants = jax.tree.map(lambda *xs: np.concatenate([np.asarray(x) for x in xs]), *(p for _, p in labelled))
        sizes = [jax.tree.leaves(p)[0].shape[0] for _, p in labelled]
        n = sum(sizes)
        start = time.perf_counter()
        dt = jnp.asarray(settings.dt, dtype)
        ctrls = FOSMC(_stack([_controller(paper.DELTA_SETS[k], dtype) for k in sets]), switching)
        # every step of the primary plant's SGN runs is kept, to show the chattering period
        save_every = 1 if settings.save_every and switching == "sign" and g == 0 else settings.save_every
        result = _batched(plants, ctrls, reference, X0, dt, n_steps=n_steps, integrator=settings.integrator,
                          save_every=save_every)  # fmt: skip
        cases, offset = [], 0
        for k in sets:
            for (label, _), size in zip(labelled, sizes):
                part = jax.tree.map(lambda x, o=offset, m=size: np.asarray(x)[o : o + m], result)
                cases.append(Case(plant_kind, label, "sign" if switching == "sign" else f"set {k + 1}", part))
                offset += size
        log(f"{plant_kind:6} {switching:5} {n * len(sets):4d} rollout(s) x {n_steps} steps "
            f"({settings.integrator}, dt = {settings.dt} s)  {time.perf_counter() - start:6.2f} s")  # fmt: skip
        return cases

    jobs = [functools.partial(run, g, plant_kind, labelled, switching, sets)
            for g, (plant_kind, labelled) in enumerate(groups)
            for switching, sets in (("sign", [0]), ("ratio", [0, 1, 2]))]  # fmt: skip
    order = {s: i for i, s in enumerate(SWITCHINGS)}
    key = lambda c: (c.plant != kind, "vertices" in c.payload, c.payload, order[c.switching])
    return Jobs(jobs, lambda parts: sorted((c for part in parts for c in part), key=key))


# ---------------------------------------------------------------------------- the realistic loop

#: The realistic digital loop (sample rate, encoder, difference estimator, delay, voltage
#: limit), with the sources of its numbers; ``tuning/configs/realistic_arm.toml`` is this file.
REALISTIC_PRESET = problems.PRESETS["realistic_arm"]
#: The trade-off sweep: delta as multiples of Table 1 set 1, and the poles (33) sped up.
DELTA_SCALES = (3.0, 1.0, 0.3, 0.1, 0.03, 0.01, 0.003, 0.001)
POLE_SPEEDUPS = (1.0, 3.0, 10.0, 30.0, 100.0)


def realistic_config(t_final: float | None = None) -> problems.Config:
    """The resolved realistic preset (optionally with a shorter horizon)."""
    cfg = problems.load(REALISTIC_PRESET)
    return cfg if t_final is None else problems.replace(cfg, sim={"t_final": t_final})


def _run(cfg: problems.Config, params: list[FOSMCParams], switching: str, realistic: bool, save_every: int = 0):
    """Every (params x payload) of ``cfg``'s arm, each run in the ideal loop or the config's
    digital loop: one vmapped call, results with a leading axis (len(params) * P)."""
    problem = problems.build(problems.replace(cfg, controller={"switching": switching}))
    controller_of = problem.make if realistic else functools.partial(FOSMC, switching=switching)
    keys = None if problem.keys is None else problem.keys[:1]
    return _batched(problem.plants, jax.vmap(controller_of)(_stack(params)), problem.reference, problem.X0s[0],
                    problem.dt, keys=keys, n_steps=problem.options["n_steps"],
                    integrator=problem.options["integrator"], save_every=save_every)  # fmt: skip


def run_realistic_cases(t_final: float | None = None, log: Callable[[str], None] = print) -> list[Case]:
    """SGN and Table 1's sets with the paper's gains on the arm at 0 and 10 kg, in the
    realistic loop (the ideal loop's cases are :func:`run_cases`')."""
    return realistic_jobs(t_final, log).run()


def realistic_jobs(t_final: float | None = None, log: Callable[[str], None] = print) -> Jobs:
    """The runs of :func:`run_realistic_cases`: SGN, and the three sets in one call."""
    cfg = realistic_config(t_final)
    dtype = jnp.dtype(cfg.sim.precision)
    payloads = [f"{p:g} kg" for p in cfg.plant.payloads]

    def run(switching: str, sets: list[int]) -> list[Case]:
        start = time.perf_counter()
        params = [_controller(paper.DELTA_SETS[k], dtype) for k in sets]
        result = _run(cfg, params, switching, True, save_every=problems.sample_steps(cfg))
        cases, i = [], 0
        for k in sets:
            for load in payloads:
                part = jax.tree.map(lambda x, i=i: np.asarray(x)[i : i + 1], result)
                cases.append(Case("arm, realistic loop", load, "sign" if switching == "sign" else f"set {k + 1}", part))
                i += 1
        log(f"arm realistic {switching:5} {i:2d} rollout(s) x {cfg.sim.t_final} s  "
            f"{time.perf_counter() - start:6.2f} s")  # fmt: skip
        return cases

    thunks = [functools.partial(run, switching, sets) for switching, sets in (("sign", [0]), ("ratio", [0, 1, 2]))]
    return Jobs(thunks, lambda parts: [c for part in parts for c in part])


class Sweep(NamedTuple):
    """Mean (over payloads) metrics of the trade-off sweep, each (len(values), 3)."""

    name: str  # "delta scale" or "pole speed-up"
    values: tuple[float, ...]
    ideal: Any  # Metrics
    realistic: Any  # Metrics


def tradeoff_sweeps(t_final: float | None = None, log: Callable[[str], None] = print) -> list[Sweep]:
    """Table 1 set 1 with delta scaled by :data:`DELTA_SCALES`, and with the poles (33) sped up
    by :data:`POLE_SPEEDUPS`, on the arm at 0 and 10 kg, in both loops (one call per loop)."""
    return tradeoff_jobs(t_final, log).run()


def tradeoff_jobs(t_final: float | None = None, log: Callable[[str], None] = print) -> Jobs:
    """The runs of :func:`tradeoff_sweeps`: the ideal loop's, the realistic loop's."""
    cfg = realistic_config(t_final)
    dtype = jnp.dtype(cfg.sim.precision)
    base = _controller(paper.DELTA_SETS[0], dtype)
    P = len(cfg.plant.payloads)
    axes = (("delta scale", DELTA_SCALES, lambda v: base._replace(delta=base.delta * v)),
            ("pole speed-up", POLE_SPEEDUPS, lambda v: base._replace(poles=base.poles * v)))  # fmt: skip
    params = [vary(v) for _, values, vary in axes for v in values]

    def run(realistic: bool):
        start = time.perf_counter()
        r = _run(cfg, params, "ratio", realistic)
        ok = ~np.asarray(r.diverged).reshape(len(params), P, 1)
        mean = lambda x, ok=ok: np.nanmean(np.where(ok, np.asarray(x).reshape(len(params), P, 3), np.nan), axis=1)
        log(f"trade-off {'realistic' if realistic else 'ideal':9} {len(params) * P:3d} rollouts  "
            f"{time.perf_counter() - start:6.2f} s")  # fmt: skip
        return jax.tree.map(mean, r.metrics)

    def combine(loops) -> list[Sweep]:
        sweeps, i = [], 0
        for name, values, _ in axes:
            part = lambda m, i=i, n=len(values): jax.tree.map(lambda x: x[i : i + n], m)  # noqa: B008
            sweeps.append(Sweep(name, values, part(loops[0]), part(loops[1])))
            i += len(values)
        return sweeps

    return Jobs([functools.partial(run, False), functools.partial(run, True)], combine)


def sweep_markdown(sweeps: list[Sweep]) -> str:
    """The trade-off sweeps as a Markdown table (means over joints and payloads)."""
    lines = ["| sweep | value | loop | rms_error (rad) | chattering_hf (V) | chattering (V/s) | saturation_fraction |",
             "|---|---:|---|---:|---:|---:|---:|"]  # fmt: skip
    for sw in sweeps:
        for i, v in enumerate(sw.values):
            for loop_name, m in (("ideal", sw.ideal), ("realistic", sw.realistic)):
                cells = [f"{np.mean(getattr(m, k)[i]):.3g}" for k in
                         ("rms_error", "chattering_hf", "chattering", "saturation_fraction")]  # fmt: skip
                lines.append(f"| {sw.name} | {v:g} | {loop_name} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------------- tables

#: The metrics of the main tables (the paper's loop has no actuator limit to saturate).
TABLE_METRICS = tuple(m for m in METRIC_NAMES if m != "saturation_fraction")
COLUMNS = ["plant", "payload", "switching", "delta", "rollouts", "diverged"] + [
    f"{m}_{j}" for m in TABLE_METRICS for j in (1, 2, 3)
]


def metric_rows(cases: list[Case], metrics: tuple[str, ...] = TABLE_METRICS) -> list[dict[str, Any]]:
    """One row per case; batched cases (box vertices) report the worst rollout per metric
    (max over the batch), excluding diverged rollouts."""
    rows = []
    for c in cases:
        ok = ~np.asarray(c.result.diverged)
        row = {
            "plant": c.plant,
            "payload": c.payload,
            "switching": "sign" if c.switching == "sign" else "ratio",
            "delta": "-" if c.switching == "sign" else c.switching,
            "rollouts": int(ok.size),
            "diverged": int((~ok).sum()),
        }
        for m in metrics:
            v = np.asarray(getattr(c.result.metrics, m))[ok]
            worst = v.max(axis=0) if v.size else np.full(3, np.nan)
            for j in range(3):
                row[f"{m}_{j + 1}"] = float(f"{worst[j]:.4g}")
        rows.append(row)
    return rows


def to_csv(rows: list[dict[str, Any]]) -> str:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=COLUMNS, lineterminator="\n")
    w.writeheader()
    w.writerows(rows)
    return buf.getvalue()


def read_csv(text: str) -> list[dict[str, Any]]:
    rows = []
    for r in csv.DictReader(io.StringIO(text)):
        rows.append({k: (float(v) if k not in COLUMNS[:4] else v) for k, v in r.items()})
        for k in ("rollouts", "diverged"):
            rows[-1][k] = int(rows[-1][k])
    return rows


def to_markdown(rows: list[dict[str, Any]], metrics: tuple[str, ...] = TABLE_METRICS) -> str:
    """Markdown table; each metric cell lists joints 1 / 2 / 3."""
    head = ["plant", "payload", "switching", "delta", "rollouts"] + [f"{m} ({UNITS[m]})" for m in metrics]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        cells = [r["plant"], r["payload"], r["switching"], r["delta"],
                 str(r["rollouts"]) + (f" ({r['diverged']} diverged)" if r["diverged"] else "")]  # fmt: skip
        cells += [" / ".join(f"{r[f'{m}_{j}']:.3g}" for j in (1, 2, 3)) for m in metrics]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------------- design facts


def design_facts() -> str:
    """docs/paper.md, recomputed: a Markdown section with the package's numbers
    beside the paper's printed ones."""
    box = (paper.A_LOWER, paper.A_UPPER, paper.B_LOWER, paper.B_UPPER)
    d = summarize(paper.A_ROWS, paper.B_ROWS, box, paper.C, paper.POLES)
    A, B = paper.full_A(paper.A_ROWS), paper.full_B(paper.B_ROWS)
    eig = lambda M: np.sort_complex(np.linalg.eigvals(M))
    fmt_eig = lambda z: ", ".join(f"{x.real:.3g}" + (f"{x.imag:+.2g}j" if abs(x.imag) > 1e-9 else "") for x in z)
    minus, plus = eig(A - B @ paper.K_PRINTED), eig(A + B @ paper.K_PRINTED)
    mid_A = (paper.A_LOWER + paper.A_UPPER) / 2 - paper.A_ROWS
    mid_B = (paper.B_LOWER + paper.B_UPPER) / 2 - paper.B_ROWS
    worst = np.unravel_index(np.abs(mid_B).argmax(), mid_B.shape)
    s_cb = np.linalg.svd(d.CB, compute_uv=False)
    f3 = lambda v: " / ".join(f"{x:.4g}" for x in v)
    one_minus = {c: d.gamma_min[c] * (1 + d.beta.value) / (1 - d.beta.value) for c in d.gamma_min}
    lines = [
        "| quantity | computed by fosmc_jax | printed in the paper |",
        "|---|---|---|",
        f"| alpha (31), max over {d.alpha.vertices_checked} vertices | {d.alpha.value:.4f} | {paper.ALPHA_PRINTED} |",
        f"| beta (31), max over {d.beta.vertices_checked} vertices | {d.beta.value:.4f} | {paper.BETA_PRINTED} |",
        f"| largest \\|box midpoint - nominal (29)\\|, A rows | {np.abs(mid_A).max():.3g} | 0 (rounding) |",
        f"| largest \\|box midpoint - nominal (29)\\|, B rows | {np.abs(mid_B).max():.3g} "
        f"at B({3 * worst[0] + 3},{worst[1] + 1}) | 0 |",
        f"| eig(A + BK), K placed from (33) | {fmt_eig(d.closed_loop_poles)} | (33) |",
        f"| eig(A + B K_printed) | {fmt_eig(plus)} | (33) claimed |",
        f"| eig(A - B K_printed) | {fmt_eig(minus)} | (33) claimed |",
        f"| singular values of CB | {f3(s_cb)} | - |",
        f"| gamma bounds, `spectral` (24)-(26) | {f3(d.gamma_min['spectral'])} | {f3(paper.GAMMA_MIN_PRINTED)} (35) |",
        f"| gamma bounds, `paper` (\\|\\|CB\\|\\| = sigma_min) | {f3(d.gamma_min['paper'])} "
        f"| {f3(paper.GAMMA_MIN_PRINTED)} (35) |",
        f"| `spectral` bounds with 1 - beta for 1 + beta | {f3(one_minus['spectral'])} | - |",
        f"| `paper` bounds with 1 - beta for 1 + beta | {f3(one_minus['paper'])} | - |",
        f"| gains used (36) | {f3(paper.GAMMA)} | {f3(paper.GAMMA)} |",
    ]
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------------- figures


def write_figures(cases: list[Case], out_dir, kind: str) -> list[str]:
    """Figs. 2-5 of the paper and three extra figures; returns the file names written."""
    from .plots import plot_joint_series

    by = {(c.plant, c.payload, c.switching): c for c in cases}
    primary = [c for c in cases if c.plant == kind and "vertices" not in c.payload]
    loads = list(dict.fromkeys(c.payload for c in primary))
    heavy = loads[-1]
    theta = slice(0, 9, 3)

    def tr(case, b=0):
        t = case.result.trace
        return np.asarray(t.t[b]), t

    written = []

    def save(name, series, ylabel, title, **kwargs):
        plot_joint_series(series, ylabel, out_dir / name, title, **kwargs)
        written.append(name)

    where = f"{kind} plant" if kind == "linear" else "arm"
    series = []
    t, trace = tr(by[(kind, loads[0], "sign")])
    series.append(("desired", t, np.asarray(trace.X_d[0][:, theta])))
    for load in loads:
        t, trace = tr(by[(kind, load, "sign")])
        series.append((f"actual, {load}", t, np.asarray(trace.X[0][:, theta])))
    styles = {"desired": {"color": "k", "ls": "--", "lw": 2}}
    save("fig2_tracking.png", series, "angle (rad)", f"Fig. 2: tracking with SGN control (23), {where}", styles=styles)

    t, trace = tr(by[(kind, heavy, "sign")])
    save("fig3_sign_control.png", [(f"SGN, {heavy}", t, trace.U[0])], "control U (V)",
         f"Fig. 3: control inputs with SGN, {where}, {heavy}")  # fmt: skip
    mid = t[len(t) // 4]
    save("fig_extra_chattering_zoom.png", [(f"SGN, {heavy}", t, trace.U[0])], "control U (V)",
         f"Chattering period: SGN control over 4 ms (every step shown), {where}, {heavy}",
         styles={f"SGN, {heavy}": {"marker": ".", "drawstyle": "steps-post"}}, xlim=(mid, mid + 0.004))  # fmt: skip

    sets = [s for s in SWITCHINGS if s != "sign"]
    for name, field, ylabel, title in (
        ("fig4_continuous_control.png", "U", "control U (V)", "Fig. 4: control inputs with (28)"),
        ("fig5_tracking_errors.png", "e", "tracking error (rad)", "Fig. 5: tracking errors with (28)"),
    ):
        series = []
        for s in sets:
            t, trace = tr(by[(kind, heavy, s)])
            Y = trace.U[0] if field == "U" else trace.X[0][:, theta] - trace.X_d[0][:, theta]
            series.append((f"{s}: delta = {paper.DELTA_SETS[int(s[-1]) - 1].tolist()}", t, Y))
        save(name, series, ylabel, f"{title}, Table 1 sets, {where}, {heavy}")

    series = [(s, *(lambda t, trace: (t, trace.s[0]))(*tr(by[(kind, heavy, s)]))) for s in SWITCHINGS]
    save("fig_extra_sliding_variables.png", series, "s (sliding variable)",
         f"Sliding variables s(t) of (14), {where}, {heavy}", logy=True)  # fmt: skip

    series = []
    vert = [c for c in cases if "vertices" in c.payload]
    for c in vert:
        t = np.asarray(c.result.trace.t[0])
        e = np.abs(np.asarray(c.result.trace.X)[:, :, theta] - np.asarray(c.result.trace.X_d)[:, :, theta])
        ok = ~np.asarray(c.result.diverged)
        series.append((c.switching, t, e[ok].max(axis=0)))
    save("fig_extra_box_vertices.png", series, "tracking error (rad)",
         f"Linear model (3) at {vert[0].payload}: worst |error| over the vertices", logy=True)  # fmt: skip
    return written


def write_realistic_figure(cases: list[Case], out_dir) -> str:
    """The realistic loop's control beside the ideal loop's (Table 1 set 1, heaviest payload;
    ``cases`` holds both: the realistic ones and :func:`run_cases`' arm cases)."""
    from .plots import plot_joint_series

    heavy = cases[-1].payload
    by = {(c.plant.replace("arm", "arm, ideal loop") if c.plant == "arm" else c.plant, c.payload, c.switching): c
          for c in cases}  # fmt: skip
    series = []
    for loop in ("ideal", "realistic"):
        trace = by[(f"arm, {loop} loop", heavy, "set 1")].result.trace
        series.append((f"Table 1 set 1, {loop} loop", np.asarray(trace.t[0]), np.asarray(trace.U[0])))
    name = "fig_realistic_control.png"
    plot_joint_series(series, "applied voltage U (V)", out_dir / name,
                      f"Table 1 set 1 in the ideal and the realistic loop (REPRODUCTION.md), arm, {heavy}",
                      styles={"Table 1 set 1, realistic loop": {"lw": 0.5}})  # fmt: skip
    return name


def write_tradeoff_figure(sweeps: list[Sweep], out_dir) -> str:
    """The trade-off sweeps (:func:`tradeoff_sweeps`)."""
    from .plots import plot_tradeoff

    name = "fig_realistic_tradeoff.png"
    plot_tradeoff(sweeps, out_dir / name,
                  "Table 1 set 1 on the arm (mean of 0 and 10 kg): smaller delta or faster poles")  # fmt: skip
    return name


# ---------------------------------------------------------------------------- report


def replace_block(text: str, name: str, content: str) -> str:
    """Replace what stands between ``<!-- begin:name -->`` and ``<!-- end:name -->``."""
    begin, end = f"<!-- begin:{name} -->", f"<!-- end:{name} -->"
    i, j = text.find(begin), text.find(end)
    if i < 0 or j < i:
        raise ValueError(f"report has no block {begin} ... {end}")
    return text[: i + len(begin)] + "\n" + content + text[j:]


@_with_x64
def run_reproduce(
    out: str | Path | None = None,
    *,
    plant: str = "arm",
    t_final: float = 4.0,
    dt: float = 1e-4,
    integrator: str = "rk4",
    force: bool = False,
    report: str | Path | None = None,
    log: Log = _quiet,
) -> dict[str, Any]:
    """``fosmc reproduce``: the paper's cases (Table 1's sets and SGN, nominal and box
    vertices or the arm at 0 and 10 kg) at ``t_final``, ``dt``, ``integrator``; the shortened
    check table; for ``plant = "arm"`` the realistic loop beside the ideal one and the
    trade-off sweeps. It takes no config: the cases are the paper's.

    ``out``: folder for the tables and figures (None: nothing written, no figures).
    ``report``: a Markdown file whose generated blocks are refreshed.
    Returns ``{"files": {file name: text}, "figures": [file names], "rows": {"metrics",
    "metrics_short"[, "realistic"]: metric rows}}``; ``files`` holds ``metrics.csv``,
    ``metrics.md``, ``design.md``, ``metrics_short.csv`` (and ``realistic.md``,
    ``tradeoff.md`` for the arm), exactly as written to ``out``.
    """
    report = _checked_options(plant, t_final, dt, integrator, report)
    if out is not None:
        out = _fresh_out(out, force, "use --force to overwrite")
        out.mkdir(parents=True, exist_ok=True)
    settings = Settings(t_final=t_final, dt=dt, integrator=integrator)
    log(f"fosmc reproduce: {plant} plant, {settings.integrator}, dt = {settings.dt} s, "
        f"{settings.t_final} s; compiling and running the cases ...")  # fmt: skip
    log(
        f"fosmc reproduce: the shortened check table ({SHORT.t_final} s)"
        f"{', the realistic loop and the trade-off sweeps' if plant == 'arm' else ''}, beside ..."
    )

    # one pool for every group's runs, the paper's cases first: their figures are drawn while
    # the other groups compile (drawing holds the GIL; compiling does not)
    groups = [case_jobs(plant, settings, log=log)]
    if plant == "arm":
        groups += [realistic_jobs(t_final, log=log), tradeoff_jobs(t_final, log=log)]
    groups += [Jobs([design_facts], lambda parts: parts[0]), case_jobs(plant, SHORT, log=log)]
    figures: list[str] = []

    def draw(i: int, done: list) -> None:
        if out is None:
            return
        if i == 0:
            log("fosmc reproduce: drawing figures ...")
            figures.extend(write_figures(done[0], out, plant))
        elif plant == "arm" and i == 1:
            figures.append(write_realistic_figure(done[0] + done[1], out))
        elif plant == "arm" and i == 2:
            figures.append(write_tradeoff_figure(done[2], out))

    cases, *arm_only, design, short_cases = run_groups(groups, draw)
    rows, short = metric_rows(cases), metric_rows(short_cases)
    files = {"metrics.csv": to_csv(rows), "metrics.md": to_markdown(rows),
             "design.md": design, "metrics_short.csv": to_csv(short)}  # fmt: skip
    tables = {"metrics": rows, "metrics_short": short}
    if plant == "arm":
        realistic, sweeps = arm_only
        tables["realistic"] = metric_rows(realistic, METRIC_NAMES)
        files.update({"realistic.md": to_markdown(tables["realistic"], METRIC_NAMES),
                      "tradeoff.md": sweep_markdown(sweeps)})  # fmt: skip
    if out is not None:
        for name, text in files.items():
            write_text(out / name, text)
    if report:
        _refresh(report, files)
        log(f"fosmc reproduce: updated {report}")
    return {"files": files, "figures": figures, "rows": tables}


def _checked_options(plant: str, t_final: float, dt: float, integrator: str, report) -> Path | None:
    """The ``report`` file (checked readable and writable), once every option is in range (a
    one-line :class:`ConfigError` naming the first that is not), before any case runs."""
    if plant not in ("arm", "linear"):
        raise ConfigError(f"--plant: expected 'arm' or 'linear', got {plant!r}")
    if integrator not in ("euler", "rk4"):
        raise ConfigError(f"--integrator: expected 'euler' or 'rk4', got {integrator!r}")
    problems.check_horizon(t_final, dt, ("--t-final", "--dt"))  # as the config's [sim] t_final and dt
    if plant == "arm":  # the realistic loop's horizon too (its period, its delay)
        try:
            problems.resolve(realistic_config(t_final))
        except ConfigError as e:
            raise ConfigError(f"--t-final: too short for the realistic loop ({e})") from None
    if report:
        report = writable(report, "--report")
        try:
            report.read_text()
        except (OSError, ValueError) as e:
            raise ConfigError(f"--report: cannot read {report}: {getattr(e, 'strerror', None) or e}") from None
    return report


def _refresh(report: Path, files: dict[str, str]) -> None:
    """The generated blocks of the Markdown file ``report`` replaced by the tables in ``files``."""
    text = report.read_text()
    text = replace_block(text, "metrics", files["metrics.md"])
    text = replace_block(text, "design", files["design.md"])
    for name in ("realistic", "tradeoff"):
        if f"{name}.md" in files:
            text = replace_block(text, name, files[f"{name}.md"])
    write_text(report, text)
