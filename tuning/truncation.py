"""Is tune's gradient finite, of sane size and informative, and at which ``[tune] gradient_window``?

For every config in tuning/configs/*.toml that ``fosmc tune`` accepts (those that fail to load
or that tune refuses are listed as skipped) and each gradient window W (s; 0 = the whole
training horizon; ``cfg["tune"]["gradient_window"] = W`` before
``_config.tuning_problems``), at two points, p0 (the config's parameters) and tune's start (the
best of the global stage of ``tune.global_candidates``, as ``run_tune`` computes it: same
problem, objective and seed, computed once per config), in tune's internal coordinates u (15
entries: log delta, log gamma, log(-poles)), float64:

a. the AD gradient of tune's training loss (``_tuning.make_loss``, reverse mode): its max
   |entry|, norm, finiteness;
b. its informativeness: the cosine between it and central finite differences of the SAME loss
   at h = 0.01, 0.05, 0.2 in u (one batched call of 2 x 15 perturbed points + the centre per
   h; the loss's values do not depend on W, so FD is computed once per point); the cosine
   between FD gradients at two h says at which h FD is a stable (smoothed) slope rather than
   noise. And the change of the PLAIN problem's loss (the ``[sim]`` simulation, the same
   objective) after a step of s = 0.01, 0.03, 0.1 in u along -g/|g|, against the same steps
   along 3 random unit directions (the control) and along -FD(h = 0.2);
c. per second, for the configs of ``--tune-configs`` and W in ``--tune-windows``: a short
   tune (``_tuning.run``, ``--tune-steps`` Adam steps, the config's learning rate, schedule
   and clip, reverse mode) from tune's start, timed without its compilation (reported
   apart), and the plain loss it reaches, against CMA-ES (``_search.cma_es``, popsize 16,
   sigma 0.1 and 0.3 in u, on the same training loss evaluated batched, from the same start)
   for the same wall time (one CMA-ES run per sigma, read off at each tune run's time).

Then a diagnosis on realistic_arm of where the full-horizon growth starts: the W = 0 gradient
at its tune start with one ingredient of the digital loop changed at a time (exact rates,
no quantization, no delay, no saturation, all four off, delta x 10).

Timings are wall times on a shared 2-core machine; each comes with the load averages
(os.getloadavg) taken beside it; compare timings within one run only. The persistent
compilation cache is on, in a fresh folder per run (so the first compile of each program is a
real one; tune's own jit of the same program then loads it).

    .venv/bin/python tuning/truncation.py               # the study (about 30-45 min on 2 cores)
    .venv/bin/python tuning/truncation.py --quick --out /tmp/truncation   # a smoke run
    .venv/bin/python tuning/truncation.py --report-only  # the Markdown again from the JSON

Writes tuning/results/truncation.json, then tuning/results/truncation.md generated from it.
"""

from __future__ import annotations

import argparse
import copy
import math
import os
import pathlib
import platform
import subprocess
import sys
import tempfile
import time
import tomllib

from fosmc_jax._sharding import use_all_cores

use_all_cores()  # before the first JAX operation, as the command line does

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from jax.flatten_util import ravel_pytree  # noqa: E402
from jax.sharding import Mesh  # noqa: E402
from jax.sharding import PartitionSpec as Spec  # noqa: E402

from fosmc_jax import _config  # noqa: E402
from fosmc_jax import _tuning as T  # noqa: E402
from fosmc_jax._cache import use_compilation_cache  # noqa: E402
from fosmc_jax._front import global_stage  # noqa: E402
from fosmc_jax._io import jsonable, write_text  # noqa: E402
from fosmc_jax._search import cma_es  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parent.parent
CONFIGS = ROOT / "tuning" / "configs"
OUT = ROOT / "tuning" / "results" / "truncation"

WINDOWS = (0.0, 0.5, 0.1, 0.05, 0.02, 0.01, 0.005)
FD_STEPS = (0.01, 0.05, 0.2)
FD_MAIN = 0.2  # the FD gradient the AD one is compared with in the summary tables (see the report)
STEP_SIZES = (0.01, 0.03, 0.1)
RANDOM_SEEDS = (0, 1, 2)
TUNE_CONFIGS = ("realistic_arm", "realistic_arm_short_training", "arm_set2", "vertices")
TUNE_WINDOWS = (0.0, 0.1, 0.02, 0.005)
TUNE_STEPS = 30
CMA_SIGMAS = (0.1, 0.3)
POPSIZE = 16
DIAG_CONFIG = "realistic_arm"

T0 = time.perf_counter()


def log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')} +{time.perf_counter() - T0:6.0f} s] {msg}", flush=True)


def load() -> list[float]:
    return [round(x, 2) for x in os.getloadavg()]


