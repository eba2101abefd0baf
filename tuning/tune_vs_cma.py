"""tune vs CMA-ES at equal wall time from the same start on the same loss (issue 33, "Done when": tune vs CMA-ES).

For each config (default: realistic_arm, arm_ideal_set2, arm_set2, unseen_arm, vertices,
realistic_arm_uncertain of tuning/configs/, and two configs nobody tuned on,
tuning/configs/unseen_ideal_payloads.toml and unseen_ideal_set3.toml; ``--configs`` for others):

1. tune's start, exactly as ``fosmc tune`` (``run_tune`` in fosmc_jax/_app/tune.py) computes
   it: ``_config.tuning_problems(cfg)``, the objective ``tuner.objective_of`` with its scales from
   the training problem's metrics at the config's parameters p0, ``global_stage`` of
   ``[tune] global_candidates`` on the training problem (same seed), ``tuner.to_internal``;
   the training loss is ``tuner.make_loss(train, obj, None)`` (its value does not depend on the
   gradient window, which changes derivatives only).
2. A race of three methods from that start, each given ``--budget`` (60) s of its own wall time:
   - tune: the package's tuner loop ``fosmc_jax._search.tune.run`` (``fs.tune``) with the
     config's learning rate (``tuner.learning_rate``), schedule and clip, mode reverse, the
     config's free parameters, for N steps, N the number of steps that covers the budget at the
     step time measured just before (x 1.3), so that the cosine schedule spans about the budget
     (as ``fosmc tune --budget`` fits its steps); stopped once its own time passes the budget;
   - CMA-ES (``fs.cma_es``, pycma) with popsize 16 and sigma 0.1 and 0.3 in tune's internal
     coordinates u, on the same training loss evaluated batched: one vmapped call of the 16
     candidates per generation (split over the local devices).
   The three run interleaved in one process, one at a time: whichever has used the least of
   its own time takes the next turn (one tune step or one CMA-ES generation), so their clocks
   advance together and the machine's load (2 shared cores) reaches them alike. Each method's
   time counts only its own turns. Compilation is excluded from both and reported apart: the
   batched training evaluator is compiled before the race; tune's gradient is compiled once
   before the race (to time a step), and its first step in the race (which loads that program
   from the persistent compilation cache, traces and compiles the Adam update) is counted as
   one median step, its excess reported as tune's in-race compilation.
3. At 10, 30 and 60 s of each method's time: its best-so-far point by TRAINING loss (tune: the
   lowest loss among the steps finished by then, as ``run`` returns; CMA-ES: the lowest
   among the candidates evaluated by then), and the PLAIN loss of that point: the same
   objective (same scales) on the config's ``[sim]`` problem, in one batched call.

The same race again from the config's parameters p0 (no global stage: the gradient alone
against CMA-ES, both from p0) on the ideal loops (``--p0 all`` on every config, ``none`` never).
The global stage's time and its share of the plain loss's improvement are reported beside.

Float64. Timings are wall times on a shared 2-core machine; each comes with the load averages
(``os.getloadavg``) sampled during it; compare timings within one run only. The persistent
compilation cache is on, in a fresh folder per run; the generated kernels' C++ libraries come
from the package's cache (~/.cache/fosmc_jax) as in any run.

    .venv/bin/python tuning/tune_vs_cma.py                 # the study (53 min on 2 cores at load 5-9)
    .venv/bin/python tuning/tune_vs_cma.py --quick         # a smoke run (10 s, 2 configs, 4 min) to /tmp
    .venv/bin/python tuning/tune_vs_cma.py --report-only   # the Markdown again from the JSON
    .venv/bin/python tuning/tune_vs_cma.py --configs a,b --merge   # add or redo configs in the JSON

The committed tuning/results/tune_vs_cma.{json,md} came from these two commands, one after the
other (the JSON's "runs" holds each, with its load): the default set (8 configs, the race from
p0 on its 5 ideal loops), then the other committed configs without the race from p0 (24 min):

    PYTHONPATH=. .venv/bin/python tuning/tune_vs_cma.py
    PYTHONPATH=. .venv/bin/python tuning/tune_vs_cma.py --configs \
realistic_arm_short_training,realistic_arm_exact_rates,arm_sign_dt,arm_set2_truncated,example --p0 none --merge

tune's N covers the budget, so its cosine schedule spans about 60 s of steps: on a config whose
``[tune] steps`` is smaller (arm_set2: 60) the learning rate stays high for longer than in a
plain ``fosmc tune`` run of that config.

Progress lines go to stderr.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import pathlib
import platform
import re
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
from jax.flatten_util import ravel_pytree  # noqa: E402
from jax.sharding import Mesh, NamedSharding  # noqa: E402
from jax.sharding import PartitionSpec as Spec  # noqa: E402

from fosmc_jax import config as _config  # noqa: E402
from fosmc_jax import search as fs  # noqa: E402
from fosmc_jax import use_compilation_cache  # noqa: E402
from fosmc_jax._search import tune as tuner  # noqa: E402  (learning_rate, _on_adjoint_kernel: run_tune's own choices)
from fosmc_jax.io import jsonable, write_text  # noqa: E402
from fosmc_jax.search import cma_es, global_stage, global_starts  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parent.parent
CONFIGS = ROOT / "tuning" / "configs"
OUT = ROOT / "tuning" / "results" / "tune_vs_cma"
QUICK_OUT = pathlib.Path(tempfile.gettempdir()) / "tune_vs_cma_quick"

DEFAULT_CONFIGS = ("realistic_arm", "arm_ideal_set2", "arm_set2", "unseen_arm", "vertices", "realistic_arm_uncertain",
                   "unseen_ideal_payloads", "unseen_ideal_set3")  # fmt: skip
NOT_TUNED_ON = ("unseen_ideal_payloads", "unseen_ideal_set3")  # written for this study
QUICK_CONFIGS = ("arm_set2", "realistic_arm")
SIGMAS = (0.1, 0.3)
POPSIZE = 16
BUDGET = 60.0
TIMES = (10.0, 30.0, 60.0)
QUICK_BUDGET, QUICK_TIMES, QUICK_GLOBAL = 10.0, (2.0, 5.0, 10.0), 64
STEP_MARGIN = 1.3  # tune's N = this x the steps that fit the budget at the measured step time

T0 = time.perf_counter()


def log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')} +{time.perf_counter() - T0:6.0f} s] {msg}", file=sys.stderr, flush=True)


def load() -> list[float]:
    return [round(x, 2) for x in os.getloadavg()]


def uptime() -> str:
    try:
        return subprocess.run(["uptime"], capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return f"load average: {os.getloadavg()}"


def replicated(tree):
    """``tree`` replicated over the local devices' mesh: the sharding tune's parameters get
    from its gradient, so that ``run`` compiles its value_and_grad once (tuning/truncation.py)."""
    return jax.device_put(tree, NamedSharding(Mesh(np.asarray(jax.local_devices()), ("batch",)), Spec()))


def fresh_models() -> None:
    """Forget the generated kernels' printed models (``fosmc_jax._simulator.generated._MODELS``)
    before a program is traced under another mesh: a model traced under one ``shard_map`` mesh
    (the global stage's ``candidates``, CMA-ES's ``c``) and replayed under another (the gradient's
    ``batch``) fails on the digital loops at 97ae33a ("context mesh ... should match the aval
    mesh", generated.py ``_replay``). The libraries stay built; only the tracing is redone."""
    from fosmc_jax._simulator import generated

    getattr(generated, "_MODELS", {}).clear()


def loop_of(cfg: dict) -> str:
    T_s = cfg["controller"]["sample_period"]
    return "ideal" if not T_s else f"digital ({1 / T_s / 1000:g} kHz)"


# ---------------------------------------------------------------------------- batched losses


class Batched:
    """The objective ``obj`` of ``problem`` at many flat u at once: vmapped over candidates, the
    candidates split over the local devices; compiled once per chunk size (as in
    tuning/truncation.py). On the training problem its values are those of tune's loss."""

    def __init__(self, problem: fs.Problem, obj: fs.Objective, unravel):
        self.devices = jax.local_devices()
        mesh = Mesh(np.asarray(self.devices), ("c",))

        def one(x):
            r = problem.simulate(fs.to_physical(unravel(x), problem.base, None), checkpoint_every=0, truncate_every=0)
            J, _, _ = fs.rollout_costs(r.metrics, r.diverged, obj)
            return fs.aggregate(J, obj), jnp.sum(r.diverged)

        self.run = jax.jit(jax.shard_map(jax.vmap(one), mesh=mesh, in_specs=Spec("c"), out_specs=Spec("c"),
                                         check_vma=False))  # fmt: skip
        self.compile_s: dict[int, float] = {}

    def __call__(self, X: np.ndarray, chunk: int = POPSIZE) -> tuple[np.ndarray, np.ndarray]:
        X = np.atleast_2d(np.asarray(X, float))
        size = -(-chunk // len(self.devices)) * len(self.devices)
        vals, div = [], []
        for i in range(0, len(X), size):
            part = X[i : i + size]
            pad = size - len(part)
            if pad:
                part = np.concatenate([part, np.repeat(part[-1:], pad, 0)])
            t = time.perf_counter()
            v, d = self.run(jnp.asarray(part))
            v, d = np.asarray(v), np.asarray(d)
            self.compile_s.setdefault(size, time.perf_counter() - t)
            vals.append(v[: len(part) - pad])
            div.append(d[: len(part) - pad])
        return np.concatenate(vals), np.concatenate(div)


# ---------------------------------------------------------------------------- the race


class Stop(Exception):
    """A method's time is spent."""


class Baton:
    """Turns among workers (threads): one computes at a time; a worker gives up its turn after
    each unit of work (a tune step, a CMA-ES generation) and the next turn goes to the live
    worker that has used the least of its own time. ``now(me)``: a worker's own time."""

    def __init__(self, names: list[str]):
        self.order, self.alive = list(names), set(names)
        self.clock = {n: 0.0 for n in names}
        self.since: dict[str, float] = {}
        self.turn: str | None = self.order[0]
        self.cv = threading.Condition()
        self.t0 = time.perf_counter()
        self.loads: list[tuple[float, list[float]]] = [(0.0, load())]

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
            if t - self.t0 - self.loads[-1][0] >= 5.0:
                self.loads.append((t - self.t0, load()))
            self.cv.notify_all()

    def pause(self, me: str) -> None:
        self.release(me)
        self.acquire(me)


STEP_LINE = re.compile(r"tune: step\s+(\d+)/(\d+)\s+loss")


def race(s: dict, u_flat: np.ndarray, budget: float, per_step: float, label: str) -> dict:
    """tune and CMA-ES (each sigma) from flat u, interleaved (:class:`Baton`), each for
    ``budget`` s of its own time. Returns their traces."""
    tcfg, unravel = s["tcfg"], s["unravel"]
    names = ["tune"] + [f"cma {sg:g}" for sg in SIGMAS]
    baton = Baton(names)
    errors: list[BaseException] = []
    if s["starts"] is not None and label.endswith("from start"):
        per_step = s["per_step_starts"]
    n_steps = max(2, math.ceil(STEP_MARGIN * budget / per_step))
    settings = fs.TuneSettings(n_steps, s["lr"], tcfg["schedule"], tcfg["clip"], "reverse", tuple(tcfg["params"]), 0,
                               s["optimizer"])  # fmt: skip
    tune_out: dict = {"stamps": [], "n_steps": n_steps}

    def tune_worker():
        baton.acquire("tune")
        ref: dict = {}

        def hook(msg: str) -> None:
            m = STEP_LINE.match(msg)
            if not m:
                return
            t = baton.now("tune")
            if "history" not in ref:  # run's history, which it fills step by step (one reference, read at the end)
                ref["history"] = sys._getframe(1).f_locals["history"]
            tune_out["stamps"].append(t)
            own = t - tune_out["stamps"][0] + per_step  # compilation excluded: the first step counts as one step
            if own > budget + per_step:  # one step's margin over the budget (the read-offs use the median step)
                raise Stop
            baton.pause("tune")

        try:
            fresh_models()  # run's (or run_starts's) own jit traces afresh, after CMA-ES's compilation
            if s["starts"] is not None and label.endswith("from start"):  # K starts at once (run_starts)
                U0 = jax.vmap(unravel)(jnp.asarray(s["starts"]))
                rates = tuner.rates_of(s["lr"], len(s["starts"]), s["spread"])
                u, hist = tuner.run_starts(s["loss"], U0, settings, rates=rates, log=hook)
            else:
                u, hist = fs.tune(s["loss"], replicated(unravel(jnp.asarray(u_flat))), settings, log=hook)
            tune_out["finished"] = True
            tune_out["end_time"] = baton.now("tune")
            tune_out["returned"] = np.asarray(ravel_pytree(u)[0])
            tune_out["best_step"] = int(hist["best_step"])
        except Stop:
            tune_out["finished"] = False
        except BaseException as e:  # noqa: BLE001
            errors.append(e)
        finally:
            tune_out["history"] = ref.get("history")
            baton.release("tune", done=True)

    cma_out: dict = {}

    def cma_worker(sigma: float):
        me = f"cma {sigma:g}"
        gens: list[tuple[float, np.ndarray, np.ndarray]] = []
        cma_out[me] = {"gens": gens}
        baton.acquire(me)

        def objective(X):
            if gens:
                baton.pause(me)  # its ask/tell so far counted in its turn
            if baton.now(me) >= budget:
                raise Stop
            F = s["train_eval"](X, chunk=POPSIZE)[0]
            gens.append((baton.now(me), np.array(X), F))
            return F

        try:
            cma_es(objective, u_flat, sigma, 1e9, POPSIZE, seed=0, log=lambda _: None)
            cma_out[me]["stopped_itself"] = True  # pycma's own stop criteria before the budget
        except Stop:
            cma_out[me]["stopped_itself"] = False
        except BaseException as e:  # noqa: BLE001
            errors.append(e)
        finally:
            baton.release(me, done=True)

    threads = [threading.Thread(target=tune_worker)] + [
        threading.Thread(target=cma_worker, args=(sg,)) for sg in SIGMAS
    ]
    t = time.perf_counter()
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    wall = time.perf_counter() - t
    baton.loads.append((wall, load()))
    if errors:
        raise errors[0]
    log(f"  {label} race: {wall:.0f} s wall; tune {len(tune_out['stamps'])} steps, "
        + ", ".join(f"{k} {len(v['gens'])} generations" for k, v in cma_out.items()) + f"; load {load()}")  # fmt: skip
    return {"tune": tune_out, "cma": cma_out, "wall_s": wall, "loads": baton.loads, "clock": dict(baton.clock)}


def readouts(s: dict, raced: dict, u_flat: np.ndarray, times: tuple[float, ...]) -> dict:
    """Best-so-far points by training loss at each time, for every method, and their plain losses."""
    unravel = s["unravel"]
    tr = raced["tune"]
    hist = tr["history"]
    stamps = np.asarray(tr["stamps"], float)
    n = len(stamps)
    d = np.diff(stamps)
    median = float(np.median(d)) if len(d) else float(stamps[0])
    compile_in_race = max(float(stamps[0]) - median, 0.0) if n else 0.0
    t_tune = stamps - compile_in_race  # the first step counted as one median step
    losses = np.asarray(hist["loss"][:n], float)
    points = [np.asarray(ravel_pytree(type(unravel(jnp.asarray(u_flat)))(*map(jnp.asarray, p)))[0])
              for p in hist["params"][:n]]  # fmt: skip
    if tr.get("finished") and tr.get("best_step", -1) == len(hist["loss"]):  # run's last update is its best
        v, _ = s["train_eval"](tr["returned"][None], chunk=POPSIZE)
        t_tune = np.append(t_tune, tr["end_time"] - compile_in_race)
        losses = np.append(losses, v[0])
        points.append(tr["returned"])
    methods = {"tune": (t_tune, losses, points)}
    for k, c in raced["cma"].items():
        tg = np.repeat([g[0] for g in c["gens"]], POPSIZE)
        F = np.concatenate([g[2] for g in c["gens"]]) if c["gens"] else np.zeros(0)
        X = np.concatenate([g[1] for g in c["gens"]]) if c["gens"] else np.zeros((0, len(u_flat)))
        methods[k] = (tg, F, list(X))
    pts, keys = [u_flat], [("start", None)]
    out: dict = {"methods": {}}
    for k, (tt, F, P) in methods.items():
        out["methods"][k] = {}
        for T_read in times:
            sel = np.nonzero((tt <= T_read + 1e-9) & np.isfinite(F))[0]
            if len(sel):
                i = int(sel[np.argmin(F[sel])])
                pts.append(np.asarray(P[i]))
                rec = {"train_loss": float(F[i]), "found_at_s": float(tt[i])}
            else:  # nothing finished by then: the start
                pts.append(u_flat)
                rec = {"train_loss": None, "found_at_s": None}
            rec["units"] = int(np.sum(tt <= T_read + 1e-9)) // (1 if k == "tune" else POPSIZE)
            out["methods"][k][f"{T_read:g}"] = rec
            keys.append((k, f"{T_read:g}"))
    v, div = s["plain_eval"](np.asarray(pts), chunk=POPSIZE)
    out["start_plain_loss"] = float(v[0])
    for (k, tk), val, dv in zip(keys[1:], v[1:], div[1:]):
        out["methods"][k][tk].update(plain_loss=float(val), plain_diverged=int(dv))
    # steps and generations, their times
    t_all = methods["tune"][0]
    out["tune"] = {"n_steps_planned": tr["n_steps"], "steps_done": n, "finished": bool(tr.get("finished")),
                   "compile_in_race_s": compile_in_race, "step_s_median": median,
                   "step_s": [float(x) for x in d], "time_s": float(t_all[-1]) if len(t_all) else 0.0,
                   "train_loss": [float(x) for x in hist["loss"][:n]], "grad_norm": [float(x) for x in hist["grad_norm"][:n]],
                   "skipped": int(np.sum(hist["skipped"][:n])),
                   "descended": bool(n > 1 and np.nanmin(np.where(np.isfinite(losses[1:]), losses[1:], np.nan),
                                                          initial=np.inf) < losses[0])}  # fmt: skip
    for k, c in raced["cma"].items():
        tg = np.asarray([g[0] for g in c["gens"]])
        out[k] = {"generations": len(tg), "gen_s_median": float(np.median(np.diff(np.r_[0.0, tg]))) if len(tg) else None,
                  "time_s": float(tg[-1]) if len(tg) else 0.0, "stopped_itself": c.get("stopped_itself"),
                  "best_train_loss": float(np.nanmin(np.concatenate([g[2] for g in c["gens"]]))) if len(tg) else None}  # fmt: skip
    out["start_train_loss"] = float(losses[0]) if len(losses) else None
    out["race_wall_s"] = raced["wall_s"]
    out["loads"] = raced["loads"]
    out["load_mean_1min"] = float(np.mean([x[1][0] for x in raced["loads"]]))
    return out


def polish(s: dict, raced: dict, u_flat: np.ndarray, args) -> dict:
    """CMA-ES, then gradient steps (``--polish SHARE``): the race's CMA-ES sigma 0.3 run up to its
    switch, the time pycma stopped it or SHARE x the budget, whichever comes first; from its best
    point so far, ``--polish-starts`` K Adam starts at once (``fosmc_jax._search.tune.run_starts``,
    the config's rate times 4**(-1..1); K = 1: ``fosmc tune``'s one-start loop ``run``) for the rest
    of the budget, timed alone after the race (compilation excluded: the gradient is compiled and
    timed first; ``run``'s first step counts as one median step). Read off at each time:
    the best point so far by training loss of CMA-ES's part and the gradient's, and its plain loss."""
    gens = raced["cma"]["cma 0.3"]["gens"]
    tg = np.asarray([g[0] for g in gens])
    stopped = bool(raced["cma"]["cma 0.3"].get("stopped_itself"))
    switch = min(args.polish * args.budget, float(tg[-1]) if stopped else np.inf)
    upto = [g for g in gens if g[0] <= switch + 1e-9] or gens[:1]
    X = np.concatenate([g[1] for g in upto])
    F = np.concatenate([g[2] for g in upto])
    i = int(np.nanargmin(np.where(np.isfinite(F), F, np.nan)))
    x_s, f_s = X[i], float(F[i])
    K, unravel = args.polish_starts, s["unravel"]
    U0 = jax.vmap(unravel)(jnp.asarray(np.repeat(x_s[None], K, 0)))
    rates = tuner.rates_of(s["lr"], K)
    fresh_models()
    vk = jax.jit(jax.vmap(jax.value_and_grad(s["loss"], has_aux=True)))
    jax.block_until_ready(vk(U0))
    t = time.perf_counter()
    jax.block_until_ready(vk(U0))
    per_step = time.perf_counter() - t
    left = args.budget - switch
    tcfg = s["tcfg"]
    n_steps = max(2, math.ceil(STEP_MARGIN * left / per_step))
    settings = fs.TuneSettings(n_steps, s["lr"], tcfg["schedule"], tcfg["clip"], "reverse", tuple(tcfg["params"]), 0)
    stamps: list[float] = []
    ref: dict = {}
    t0 = time.perf_counter()

    def hook(msg: str) -> None:
        if not STEP_LINE.match(msg):
            return
        if "history" not in ref:
            ref["history"] = sys._getframe(1).f_locals["history"]
        stamps.append(time.perf_counter() - t0)
        if stamps[-1] - stamps[0] + per_step > left + per_step:
            raise Stop

    loads = [load()]
    if left > 0:
        try:
            # one start: fosmc tune's own loop (run: no restarts), its gradient compiled on its first step
            if K == 1:
                fs.tune(s["loss"], replicated(unravel(jnp.asarray(x_s))), settings, log=hook)
            else:
                tuner.run_starts(s["loss"], U0, settings, rates=rates,
                                 stepper=tuner.Stepper(vk, "reverse", 0.0, per_step), log=hook)  # fmt: skip
        except Stop:
            pass
    loads.append(load())
    hist = ref.get("history", {"loss": [], "params": []})
    n = len(stamps)
    st = np.asarray(stamps, float)
    median = float(np.median(np.diff(st))) if n > 1 else per_step
    t_grad = switch + st - (st[0] - median if n else 0.0)  # the first step counted as one median step
    losses = np.asarray(hist["loss"][:n], float)
    pts_grad = [np.asarray(ravel_pytree(type(unravel(jnp.asarray(u_flat)))(*map(jnp.asarray, p)))[0])
                for p in hist["params"][:n]]  # fmt: skip
    t_cma = np.repeat(tg, POPSIZE)
    F_cma = np.concatenate([g[2] for g in gens])
    X_cma = np.concatenate([g[1] for g in gens])
    at, pts = {}, []
    for T in args.times:
        if T <= switch + 1e-9:
            sel = np.nonzero((t_cma <= T + 1e-9) & np.isfinite(F_cma))[0]
            j = int(sel[np.argmin(F_cma[sel])]) if len(sel) else None
            at[f"{T:g}"] = {"from": "cma-es", "train_loss": None if j is None else float(F_cma[j])}
            pts.append(u_flat if j is None else X_cma[j])
            continue
        sel = np.nonzero((t_grad <= T + 1e-9) & np.isfinite(losses))[0]
        j = int(sel[np.argmin(losses[sel])]) if len(sel) else None
        if j is not None and losses[j] < f_s:
            at[f"{T:g}"] = {"from": "gradient", "train_loss": float(losses[j]), "step": j + 1}
            pts.append(pts_grad[j])
        else:
            at[f"{T:g}"] = {"from": "cma-es", "train_loss": f_s}
            pts.append(x_s)
    v, div = s["plain_eval"](np.asarray(pts), chunk=POPSIZE)
    for rec, val, dv in zip(at.values(), v, div):
        rec.update(plain_loss=float(val), plain_diverged=int(dv))
    log(f"  polish: switch at {switch:.1f} s ({'pycma stopped' if switch < args.polish * args.budget else 'share'}), "
        f"CMA-ES's best {f_s:.4f}; {n} gradient steps of {K} starts ({per_step:.3f} s each); plain at the end "
        f"{v[-1]:.4f}")  # fmt: skip
    return {"switch_s": switch, "pycma_stopped": switch < args.polish * args.budget, "share": args.polish,
            "switch_train_loss": f_s, "starts": K, "rates": rates.tolist(), "step_s": per_step, "steps": n,
            "step_s_median": median, "train_loss": losses.tolist(), "at": at, "loads": loads}  # fmt: skip


# ---------------------------------------------------------------------------- one config


def study_config(name: str, cfg: dict, args) -> dict:
    t_cfg = time.perf_counter()
    if args.quick:
        cfg = _config.replace(cfg, tune={"global_candidates": min(cfg.tune.global_candidates, QUICK_GLOBAL)})
    if args.window is not None:  # tune's gradient window (s; beyond the horizon: the whole horizon)
        cfg = _config.replace(cfg, tune={"gradient_window": args.window})
    tcfg = cfg["tune"]
    plain, train, p0 = _config.tuning_problems(cfg)  # as run_tune
    m = fs.evaluate(train, p0)["metrics"]
    obj = fs.objective_of(tcfg, m)
    start, score, t_global = p0, None, 0.0
    if tcfg["global_candidates"]:
        fresh_models()
        t = time.perf_counter()
        if args.starts > 1:  # fosmc tune's [tune] starts: the best K of the same candidates
            top = global_starts(train, obj, p0, tcfg["global_candidates"], args.starts, free=tuple(tcfg["params"]),
                                log=lambda _: None)  # fmt: skip
            start, score = jax.tree.map(lambda x: x[0], top[0]), float(top[1][0])
        else:
            start, score = global_stage(train, obj, p0, tcfg["global_candidates"], free=tuple(tcfg["params"]),
                                        log=lambda _: None, command="tune")  # fmt: skip
        t_global = time.perf_counter() - t
    log(f"{name}: global stage of {tcfg['global_candidates']} candidates: score {score} in {t_global:.1f} s "
        f"(load {load()})")  # fmt: skip
    u_p0 = fs.to_internal(p0, plain.base, None)
    flat_p0, unravel = ravel_pytree(u_p0)
    flat_start = ravel_pytree(fs.to_internal(start, plain.base, None))[0]
    s = {"tcfg": tcfg, "unravel": unravel, "lr": tuner.learning_rate(tcfg["learning_rate"], _config.rough_loop(cfg)),
         "optimizer": args.optimizer or tcfg.get("optimizer", "adam"),
         "loss": fs.make_loss(train, obj, None), "train_eval": Batched(train, obj, unravel),
         "plain_eval": Batched(plain, obj, unravel), "starts": None, "spread": args.spread}  # fmt: skip
    if args.starts > 1 and tcfg["global_candidates"]:
        s["starts"] = np.stack([np.asarray(ravel_pytree(fs.to_internal(jax.tree.map(lambda x, i=i: x[i], top[0]),
                                                                        plain.base, None))[0])
                                for i in range(len(top[1]))])  # fmt: skip
    # compile before the races: tune's gradient (to time a step; run's own jit loads it from the
    # persistent cache), the batched training loss (CMA-ES's), the plain one (the read-offs)
    u0 = replicated(unravel(jnp.asarray(flat_start)))
    fresh_models()
    t = time.perf_counter()
    on_kernel = tuner._on_adjoint_kernel(
        s["loss"], u0
    )  # traces the gradient once: the kernels are generated (and built)
    trace_s = time.perf_counter() - t
    vg = fs.value_and_grad(s["loss"], "reverse")
    t = time.perf_counter()
    (value, _), grad = jax.block_until_ready(vg(u0))
    grad_compile = time.perf_counter() - t
    # as fosmc tune: on a rough loop the whole horizon, or the window where its gradient explodes at the start
    fallback = None
    if (truncated := _config.fallback_problem(cfg, train)) is not None:
        fallback = bool(not (np.isfinite(float(value)) and tuner._norm(grad) <= _config.GRADIENT_GUARD))
        log(f"{name}: the whole horizon's gradient at the start has norm {tuner._norm(grad):.3e}"
            + (f": the {_config.GRADIENT_WINDOW:g} s window's instead" if fallback else ""))  # fmt: skip
        if fallback:
            s["loss"] = fs.make_loss(truncated, obj, None)
            vg = fs.value_and_grad(s["loss"], "reverse")
            jax.block_until_ready(vg(u0))
    ts = []
    for _ in range(2):
        t = time.perf_counter()
        jax.block_until_ready(vg(u0))
        ts.append(time.perf_counter() - t)
    per_step = min(ts)
    if s["starts"] is not None:  # one batched step of the K starts (run_starts's program)
        fresh_models()
        vk = jax.jit(jax.vmap(jax.value_and_grad(s["loss"], has_aux=True)))
        UK = jax.vmap(unravel)(jnp.asarray(s["starts"]))
        jax.block_until_ready(vk(UK))
        ts = []
        for _ in range(2):
            t = time.perf_counter()
            jax.block_until_ready(vk(UK))
            ts.append(time.perf_counter() - t)
        s["per_step_starts"] = min(ts)
        log(f"{name}: {len(s['starts'])} starts (train losses {np.round(top[1], 3).tolist()}): "
            f"{s['per_step_starts']:.3f} s per batched step")  # fmt: skip
    X = np.repeat(np.asarray(flat_start)[None], POPSIZE, 0)
    fresh_models()
    s["train_eval"](X)
    t = time.perf_counter()
    s["train_eval"](X)
    per_gen = time.perf_counter() - t
    fresh_models()
    s["plain_eval"](X)
    log(f"{name}: compiled: first trace of the gradient {trace_s:.1f} s, gradient {grad_compile:.1f} s ({'adjoint kernel' if on_kernel else 'vmap path'}; "
        f"{per_step:.3f} s per gradient), batched training loss {s['train_eval'].compile_s[POPSIZE]:.1f} s "
        f"({per_gen:.3f} s per 16), plain {s['plain_eval'].compile_s[POPSIZE]:.1f} s; load {load()}")  # fmt: skip
    res = {
        "loop": loop_of(cfg), "not_tuned_on": name in NOT_TUNED_ON, "fallback": fallback,
        "plant": cfg["plant"]["kind"], "switching": cfg["controller"]["switching"],
        "train": {"dt": float(train.dt), "n_steps": int(train.options["n_steps"]), "rollouts": int(train.rollouts),
                  "truncate_every": int(train.options.get("truncate_every") or 0)},
        "plain": {"dt": float(plain.dt), "n_steps": int(plain.options["n_steps"]), "rollouts": int(plain.rollouts)},
        "objective": obj._asdict(),
        "tune_settings": {"optimizer": s["optimizer"], "learning_rate": s["lr"], "schedule": tcfg["schedule"],
                          "clip": tcfg["clip"],
                          "mode": "reverse", "config_mode": tcfg["mode"], "config_steps": tcfg["steps"],
                          "params": list(tcfg["params"]), "gradient_path": "adjoint kernel" if on_kernel else "vmap",
                          "starts": 1 if s["starts"] is None else len(s["starts"]),
                          "spread": args.spread if s["starts"] is not None else None,
                          "per_step_starts": s.get("per_step_starts")},
        "global_stage": {"candidates": tcfg["global_candidates"], "score": score, "time_s": t_global},
        "compile": {"trace_s": trace_s, "gradient_s": grad_compile, "train_batch_s": s["train_eval"].compile_s[POPSIZE],
                    "plain_batch_s": s["plain_eval"].compile_s[POPSIZE]},
        "before_race": {"gradient_s": per_step, "generation_s": per_gen, "load": load()},
        "params": {"p0": {k: np.asarray(v).tolist() for k, v in p0._asdict().items()},
                   "start": {k: np.asarray(v).tolist() for k, v in start._asdict().items()}},
        "races": {},
    }  # fmt: skip
    starts = [("start", flat_start)]
    if tcfg["global_candidates"] and (args.p0 == "all" or (args.p0 == "ideal" and res["loop"] == "ideal")):
        starts.append(("p0", flat_p0))
    for label, u_flat in starts:
        log(f"{name}: race from {label}: tune (N planned from {per_step:.3f} s/step) vs CMA-ES sigma "
            f"{', '.join(map(str, SIGMAS))}, {args.budget:g} s each, interleaved; load {load()}")  # fmt: skip
        raced = race(s, np.asarray(u_flat), args.budget, per_step, f"{name} from {label}")
        r = readouts(s, raced, np.asarray(u_flat), args.times)
        res["races"][label] = r
        if args.polish and label == "start":
            r["polish"] = polish(s, raced, np.asarray(u_flat), args)
        tl = args.times[-1]
        log(f"{name} from {label}: plain loss start {r['start_plain_loss']:.4f}; at {tl:g} s: "
            + ", ".join(f"{k} {r['methods'][k][f'{tl:g}']['plain_loss']:.4f}" for k in r["methods"]))  # fmt: skip
    if "p0" not in res["races"]:  # the plain loss at p0, for the global stage's share
        v, _ = s["plain_eval"](np.asarray(flat_p0)[None])
        res["p0_plain_loss"] = float(v[0])
    else:
        res["p0_plain_loss"] = res["races"]["p0"]["start_plain_loss"]
    res["wall_s"] = time.perf_counter() - t_cfg
    return res


# ---------------------------------------------------------------------------- report


def f3(x) -> str:
    return "-" if x is None else f"{x:.3f}"


def _cell(r: dict, tk: str) -> str:
    keys = ["tune"] + [f"cma {sg:g}" for sg in SIGMAS]
    vals = [r["methods"][k][tk].get("plain_loss") for k in keys]
    best = min((v for v in vals if v is not None and math.isfinite(v)), default=None)
    return " / ".join(f"**{f3(v)}**" if v is not None and v == best else f3(v) for v in vals)


def _wins(r: dict, tk: str) -> bool | None:
    t = r["methods"]["tune"][tk].get("plain_loss")
    c = [r["methods"][f"cma {sg:g}"][tk].get("plain_loss") for sg in SIGMAS]
    if t is None or any(x is None for x in c):
        return None
    return t <= min(c)


def _loop(c: dict) -> str:
    """The loop, and what else sets the gradient's kind: a linear plant, the sign law."""
    extra = [x for x, on in (("linear plant", c["plant"] != "arm"), ("sign law", c["switching"] == "sign")) if on]
    return ", ".join([c["loop"], *extra])


def _gens(g: dict) -> str:
    """A CMA-ES run's generations, and when pycma's own criteria stopped it before the budget."""
    return f"{g['generations']}" + (f" (converged, stopped at {g['time_s']:.0f} s)" if g.get("stopped_itself") else "")


def race_table(data: dict, label: str) -> str:
    times = [f"{t:g}" for t in data["settings"]["times"]]
    L = ["| config | loop | start | " + " | ".join(f"{t} s: tune / CMA 0.1 / CMA 0.3" for t in times)
         + " | tune <= CMA at " + ", ".join(times) + " s | tune s/step (steps) | CMA s/gen (gens 0.1, 0.3) "
         "| load (1-min: mean, range) |",
         "|---" * (7 + len(times)) + "|"]  # fmt: skip
    for name, c in data["configs"].items():
        r = c["races"].get(label)
        if r is None:
            continue
        wins = ["yes" if w else ("no" if w is False else "-") for w in (_wins(r, t) for t in times)]
        gens = [r[f"cma {sg:g}"] for sg in SIGMAS]
        ls = [x[1][0] for x in r["loads"]]
        nm = name + (" (not tuned on)" if c.get("not_tuned_on") else "")
        L.append(f"| {nm} | {_loop(c)} | {f3(r['start_plain_loss'])} | " + " | ".join(_cell(r, t) for t in times)
                 + f" | {', '.join(wins)} | {r['tune']['step_s_median']:.3f} ({r['tune']['steps_done']}) | "
                 f"{np.median([g['gen_s_median'] for g in gens]):.3f} ({', '.join(_gens(g) for g in gens)}) | "
                 f"{np.mean(ls):.1f}, {min(ls):.1f}-{max(ls):.1f} |")  # fmt: skip
    return "\n".join(L) + "\n"


def _diverged_from(r: dict, penalty: float) -> int | None:
    """The first of tune's steps (1-based) from which every step's training loss is the divergence
    penalty (a diverged rollout: a flat loss, no gradient), None if the run did not end there."""
    loss = np.asarray(r["tune"]["train_loss"], float)
    flat = ~np.isfinite(loss) | (loss >= penalty * (1 - 1e-9))
    if not len(loss) or not flat[-1]:
        return None
    i = len(loss) - 1
    while i > 0 and flat[i - 1]:
        i -= 1
    return i + 1


def _best_step(r: dict) -> str:
    """tune's training loss: first step's, lowest within the budget (its step and time), last step's."""
    tr, tl = r["tune"], f"{max(float(k) for k in r['methods']['tune']):g}"
    loss = np.asarray(tr["train_loss"], float)
    at, best = r["methods"]["tune"][tl]["found_at_s"], r["methods"]["tune"][tl]["train_loss"]
    if not len(loss) or at is None:
        return "-"
    i = int(np.nanargmin(np.where(np.isfinite(loss) & (np.arange(len(loss)) < tr["steps_done"]), loss, np.nan)))
    return f"{loss[0]:.3f} -> {best:.3f} (step {i + 1} of {len(loss)}, {at:.0f} s) -> {loss[-1]:.3f}"


def train_table(data: dict, label: str) -> str:
    tl = f"{data['settings']['times'][-1]:g}"
    L = [f"| config | start: train / plain | tune at {tl} s: train / plain | CMA 0.1: train / plain | "
         "CMA 0.3: train / plain | tune's training loss: first step -> lowest (step, time) -> last step "
         "| tune: skipped steps; diverged from step |", "|---" * 8 + "|"]  # fmt: skip
    for name, c in data["configs"].items():
        r = c["races"].get(label)
        if r is None:
            continue
        cells = [f"{f3(r['methods'][k][tl]['train_loss'])} / {f3(r['methods'][k][tl]['plain_loss'])}"
                 for k in ["tune"] + [f"cma {sg:g}" for sg in SIGMAS]]  # fmt: skip
        L.append(
            f"| {name} | {f3(r['start_train_loss'])} / {f3(r['start_plain_loss'])} | "
            + " | ".join(cells)
            + f" | {_best_step(r)} | {r['tune']['skipped']}; {_diverged_from(r, c['objective']['penalty']) or '-'} |"
        )
    return "\n".join(L) + "\n"


def _distance(c: dict) -> float:
    """max_i |u_start - u_p0| in tune's internal coordinates (log |parameter|)."""
    p0, st = c["params"]["p0"], c["params"]["start"]
    return float(max(np.max(np.abs(np.log(np.abs(np.asarray(st[k], float)) / np.abs(np.asarray(p0[k], float)))))
                     for k in p0))  # fmt: skip


def _reach(c: dict, r: dict, budget: float) -> float:
    """The sum of tune's learning rates over the steps it took within the budget (its schedule over
    the planned N steps): about the most an Adam step sequence moves one entry of u."""
    ts = c["tune_settings"]
    n, N = r["tune"]["steps_done"], r["tune"]["n_steps_planned"]
    lr = ts["learning_rate"]
    if ts["schedule"] == "cosine":  # optax.cosine_decay_schedule(lr, N, alpha=0.1)
        k = np.arange(n)
        rates = lr * (0.1 + 0.9 * 0.5 * (1 + np.cos(np.pi * np.minimum(k, N) / N)))
    else:
        rates = np.full(n, lr)
    return float(np.sum(rates))


def share_table(data: dict) -> str:
    tl = f"{data['settings']['times'][-1]:g}"
    L = [f"| config | global stage: candidates, time (s) | plain loss p0 -> start -> tune at {tl} s | "
         f"share of tune's time in gradient steps | share of its plain improvement from gradient steps | "
         f"start's distance from p0 in u (largest entry) | tune's reach in {tl} s: sum of its learning rates |",
         "|---" * 7 + "|"]  # fmt: skip
    for name, c in data["configs"].items():
        r = c["races"]["start"]
        g = c["global_stage"]
        p0l, st, end = c["p0_plain_loss"], r["start_plain_loss"], r["methods"]["tune"][tl]["plain_loss"]
        t_grad = min(r["tune"]["time_s"], data["settings"]["budget"])
        share_t = t_grad / (t_grad + g["time_s"]) if t_grad + g["time_s"] > 0 else None
        total = p0l - end
        share_i = (st - end) / total if total > 0 else None
        L.append(
            f"| {name} | {g['candidates']}, {g['time_s']:.1f} | {f3(p0l)} -> {f3(st)} -> {f3(end)} | "
            f"{'-' if share_t is None else f'{share_t:.0%}'} | {'-' if share_i is None else f'{share_i:.0%}'} | "
            f"{_distance(c):.2f} | {_reach(c, r, data['settings']['budget']):.2f} |"
        )
    return "\n".join(L) + "\n"


def polish_table(data: dict) -> str:
    """``--polish``'s read-offs beside the race's CMA-ES runs."""
    times = [f"{t:g}" for t in data["settings"]["times"]]
    L = ["| config | loop | switch (s): why | CMA-ES's best there (train) | "
         + " | ".join(f"{t} s: CMA-ES+gradient / CMA 0.1 / CMA 0.3" for t in times)
         + " | at or below both at " + ", ".join(times) + " s | gradient steps (s/step) | training loss: switch -> gradient's best | load (1-min, after / before) |",
         "|" + "---|" * (8 + len(times))]  # fmt: skip
    for name, c in data["configs"].items():
        r = c["races"].get("start", {})
        if "polish" not in r:
            continue
        q = r["polish"]
        cells, wins = [], []
        for t in times:
            own = q["at"][t]["plain_loss"]
            a, b = (r["methods"][k][t]["plain_loss"] for k in ("cma 0.1", "cma 0.3"))
            low = min(own, a, b)
            cells.append(" / ".join(f"**{x:.3f}**" if x == low else f"{x:.3f}" for x in (own, a, b))
                         + ("" if q["at"][t]["from"] == "gradient" else " (cma)"))  # fmt: skip
            wins.append("yes" if own <= min(a, b) else "no")
        best = min(q["train_loss"], default=np.inf)
        L.append(f"| {name} | {_loop(c)} | {q['switch_s']:.1f}: {'pycma stopped' if q['pycma_stopped'] else 'share'} | "
                 f"{q['switch_train_loss']:.3f} | " + " | ".join(cells) + f" | {', '.join(wins)} | "
                 f"{q['steps']} of {q['starts']} starts ({q['step_s_median']:.3f}) | {q['switch_train_loss']:.3f} -> "
                 f"{best:.3f} | {q['loads'][1][0]:.1f} / {q['loads'][0][0]:.1f} |")  # fmt: skip
    return "\n".join(L) + "\n"


def compile_table(data: dict) -> str:
    L = ["| config | gradient path | train: rollouts x steps (dt) | plain: rollouts x steps | lr, schedule | "
         "compile (s): first trace of the gradient / gradient / in race / batched train / batched plain | before the race: s per gradient, "
         "per 16 candidates (load) | config wall (s) |", "|---" * 8 + "|"]  # fmt: skip
    for name, c in data["configs"].items():
        ts, tr, pl, cp, br = c["tune_settings"], c["train"], c["plain"], c["compile"], c["before_race"]
        in_race = "/".join(f"{r['tune']['compile_in_race_s']:.1f}" for r in c["races"].values())
        L.append(
            f"| {name} | {ts['gradient_path']} | {tr['rollouts']} x {tr['n_steps']} ({tr['dt']:g} s) | "
            f"{pl['rollouts']} x {pl['n_steps']} | {ts['learning_rate']:g}, {ts['schedule']} | "
            f"{cp.get('trace_s', float('nan')):.1f} / {cp['gradient_s']:.1f} / {in_race} / {cp['train_batch_s']:.1f} / {cp['plain_batch_s']:.1f} | "
            f"{br['gradient_s']:.3f}, {br['generation_s']:.3f} ({br['load'][0]:.1f}) | {c['wall_s']:.0f} |"
        )
    return "\n".join(L) + "\n"


def findings(data: dict) -> list[str]:
    times = [f"{t:g}" for t in data["settings"]["times"]]
    tl = times[-1]
    out = []
    for label, what in (("start", "from tune's start"), ("p0", "from p0 (the gradient alone)")):
        rows = {n: c["races"][label] for n, c in data["configs"].items() if label in c["races"]}
        if not rows:
            continue
        allw = [n for n, r in rows.items() if all(_wins(r, t) for t in times)]
        none = [n for n, r in rows.items() if not any(_wins(r, t) for t in times)]
        some = [n for n in rows if n not in allw and n not in none]
        out.append(f"{what.capitalize()}: tune's plain loss is at or below both CMA-ES runs' at every read-off on "
                   f"{', '.join(allw) or 'no config'}; at none on {', '.join(none) or 'no config'}"
                   + (f"; at some on {', '.join(some)}" if some else "") + ".")  # fmt: skip
        drop = {n: r["tune"]["train_loss"][0] - r["methods"]["tune"][tl]["train_loss"] for n, r in rows.items()}
        nd = [f"{n} ({d:.3f})" for n, d in drop.items() if d < 0.05]
        if nd:
            out.append(f"{what.capitalize()}: tune's training loss fell by less than 0.05 within {tl} s on "
                       f"{', '.join(nd)}: the gradient steps do not descend there.")  # fmt: skip
        dv = {n: _diverged_from(r, data["configs"][n]["objective"]["penalty"]) for n, r in rows.items()}
        dv = {n: k for n, k in dv.items() if k}
        if dv:
            out.append(f"{what.capitalize()}: tune's steps reached parameters where every training rollout diverges "
                       "and stayed there (the loss is the flat divergence penalty, whose gradient is zero; Adam's "
                       "momentum carries on, nothing brings it back) on " + ", ".join(
                           f"{n} (from step {k} of {len(rows[n]['tune']['train_loss'])})" for n, k in dv.items())
                       + ": the rest of its time is lost; `run` returns its best point.")  # fmt: skip
        over = []
        for n, r in rows.items():
            t = r["methods"]["tune"][tl]
            for sg in SIGMAS:
                c = r["methods"][f"cma {sg:g}"][tl]
                if None in (c["train_loss"], t["train_loss"]):
                    continue
                if c["train_loss"] < t["train_loss"] and c["plain_loss"] > t["plain_loss"]:
                    over.append(
                        f"{n} (sigma {sg:g}: train {c['train_loss']:.3f} vs tune's {t['train_loss']:.3f}, "
                        f"plain {c['plain_loss']:.3f} vs {t['plain_loss']:.3f})"
                    )
                elif c["plain_loss"] > r["start_plain_loss"] and c["train_loss"] < (r["start_train_loss"] or np.inf):
                    over.append(
                        f"{n} (sigma {sg:g}: plain {c['plain_loss']:.3f} worse than the start's "
                        f"{r['start_plain_loss']:.3f} while its training loss fell)"
                    )
        t_over = [f"{n} (training {r['start_train_loss']:.3f} -> {r['methods']['tune'][tl]['train_loss']:.3f}, plain "
                  f"{r['start_plain_loss']:.3f} -> {r['methods']['tune'][tl]['plain_loss']:.3f})"
                  for n, r in rows.items() if r["methods"]["tune"][tl]["plain_loss"] > r["start_plain_loss"]
                  and r["methods"]["tune"][tl]["train_loss"] < r["start_train_loss"]]  # fmt: skip
        if t_over:
            out.append(f"{what.capitalize()}, at {tl} s: tune's own best training point is worse than the start on the "
                       "plain loss while its training loss fell: " + "; ".join(t_over) + ".")  # fmt: skip
        if over:
            out.append(f"{what.capitalize()}, at {tl} s: CMA-ES's best training point is better on the training "
                       "loss and worse on the plain one than tune's, or worse than the start on the plain loss "
                       "(it exploits the training surrogate): " + "; ".join(over) + ".")  # fmt: skip
    polished = {n: c["races"]["start"] for n, c in data["configs"].items() if "polish" in c["races"].get("start", {})}
    if polished:
        ok = lambda r, t: r["polish"]["at"][t]["plain_loss"] <= min(r["methods"][f"cma {sg:g}"][t]["plain_loss"]
                                                                    for sg in SIGMAS)  # fmt: skip
        allw = [n for n, r in polished.items() if all(ok(r, t) for t in times)]
        at_end = [n for n, r in polished.items() if ok(r, tl)]
        gained = {n: r["polish"]["switch_train_loss"] - min(r["polish"]["train_loss"], default=np.inf)
                  for n, r in polished.items()}  # fmt: skip
        out.append(f"CMA-ES then gradient steps (`--polish`): its plain loss is at or below both CMA-ES runs' at every "
                   f"read-off on {', '.join(allw) or 'no config'} and at {tl} s on {len(at_end)} of {len(polished)} "
                   "configs; the gradient steps lowered the training loss below CMA-ES's at the switch by "
                   + ", ".join(f"{d:.3f} ({n})" for n, d in gained.items()) + ".")  # fmt: skip
    return out


def report(data: dict) -> str:
    st = data["settings"]
    times = ", ".join(f"{t:g}" for t in st["times"])
    L = [f"# tune vs CMA-ES at equal wall time (issue 33)\n\nGenerated by `tuning/tune_vs_cma.py` from "
         f"`{data['json']}` (`--report-only` regenerates it). Every method from the same start, on the same training "
         f"loss (`fosmc_jax.search.make_loss` of `fosmc tune`'s training problem and objective), for {st['budget']:g} s "
         f"of its own wall time; read off at {times} s: each method's best point so far by training loss, and that "
         "point's **plain loss** (the same objective on the config's `[sim]` problem; lower is better; the "
         "objective's scales make the config's parameters score about 0).\n\n"]  # fmt: skip
    A = L.append
    A("Runs (each command, its machine and load):\n")
    for r in data["runs"]:
        A(
            f"- `{r['command']}`: {r['started']}, {r['wall_s'] / 60:.0f} min, configs {', '.join(r['configs'])}; "
            f"{r['machine']['cores']} cores, {r['machine']['devices']} JAX CPU devices, jax {r['machine']['jax']}; "
            f"`uptime` at the start: `{r['uptime_start']}`; at the end: `{r['uptime_end']}`"
        )
    starts = {c["tune_settings"].get("starts", 1) for c in data["configs"].values()}
    if starts != {1}:
        spread = {c["tune_settings"].get("spread") for c in data["configs"].values()} - {None}
        A(
            f"\n**tune here: {' or '.join(map(str, sorted(starts)))} starts at once from its start** (`--starts`, "
            "`fosmc tune`'s `[tune] starts`: `fosmc_jax._search.tune.run_starts`): the best K of the global stage's "
            "candidates, each with its own Adam state and learning rate (the config's rate times "
            f"{' or '.join(f'{x:g}' for x in sorted(spread))}**(-1..1), spaced geometrically), all K in one vmapped "
            "value-and-gradient call per step (the generated kernels fold them into their lanes); a start whose "
            "rollouts all diverge goes back to its best point at half its rate. A step of the tables is one such call "
            "(s/step: of the K together); tune's point is the best of all K. CMA-ES starts from the best of the K, "
            "as before. The race from p0 (where run) is the one-start tune."
        )
    opts = {c["tune_settings"].get("optimizer", "adam") for c in data["configs"].values()}
    if opts == {"lbfgs"}:
        A(
            "\n**tune's optimizer here: L-BFGS** (`--optimizer lbfgs`: `optax.scale_by_lbfgs`'s directions and a "
            "backtracking line search, `fosmc_jax._search.tune._LineSearch`; the learning rate, schedule and clip below "
            "are Adam's and unused; a step of the table is an accepted line search, its time that of all its trials; "
            "tune stops where the line search finds no decrease)."
        )
    A("\n**How.** tune = the package's tuner loop (`fosmc_jax._search.tune.run`, Adam with the config's learning "
      "rate as `tuner.learning_rate` resolves it, its schedule and clip, mode reverse, its free parameters) for N steps, "
      f"N = {st['step_margin']:g} x the steps that fit the budget at the step time measured before the race (the cosine "
      "schedule spans about the budget, as `fosmc tune --budget` fits its steps), stopped when its time passes the "
      f"budget. CMA-ES = `fosmc_jax.search.cma_es` (pycma), popsize {st['popsize']}, sigma "
      f"{' and '.join(f'{s:g}' for s in st['sigmas'])} in tune's internal coordinates u (log delta, log gamma, "
      "log(-poles)), one vmapped call of 16 candidates of the training loss per generation. The three run "
      "interleaved in one process, one at a time, the next turn (a step, a generation) going to the one that has "
      "used the least of its own time, so that the load of the shared machine reaches them alike; each one's time "
      "counts its own turns only. **Compilation is excluded for both and reported apart** (table below): CMA-ES's "
      "batched loss is compiled before the race; tune's gradient is compiled before the race to time a step, and its "
      "first step in the race (the program loaded from the persistent cache, the Adam update compiled) counts as one "
      "median step. tune's start = `fosmc tune`'s: the best of the global stage's candidates "
      "(`[tune] global_candidates`, seed 0) on the training problem, from the config's parameters p0.\n")  # fmt: skip
    A(f"\n## From tune's start (after its global stage)\n\nPlain loss at {times} s: tune / CMA-ES sigma 0.1 / "
      "sigma 0.3, the lowest in bold. s/step and s/gen: medians during the race. Load: the 1-min load average "
      "sampled every 5 s during the race (2 cores).\n\n")  # fmt: skip
    A(race_table(data, "start"))
    if any("p0" in c["races"] for c in data["configs"].values()):
        A("\n## The gradient alone: from the config's parameters p0 (no global stage)\n\nThe same race from p0, on "
          "the configs below (`--p0`: the ideal loops by default; issue 33: \"On the ideal loops the gradient "
          "steps carry it: tune with any zeroth-order part turned off is still at or below CMA-ES\").\n\n")  # fmt: skip
        A(race_table(data, "p0"))
    A(f"\n## Training loss against plain loss at {st['times'][-1]:g} s\n\nThe training loss each method minimised and "
      "the plain loss of the same point: where they disagree the method exploited the training surrogate (coarser "
      "step or shorter horizon than `[sim]`).\n\n")  # fmt: skip
    for label, what in (("start", "From tune's start"), ("p0", "From p0")):
        if any(label in c["races"] for c in data["configs"].values()):
            A(f"{what}:\n\n" + train_table(data, label) + "\n")
    A("## The global stage's share\n\nWhat `fosmc tune` spends before its gradient steps (its global stage, timed "
      "here with its evaluator's compilation) against the gradient steps' time in the race (compilation excluded), "
      "and which part of the plain loss's fall from p0 to tune's point at the end the gradient steps made. Beside "
      "them, how far the global stage's best lies from p0 in u, and how far Adam's steps can carry one entry of u "
      "in the race (an Adam step moves each entry by about its learning rate at most, whatever the gradient's "
      "size).\n\n")  # fmt: skip
    A(share_table(data))
    if any("polish" in c["races"].get("start", {}) for c in data["configs"].values()):
        A("\n## CMA-ES, then gradient steps (`--polish`)\n\nThe race's CMA-ES sigma 0.3 run up to the switch (the "
          f"time pycma stopped it, or {st['polish']:g} x the budget, the earlier), then "
          + ("`fosmc tune`'s own one-start Adam loop (`run`, the config's rate)" if st["polish_starts"] == 1 else
             f"{st['polish_starts']} Adam starts at once (`run_starts`, the config's rate times 4**(-1..1))")
          + " from its best point so far for the rest of the budget, timed alone after the race. Before the switch its point is CMA-ES sigma 0.3's ((cma)); after it the better "
          "of CMA-ES's point and the gradient steps' best by training loss. Plain loss, the lowest in bold.\n\n")  # fmt: skip
        A(polish_table(data))
    A("\n## Costs and compilation\n\n")
    A(compile_table(data))
    text = findings(data)
    if text:
        A("\n## Findings (computed from the JSON)\n\n" + "\n".join(f"- {x}" for x in text) + "\n")
    if data.get("notes"):
        A("\n## Notes\n\n" + "\n".join(f"- {x}" for x in data["notes"]) + "\n")
    return "".join(x if x.endswith("\n") else x + "\n" for x in L)


# ---------------------------------------------------------------------------- main


#: ``--cold``'s runs: config name and ``--budget`` (None: none, the default settings)
COLD_RUNS = (("realistic_arm", 60.0), ("realistic_arm", 30.0), ("arm_ideal_set2", None), ("arm_ideal_set2", 30.0),
             ("arm_ideal_set2", 60.0))  # fmt: skip
COLD_OUT = ROOT / "tuning" / "results" / "tune_budget"
REFERENCES = ROOT / "tuning" / "results" / "reference"


def _log_product(metrics: dict) -> float:
    """log10(E x C), E and C the means over rollouts and joints of rms_error and chattering_hf."""
    return float(np.log10(np.mean(metrics["rms_error"]) * np.mean(metrics["chattering_hf"])))


def cold_run(name: str, budget: float | None, tune_set: str = "") -> dict:
    """One ``fosmc tune`` as a new user runs it: a fresh process with empty caches (the kernels'
    and XLA's), its wall time from before its start to its exit, and its point's measures: the
    issue's log10(E x C) against the smallest among the reference front's points (where
    tuning/results/reference/<name>/ has one), and mean rms_error and total variation.
    ``tune_set`` (``KEY=VALUE,...``, TOML values): ``[tune]`` keys added to the config (one
    without a ``[tune]`` table of its own), in a copy beside the run."""
    out = pathlib.Path(tempfile.mkdtemp(prefix=f"tune-cold-{name}-"))
    env = dict(os.environ, XDG_CACHE_HOME=tempfile.mkdtemp(), FOSMC_JAX_CACHE=tempfile.mkdtemp())
    config = CONFIGS / f"{name}.toml"
    if tune_set:
        text = config.read_text()
        if any(line.strip().startswith("[tune]") for line in text.splitlines()):
            raise SystemExit(f"--tune-set: {config} has a [tune] table of its own")
        config = out / config.name
        config.write_text(
            text + "\n[tune]\n" + "\n".join(kv.replace("=", " = ", 1) for kv in tune_set.split(",")) + "\n"
        )
    cmd = [str(ROOT / ".venv" / "bin" / "fosmc"), "tune", "--config", str(config), "--out",
           str(out / "run")] + ([] if budget is None else ["--budget", f"{budget:g}"])  # fmt: skip
    before = load()
    t0 = time.perf_counter()
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - t0
    row = {"config": name, "budget": budget, "tune_set": tune_set, "wall_s": round(wall, 2),
           "load_start_end": [before, load()],
           "returncode": done.returncode, "log": [x for x in done.stderr.splitlines() if "step " not in x][-12:]}  # fmt: skip
    if done.returncode:
        return row
    result = json.loads((out / "run" / "result.json").read_text())
    final, history = result["final"]["metrics"], result["history"]
    row.update(rms_error=float(np.mean(final["rms_error"])), chattering_hf=float(np.mean(final["chattering_hf"])),
               total_variation=float(np.mean(final["chattering"])), log10_EC=_log_product(final),
               steps=len(history["loss"]), start_loss=history["loss"][0] if history["loss"] else None,
               cma=result["start"].get("cma"),
               best_loss=min(history["loss"] + [history.get("last", np.inf)]) if history["loss"] else None)  # fmt: skip
    if budget is not None:
        row["within_margin"] = bool(wall <= 1.05 * budget + 2.0)
    reference = REFERENCES / name / "reference.json"
    if reference.exists():
        points = [q for q in json.loads(reference.read_text())["points"] if not q["diverged"]]
        row["reference_min_log10_EC"] = min(_log_product(q["metrics"]) for q in points)
        row["above_reference_min"] = row["log10_EC"] - row["reference_min_log10_EC"]
    return row


def cold_report(data: dict) -> str:
    lines = ["# `fosmc tune` from cold caches: the budget held, and the point it reaches", "",
             f"Written by `{data['command']}` at {data['commit']} (uncommitted in fosmc_jax/: "
             f"{', '.join(data['uncommitted']) or 'nothing'}; {data['started']}; {data['uptime_start']} -> "
             f"{data['uptime_end']}; {data['cores']} cores, shared). Each run: a fresh process with empty caches (`XDG_CACHE_HOME`, "
             "`FOSMC_JAX_CACHE`: the kernels' C++ and XLA's programs compiled anew), its wall time from before its "
             "start to its exit; E and C: the means over rollouts and joints of `rms_error` and `chattering_hf` in "
             "result.json's `final.metrics`, TV of `chattering` (total variation); the reference: the smallest "
             "log10(E x C) among tuning/results/reference/<config>/reference.json's points.", "",
             "| config | --budget | wall, s | within 1.05 B + 2 s | load start / end | CMA-ES stage: generations, loss "
             "| steps | E, rad | C, V | TV, V/s | log10(E x C) | minus the reference's smallest |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for r in data["rows"]:
        if r["returncode"]:
            lines.append(f"| {r['config']} | {r['budget']} | {r['wall_s']:.1f} | failed ({r['returncode']}) |"
                         " | | | | | | | |")  # fmt: skip
            continue
        margin = "" if r["budget"] is None else ("yes" if r["within_margin"] else "**no**")
        above = f"{r['above_reference_min']:+.3f}" if "above_reference_min" in r else ""
        budget = "none" if r["budget"] is None else f"{r['budget']:g}"
        name = r["config"] + (f" ({r['tune_set']})" if r.get("tune_set") else "")
        c = r.get("cma")
        cma = "none" if not c else f"{c['generations']}, {c['start_loss']:.3f} -> {c['loss']:.3f}"
        lines.append(f"| {name} | {budget} | {r['wall_s']:.1f} | "
                     f"{margin} | {r['load_start_end'][0][0]:.1f} / {r['load_start_end'][1][0]:.1f} | {cma} | {r['steps']} | "
                     f"{r['rms_error']:.3g} | {r['chattering_hf']:.3g} | {r['total_variation']:.3g} | "
                     f"{r['log10_EC']:.3f} | {above} |")  # fmt: skip
    return "\n".join(lines) + "\n"


def cold(args) -> int:
    """``--cold``: :data:`COLD_RUNS` one after another (or ``--configs`` NAME:BUDGET,...), to
    ``--out`` (default tuning/results/tune_budget.{json,md})."""
    runs = COLD_RUNS
    if args.configs:
        runs = tuple((n, None if b in ("", "none") else float(b)) for n, _, b in (c.partition(":") for c in
                                                                                args.configs.split(",")))  # fmt: skip
    stem = pathlib.Path(args.out) if args.out else COLD_OUT
    git = lambda *a: subprocess.run(["git", *a], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    data = {"command": " ".join(["tuning/tune_vs_cma.py"] + sys.argv[1:]), "started": time.strftime("%Y-%m-%d %H:%M:%S"),
            "uptime_start": uptime(), "cores": os.cpu_count(), "commit": git("rev-parse", "--short", "HEAD"),
            "uncommitted": git("status", "--short", "--untracked-files=no", "fosmc_jax").splitlines(),
            "rows": []}  # fmt: skip
    for name, budget in runs:
        log(f"cold: {name} --budget {budget} ({uptime()})")
        data["rows"].append(cold_run(name, budget, args.tune_set or ""))
        log(f"cold: {name}: {data['rows'][-1]['wall_s']:.1f} s")
    data["uptime_end"] = uptime()
    write_text(stem.with_suffix(".json"), json.dumps(jsonable(data), indent=1))
    write_text(stem.with_suffix(".md"), cold_report(data))
    log(f"wrote {stem.with_suffix('.json')} and {stem.with_suffix('.md')}")
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--configs", help="comma-separated config names of tuning/configs (default: "
                    + ",".join(DEFAULT_CONFIGS) + ")")  # fmt: skip
    ap.add_argument("--quick", action="store_true", help=f"a smoke run: {QUICK_BUDGET:g} s, read-offs at "
                    f"{QUICK_TIMES}, {','.join(QUICK_CONFIGS)}, {QUICK_GLOBAL} global candidates, to {QUICK_OUT}")  # fmt: skip
    ap.add_argument("--budget", type=float, help=f"seconds per method (default {BUDGET:g}; read-offs at {TIMES})")
    ap.add_argument(
        "--p0",
        choices=("ideal", "all", "none"),
        default="ideal",
        help="where the race from p0 (no global stage) runs too (default: the ideal loops)",
    )
    ap.add_argument("--optimizer", choices=tuner.OPTIMIZERS, help="tune's optimizer (default: the config's)")
    ap.add_argument("--window", type=float, help="tune's [tune] gradient_window, s (default: the config's; a window "
                    "longer than the training horizon gives the whole horizon's gradient)")  # fmt: skip
    ap.add_argument("--starts", type=int, default=1, help="tune's starts from the global stage, run at once "
                    "(fosmc tune's [tune] starts; default 1: the one-start tune)")  # fmt: skip
    ap.add_argument("--spread", type=float, default=tuner.SPREAD, help="with --starts: the starts' learning rates span the "
                    f"config's rate / SPREAD .. x SPREAD (default fosmc tune's, {tuner.SPREAD:g})")  # fmt: skip
    ap.add_argument("--tune-set", metavar="KEY=VALUE,...", help="with --cold: [tune] keys added to each config "
                    "(TOML values, e.g. cma_generations=0,starts=8)")  # fmt: skip
    ap.add_argument("--polish", type=float, metavar="SHARE", help="CMA-ES then gradient steps, after the race from "
                    "tune's start: the CMA-ES sigma 0.3 run's best point when pycma stopped it or at SHARE x the budget "
                    "(the earlier), then K Adam starts from it for the rest (polish())")  # fmt: skip
    ap.add_argument("--polish-starts", type=int, default=8, help="with --polish: K (default 8)")
    ap.add_argument("--out", help=f"output stem (writes STEM.json and STEM.md; default {OUT.relative_to(ROOT)})")
    ap.add_argument("--merge", action="store_true", help="add (or redo) the configs into the existing JSON")
    ap.add_argument("--report-only", action="store_true", help="rewrite the Markdown from the JSON")
    ap.add_argument("--cold", action="store_true", help="fosmc tune itself, fresh processes with empty caches: "
                    "the budget's margin and the point's measures (--configs NAME:BUDGET,...; default "
                    f"{', '.join(f'{n}:{b}' for n, b in COLD_RUNS)}; --out default {COLD_OUT.relative_to(ROOT)})")  # fmt: skip
    args = ap.parse_args()
    if args.cold:
        return cold(args)
    stem = pathlib.Path(args.out) if args.out else (QUICK_OUT if args.quick else OUT)
    json_path, md_path = stem.with_suffix(".json"), stem.with_suffix(".md")
    if args.report_only:
        data = json.loads(json_path.read_text())
        write_text(md_path, report(data))
        log(f"wrote {md_path}")
        return 0
    args.budget = args.budget or (QUICK_BUDGET if args.quick else BUDGET)
    args.times = (QUICK_TIMES if args.quick else TIMES) if args.budget == (QUICK_BUDGET if args.quick else BUDGET) \
        else tuple(args.budget * x for x in (1 / 6, 1 / 2, 1))  # fmt: skip
    names = args.configs.split(",") if args.configs else list(QUICK_CONFIGS if args.quick else DEFAULT_CONFIGS)
    cache = pathlib.Path(tempfile.mkdtemp(prefix="tune-vs-cma-xla-"))
    use_compilation_cache(cache)
    import cma  # noqa: F401  (pycma's import, 1-2 s, before any clock)

    run = {"command": " ".join(["tuning/tune_vs_cma.py"] + sys.argv[1:]), "started": time.strftime("%Y-%m-%d %H:%M:%S"),
           "uptime_start": uptime(), "configs": names, "p0": args.p0,
           "machine": {"cores": os.cpu_count(), "devices": jax.local_device_count(), "jax": jax.__version__,
                       "python": platform.python_version()}}  # fmt: skip
    log(f"start: {run['uptime_start']}; configs {names}; {args.budget:g} s per method; compilation cache {cache}")
    settings = {"budget": args.budget, "times": list(args.times), "sigmas": list(SIGMAS), "popsize": POPSIZE,
                "step_margin": STEP_MARGIN, "quick": args.quick}  # fmt: skip
    if args.polish:
        settings.update(polish=args.polish, polish_starts=args.polish_starts)
    if args.merge and json_path.exists():
        data = json.loads(json_path.read_text())
        if data["settings"] != settings:
            raise SystemExit(f"--merge: {json_path}'s settings {data['settings']} differ from this run's {settings}")
    else:
        data = {"json": str(json_path.relative_to(ROOT)) if json_path.is_relative_to(ROOT) else str(json_path),
                "settings": settings, "runs": [], "skipped": {}, "configs": {}}  # fmt: skip
    data["runs"].append(run)
    for name in names:
        try:
            cfg = _config.load(CONFIGS / f"{name}.toml")
        except Exception as e:  # noqa: BLE001
            data["skipped"][name] = f"does not load: {e}"
            log(f"{name}: skipped ({e})")
            continue
        kind = cfg["controller"]["kind"]
        if not set(cfg["tune"]["params"]) <= set(fs.SPACES[kind].names) or cfg["tune"]["keep_gamma_bound"]:
            data["skipped"][name] = "tune refuses it or keeps the gamma floor (not covered)"
            log(f"{name}: skipped")
            continue
        log(f"{name}: start ({uptime()})")
        res = study_config(name, cfg, args)
        res["run"] = len(data["runs"]) - 1
        data["configs"][name] = res
        run["wall_s"] = time.perf_counter() - T0
        run["uptime_end"] = uptime()
        write_text(json_path, json.dumps(jsonable(data), indent=1))  # progress: after each config
        log(f"{name}: done in {res['wall_s']:.0f} s")
    run["wall_s"] = time.perf_counter() - T0
    run["uptime_end"] = uptime()
    write_text(json_path, json.dumps(jsonable(data), indent=1))
    write_text(md_path, report(data))
    log(f"wrote {json_path} and {md_path}; {run['uptime_end']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
