"""Pareto fronts of tracking error against chattering (``fosmc front``).

A front is found in three stages, within a wall-time budget:

1. global: ``candidates`` points around the start (delta x 10^[-3, 1.5], poles x 10^[0, 2],
   gamma x 10^[-0.5, 0.5]): a log grid of factors common to the joints (about half), the rest
   log-uniform per joint, simulated in vmapped chunks on the training problem;
2. refinement: up to ``points`` non-dominated candidates, spread along the front, start
   Adam runs (vmapped over the starts) on the weighted log objective of
   :mod:`fosmc_jax._tuning`, log E + w_k log C, with w_k the slope of the front at start k
   (so each run moves along the front's normal, not to one end of it);
3. every candidate and every refined point is re-evaluated on the plain problem; the front is
   the non-dominated set in (mean ``rms_error``, mean ``chattering_hf``), sorted by
   chattering.

The stage sizes are fixed once (from the budget and the first timings, or given) and stored
in the checkpoint, so a resumed run ends where an uninterrupted one does.
"""

from __future__ import annotations

import copy
import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from . import _config
from . import _paper as paper
from . import _tuning as T
from ._io import jsonable, write_text
from ._metrics import METRIC_NAMES

#: The two metrics a front is drawn in (means over rollouts and joints).
AXES = ("rms_error", "chattering_hf")
#: log10 ranges of the global stage's scale factors, per joint.
RANGES = {"delta": (-3.0, 1.5), "poles": (0.0, 2.0), "gamma": (-0.5, 0.5)}


class Settings(NamedTuple):
    points: int = 8  # refined starts (the front may keep more or fewer points)
    budget: float = 300.0  # s, wall time of the whole run
    candidates: int = 0  # global stage size; 0: from the budget
    steps: int = 0  # refinement steps; 0: from the budget
    learning_rate: float = 0.05
    chunk: int = 16  # candidates per vmapped evaluation
    seed: int = 0
    checkpoint_every: int = 5  # refinement steps between checkpoints