def uptime() -> str:
    try:
        return subprocess.run(["uptime"], capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return f"load average: {os.getloadavg()}"


def num(x) -> float | str:
    """A float, or 'inf' / '-inf' / 'nan' (JSON has none of them)."""
    x = float(x)
    return x if math.isfinite(x) else str(x)


def wkey(w: float) -> str:
    return f"{w:g}"


def cosine(a: np.ndarray, b: np.ndarray) -> float | None:
    a, b = np.asarray(a, float), np.asarray(b, float)
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        return None
    a, b = a / max(np.max(np.abs(a)), 1e-300), b / max(np.max(np.abs(b)), 1e-300)  # huge entries: no overflow
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    return float(a @ b / (na * nb)) if na > 0 and nb > 0 else None


def unit(g: np.ndarray) -> np.ndarray | None:
    """g / |g|, robust to huge finite entries; None when g has a non-finite entry or is 0."""
    g = np.asarray(g, float)
    if not np.all(np.isfinite(g)) or not np.any(g):
        return None
    g = g / np.max(np.abs(g))
    return g / np.linalg.norm(g)


def grad_stats(g: np.ndarray) -> dict:
    g = np.asarray(g, float)
    with np.errstate(over="ignore", invalid="ignore"):
        finite = bool(np.all(np.isfinite(g)))
        norm = float(np.linalg.norm(g)) if finite else float("nan")
        if finite and not math.isfinite(norm):  # overflow of the sum of squares
            m = np.max(np.abs(g))
            norm = float("inf") if m == 0 else m * float(np.linalg.norm(g / m))
    big = np.nanmax(np.abs(g)) if np.any(~np.isnan(g)) else float("nan")
    return {"max": num(big), "norm": num(norm), "finite": finite, "n_nan": int(np.isnan(g).sum()),
            "n_inf": int(np.isinf(g).sum()), "grad": [num(x) for x in g]}  # fmt: skip


# ---------------------------------------------------------------------------- batched losses


class Batched:
    """The tuning objective of ``problem`` (same obj) at many flat u at once: vmapped over
    candidates, the candidates split over the local devices (as fosmc_jax._front's chunk
    evaluator); compiled once per chunk size. Values of the training problem do not depend on
    the gradient window (truncation changes derivatives only)."""

    def __init__(self, problem: T.Problem, obj: T.Objective, unravel):
        self.devices = jax.local_devices()
        mesh = Mesh(np.asarray(self.devices), ("c",))

        def one(x):
            r = problem.simulate(T.to_physical(unravel(x), problem.base, None), checkpoint_every=0, truncate_every=0)
            J, _, _ = T.rollout_costs(r.metrics, r.diverged, obj)
            return T.aggregate(J, obj), jnp.sum(r.diverged)

        self.run = jax.jit(jax.shard_map(jax.vmap(one), mesh=mesh, in_specs=Spec("c"), out_specs=Spec("c"),
                                         check_vma=False))  # fmt: skip
        self.compile_s: dict[int, float] = {}

    def __call__(self, X: np.ndarray, chunk: int = 16) -> tuple[np.ndarray, np.ndarray]:
        X = np.atleast_2d(np.asarray(X, float))
        n = len(X)
        size = -(-chunk // len(self.devices)) * len(self.devices)  # the compiled size: a multiple of the devices
        vals, div = [], []
        for i in range(0, n, size):
            part = X[i : i + size]
            pad = size - len(part)
            if pad:
                part = np.concatenate([part, np.repeat(part[-1:], pad, 0)])
            t = time.perf_counter()
            v, d = self.run(jnp.asarray(part))
            v, d = np.asarray(v), np.asarray(d)
            if size not in self.compile_s:
                self.compile_s[size] = time.perf_counter() - t
            vals.append(v[: len(part) - pad])
            div.append(d[: len(part) - pad])
        return np.concatenate(vals), np.concatenate(div)


# ---------------------------------------------------------------------------- one config


def accepted(cfg: dict) -> str | None:
    """Why ``fosmc tune`` (or this study) would refuse the config, else None."""
    kind = cfg["controller"]["kind"]
    names = T.SPACES[kind].names
    if not set(cfg["tune"]["params"]) <= set(names):
        return f"tune.params {cfg['tune']['params']} not parameters of kind {kind}"
    if cfg["tune"]["keep_gamma_bound"]:
        return "tune.keep_gamma_bound: the gamma floor is not covered by this study"
    return None


def setup(cfg: dict) -> dict:
    """What run_tune computes before its optimizer: problems, objective, tune's start."""
    c = copy.deepcopy(cfg)
    c["tune"]["gradient_window"] = 0.0
    plain, train, p0 = _config.tuning_problems(c)
    m = T.evaluate(train, p0)["metrics"]
    obj = T.objective_of(c["tune"], m)
    start, score, t_global = p0, None, 0.0
    if cfg["tune"]["global_candidates"]:
        t = time.perf_counter()
        start, score = global_stage(train, obj, p0, cfg["tune"]["global_candidates"],
                                    free=tuple(cfg["tune"]["params"]), log=lambda _: None)  # fmt: skip
        t_global = time.perf_counter() - t
    u_p0 = T.to_internal(p0, plain.base, None)
    u_start = T.to_internal(start, plain.base, None)
    flat_p0, unravel = ravel_pytree(u_p0)
    flat_start = ravel_pytree(u_start)[0]
    return {"plain": plain, "train": train, "p0": p0, "start": start, "obj": obj, "score": score,
            "t_global": t_global, "unravel": unravel, "u": {"p0": np.asarray(flat_p0), "start": np.asarray(flat_start)},
            "train_eval": Batched(train, obj, unravel), "plain_eval": Batched(plain, obj, unravel)}  # fmt: skip


def fd_gradient(evaluate: Batched, u: np.ndarray, h: float) -> dict:
    """Central differences of the batched loss at u, step h in u: 2 x 15 points + the centre, one call."""
    d = len(u)
    E = np.eye(d)
    X = np.concatenate([u[None], u + h * E, u - h * E])
    v, div = evaluate(X, chunk=2 * d + 2)
    g = (v[1 : d + 1] - v[d + 1 :]) / (2 * h)
    return {"grad": g, "centre": float(v[0]), "diverged_points": int(np.sum(div[1:] > 0))}


def ad_gradient(cfg: dict, s: dict, w: float, points: dict) -> dict:
    """Tune's AD gradient (reverse mode, its training loss with gradient_window = w) at each point."""
    c = copy.deepcopy(cfg)
    c["tune"]["gradient_window"] = w
    _, train, _ = _config.tuning_problems(c)
    loss = T.make_loss(train, s["obj"], None)
    vg = jax.jit(jax.value_and_grad(loss, has_aux=True))
    out = {"truncate_every": train.options["truncate_every"], "points": {}}
    first = True
    for name, u in points.items():
        t = time.perf_counter()
        (value, _), g = jax.block_until_ready(vg(s["unravel"](jnp.asarray(u))))
        dt = time.perf_counter() - t
        if first:  # the first call compiles; time a second one
            out["compile_s"] = dt
            t = time.perf_counter()
            jax.block_until_ready(vg(s["unravel"](jnp.asarray(u))))
            dt = time.perf_counter() - t
            first = False
        out["grad_s"] = dt
        out["load"] = load()
        out["points"][name] = dict(grad_stats(ravel_pytree(g)[0]), loss=num(value))
    return out


def study_config(name: str, cfg: dict, args, tune_part: bool) -> dict:
    t_cfg = time.perf_counter()
    s = setup(cfg)
    train = s["train"]
    res = {
        "train": {"dt": float(train.dt), "n_steps": int(train.options["n_steps"]),
                  "t_final": float(train.dt) * int(train.options["n_steps"]),
                  "sample_period": cfg["controller"]["sample_period"]},
        "plain": {"dt": float(s["plain"].dt), "n_steps": int(s["plain"].options["n_steps"])},
        "objective": s["obj"]._asdict(),
        "global_stage": {"candidates": cfg["tune"]["global_candidates"], "score": s["score"], "time_s": s["t_global"]},
        "params": {"p0": {k: np.asarray(v).tolist() for k, v in s["p0"]._asdict().items()},
                   "start": {k: np.asarray(v).tolist() for k, v in s["start"]._asdict().items()}},  # fmt: skip
        "points": {}, "windows": {},
    }  # fmt: skip
    log(f"{name}: train dt {res['train']['dt']:g} s x {res['train']['n_steps']} steps; global stage "
        f"{s['t_global']:.1f} s, score {s['score']}")  # fmt: skip
    d = len(s["u"]["start"])
    randoms = {seed: unit(np.random.default_rng(seed).standard_normal(d)) for seed in RANDOM_SEEDS}
    # b. FD gradients (W-independent), random and -FD steps on the plain loss
    for pname, u in s["u"].items():
        t = time.perf_counter()
        fd = {wkey(h): fd_gradient(s["train_eval"], u, h) for h in args.fd_steps}
        t_fd = time.perf_counter() - t
        X = [u]
        labels = []
        for seed, r in randoms.items():
            for step in STEP_SIZES:
                X.append(u + step * r)
                labels.append(("random", seed, step))
        dfd = unit(fd[wkey(FD_MAIN)]["grad"]) if wkey(FD_MAIN) in fd else None
        if dfd is not None:
            for step in STEP_SIZES:
                X.append(u - step * dfd)
                labels.append(("fd", None, step))
        v, div = s["plain_eval"](np.asarray(X))
        base = float(v[0])
        rand = {wkey(step): [float(v[1 + i]) - base for i, lab in enumerate(labels) if lab[0] == "random" and lab[2] == step]
                for step in STEP_SIZES}  # fmt: skip
        fds = {wkey(lab[2]): float(v[1 + i]) - base for i, lab in enumerate(labels) if lab[0] == "fd"}
        hs = list(fd)
        res["points"][pname] = {
            "train_loss": fd[hs[0]]["centre"], "plain_loss": base, "plain_diverged": int(div[0]),
            "fd": {h: {"grad": [num(x) for x in f["grad"]], "norm": num(np.linalg.norm(f["grad"])),
                       "diverged_points": f["diverged_points"]} for h, f in fd.items()},
            "fd_agreement": {f"{a}|{b}": cosine(fd[a]["grad"], fd[b]["grad"]) for i, a in enumerate(hs) for b in hs[i + 1 :]},
            "random_steps": rand, "fd_steps": fds, "fd_time_s": t_fd, "fd_load": load(),
        }  # fmt: skip
        log(f"{name} @ {pname}: train loss {res['points'][pname]['train_loss']:.4f}, plain {base:.4f}; FD "
            + ", ".join(f"h={h}: |g| {np.linalg.norm(f['grad']):.3g}" for h, f in fd.items())
            + "; cos(FD_h, FD_h') " + ", ".join(f"{k} {v:.2f}" if v is not None else f"{k} -"
                                               for k, v in res["points"][pname]["fd_agreement"].items()))  # fmt: skip
    fd_all = {p: {h: np.asarray(res["points"][p]["fd"][h]["grad"], float) for h in res["points"][p]["fd"]}
              for p in s["u"]}  # fmt: skip
    # a. AD gradients per window; b. cosines with FD; step directions
    grad_steps = []  # (window, point, step, x)
    for w in args.windows:
        try:
            r = ad_gradient(cfg, s, w, s["u"])
        except Exception as e:  # noqa: BLE001 - a window that fails is reported, not fatal
            res["windows"][wkey(w)] = {"error": f"{type(e).__name__}: {e}"}
            log(f"{name} W={w:g}: failed: {e}")
            continue
        for pname, pr in r["points"].items():
            g = np.asarray([float(x) for x in pr["grad"]], float)
            pr["cos_fd"] = {h: cosine(g, f) for h, f in fd_all[pname].items()}
            direction = unit(g)
            pr["direction_defined"] = direction is not None
            if direction is not None:
                for step in STEP_SIZES:
                    grad_steps.append((wkey(w), pname, wkey(step), s["u"][pname] - step * direction))
            pr["train_loss_vs_batched"] = (float(pr["loss"]) - res["points"][pname]["train_loss"]
                                           if isinstance(pr["loss"], float) else None)  # fmt: skip
        res["windows"][wkey(w)] = r
        log(f"{name} W={w:g} ({r['truncate_every']} steps): compile {r['compile_s']:.1f} s, grad {r['grad_s']:.2f} s "
            f"(load {r['load']}); " + "; ".join(
                f"{p}: max|g| {pr['max'] if isinstance(pr['max'], str) else format(pr['max'], '.3g')}, cos(FD {FD_MAIN}) "
                + (f"{pr['cos_fd'].get(wkey(FD_MAIN)):.2f}" if pr["cos_fd"].get(wkey(FD_MAIN)) is not None else "-")
                for p, pr in r["points"].items()))  # fmt: skip
    if grad_steps:
        v, _ = s["plain_eval"](np.asarray([x for *_, x in grad_steps]), chunk=32)
        for (wk, pname, sk, _), val in zip(grad_steps, v):
            pr = res["windows"][wk]["points"][pname]
            pr.setdefault("steps", {})[sk] = float(val) - res["points"][pname]["plain_loss"]
    for pname in s["u"]:
        res["points"][pname]["growth"] = growth(res, pname)
    # c. short tune against CMA-ES at equal wall time
    if tune_part:
        res["tune_vs_cma"] = tune_vs_cma(name, cfg, s, args)
    res["wall_s"] = time.perf_counter() - t_cfg
    res["evaluator_compile_s"] = {"train": s["train_eval"].compile_s, "plain": s["plain_eval"].compile_s}
    return res


def growth(res: dict, pname: str) -> dict:
    """Growth of max |g| with the window: a least-squares slope of log10 max|g| against W over
    the windows with finite, nonzero gradients (W = 0 counted at the training horizon), in
    decades per second, and over the windows of 0.02 s and longer (the short windows hold
    little growth: the gradient there is the window's own sensitivity)."""
    t_final = res["train"]["t_final"]
    xs, ys = [], []
    for wk, r in res["windows"].items():
        if "points" not in r:
            continue
        m = r["points"][pname]["max"]
        if isinstance(m, float) and m > 0:
            w = float(wk) or t_final
            xs.append(min(w, t_final))
            ys.append(math.log10(m))
    out = {"windows": xs, "log10_max": ys}
    for label, lo in (("all", 0.0), ("from_0.02", 0.02)):
        sel = [(x, y) for x, y in zip(xs, ys) if x >= lo - 1e-12]
        if len({x for x, _ in sel}) >= 2:
            x, y = np.asarray(sel).T
            out[f"decades_per_s_{label}"] = float(np.polyfit(x, y, 1)[0])
    return out


def tune_vs_cma(name: str, cfg: dict, s: dict, args) -> dict:
    tcfg = cfg["tune"]
    u0 = s["unravel"](jnp.asarray(s["u"]["start"]))
    start_plain = None
    runs = {}
    for w in args.tune_windows:
        c = copy.deepcopy(cfg)
        c["tune"]["gradient_window"] = w
        _, train, _ = _config.tuning_problems(c)
        settings = T.Settings(args.tune_steps, tcfg["learning_rate"], tcfg["schedule"], tcfg["clip"], "reverse",
                              tuple(tcfg["params"]), 0)  # fmt: skip
        stamps = []
        t = time.perf_counter()
        u, hist = T.run(T.make_loss(train, s["obj"], None), u0, settings, log=lambda m: stamps.append(time.perf_counter()) if m.startswith("step ") else None)
        wall = time.perf_counter() - t
        steps = [b - a for a, b in zip(stamps[:-1], stamps[1:])][: args.tune_steps - 1]
        per_step = float(np.median(steps)) if steps else float("nan")
        first = stamps[0] - t if stamps else float("nan")
        compile_s = max(first - per_step, 0.0) if steps else 0.0
        runs[wkey(w)] = {"u": np.asarray(ravel_pytree(u)[0]), "wall_s": wall, "compile_s": compile_s,
                         "time_s": wall - compile_s, "step_s": per_step, "load": load(),
                         "skipped": int(np.sum(hist["skipped"])), "best_step": int(hist["best_step"]),
                         "train_loss": [num(x) for x in hist["loss"]], "grad_norm": [num(x) for x in hist["grad_norm"]]}  # fmt: skip
        log(f"{name} tune W={w:g}: {args.tune_steps} steps in {wall:.1f} s ({compile_s:.1f} s compiling, "
            f"{per_step:.3f} s/step, load {load()}), skipped {runs[wkey(w)]['skipped']}, train loss "
            f"{hist['loss'][0]:.4f} -> best {np.nanmin(np.where(np.isfinite(hist['loss']), hist['loss'], np.nan)) if np.any(np.isfinite(hist['loss'])) else float('nan'):.4f}")  # fmt: skip
    budget = max(r["time_s"] for r in runs.values())
    cmas = {}
    for sigma in args.cma_sigmas:
        gens = []

        def objective(X):
            return s["train_eval"](X, chunk=POPSIZE)[0]

        t = time.perf_counter()
        _, fbest, X, F = cma_es(objective, s["u"]["start"], sigma, budget, POPSIZE, seed=0,
                                log=lambda m: gens.append(time.perf_counter()))  # fmt: skip
        gens = np.asarray(gens) - t
        cmas[wkey(sigma)] = {"X": X, "F": F, "gen_times": gens, "load": load()}
        log(f"{name} cma-es sigma {sigma}: {len(gens)} generations in {gens[-1]:.1f} s (load {load()}), best train "
            f"loss {fbest:.4f}")  # fmt: skip
    # the plain loss of every end point, in one batched call
    pts, keys = [s["u"]["start"]], [("start",)]
    for wk, r in runs.items():
        pts.append(r["u"])
        keys.append(("tune", wk))
        for sk, cm in cmas.items():
            n_gen = max(1, int(np.sum(cm["gen_times"] <= r["time_s"])))
            F = np.where(np.isfinite(cm["F"][: n_gen * POPSIZE]), cm["F"][: n_gen * POPSIZE], np.inf)
            i = int(np.argmin(F))
            pts.append(cm["X"][i])
            keys.append(("cma", wk, sk, n_gen, float(F[i]), float(cm["gen_times"][n_gen - 1])))
    v, div = s["plain_eval"](np.asarray(pts), chunk=32)
    start_plain = float(v[0])
    out = {"start_plain_loss": start_plain, "budget_s": budget, "tune": {}, "cma": {sk: {} for sk in cmas}}
    for key, val, dv in zip(keys[1:], v[1:], div[1:]):
        if key[0] == "tune":
            r = runs[key[1]]
            out["tune"][key[1]] = {k: x for k, x in r.items() if k != "u"} | {
                "plain_loss": float(val), "plain_diverged": int(dv), "improvement": start_plain - float(val),
                "improvement_per_s": (start_plain - float(val)) / r["time_s"]}  # fmt: skip
        else:
            _, wk, sk, n_gen, ftrain, tgen = key
            out["cma"][sk][wk] = {"generations": n_gen, "evaluations": n_gen * POPSIZE, "time_s": tgen,
                                  "best_train_loss": ftrain, "plain_loss": float(val), "plain_diverged": int(dv),
                                  "improvement": start_plain - float(val),
                                  "improvement_per_s": (start_plain - float(val)) / max(tgen, 1e-9)}  # fmt: skip
    for sk, cm in cmas.items():
        out["cma"][sk]["_run"] = {"generations": len(cm["gen_times"]), "time_s": float(cm["gen_times"][-1]),
                                  "load": cm["load"]}  # fmt: skip
    return out


# ---------------------------------------------------------------------------- diagnosis


VARIANTS = {
    "as is": lambda u: None,
    "exact rates (derivatives = measured)": lambda u: u["sensors"].update(derivatives="measured"),
    "no quantization (encoder_counts 0)": lambda u: u["sensors"].update(encoder_counts=[0, 0, 0]),
    "no delay (delay_samples 0)": lambda u: u["controller"].update(delay_samples=0),
    "no saturation (no u_max)": lambda u: u["actuator"].pop("u_max", None),
    "all four off (sampled ideal law)": lambda u: (u["sensors"].update(derivatives="measured", encoder_counts=[0, 0, 0]),
                                                    u["controller"].update(delay_samples=0),
                                                    u["actuator"].pop("u_max", None)),
    "delta x 10": "delta",
    "delta x 10, all four off": "delta+off",
}  # fmt: skip


def diagnosis(start: T.Params | None, variants: list[str]) -> dict:
    """Full-horizon (W = 0) gradient at realistic_arm's tune start with one ingredient changed."""
    user0 = tomllib.loads((CONFIGS / f"{DIAG_CONFIG}.toml").read_text())
    out = {}
    base_cfg = _config.resolve(copy.deepcopy(user0))
    if start is None:
        start = setup(base_cfg)["start"]
    for label in variants:
        change = VARIANTS[label]
        user = copy.deepcopy(user0)
        user.setdefault("actuator", {})
        p = start
        if change == "delta":
            p = start._replace(delta=start.delta * 10)
        elif change == "delta+off":
            p = start._replace(delta=start.delta * 10)
            VARIANTS["all four off (sampled ideal law)"](user)
        else:
            change(user)
        cfg = _config.resolve(user)
        cfg["tune"]["gradient_window"] = 0.0
        plain, train, p0 = _config.tuning_problems(cfg)
        obj = T.objective_of(cfg["tune"], T.evaluate(train, p0)["metrics"])
        loss = T.make_loss(train, obj, None)
        vg = jax.jit(jax.value_and_grad(loss, has_aux=True))
        u = T.to_internal(p, plain.base, None)
        t = time.perf_counter()
        (value, _), g = jax.block_until_ready(vg(u))
        compile_s = time.perf_counter() - t
        t = time.perf_counter()
        jax.block_until_ready(vg(u))
        out[label] = dict(grad_stats(ravel_pytree(g)[0]), loss=num(value), compile_s=compile_s,
                          grad_s=time.perf_counter() - t, load=load())  # fmt: skip
        log(f"diagnosis {label}: max|g| {out[label]['max']}, loss {out[label]['loss']}")
    return out


# ---------------------------------------------------------------------------- report


def fmt(x, spec=".2g") -> str:
    if x is None:
        return "-"
    if isinstance(x, str):
        return x
    return format(x, spec)


def report(data: dict) -> str:
    cfgs = data["configs"]
    ws = [wkey(w) for w in data["settings"]["windows"]]
    head = lambda first: "| " + first + " | " + " | ".join("whole" if w == "0" else f"{w} s" for w in ws) + " |\n" \
        + "|---" * (len(ws) + 1) + "|\n"  # fmt: skip
    L = []
    A = L.append
    A("# Truncated backpropagation through time: tune's gradient by window\n")
    A(f"Generated by `tuning/truncation.py` from `{data['json']}` (command: `{data['command']}`). "
      f"Wall time of the study: {data['wall_s'] / 60:.1f} min on {data['machine']['cores']} cores "
      f"(`uptime` at the start: `{data['uptime_start']}`; at the end: `{data['uptime_end']}`). jax "
      f"{data['machine']['jax']}, float64, {data['machine']['devices']} CPU devices.\n")  # fmt: skip
    if data["skipped"]:
        A("Configs skipped: " + "; ".join(f"`{k}` ({v})" for k, v in data["skipped"].items()) + ".\n")
    A("Points: **p0** = the config's parameters; **start** = tune's start, the best of the global stage "
      "(`tune.global_candidates`, seed 0, on the training problem and objective, as `run_tune`). Gradients are in "
      "tune's internal coordinates u (log delta, log gamma, log(-poles)), 15 entries, reverse mode, of tune's "
      "training loss with `gradient_window` = W (whole = the training horizon). W is rounded to training steps "
      "(train dt in the first table).\n")  # fmt: skip
    A("## Configs\n")
    A("| config | train dt (s) x steps | sample period (s) | global stage (s) | start: train loss | start: plain loss "
      "| p0: plain loss | config wall (s) |\n|---|---|---|---|---|---|---|---|\n")  # fmt: skip
    for n, c in cfgs.items():
        A(f"| {n} | {c['train']['dt']:g} x {c['train']['n_steps']} | {c['train']['sample_period']:g} | "
          f"{c['global_stage']['time_s']:.1f} | {c['points']['start']['train_loss']:.4f} | "
          f"{c['points']['start']['plain_loss']:.4f} | {c['points']['p0']['plain_loss']:.4f} | {c['wall_s']:.0f} |\n")  # fmt: skip
    for pname, title in (("start", "tune's start"), ("p0", "p0")):
        A(f"\n## a. max |gradient entry| at {title}\n")
        A(head("config"))
        for n, c in cfgs.items():
            A(f"| {n} | " + " | ".join(fmt(c["windows"].get(w, {}).get("points", {}).get(pname, {}).get("max"), ".2g")
                                       for w in ws) + " |\n")  # fmt: skip
    A("\nNorms (same layout, tune's start): the clip of tune is 1.0 on this norm.\n\n")
    A(head("config"))
    for n, c in cfgs.items():
        A(f"| {n} | " + " | ".join(fmt(c["windows"].get(w, {}).get("points", {}).get("start", {}).get("norm"), ".2g")
                                   for w in ws) + " |\n")  # fmt: skip
    A("\n## Growth rate of the gradient with the window\n")
    A("Least-squares slope of log10 max|g| against the window length (W = whole counted as the training "
      "horizon), over every window and over those of 0.02 s and longer; decades per second.\n\n")
    A("| config | start: all | start: >= 0.02 s | p0: all | p0: >= 0.02 s |\n|---|---|---|---|---|\n")
    for n, c in cfgs.items():
        gs, gp = c["points"]["start"]["growth"], c["points"]["p0"]["growth"]
        A(f"| {n} | {fmt(gs.get('decades_per_s_all'), '.1f')} | {fmt(gs.get('decades_per_s_from_0.02'), '.1f')} | "
          f"{fmt(gp.get('decades_per_s_all'), '.1f')} | {fmt(gp.get('decades_per_s_from_0.02'), '.1f')} |\n")  # fmt: skip
    A("\n## b. Informativeness: cosine(AD gradient, finite differences of the same loss)\n")
    A("FD: central differences at step h in u, the 30 perturbed points of one h in one batched call. Choice "
      "of h: the loss is piecewise chaotic (switching, quantization), so FD at a small h measures the "
      "jitter, not the slope; an h at which FD is a slope gives the same FD gradient at a neighbouring h. "
      "The cosines between the FD gradients at the three h:\n\n")  # fmt: skip
    pairs = list(next(iter(cfgs.values()))["points"]["start"]["fd_agreement"])
    A("| config | " + " | ".join(f"start: {p}" for p in pairs) + " | " + " | ".join(f"p0: {p}" for p in pairs)
      + " |\n" + "|---" * (2 * len(pairs) + 1) + "|\n")  # fmt: skip
    for n, c in cfgs.items():
        A(f"| {n} | " + " | ".join(fmt(c["points"]["start"]["fd_agreement"][p], ".2f") for p in pairs) + " | "
          + " | ".join(fmt(c["points"]["p0"]["fd_agreement"][p], ".2f") for p in pairs) + " |\n")  # fmt: skip
    for h in [wkey(x) for x in data["settings"]["fd_steps"]][::-1]:
        for pname, title in (("start", "tune's start"), ("p0", "p0")):
            if h == wkey(FD_STEPS[0]):
                continue
            A(f"\n### cos(AD, FD h = {h}) at {title}\n\n")
            A(head("config"))
            for n, c in cfgs.items():
                A(f"| {n} | " + " | ".join(
                    fmt(c["windows"].get(w, {}).get("points", {}).get(pname, {}).get("cos_fd", {}).get(h), ".2f")
                    for w in ws) + " |\n")  # fmt: skip
    for pname, title in (("start", "tune's start"), ("p0", "p0")):
        for sk in [wkey(x) for x in STEP_SIZES[1:]]:
            A(f"\n### Change of the PLAIN loss after a step of {sk} in u along -g/|g| at {title}\n\n")
            A("Negative: the step improves the plain loss. Columns after the windows: the same step along 3 "
              f"random unit directions (the control: min / mean / max) and along -FD(h = {wkey(FD_MAIN)}).\n\n")
            A("| config | " + " | ".join("whole" if w == "0" else f"{w} s" for w in ws)
              + " | random min / mean / max | -FD |\n" + "|---" * (len(ws) + 3) + "|\n")  # fmt: skip
            for n, c in cfgs.items():
                pt = c["points"][pname]
                rnd = pt["random_steps"][sk]
                A(f"| {n} | " + " | ".join(
                    fmt(c["windows"].get(w, {}).get("points", {}).get(pname, {}).get("steps", {}).get(sk), "+.3f")
                    for w in ws) + f" | {min(rnd):+.3f} / {np.mean(rnd):+.3f} / {max(rnd):+.3f} | "
                    f"{fmt(pt['fd_steps'].get(sk), '+.3f')} |\n")  # fmt: skip
    A("\n## Cost of one gradient\n")
    A("Seconds per AD gradient (second call; compilation apart), with the 1-min load average beside it.\n\n")
    A(head("config"))
    for n, c in cfgs.items():
        A(f"| {n} | " + " | ".join(
            (f"{c['windows'][w]['grad_s']:.2f} (c {c['windows'][w]['compile_s']:.0f}, l {c['windows'][w]['load'][0]:.1f})"
             if "grad_s" in c["windows"].get(w, {}) else "-") for w in ws) + " |\n")  # fmt: skip
    A("\n(c: compile + first call, s; l: 1-min load average.) One batched evaluation of 16 candidates of the "
      "training problem (the fast path; what CMA-ES pays per generation) and of 32 on the plain problem take, "
      "compile + first call:\n\n")  # fmt: skip
    A("| config | train: {size: s} | plain: {size: s} |\n|---|---|---|\n")
    for n, c in cfgs.items():
        A(f"| {n} | {', '.join(f'{k}: {v:.1f}' for k, v in c['evaluator_compile_s']['train'].items())} | "
          f"{', '.join(f'{k}: {v:.1f}' for k, v in c['evaluator_compile_s']['plain'].items())} |\n")  # fmt: skip
    tv = {n: c["tune_vs_cma"] for n, c in cfgs.items() if "tune_vs_cma" in c}
    if tv:
        A("\n## c. Per second: a short tune against CMA-ES at the same wall time\n")
        A(f"Tune: `_tuning.run`, {data['settings']['tune_steps']} Adam steps from tune's start, the config's "
          "learning rate, schedule and clip, reverse mode; time = its wall time less its compilation (the first "
          "step's excess over the median step). It returns the parameters of its lowest training loss. CMA-ES: "
          f"`_search.cma_es`, popsize {POPSIZE}, on the same training loss in u, one batched call per generation, "
          "from the same start, read off at the generation that ends within the tune run's time; its best "
          "training point. Both end points evaluated on the plain problem. Improvement = plain loss at the start "
          "minus at the end (positive: better); per s = over the time.\n\n")  # fmt: skip
        A("| config | W | tune: steps skipped | tune: time (s) [compile] | tune: plain loss | tune: improvement "
          "(/s) | " + " | ".join(f"CMA-ES sigma {sk}: gens, plain loss, improvement (/s)" for sk in data["settings"]["cma_sigmas_keys"])
          + " | load |\n" + "|---" * (7 + len(data["settings"]["cma_sigmas_keys"])) + "|\n")  # fmt: skip
        for n, t in tv.items():
            for wk, r in t["tune"].items():
                cells = []
                for sk in data["settings"]["cma_sigmas_keys"]:
                    cm = t["cma"][sk][wk]
                    cells.append(f"{cm['generations']}, {cm['plain_loss']:.4f}, {cm['improvement']:+.4f} "
                                 f"({cm['improvement_per_s']:+.4f})")  # fmt: skip
                A(f"| {n} (start {t['start_plain_loss']:.4f}) | {'whole' if wk == '0' else wk + ' s'} | {r['skipped']} | "
                  f"{r['time_s']:.1f} [{r['compile_s']:.0f}] | {r['plain_loss']:.4f} | {r['improvement']:+.4f} "
                  f"({r['improvement_per_s']:+.4f}) | " + " | ".join(cells) + f" | {r['load'][0]:.1f} |\n")  # fmt: skip
    if data.get("diagnosis"):
        A(f"\n## Where the growth starts ({DIAG_CONFIG}, whole horizon, tune's start)\n\n")
        A("One ingredient of the digital loop changed at a time (the same start parameters; `delta x 10`: the "
          "start's delta times 10). max |g| over the 15 entries, norm, NaN / inf entries, the training loss.\n\n")  # fmt: skip
        A("| variant | max abs g | norm | NaN | inf | loss |\n|---|---|---|---|---|---|\n")
        for k, r in data["diagnosis"].items():
            A(f"| {k} | {fmt(r['max'])} | {fmt(r['norm'])} | {r['n_nan']} | {r['n_inf']} | {fmt(r['loss'], '.4f')} |\n")
    if data.get("findings"):
        A("\n## Findings\n\n" + data["findings"] + "\n")
    return "".join(L)


# ---------------------------------------------------------------------------- main


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--configs", help="comma-separated config names (default: every tuning/configs/*.toml)")
    ap.add_argument("--quick", action="store_true", help="a smoke run: windows 0 and 0.02, 5 tune steps, "
                    "sigma 0.1, two diagnosis variants")  # fmt: skip
    ap.add_argument("--out", default=str(OUT), help="output stem (writes STEM.json and STEM.md)")
    ap.add_argument("--no-diagnosis", action="store_true")
    ap.add_argument("--report-only", action="store_true", help="rewrite the Markdown from the JSON")
    args = ap.parse_args()
    stem = pathlib.Path(args.out)
    json_path, md_path = stem.with_suffix(".json"), stem.with_suffix(".md")
    if args.report_only:
        import json

        data = json.loads(json_path.read_text())
        write_text(md_path, report(data))
        log(f"wrote {md_path}")
        return 0
    import json

    args.windows = (0.0, 0.02) if args.quick else WINDOWS
    args.fd_steps = (0.05, 0.2) if args.quick else FD_STEPS
    args.tune_windows = (0.0, 0.02) if args.quick else TUNE_WINDOWS
    args.tune_steps = 5 if args.quick else TUNE_STEPS
    args.cma_sigmas = (0.1,) if args.quick else CMA_SIGMAS
    cache = pathlib.Path(tempfile.mkdtemp(prefix="truncation-xla-"))
    use_compilation_cache(cache)
    started = time.strftime("%Y-%m-%d %H:%M:%S")
    up0 = uptime()
    log(f"start: {up0}; devices {jax.local_device_count()}; compilation cache {cache}")
    names = args.configs.split(",") if args.configs else sorted(p.stem for p in CONFIGS.glob("*.toml"))
    data = {
        "command": " ".join(["tuning/truncation.py"] + sys.argv[1:]), "json": str(json_path.relative_to(ROOT))
        if json_path.is_relative_to(ROOT) else str(json_path), "started": started, "uptime_start": up0,
        "machine": {"cores": os.cpu_count(), "devices": jax.local_device_count(), "jax": jax.__version__,
                    "python": platform.python_version()},
        "settings": {"windows": list(args.windows), "fd_steps": list(args.fd_steps), "fd_main": FD_MAIN,
                     "step_sizes": list(STEP_SIZES), "random_seeds": list(RANDOM_SEEDS),
                     "tune_configs": list(TUNE_CONFIGS), "tune_windows": list(args.tune_windows),
                     "tune_steps": args.tune_steps, "cma_sigmas": list(args.cma_sigmas),
                     "cma_sigmas_keys": [wkey(x) for x in args.cma_sigmas], "popsize": POPSIZE},
        "skipped": {}, "configs": {},
    }  # fmt: skip
    diag_start = None
    for name in names:
        try:
            cfg = _config.load(CONFIGS / f"{name}.toml")
        except Exception as e:  # noqa: BLE001
            data["skipped"][name] = f"does not load: {e}"
            log(f"{name}: skipped ({e})")
            continue
        why = accepted(cfg)
        if why:
            data["skipped"][name] = why
            log(f"{name}: skipped ({why})")
            continue
        log(f"{name}: start ({uptime()})")
        data["configs"][name] = study_config(name, cfg, args, name in TUNE_CONFIGS)
        if name == DIAG_CONFIG:
            diag_start = T.Tunable(*(jnp.asarray(v) for v in data["configs"][name]["params"]["start"].values()))
        write_text(json_path, json.dumps(jsonable(data), indent=1))  # progress: a partial file after each config
    if not args.no_diagnosis:
        variants = list(VARIANTS)[:: 1 if not args.quick else 6][: 2 if args.quick else None]
        data["diagnosis"] = diagnosis(diag_start, variants)
    data["wall_s"] = time.perf_counter() - T0
    data["uptime_end"] = uptime()
    data["findings"] = findings(data)
    write_text(json_path, json.dumps(jsonable(data), indent=1))
    write_text(md_path, report(data))
    log(f"wrote {json_path} and {md_path}; {data['uptime_end']}")
    return 0


def findings(data: dict) -> str:
    """Filled in from the numbers once they were known (see the report back); empty here."""
    return data.get("findings", "")


if __name__ == "__main__":
    raise SystemExit(main())
