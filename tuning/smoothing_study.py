"""Gradients that carry information on quantized loops: randomized smoothing, a growing window and a
mixed (first/zeroth-order) estimator against the truncated window and CMA-ES (issue 33, item 2).

Per loop (default: realistic_arm (digital, differenced encoder), realistic_arm_exact_rates (digital,
measured rates), arm_sign_dt (ideal loop, sign law), arm_set2 (ideal loop, smooth ratio law)), on a
short horizon (``--horizon``, 0.3 s: ``[sim] t_final``; the training problem is tune's,
``_config.tuning_problems``), the loss is tune's training loss (``fs.rollout_costs`` +
``fs.aggregate`` with tune's objective, its scales from the training metrics at p0) in tune's
internal coordinates u (15 entries). Points: p0 (the config's parameters), tune's start (the best
of ``[tune] global_candidates`` of the global stage, seed 0, on that training problem) and the
full-horizon start (the same global stage on the config's own horizon: tuning/truncation.py's
start, the near-sign corner where the digital loops' gradient exploded).

The smoothing distribution D (what every smoothed estimator and the reference average over): u +
sigma eps, eps ~ N(0, I) (``--sigma``, 0.05 in u: about 5% in each parameter), and a random encoder
phase: the initial angles offset by U(-q/2, q/2), q = 2 pi / encoder counts (the same 2.4e-6 rad on
the ideal loops), drawn per sample as the problem's initial state (``Problem.X0s``): what a user can
do without a package change (the quantizer has no dither input; ``[sensors] noise_std`` on the
angles with several noise keys is a dither too, but in a trial outside this study the gradient of
such a noisy loop did not run the generated adjoint kernel). L_D(u) = E_D L.

Estimators of grad L_D (B = ``--batch``):
- ``fo W``: tune's own gradient (reverse mode, ``fs.make_loss`` split over the devices) of the
  nominal loss with ``gradient_window`` W (0.02, 0.05, 0.1 s, whole horizon): no smoothing;
- ``rs-fo W`` (randomized smoothing, first order): the mean of B AD gradients at B draws of D
  (a vmapped gradient, the draws split over the devices), W = 0.02 s and whole;
- ``zo`` (zeroth order, antithetic Gaussian smoothing / ES): (1 / 2 sigma B') sum_b (L(u + sigma
  eps_b; phase_b) - L(u - sigma eps_b; phase_b)) eps_b, B' = 2 B pairs (4 B forward runs, one
  batched call);
- ``mixed W`` (Suh et al. 2022's alpha-order estimator): alpha g_rs-fo + (1 - alpha) g_zo with
  alpha = V_zo / (V_fo + V_zo) (V: the trace of the empirical covariance of each mean, from the
  per-sample estimates), alpha = 0 where the first-order mean is not finite, and alpha capped
  at gamma / ||g_fo - g_zo|| with gamma = sqrt(V_zo) (a first-order bias larger than the zeroth-
  order noise is refused: the chaotic case);
- ``grow`` (in the races only): tune's gradient with a window that grows with the method's own
  time: 0.02, 0.05, 0.1 s, whole, a quarter of the budget each.

a. cosine of each estimator to a smoothed finite-difference reference: central differences of
   L_D at step h (``--fd-step``, 0.025) in each of the 15 directions, each side averaged over
   the same ``--ref-samples`` (256) draws of D (common random numbers); its noise: the standard
   error of each entry from the per-draw differences, reported as ||se|| / ||g_ref|| and as the
   cosine a perfect estimator would reach against the noisy reference (E cos ~ 1 / sqrt(1 +
   (||se|| / ||g_ref||)^2)). Each random estimator ``--repeats`` (5) times with fresh draws:
   mean and spread of the cosine. Also: the cosine of the plain (unsmoothed) FD at the same h.
b. wall time per estimate (median of the repeats, compilation excluded and reported apart), with
   the 1-minute load average.
c. races from tune's start, equal wall time per method (``--budget``, 15 s), interleaved (the
   method with the least own time takes the next turn: one Adam step or one CMA-ES generation,
   as tuning/tune_vs_cma.py), ``--seeds`` (2) seeds: Adam (optax, the config's learning rate as
   ``fs.learning_rate`` resolves it, constant, global-norm clip 1) fed by each estimator, against
   CMA-ES (``fs.cma_es``, popsize 16, sigma 0.1 and 0.3 in u, the nominal training loss batched).
   Read off at 1/3, 2/3 and all of the budget: the best point so far by nominal training loss
   (CMA-ES: among its candidates; Adam: among its iterates, their training losses computed after
   the race, outside the clock) and its plain loss (the same objective on the config's ``[sim]``
   problem at the same horizon).
d. the slow-tier check of tests/test_tuning.py (start = best of 16 global candidates, 1 s horizon,
   five Adam steps at the config's learning rate): does any estimator lower the nominal training
   loss within five steps where tune's gradient does not (``--skip-check`` leaves it out).

Float64; timings are wall times on a shared 2-core machine, each with ``os.getloadavg()``; compare
within one run only.

    .venv/bin/python tuning/smoothing_study.py                 # the study (34 min on 2 cores at load 8-10)
    .venv/bin/python tuning/smoothing_study.py --quick         # a smoke run to /tmp
    .venv/bin/python tuning/smoothing_study.py --report-only   # the Markdown again from the JSON
    .venv/bin/python tuning/smoothing_study.py --configs realistic_arm,realistic_arm_exact_rates --horizon 4 \
        --ref-samples 128 --repeats 3 --seeds 1 --skip-check --out tuning/results/smoothing_study_4s
        # the digital loops on their own 4 s horizon (8 min); with --configs realistic_arm
        # --global-candidates 64 --out tuning/results/smoothing_study_4s_64: the exploding start (4 min)

Writes tuning/results/smoothing_study.json and .md. Progress lines go to stderr.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import pathlib
import platform
import subprocess
import sys
import tempfile
import threading
import time

from fosmc_jax import use_all_cores

use_all_cores()  # before the first JAX operation, as the command line does

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import optax  # noqa: E402
from jax.flatten_util import ravel_pytree  # noqa: E402
from jax.sharding import Mesh, NamedSharding  # noqa: E402
from jax.sharding import PartitionSpec as Spec  # noqa: E402

from fosmc_jax import config as _config  # noqa: E402
from fosmc_jax import search as fs  # noqa: E402
from fosmc_jax import use_compilation_cache  # noqa: E402
from fosmc_jax.io import jsonable, write_text  # noqa: E402
from fosmc_jax.search import cma_es, global_stage  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parent.parent
CONFIGS = ROOT / "tuning" / "configs"
OUT = ROOT / "tuning" / "results" / "smoothing_study"
QUICK_OUT = pathlib.Path(tempfile.gettempdir()) / "smoothing_study_quick"

LOOPS = {"realistic_arm": "digital, differenced", "realistic_arm_exact_rates": "digital, measured rates",
         "arm_sign_dt": "ideal, sign law", "arm_set2": "ideal, smooth law"}  # fmt: skip
WINDOWS = (0.02, 0.05, 0.1, 0.0)  # s; 0 = the whole horizon
RS_WINDOWS = (0.02, 0.0)
GROW = (0.02, 0.05, 0.1, 0.0)
CMA_SIGMAS = (0.1, 0.3)
POPSIZE = 16
STANDARD_Q = 2 * np.pi / 2621440  # the realistic preset's encoder step, used as the phase on ideal loops

T0 = time.perf_counter()


def log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')} +{time.perf_counter() - T0:6.0f} s] {msg}", file=sys.stderr, flush=True)


def load() -> float:
    return round(os.getloadavg()[0], 2)


def uptime() -> str:
    try:
        return subprocess.run(["uptime"], capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return f"load average: {os.getloadavg()}"


def wname(w: float) -> str:
    return "whole" if w == 0 else f"{w:g} s"


def cosine(a, b) -> float | None:
    a, b = np.asarray(a, float), np.asarray(b, float)
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        return None
    a, b = a / max(np.max(np.abs(a)), 1e-300), b / max(np.max(np.abs(b)), 1e-300)  # huge entries: no overflow
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    return float(a @ b / (na * nb)) if na > 0 and nb > 0 else None


def norm(g) -> float:
    g = np.asarray(g, float)
    if not np.all(np.isfinite(g)):
        return float("inf")
    m = np.max(np.abs(g))
    return 0.0 if m == 0 else float(m * np.linalg.norm(g / m))


# ---------------------------------------------------------------------------- one loop's losses


class Loop:
    """One config at the study's horizon: its problems, objective, points, and the compiled
    losses and estimators (each compiled once, timed apart)."""

    def __init__(self, name: str, horizon: float, global_candidates: int | None, sigma: float, batch: int):
        cfg = self.full_cfg = _config.load(CONFIGS / f"{name}.toml")
        t_final = {"t_final": horizon}
        cfg = _config.replace(cfg, sim=t_final, tune={"train_t_final": min(cfg["tune"]["train_t_final"] or horizon,
                                                                            horizon)})  # fmt: skip
        if global_candidates is not None:
            cfg = _config.replace(cfg, tune={"global_candidates": global_candidates})
        self.name, self.cfg, self.sigma, self.batch = name, cfg, sigma, batch
        self.tcfg = cfg["tune"]
        self.plain, self.train, self.p0 = _config.tuning_problems(cfg)
        self.obj = fs.objective_of(self.tcfg, fs.evaluate(self.train, self.p0)["metrics"])
        counts = [c for c in np.atleast_1d(cfg["sensors"]["encoder_counts"]) if c > 0]
        self.q = 2 * np.pi / counts[0] if counts else STANDARD_Q
        self.lr = fs.learning_rate(self.tcfg["learning_rate"], bool(self.train.options.get("truncate_every")))
        self.devices = jax.local_devices()
        self.mesh = Mesh(
            np.asarray(self.devices), ("batch",)
        )  # the package's own axis name (its kernels' gradient needs it)
        flat, self.unravel = ravel_pytree(fs.to_internal(self.p0, self.plain.base, None))
        self.u = {"p0": np.asarray(flat)}
        self.compile_s: dict[str, float] = {}
        self._forward = {"train": self._batched(self.train), "plain": self._batched(self.plain)}
        self._fo: dict[float, callable] = {}
        self._rs: dict[float, callable] = {}

    def start(self) -> float:
        t = time.perf_counter()
        start, _ = global_stage(self.train, self.obj, self.p0, self.tcfg["global_candidates"],
                                free=tuple(self.tcfg["params"]), log=lambda _: None, command="tune")  # fmt: skip
        self.u["start"] = np.asarray(ravel_pytree(fs.to_internal(start, self.plain.base, None))[0])
        return time.perf_counter() - t

    def full_start(self) -> float:
        """u["full start"]: tune's start on the config's own horizon (tuning/truncation.py's start, where
        the digital loops' whole-horizon gradient exploded), the same global stage on that training problem."""
        t = time.perf_counter()
        cfg = self.full_cfg
        if self.cfg["tune"]["global_candidates"] != cfg["tune"]["global_candidates"]:
            cfg = _config.replace(cfg, tune={"global_candidates": self.cfg["tune"]["global_candidates"]})
        _, train, p0 = _config.tuning_problems(cfg)
        obj = fs.objective_of(cfg["tune"], fs.evaluate(train, p0)["metrics"])
        start, _ = global_stage(train, obj, p0, cfg["tune"]["global_candidates"], free=tuple(cfg["tune"]["params"]),
                                log=lambda _: None, command="tune")  # fmt: skip
        self.u["full start"] = np.asarray(ravel_pytree(fs.to_internal(start, self.plain.base, None))[0])
        return time.perf_counter() - t

    # one rollout set (the problem's plants) at one u and one initial-state offset (9,)
    def _loss_one(self, problem, truncate_every: int | None = None):
        """loss(x (15,), offset (9,)) of one draw: the problem's plants from X0 + offset; None: a
        forward-only run (no rematerialisation), else the gradient's window in steps."""
        obj, unravel = self.obj, self.unravel
        X0 = problem.X0s[:1]
        options = {"checkpoint_every": 0} if truncate_every is None else {"truncate_every": truncate_every}

        def one(x, offset):
            pr = problem._replace(X0s=X0 + offset, options=dict(problem.options, **options))
            r = pr.simulate(fs.to_physical(unravel(x), pr.base, None))
            J, _, _ = fs.rollout_costs(r.metrics, r.diverged, obj)
            return fs.aggregate(J, obj)

        return one

    def _batched(self, problem):
        one = self._loss_one(problem)
        return jax.jit(jax.shard_map(jax.vmap(one), mesh=self.mesh, in_specs=(Spec("batch"), Spec("batch")),
                                     out_specs=Spec("batch"), check_vma=False))  # fmt: skip

    def forward(self, X, offsets=None, which: str = "train", chunk: int = 32) -> np.ndarray:
        """The loss at many u (n, 15) with initial offsets (n, 9) (None: 0), in chunks of a fixed size."""
        X = np.atleast_2d(np.asarray(X, float))
        offsets = np.zeros((len(X), 9)) if offsets is None else np.asarray(offsets, float)
        out = []
        for i in range(0, len(X), chunk):
            part, off = X[i : i + chunk], offsets[i : i + chunk]
            pad = chunk - len(part)
            if pad:
                part, off = (np.concatenate([a, np.repeat(a[-1:], pad, 0)]) for a in (part, off))
            key = f"forward {which} {chunk}"
            t = time.perf_counter()
            v = np.asarray(self._forward[which](jnp.asarray(part), jnp.asarray(off)))
            self.compile_s.setdefault(key, time.perf_counter() - t)
            out.append(v[: len(part) - pad] if pad else v)
        return np.concatenate(out)

    def window_steps(self, w: float) -> int:
        return int(round(w / float(self.train.dt))) if w else 0

    def fo(self, w: float):
        """tune's gradient of the nominal loss with window w: u (15,) -> (loss, grad (15,))."""
        if w not in self._fo:
            train = self.train._replace(options=dict(self.train.options, truncate_every=self.window_steps(w)))
            vg = fs.value_and_grad(fs.make_loss(train, self.obj, None), "reverse")
            rep = NamedSharding(self.mesh, Spec())

            def call(x):
                (v, _), g = vg(jax.device_put(self.unravel(jnp.asarray(x)), rep))
                return float(v), np.asarray(ravel_pytree(g)[0])

            t = time.perf_counter()
            call(self.u["p0"])
            self.compile_s[f"fo {wname(w)}"] = time.perf_counter() - t
            self._fo[w] = call
        return self._fo[w]

    def rs_grads(self, w: float):
        """Per-draw AD gradients (B, 15) at B draws (u_b, offset_b), the draws split over the devices."""
        if w not in self._rs:
            one = self._loss_one(self.train, truncate_every=self.window_steps(w))
            f = jax.jit(jax.shard_map(jax.vmap(jax.grad(one)), mesh=self.mesh, in_specs=(Spec("batch"), Spec("batch")),
                                      out_specs=Spec("batch"), check_vma=False))  # fmt: skip
            self._rs[w] = f
            t = time.perf_counter()
            self.draw_grads(w, self.u["p0"], np.random.default_rng(0))
            self.compile_s[f"rs-fo {wname(w)}"] = time.perf_counter() - t
        return self._rs[w]

    def draws(self, rng, n: int) -> tuple[np.ndarray, np.ndarray]:
        """n draws of D: eps (n, 15) ~ N(0, I) and initial offsets (n, 9), angles ~ U(-q/2, q/2)."""
        eps = rng.standard_normal((n, len(self.u["p0"])))
        off = np.zeros((n, 9))
        off[:, 0::3] = rng.uniform(-self.q / 2, self.q / 2, (n, 3))
        return eps, off

    def draw_grads(self, w: float, u, rng) -> np.ndarray:
        eps, off = self.draws(rng, self.batch)
        return np.asarray(self.rs_grads(w)(jnp.asarray(u + self.sigma * eps), jnp.asarray(off)))

    # ------------------------------------------------------------------ the estimators
    def zo_samples(self, u, rng) -> np.ndarray:
        """Per-pair antithetic estimates (2 B, 15)."""
        n = 2 * self.batch
        eps, off = self.draws(rng, n)
        X = np.concatenate([u + self.sigma * eps, u - self.sigma * eps])
        v = self.forward(X, np.concatenate([off, off]), chunk=2 * n)
        d = np.where(np.isfinite(v[:n] - v[n:]), v[:n] - v[n:], 0.0)
        return (d / (2 * self.sigma))[:, None] * eps

    def estimate(self, kind: str, u, rng) -> np.ndarray:
        if kind.startswith("fo "):
            return self.fo(float(kind.split()[1]))(u)[1]
        if kind.startswith("rs-fo "):
            return self.draw_grads(float(kind.split()[1]), u, rng).mean(0)
        if kind == "zo":
            return self.zo_samples(u, rng).mean(0)
        if kind.startswith("mixed "):
            return mixed(self.draw_grads(float(kind.split()[1]), u, rng), self.zo_samples(u, rng))[0]
        raise ValueError(kind)

    def reference(self, u, h: float, n: int, rng) -> dict:
        """Central differences of L_D at step h, each side the mean over the same n draws of D."""
        d = len(u)
        eps, off = self.draws(rng, n)
        base = u + self.sigma * eps  # (n, 15)
        E = np.eye(d)
        X = np.concatenate([base + h * E[i] for i in range(d)] + [base - h * E[i] for i in range(d)])
        v = self.forward(X, np.tile(off, (2 * d, 1)), chunk=128)
        plus, minus = v[: d * n].reshape(d, n), v[d * n :].reshape(d, n)
        diff = (plus - minus) / (2 * h)  # (15, n) per draw
        ok = np.isfinite(diff)
        g = np.array([diff[i][ok[i]].mean() for i in range(d)])
        se = np.array([diff[i][ok[i]].std(ddof=1) / math.sqrt(ok[i].sum()) for i in range(d)])
        centre = self.forward(base, off, chunk=128)
        X1 = np.concatenate([u + h * E, u - h * E])
        v1 = self.forward(X1, chunk=32)
        plain_fd = (v1[:d] - v1[d:]) / (2 * h)
        return {"grad": g, "se": se, "rel_noise": norm(se) / norm(g), "nonfinite": int((~ok).sum()),
                "smoothed_loss": float(np.nanmean(centre)), "loss": float(self.forward(u[None])[0]),
                "plain_fd": plain_fd}  # fmt: skip


def mixed(fo_samples: np.ndarray, zo_samples: np.ndarray) -> tuple[np.ndarray, float]:
    """Suh et al.'s alpha-order gradient from per-sample first- and zeroth-order estimates."""
    g_zo = zo_samples.mean(0)
    v_zo = float(np.sum(zo_samples.var(0, ddof=1)) / len(zo_samples))
    if not np.all(np.isfinite(fo_samples)):
        return g_zo, 0.0
    g_fo = fo_samples.mean(0)
    v_fo = float(np.sum(fo_samples.var(0, ddof=1)) / len(fo_samples))
    if not (math.isfinite(v_fo) and math.isfinite(np.sum(g_fo**2))):
        return g_zo, 0.0
    alpha = v_zo / (v_fo + v_zo) if v_fo + v_zo > 0 else 0.5
    gap = float(np.linalg.norm(g_fo - g_zo))
    if gap > 0:
        alpha = min(alpha, math.sqrt(v_zo) / gap)
    return alpha * g_fo + (1 - alpha) * g_zo, alpha


ESTIMATORS = (
    [f"fo {w:g}" for w in WINDOWS]
    + [f"rs-fo {w:g}" for w in RS_WINDOWS]
    + ["zo"]
    + [f"mixed {w:g}" for w in RS_WINDOWS]
)


def label(kind: str) -> str:
    head, _, w = kind.partition(" ")
    return kind if not w else f"{head} {wname(float(w))}"


# ---------------------------------------------------------------------------- a, b: cosines and costs


def informativeness(lp: Loop, point: str, args) -> dict:
    u = lp.u[point]
    t = time.perf_counter()
    ref = lp.reference(u, args.fd_step, args.ref_samples, np.random.default_rng(12345))
    ref_s = time.perf_counter() - t
    g_ref = ref["grad"]
    out = {"reference": {"grad": g_ref.tolist(), "se": ref["se"].tolist(), "rel_noise": ref["rel_noise"],
                         "cos_ceiling": 1 / math.sqrt(1 + ref["rel_noise"] ** 2), "nonfinite": ref["nonfinite"],
                         "loss": ref["loss"], "smoothed_loss": ref["smoothed_loss"], "time_s": ref_s, "load": load(),
                         "cos_plain_fd": cosine(ref["plain_fd"], g_ref)},  # fmt: skip
           "estimators": {}}  # fmt: skip
    for kind in ESTIMATORS:
        deterministic = kind.startswith("fo ")
        reps = 1 + (1 if deterministic else args.repeats)  # the first call warms (and compiles)
        cos, times, norms, alphas = [], [], [], []
        for r in range(reps):
            rng = np.random.default_rng(1000 * r + 7)
            t = time.perf_counter()
            if kind.startswith("mixed "):
                fo_s, zo_s = lp.draw_grads(float(kind.split()[1]), u, rng), lp.zo_samples(u, rng)
                g, a = mixed(fo_s, zo_s)
                if r or reps == 1:
                    alphas.append(a)
            else:
                g = lp.estimate(kind, u, rng)
            dt = time.perf_counter() - t
            if r == 0 and reps > 1:
                continue
            times.append(dt)
            cos.append(cosine(g, g_ref))
            norms.append(norm(g))
        c = [x for x in cos if x is not None]
        out["estimators"][kind] = {"cos": cos, "cos_mean": float(np.mean(c)) if c else None,
                                   "cos_min": min(c) if c else None, "cos_max": max(c) if c else None,
                                   "finite": len(c), "norm_median": float(np.median(norms)),
                                   "time_s": float(np.median(times)), "load": load(),
                                   "alpha": alphas or None}  # fmt: skip
        e = out["estimators"][kind]
        log(f"  {lp.name} {point} {label(kind):14s} cos {_f(e['cos_mean'], '+.2f')} "
            f"[{_f(e['cos_min'], '+.2f')}, {_f(e['cos_max'], '+.2f')}]  |g| {e['norm_median']:.2g}  "
            f"{e['time_s'] * 1e3:.1f} ms  load {e['load']}" + (f"  alpha {np.round(alphas, 2).tolist()}" if alphas else ""))  # fmt: skip
    return out


# ---------------------------------------------------------------------------- c: races


class Stop(Exception):
    pass


class Baton:
    """One worker computes at a time; the next turn goes to the live worker with the least own time."""

    def __init__(self, names: list[str]):
        self.order, self.alive = list(names), set(names)
        self.clock = {n: 0.0 for n in names}
        self.since: dict[str, float] = {}
        self.turn = self.order[0]
        self.cv = threading.Condition()
        self.loads: list[float] = [load()]
        self.t_load = time.perf_counter()

    def acquire(self, me: str) -> None:
        with self.cv:
            self.cv.wait_for(lambda: self.turn == me)
        self.since[me] = time.perf_counter()

    def now(self, me: str) -> float:
        return self.clock[me] + time.perf_counter() - self.since[me]

    def release(self, me: str, done: bool = False) -> None:
        t = time.perf_counter()
        with self.cv:
            self.clock[me] += t - self.since.pop(me, t)
            if done:
                self.alive.discard(me)
            live = [n for n in self.order if n in self.alive]
            self.turn = min(live, key=lambda n: self.clock[n]) if live else None
            if t - self.t_load >= 5.0:
                self.loads.append(load())
                self.t_load = t
            self.cv.notify_all()

    def pause(self, me: str) -> None:
        self.release(me)
        self.acquire(me)


def race(lp: Loop, methods: list[str], budget: float, seed: int) -> dict:
    u0 = lp.u["start"]
    warm = optax.chain(optax.clip_by_global_norm(1.0), optax.adam(lp.lr))  # optax's eager ops compiled before any clock
    optax.apply_updates(jnp.asarray(u0), warm.update(jnp.zeros(len(u0)), warm.init(jnp.asarray(u0)))[0])
    names = [f"adam {m}" for m in methods] + [f"cma {s:g}" for s in CMA_SIGMAS]
    baton = Baton(names)
    trace: dict[str, list] = {n: [] for n in names}  # (own time, u) of each iterate / generation
    errors: list[BaseException] = []

    def adam_worker(method: str):
        me = f"adam {method}"
        rng = np.random.default_rng(seed)
        opt = optax.chain(optax.clip_by_global_norm(1.0), optax.adam(lp.lr))
        u = np.array(u0)
        state = opt.init(jnp.asarray(u))
        baton.acquire(me)
        try:
            while True:
                now = baton.now(me)
                if now >= budget:
                    break
                kind = method
                if method == "grow":
                    kind = f"fo {GROW[min(int(len(GROW) * now / budget), len(GROW) - 1)]:g}"
                g = lp.estimate(kind, u, rng)
                g = np.where(np.isfinite(g), g, 0.0)
                upd, state = opt.update(jnp.asarray(g), state)
                u = np.asarray(optax.apply_updates(jnp.asarray(u), upd))
                trace[me].append((baton.now(me), u.copy()))
                baton.pause(me)
        except BaseException as e:  # noqa: BLE001
            errors.append(e)
        finally:
            baton.release(me, done=True)

    def cma_worker(sigma: float):
        me = f"cma {sigma:g}"
        baton.acquire(me)

        def objective(X):
            if trace[me]:
                baton.pause(me)
            if baton.now(me) >= budget:
                raise Stop
            F = lp.forward(X, chunk=POPSIZE)
            trace[me].append((baton.now(me), np.array(X), F))
            return F

        try:
            cma_es(objective, u0, sigma, 1e9, POPSIZE, seed=seed, log=lambda _: None)
        except Stop:
            pass
        except BaseException as e:  # noqa: BLE001
            errors.append(e)
        finally:
            baton.release(me, done=True)

    threads = [threading.Thread(target=adam_worker, args=(m,)) for m in methods]
    threads += [threading.Thread(target=cma_worker, args=(s,)) for s in CMA_SIGMAS]
    t = time.perf_counter()
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    wall = time.perf_counter() - t
    if errors:
        raise errors[0]
    # read-offs (outside the clocks): best so far by nominal training loss, and its plain loss
    times = [budget / 3, 2 * budget / 3, budget]
    out = {"wall_s": wall, "loads": baton.loads, "methods": {}}
    start_train = float(lp.forward(u0[None])[0])
    start_plain = float(lp.forward(u0[None], which="plain")[0])
    out["start"] = {"train": start_train, "plain": start_plain}
    for n in names:
        tr = trace[n]
        if n.startswith("adam"):
            ts = np.array([x[0] for x in tr])
            U = np.array([x[1] for x in tr]) if tr else np.zeros((0, len(u0)))
            F = lp.forward(U, chunk=128) if len(U) else np.zeros(0)
            units = len(tr)
        else:
            ts = np.concatenate([np.full(len(x[2]), x[0]) for x in tr]) if tr else np.zeros(0)
            U = np.concatenate([x[1] for x in tr]) if tr else np.zeros((0, len(u0)))
            F = np.concatenate([x[2] for x in tr]) if tr else np.zeros(0)
            units = len(tr)
        F = np.where(np.isfinite(F), F, np.inf)
        best = []
        for tm in times:
            sel = np.flatnonzero(ts <= tm)
            if len(sel) == 0 or np.min(F[sel]) >= start_train:
                best.append((start_train, u0))
            else:
                i = sel[np.argmin(F[sel])]
                best.append((float(F[i]), U[i]))
        plain = lp.forward(np.array([b[1] for b in best]), which="plain", chunk=POPSIZE)
        out["methods"][n] = {"units": units, "per_unit_s": float(np.median(np.diff(np.r_[0, ts[:: (POPSIZE if n.startswith('cma') else 1)]]))) if units else None,
                             "train": [b[0] for b in best], "plain": plain.tolist(), "times": times}  # fmt: skip
    log(f"  {lp.name} race seed {seed}: {wall:.0f} s wall, load {load()}; plain at {budget:g} s: "
        + ", ".join(f"{n} {m['plain'][-1]:+.3f}" for n, m in out["methods"].items()))  # fmt: skip
    return out


# ---------------------------------------------------------------------------- d: the slow-tier check


def slow_tier_check(name: str, args) -> dict:
    """tests/test_tuning.py's setup (1 s horizon, 16 global candidates), five Adam steps with each estimator."""
    lp = Loop(name, 1.0, 16, args.sigma, args.batch)
    lp.start()
    u0 = lp.u["start"]
    L0 = float(lp.forward(u0[None])[0])
    out = {"start_loss": L0, "methods": {}}
    for kind in ["fo 0.02", "fo 0", "rs-fo 0.02", "zo", "mixed 0.02", "mixed 0"]:
        runs = []
        for seed in range(1 if kind.startswith("fo ") else args.check_seeds):
            rng = np.random.default_rng(seed)
            opt = optax.chain(optax.clip_by_global_norm(1.0), optax.adam(lp.lr))
            u = np.array(u0)
            state = opt.init(jnp.asarray(u))
            us = []
            for _ in range(5):
                g = lp.estimate(kind, u, rng)
                g = np.where(np.isfinite(g), g, 0.0)
                upd, state = opt.update(jnp.asarray(g), state)
                u = np.asarray(optax.apply_updates(jnp.asarray(u), upd))
                us.append(u)
            runs.append(lp.forward(np.array(us), chunk=POPSIZE))
        F = runs[0]
        out["methods"][kind] = {"losses": F.tolist(), "descends": bool(np.min(F) < L0), "best": float(np.min(F)),
                                "best_seeds": [float(np.min(r)) for r in runs],
                                "descends_seeds": [bool(np.min(r) < L0) for r in runs]}  # fmt: skip
        log(f"  check {name} {label(kind)}: start {L0:+.4f}, five steps {np.round(F, 4).tolist()}; best per seed "
            f"{np.round(out['methods'][kind]['best_seeds'], 4).tolist()}")  # fmt: skip
    out["compile_s"] = lp.compile_s
    return out


# ---------------------------------------------------------------------------- report


def _check_cell(m: dict) -> str:
    """Seed 0's best loss and whether it descends; with several seeds, how many descend and their range."""
    cell = f"{m['best']:+.4f} {'yes' if m['descends'] else 'no'}"
    seeds = m.get("descends_seeds") or []
    if len(seeds) > 1:
        cell += f" ({sum(seeds)}/{len(seeds)} seeds descend, best {min(m['best_seeds']):+.4f} to {max(m['best_seeds']):+.4f})"
    return cell


def _f(x, fmt: str = ".3g") -> str:
    return "-" if x is None else format(x, fmt)


def report(data: dict) -> str:
    L: list[str] = []
    A = L.append
    s = data["settings"]
    run = data["run"]
    A("# Gradients on quantized loops: randomized smoothing, a growing window, a mixed estimator (issue 33, item 2)\n")
    A(f"Generated by `tuning/smoothing_study.py` from `{data['json']}` (`--report-only` regenerates it). Command: "
      f"`{run['command']}`; commit {run['commit']}; {run['machine']}; started {run['started']}, "
      f"{run.get('wall_s', 0) / 60:.0f} min. `uptime` at the start: `{run['uptime_start']}`; at the end: "
      f"`{run.get('uptime_end', '?')}`. Other engineers' jobs shared the 2 cores throughout: timings compare within "
      "this run only, each with the 1-minute load average beside it.\n")  # fmt: skip
    A(f"Horizon {s['horizon']:g} s (`[sim] t_final`, and the training horizon), the loss = tune's training loss "
      f"(its objective, scales from p0). Smoothing distribution D: u + {s['sigma']:g} eps, eps ~ N(0, I_15), and a "
      "random encoder phase (initial angles + U(-q/2, q/2)). Estimators with B = "
      f"{s['batch']} draws (zo: {2 * s['batch']} antithetic pairs, {4 * s['batch']} forward runs). Reference: central "
      f"differences of L_D at h = {s['fd_step']:g} over {s['ref_samples']} common draws. Races: {s['budget']:g} s per "
      f"method, seeds {s['seeds']}. The module docstring defines every estimator.\n")  # fmt: skip
    if data["loops"]:  # part d alone has no loops
        A("\n## Loops\n\n| config | loop | train dt (s) x steps | encoder step q (rad) | Adam lr | global stage (s): study's, full horizon | "
          "loss p0 / start / full start | compile (s) |\n|---|---|---|---|---|---|---|---|\n")  # fmt: skip
        for n, c in data["loops"].items():
            comp = ", ".join(f"{k} {v:.0f}" for k, v in c["compile_s"].items() if not k.startswith("forward"))
            A(f"| {n} | {c['loop']} | {c['train_dt']:g} x {c['train_steps']} | {c['q']:.2g} | {c['lr']:g} | "
              f"{c['global_s']:.1f}, {c['full_global_s']:.1f} | {c['points']['p0']['reference']['loss']:+.3f} / "
              f"{c['points']['start']['reference']['loss']:+.3f} / "
              f"{c['points'].get('full start', c['points']['start'])['reference']['loss']:+.3f} | "
              f"{comp} |\n")  # fmt: skip
        where = {
            "start": "tune's start (global stage on the study's horizon)",
            "p0": "p0 (the config's parameters)",
            "full start": "the full-horizon start (global stage on the config's own horizon, truncation.md's start)",
        }
        for point in [
            p for p in ("start", "p0", "full start") if all(p in c["points"] for c in data["loops"].values())
        ]:
            A(f"\n## a. cos(estimator, smoothed FD reference) at {where[point]}\n\n"
              "Mean over the repeats [min, max] (deterministic estimators: one value). Reference noise: ||se|| / ||g_ref||, "
              "and the cosine a noise-free estimator would reach against the noisy reference (ceiling). plain FD: "
              "central differences of the unsmoothed loss at the same h.\n\n")  # fmt: skip
            A("| estimator | " + " | ".join(data["loops"]) + " |\n" + "|---" * (len(data["loops"]) + 1) + "|\n")
            row = lambda name, f: A(
                f"| {name} | " + " | ".join(f(c["points"][point]) for c in data["loops"].values()) + " |\n"
            )  # noqa: E731
            row(
                "reference noise (ceiling)",
                lambda p: f"{p['reference']['rel_noise']:.2f} ({p['reference']['cos_ceiling']:.2f})",
            )
            row("reference |g|", lambda p: f"{norm(p['reference']['grad']):.2g}")
            row("plain FD", lambda p: _f(p["reference"]["cos_plain_fd"], "+.2f"))
            for kind in ESTIMATORS:

                def cell(p, kind=kind):
                    e = p["estimators"][kind]
                    if e["cos_mean"] is None:
                        return f"not finite (|g| {e['norm_median']:.2g})"
                    spread = "" if len(e["cos"]) == 1 else f" [{e['cos_min']:+.2f}, {e['cos_max']:+.2f}]"
                    bad = "" if e["finite"] == len(e["cos"]) else f" ({len(e['cos']) - e['finite']} not finite)"
                    return f"{e['cos_mean']:+.2f}{spread}{bad}"

                row(label(kind), cell)
            A("\n|g| (median) of each estimator:\n\n| estimator | " + " | ".join(data["loops"]) + " |\n"
              + "|---" * (len(data["loops"]) + 1) + "|\n")  # fmt: skip
            for kind in ESTIMATORS:
                row(label(kind), lambda p, kind=kind: f"{p['estimators'][kind]['norm_median']:.2g}")
            alphas = {n: c["points"][point]["estimators"][k]["alpha"] for n, c in data["loops"].items()
                      for k in ESTIMATORS if k.startswith("mixed") and k == "mixed 0"}  # fmt: skip
            A("\nmixed (whole)'s alpha (the first-order share) per repeat: " + "; ".join(
                f"{n} {np.round(a, 2).tolist()}" for n, a in alphas.items()) + "\n")  # fmt: skip
        A("\n## b. Wall time per estimate (ms; median of the repeats at tune's start, compilation excluded; 1-min load)\n\n"
          "| estimator | " + " | ".join(data["loops"]) + " |\n" + "|---" * (len(data["loops"]) + 1) + "|\n")  # fmt: skip
        for kind in ESTIMATORS:
            A(f"| {label(kind)} | " + " | ".join(
                f"{c['points']['start']['estimators'][kind]['time_s'] * 1e3:.1f} ({c['points']['start']['estimators'][kind]['load']:.1f})"
                for c in data["loops"].values()) + " |\n")  # fmt: skip
        A("| reference (s) | " + " | ".join(f"{c['points']['start']['reference']['time_s']:.1f}" for c in data["loops"].values())
          + " |\n")  # fmt: skip
        if any("races" in c for c in data["loops"].values()):
            A(f"\n## c. Races from tune's start ({s['budget']:g} s of own time per method, interleaved)\n\n"
              "Plain loss of the best point so far (by nominal training loss) at 1/3, 2/3 and all of the budget, mean over "
              "the seeds (each seed's value in the JSON); per unit: s per Adam step (one estimate) or per CMA-ES "
              "generation (16 forward runs). The best method at the end in bold.\n\n")  # fmt: skip
            for n, c in data["loops"].items():
                if "races" not in c:
                    continue
                races = c["races"]
                methods = list(races[0]["methods"])
                ends = {m: np.mean([r["methods"][m]["plain"][-1] for r in races]) for m in methods}
                best = min(ends, key=ends.get)
                A(f"**{n}** ({c['loop']}), start plain loss {races[0]['start']['plain']:+.3f} (training "
                  f"{races[0]['start']['train']:+.3f}); load during the races "
                  f"{min(min(r['loads']) for r in races):.1f}-{max(max(r['loads']) for r in races):.1f}\n\n"
                  "| method | " + " | ".join(f"{t:.0f} s" for t in races[0]["methods"][methods[0]]["times"])
                  + " | plain-loss fall per s | training loss at the end | units (s per unit) |\n"
                  "|---|---|---|---|---|---|---|\n")  # fmt: skip
                for m in methods:
                    pl = np.mean([r["methods"][m]["plain"] for r in races], axis=0)
                    rate = (races[0]["start"]["plain"] - pl[-1]) / s["budget"]
                    units = np.mean([r["methods"][m]["units"] for r in races])
                    per = np.median([r["methods"][m]["per_unit_s"] or np.nan for r in races])
                    cells = [f"{x:+.3f}" for x in pl]
                    if m == best:
                        cells[-1] = f"**{cells[-1]}**"
                    train = np.mean([r["methods"][m]["train"][-1] for r in races])
                    A(f"| {m} | " + " | ".join(cells) + f" | {rate:+.3f} | {train:+.3f} | {units:.0f} ({per:.3f}) |\n")
                A("\n")
    if data.get("check"):
        A("\n## d. The slow tier's check (tests/test_tuning.py setup: 1 s horizon, 16 global candidates, five Adam "
          "steps)\n\nTraining loss at the start, and the lowest after five steps with each estimator (descends: lower "
          "than the start).\n\n| config | start | " + " | ".join(label(k) for k in next(iter(data["check"].values()))["methods"])
          + " |\n" + "|---" * (2 + len(next(iter(data["check"].values()))["methods"])) + "|\n")  # fmt: skip
        for n, c in data["check"].items():
            A(f"| {n} | {c['start_loss']:+.4f} | " + " | ".join(_check_cell(m) for m in c["methods"].values()) + " |\n")
    if data.get("findings"):
        A("\n## Findings\n\n" + data["findings"] + "\n")
    return "".join(L)


# ---------------------------------------------------------------------------- figure


def figure(paths: list[pathlib.Path], out: pathlib.Path) -> None:
    """Two panels from the runs' JSONs: each estimator's cosine to the reference at tune's start
    (mean, min-max bars), and each race method's plain-loss fall from the start at the end of the
    budget (mean over the seeds), per loop and run."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = []
    for path in paths:
        d = json.loads(path.read_text())
        tag = f"{d['settings']['horizon']:g} s" + (
            f", {d['settings']['global_candidates']} cand." if d["settings"].get("global_candidates") else ""
        )
        runs += [(f"{n} ({tag})", c) for n, c in d["loops"].items()]
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(12, 9))
    width = 0.8 / len(runs)
    for i, (name, c) in enumerate(runs):
        est = c["points"]["start"]["estimators"]
        y = [est[k]["cos_mean"] if est[k]["cos_mean"] is not None else np.nan for k in ESTIMATORS]
        lo = [y[j] - (est[k]["cos_min"] if est[k]["cos_min"] is not None else np.nan) for j, k in enumerate(ESTIMATORS)]
        hi = [(est[k]["cos_max"] if est[k]["cos_max"] is not None else np.nan) - y[j] for j, k in enumerate(ESTIMATORS)]
        ax1.bar(np.arange(len(ESTIMATORS)) + i * width, y, width, yerr=[lo, hi], label=name, capsize=2)
    ax1.set_xticks(np.arange(len(ESTIMATORS)) + 0.4 - width / 2, [label(k) for k in ESTIMATORS])
    ax1.set_ylabel("cosine to the smoothed FD reference (1)")
    ax1.set_title("Informativeness at tune's start")
    ax1.axhline(0, color="k", lw=0.5)
    ax1.legend(fontsize=7)
    methods = list(next(c for _, c in runs if "races" in c)["races"][0]["methods"])
    for i, (name, c) in enumerate(runs):
        if "races" not in c:
            continue
        start = c["races"][0]["start"]["plain"]
        fall = [start - np.mean([r["methods"][m]["plain"][-1] for r in c["races"]]) for m in methods]
        ax2.bar(np.arange(len(methods)) + i * width, fall, width, label=name)
    budget = json.loads(paths[0].read_text())["settings"]["budget"]
    ax2.set_xticks(np.arange(len(methods)) + 0.4 - width / 2, methods)
    ax2.set_ylabel(f"plain-loss fall after {budget:g} s (1, log units)")
    ax2.set_title("Races from tune's start, equal wall time")
    ax2.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


# ---------------------------------------------------------------------------- main


def commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                              check=True).stdout.strip()  # fmt: skip
    except (OSError, subprocess.CalledProcessError):
        return "?"


def cpu() -> str:
    try:
        for line in pathlib.Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return f"{os.cpu_count()} cores, {line.split(':', 1)[1].strip()}"
    except OSError:
        pass
    return f"{os.cpu_count()} cores"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--configs", default=",".join(LOOPS), help="comma-separated configs of tuning/configs")
    ap.add_argument("--horizon", type=float, default=0.3, help="s (default 0.3)")
    ap.add_argument("--sigma", type=float, default=0.05, help="Gaussian smoothing in u (default 0.05)")
    ap.add_argument("--batch", type=int, default=8, help="draws per smoothed estimate B (default 8; zo: 2B pairs)")
    ap.add_argument("--fd-step", type=float, default=0.025, help="the reference's FD step in u (default 0.025)")
    ap.add_argument("--ref-samples", type=int, default=256, help="draws of D in the reference (default 256)")
    ap.add_argument("--repeats", type=int, default=5, help="repeats of each random estimator (default 5)")
    ap.add_argument("--budget", type=float, default=15.0, help="s per method in the races (default 15; 0: no races)")
    ap.add_argument("--seeds", type=int, default=2, help="race seeds (default 2)")
    ap.add_argument("--race-methods", default="fo 0.02,fo 0,grow,rs-fo 0,zo,mixed 0",
                    help="the Adam estimators raced against CMA-ES")  # fmt: skip
    ap.add_argument("--global-candidates", type=int, help="override [tune] global_candidates")
    ap.add_argument("--skip-check", action="store_true", help="leave out part d")
    ap.add_argument("--check-configs", default="realistic_arm_exact_rates,arm_sign_dt", help="part d's configs")
    ap.add_argument("--check-seeds", type=int, default=1, help="part d's seeds of each random estimator (default 1)")
    ap.add_argument("--quick", action="store_true", help="a smoke run to " + str(QUICK_OUT))
    ap.add_argument("--out", help=f"output stem (default {OUT.relative_to(ROOT)})")
    ap.add_argument("--report-only", action="store_true", help="rewrite the Markdown from the JSON")
    ap.add_argument("--figure", help="with --report-only: comma-separated run JSONs to plot into STEM.png")
    ap.add_argument("--findings", help="with --report-only: store this Markdown file's text as the JSON's findings")
    args = ap.parse_args()
    stem = pathlib.Path(args.out) if args.out else (QUICK_OUT if args.quick else OUT)
    json_path, md_path = stem.with_suffix(".json"), stem.with_suffix(".md")
    if args.report_only:
        data = json.loads(json_path.read_text())
        if args.findings:
            data["findings"] = pathlib.Path(args.findings).read_text().strip()
            write_text(json_path, json.dumps(data, indent=1))
        write_text(md_path, report(data))
        log(f"wrote {md_path}")
        if args.figure:
            figure([pathlib.Path(p) for p in args.figure.split(",")], md_path.with_suffix(".png"))
            log(f"wrote {md_path.with_suffix('.png')}")
        return 0
    if args.quick:
        args.configs, args.ref_samples, args.repeats, args.budget, args.seeds = "arm_set2", 32, 2, 3.0, 1
        args.global_candidates, args.skip_check = 64, True
    use_compilation_cache(pathlib.Path(tempfile.mkdtemp(prefix="smoothing-xla-")))
    import cma  # noqa: F401  (pycma's import before any clock)

    settings = {k: getattr(args, k) for k in ("horizon", "sigma", "batch", "fd_step", "ref_samples", "repeats",
                                              "budget", "seeds", "race_methods", "global_candidates")}  # fmt: skip
    run = {"command": " ".join(["tuning/smoothing_study.py"] + sys.argv[1:]), "commit": commit(), "machine": cpu()
           + f", jax {jax.__version__}, {jax.local_device_count()} CPU devices, python {platform.python_version()}",
           "started": time.strftime("%Y-%m-%d %H:%M:%S"), "uptime_start": uptime()}  # fmt: skip
    rel = str(json_path.relative_to(ROOT)) if json_path.is_relative_to(ROOT) else str(json_path)
    data = {"json": rel, "settings": settings, "run": run, "loops": {}, "check": {}}
    log(f"start: {run['uptime_start']}")

    def save():
        run["wall_s"] = time.perf_counter() - T0
        run["uptime_end"] = uptime()
        write_text(json_path, json.dumps(jsonable(data), indent=1))

    for name in [n for n in args.configs.split(",") if n]:  # --configs "": part d only
        log(f"{name}: building ({LOOPS.get(name, '?')})")
        lp = Loop(name, args.horizon, args.global_candidates, args.sigma, args.batch)
        t_global = lp.start()
        full = args.horizon < lp.full_cfg["sim"]["t_final"]  # else the full-horizon start is tune's start
        t_full = lp.full_start() if full else 0.0
        res = {"loop": LOOPS.get(name, "?"), "train_dt": float(lp.train.dt), "train_steps": int(lp.train.options["n_steps"]),
               "q": lp.q, "lr": lp.lr, "global_s": t_global, "full_global_s": t_full, "u": {k: v.tolist() for k, v in lp.u.items()},
               "points": {}}  # fmt: skip
        log(f"{name}: global stage {t_global:.1f} s; load {load()}")
        for point in ("start", "p0", "full start") if full else ("start", "p0"):
            res["points"][point] = informativeness(lp, point, args)
        res["compile_s"] = dict(lp.compile_s)
        data["loops"][name] = res
        save()
        if args.budget > 0:
            methods = [m.strip() for m in args.race_methods.split(",")]
            for m in methods:  # compile outside the races
                if m == "grow":
                    for w in GROW:
                        lp.fo(w)
                elif m != "zo":
                    lp.estimate(m, lp.u["start"], np.random.default_rng(0))
            lp.forward(np.repeat(lp.u["start"][None], POPSIZE, 0), chunk=POPSIZE)
            lp.forward(np.repeat(lp.u["start"][None], POPSIZE, 0), which="plain", chunk=POPSIZE)
            lp.forward(np.repeat(lp.u["start"][None], 128, 0), chunk=128)
            res["races"] = [race(lp, methods, args.budget, seed) for seed in range(args.seeds)]
            res["compile_s"] = dict(lp.compile_s)
            save()
    if not args.skip_check:
        for name in [n for n in args.check_configs.split(",") if n]:
            log(f"check {name}")
            data["check"][name] = slow_tier_check(name, args)
            save()
    save()
    write_text(md_path, report(data))
    log(f"wrote {json_path} and {md_path}; {run['uptime_end']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