def nondominated(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Mask of the points not dominated in (x, y), both minimised (NaN points never kept)."""
    ok = np.isfinite(x) & np.isfinite(y)
    keep = ok.copy()
    for i in np.flatnonzero(ok):
        dominated = ok & (x <= x[i]) & (y <= y[i]) & ((x < x[i]) | (y < y[i]))
        keep[i] = not dominated.any()
    return keep


def sample_candidates(p0: T.Tunable, n: int, seed: int) -> T.Tunable:
    """``n`` parameter sets around p0: p0 itself, then a log grid of common factors (the same
    for every joint) filling about half, then per-joint log-uniform factors, all over
    :data:`RANGES`. Leading axis n."""
    rng = np.random.default_rng(seed)
    g = int((n / 2) ** (1 / 3)) if n >= 16 else 0
    lo, hi = np.array([RANGES[k][0] for k in T.PARAM_NAMES]), np.array([RANGES[k][1] for k in T.PARAM_NAMES])
    grid = np.stack(np.meshgrid(*(np.linspace(a, b, g) for a, b in zip(lo, hi)), indexing="ij"), -1).reshape(-1, 3)
    z = np.zeros((n, 3, 3))  # candidate, parameter, joint
    z[1 : 1 + len(grid)] = grid[:, :, None]
    z[1 + len(grid) :] = rng.uniform(lo[None, :, None], hi[None, :, None], size=(n - 1 - len(grid), 3, 3))
    out = {}
    for i, name in enumerate(T.PARAM_NAMES):
        x = np.asarray(getattr(p0, name))
        f = 10.0 ** z[:, i].reshape((n, 3) + (1,) * (x.ndim - 1))
        out[name] = jnp.asarray(x[None] * f, x.dtype)
    return T.Tunable(**out)


def evaluate_many(problem: T.Problem, params: T.Tunable, chunk: int, log: Callable[[str], None] = print,
                  what: str = "evaluating") -> dict[str, np.ndarray]:  # fmt: skip
    """Mean metrics (over non-diverged rollouts) of every parameter set (leading axis n):
    {metric: (n, 3)} and ``diverged`` (n,) counts, in vmapped chunks of ``chunk``."""
    n = jax.tree.leaves(params)[0].shape[0]
    run = _chunk_evaluator(problem)
    parts, start = [], time.perf_counter()
    for i in range(0, n, chunk):
        part = jax.tree.map(lambda x, i=i: x[i : i + chunk], params)
        size = jax.tree.leaves(part)[0].shape[0]
        if size < chunk:  # pad to the compiled size
            part = jax.tree.map(lambda x, pad=chunk - size: jnp.concatenate([x, jnp.repeat(x[-1:], pad, 0)]), part)
        parts.append(jax.tree.map(lambda x, size=size: np.asarray(x)[:size], run(part)))
        log(f"front: {what} {min(i + chunk, n)}/{n}  {time.perf_counter() - start:7.1f} s")
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def global_stage(problem: T.Problem, obj: T.Objective, p0: T.Tunable, n: int, *, free=T.PARAM_NAMES, seed: int = 0,
                 chunk: int = 16, log: Callable[[str], None] = print) -> tuple[T.Tunable, float]:  # fmt: skip
    """The coarse global stage of ``fosmc tune``: ``n`` candidates of :func:`sample_candidates`
    (frozen parameters kept at p0; p0 itself among them) scored by ``obj`` on their batch-mean
    metrics; returns the best and its score."""
    cands = sample_candidates(p0, n, seed)
    cands = T.Tunable(*(getattr(cands, k) if k in free else jnp.broadcast_to(getattr(p0, k), getattr(cands, k).shape)
                        for k in T.PARAM_NAMES))  # fmt: skip
    m = evaluate_many(problem, cands, chunk, log=log, what="global stage")
    means = type("Means", (), {k: jnp.asarray(v) for k, v in m.items()})
    J = np.asarray(T.rollout_costs(means, jnp.asarray(m["diverged"] > 0), obj)[0])
    best = int(np.nanargmin(J))
    return jax.tree.map(lambda x: x[best], cands), float(J[best])


def _chunk_evaluator(problem: T.Problem):
    @jax.jit
    def run(params):
        def one(p):
            r = problem.simulate(p, checkpoint_every=0)
            ok = ~r.diverged
            mean = lambda x: jnp.sum(jnp.where(ok[:, None], x, 0), 0) / jnp.maximum(jnp.sum(ok), 1)
            out = {name: jnp.where(jnp.any(ok), mean(getattr(r.metrics, name)), jnp.nan) for name in METRIC_NAMES}
            return dict(out, diverged=jnp.sum(r.diverged))

        return jax.vmap(one)(params)

    return run


def _axes(m: dict) -> tuple[np.ndarray, np.ndarray]:
    return np.mean(m[AXES[0]], axis=-1), np.mean(m[AXES[1]], axis=-1)


def pick_starts(m: dict, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Up to ``k`` non-dominated candidates spread evenly (in log chattering) along the front,
    and the front's slope -d log E / d log C at each (the refinement weights)."""
    e, c = _axes(m)
    idx = np.flatnonzero(nondominated(e, c))
    idx = idx[np.argsort(c[idx])]
    if len(idx) > k:
        idx = idx[np.unique(np.round(np.linspace(0, len(idx) - 1, k)).astype(int))]
    le, lc = np.log(e[idx]), np.log(c[idx])
    if len(idx) > 1:
        slope = -np.gradient(le, lc) if np.all(np.diff(lc) > 0) else np.ones(len(idx))
    else:
        slope = np.ones(1)
    return idx, np.clip(np.nan_to_num(slope, nan=1.0), 0.05, 20.0)


def _refine_loss(problem: T.Problem, obj: T.Objective):
    def loss(u: T.Tunable, w):
        r = problem.simulate(T.to_physical(u, problem.base), fast=False)
        J, e, c = T.rollout_costs(r.metrics, r.diverged, obj._replace(weight_chattering=w))
        return T.aggregate(J, obj)

    return loss


def run(
    train: T.Problem,
    plain: T.Problem,
    p0: T.Tunable,
    settings: Settings,
    *,
    checkpoint: Path | None = None,
    resume: bool = False,
    log: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Find the front (see module docstring). Returns {"points": [...], "stages": {...}} with
    every point's parameters, plain mean metrics and diverged count; non-dominated only,
    sorted by chattering."""
    t0 = time.perf_counter()
    state: dict[str, Any] = {}
    if resume and checkpoint is not None and checkpoint.exists():
        header, leaves = T._load(checkpoint)
        state = header
        log(f"front: resumed from {checkpoint} ({header['stage']})")
    n_cand = state.get("candidates") or settings.candidates
    if not n_cand:  # from the budget: time one chunk, then spend 40% of the budget on the stage
        probe = sample_candidates(p0, settings.chunk, settings.seed)
        t = time.perf_counter()
        evaluate_many(train, probe, settings.chunk, log=lambda _: None)  # compiles
        t = time.perf_counter()
        evaluate_many(train, probe, settings.chunk, log=lambda _: None)
        per = (time.perf_counter() - t) / settings.chunk
        n_cand = int(np.clip(0.4 * settings.budget / per, settings.points, 4096)) // settings.chunk * settings.chunk
        n_cand = max(n_cand, settings.chunk)
        log(f"front: one candidate costs {per * 1e3:.1f} ms on the training problem: {n_cand} candidates")
    cands = sample_candidates(p0, n_cand, settings.seed)
    if "global" in state:
        glob = {k: np.asarray(v) for k, v in state["global"].items()}
    else:
        glob = evaluate_many(train, cands, settings.chunk, log=log, what="global stage")
    starts, weights = pick_starts(glob, settings.points)
    log(f"front: global stage done, {len(starts)} refinement starts, weights {np.round(weights, 2).tolist()}")

    e_ref, c_ref = (float(np.nanmean(v[starts])) for v in _axes(glob))
    obj = T.Objective(error_ref=e_ref, chattering_ref=c_ref)
    loss = _refine_loss(train, obj)
    opt = optax.chain(optax.clip_by_global_norm(1.0), optax.adam(settings.learning_rate))
    u = jax.vmap(lambda p: T.to_internal(p, train.base))(jax.tree.map(lambda x: x[starts], cands))
    opt_state = jax.vmap(opt.init)(u)
    step0 = 0
    if state.get("stage") == "refine":
        u, opt_state = jax.tree.unflatten(jax.tree.structure((u, opt_state)), [jnp.asarray(x) for x in leaves])
        step0 = state["step"]

    @jax.jit
    def update(u, opt_state, w):
        def one(u, s, w):
            value, grad = jax.value_and_grad(loss)(u, w)
            finite = jnp.isfinite(value) & jnp.all(jnp.stack([jnp.all(jnp.isfinite(g)) for g in jax.tree.leaves(grad)]))
            grad = jax.tree.map(lambda g: jnp.where(finite, g, 0.0), grad)
            upd, s2 = opt.update(grad, s, u)
            keep = lambda new, old: jax.tree.map(lambda a, b: jnp.where(finite, a, b), new, old)
            return keep(optax.apply_updates(u, upd), u), keep(s2, s), value

        return jax.vmap(one)(u, opt_state, w)

    w = jnp.asarray(weights, jax.tree.leaves(u)[0].dtype)
    steps = state.get("steps") or settings.steps

    def save(stage: str, step: int, leaves=()) -> None:
        if checkpoint is not None:
            header = {"stage": stage, "step": step, "candidates": n_cand, "steps": steps,
                      "global": {k: v.tolist() for k, v in glob.items()}}  # fmt: skip
            T._save(checkpoint, {**header, "leaves": list(leaves)})

    if step0 == 0:
        save("global", 0)
    step, t_ref = step0, time.perf_counter()
    while steps == 0 or step < steps:
        u, opt_state, values = update(u, opt_state, w)
        values = np.asarray(values)
        step += 1
        if step == step0 + 1:
            t_ref = time.perf_counter()  # after the compilation
        if steps == 0 and step == step0 + 2:  # from the budget: spend what is left but 25% on refinement
            per = time.perf_counter() - t_ref
            steps = max(2, int((0.75 * settings.budget - (time.perf_counter() - t0)) / per))
            log(f"front: one refinement step costs {per:.2f} s: {steps} steps")
        log(f"front: refinement step {step}/{steps or '?'}  loss {np.round(values, 3).tolist()}  "
            f"{time.perf_counter() - t0:7.1f} s")  # fmt: skip
        if settings.checkpoint_every and (step % settings.checkpoint_every == 0 or step == steps):
            save("refine", step, jax.tree.leaves((u, opt_state)))

    refined = jax.vmap(lambda v: T.to_physical(v, train.base))(u)
    every = jax.tree.map(lambda a, b: jnp.concatenate([a, b]), cands, refined)
    if _same_simulation(train, plain):  # no surrogate: the global stage's metrics are the plain ones
        fresh = evaluate_many(plain, refined, settings.chunk, log=log, what="plain evaluation")
        final = {k: np.concatenate([glob[k], fresh[k]]) for k in glob}
    else:
        final = evaluate_many(plain, every, settings.chunk, log=log, what="plain evaluation")
    e, c = _axes(final)
    keep = np.flatnonzero(nondominated(e, c))
    keep = keep[np.argsort(c[keep])]
    points = [point_of(jax.tree.map(lambda x, i=i: x[i], every), final, i) for i in keep]
    return {"axes": list(AXES), "points": points,
            "stages": {"candidates": n_cand, "refinement_starts": len(starts), "refinement_steps": steps,
                       "weights": weights.tolist(), "wall_time_s": time.perf_counter() - t0,
                       "from_refinement": int(np.sum(keep >= n_cand))}}  # fmt: skip


def _same_simulation(a: T.Problem, b: T.Problem) -> bool:
    """Whether two problems simulate the same thing (the training problem is no surrogate)."""
    opts = lambda p: {k: v for k, v in p.options.items() if k != "checkpoint_every"}
    return float(a.dt) == float(b.dt) and opts(a) == opts(b) and a.make is b.make and a.keys is b.keys


def point_of(p: T.Tunable, metrics: dict, i: int) -> dict[str, Any]:
    """A front point as JSON: parameters by name, per-joint mean metrics, diverged count."""
    return {"params": {k: np.asarray(v).tolist() for k, v in p._asdict().items()},
            "metrics": {name: np.asarray(metrics[name][i]).tolist() for name in METRIC_NAMES},
            "diverged": int(metrics["diverged"][i])}  # fmt: skip


# ---------------------------------------------------------------------------- the study behind ``fosmc front``


def held_out_config(cfg: dict) -> dict:
    """The config's batch with what training did not see: arm payloads between and beside the
    training ones (2.5, 5, 7.5 kg unless trained on), fresh box samples (linear ``sample`` /
    ``vertices``), fresh noise seeds."""
    held = copy.deepcopy(cfg)
    plant = held["plant"]
    if plant["kind"] == "arm":
        fresh = [p for p in (2.5, 5.0, 7.5) if p not in plant["payloads"]]
        plant["payloads"] = fresh or [(plant["payloads"][0] + 5.0) / 2]
    elif plant["uncertainty"] in ("sample", "vertices"):
        plant["seed"] += 1
    held["sensors"]["seed"] += 1
    return _config.resolve(held)


def references(cfg: dict, chunk: int) -> dict[str, dict]:
    """Plain mean metrics of Table 1's three sets (the config's switching) and SGN, with the
    config's gains and poles, on the config's batch."""
    out = {}
    for label, switching, sets in (("Table 1", cfg["controller"]["switching"], (0, 1, 2)), ("SGN", "sign", (0,))):
        c = copy.deepcopy(cfg)
        c["controller"]["switching"] = switching
        plain, _, p0 = _config.tuning_problems(c)
        ps = T.Tunable(jnp.stack([jnp.asarray(paper.DELTA_SETS[k], p0.delta.dtype) for k in sets]),
                       jnp.stack([p0.gamma] * len(sets)), jnp.stack([p0.poles] * len(sets)))  # fmt: skip
        m = evaluate_many(plain, ps, len(sets), log=lambda _: None)
        for i, k in enumerate(sets):
            out[f"{label} set {k + 1}" if label == "Table 1" else label] = point_of(
                jax.tree.map(lambda x, i=i: x[i], ps), m, i)  # fmt: skip
    return out


def study(cfg: dict, settings: Settings, *, out: Path | None = None, resume: bool = False,
          compare: tuple = (), log: Callable[[str], None] = print) -> dict[str, Any]:  # fmt: skip
    """``fosmc front``: the front of a resolved config (training and plain problems as
    ``fosmc tune`` builds them), each point also evaluated on :func:`held_out_config`'s batch,
    Table 1's sets and SGN beside it. Writes ``front.json`` and ``front.png`` (and a
    checkpoint) to ``out`` when given; returns what ``front.json`` holds."""
    plain, train, p0 = _config.tuning_problems(cfg)
    checkpoint = None if out is None else Path(out) / "checkpoint.npz"
    result = run(train, plain, p0, settings, checkpoint=checkpoint, resume=resume, log=log)
    params = T.Tunable(*(jnp.asarray(np.array([pt["params"][k] for pt in result["points"]]), p0.delta.dtype)
                         for k in T.PARAM_NAMES))  # fmt: skip
    held_plain = _config.tuning_problems(held_out_config(cfg))[0]
    held = evaluate_many(held_plain, params, settings.chunk, log=log, what="held-out evaluation")
    for i, pt in enumerate(result["points"]):
        pt["held_out"] = point_of(jax.tree.map(lambda x, i=i: x[i], params), held, i)["metrics"]
    result["references"] = references(cfg, settings.chunk)
    result["held_out_batch"] = {k: held_out_config(cfg)["plant"][k] for k in ("kind", "payloads", "seed")}
    result["config"] = cfg
    if out is not None:
        from ._plots import plot_front

        write_text(Path(out) / "front.json", json.dumps(jsonable(result), indent=1))
        plot_front(result, [(Path(c).parent.name or str(c), json.loads(Path(c).read_text())) for c in compare],
                   Path(out) / "front.png")  # fmt: skip
        log(f"front: wrote {out}/front.json and {out}/front.png")
    return result
