"""Pareto front of tracking error against chattering, by sweeping the chattering weight.

Every weight w_c starts from the paper's gains (36), poles (33) and Table 1 set 2, and is tuned
(delta, gamma, poles; Adam in the unconstrained coordinates of :mod:`fosmc_jax.search`) on
the objective of ``fosmc tune``:

    J = mean_i [ mean_j rms_error_ij / e_ref + w_c * mean_j chattering_ij / c_ref ]

over the arm with payloads 0 and 10 kg, trained on the Euler surrogate (``--train-dt``). All
weights are tuned at once: the whole optimizer loop (loss, gradient, Adam) is ``vmap``-ed over
the weights, because one rollout is latency-bound (3x3 and 9x9 arithmetic per step), so a
batch of 8 weights x 2 payloads costs about twice one weight's time, not eight times (measured
and printed). The tuned parameters are then re-evaluated on the plain simulator (Euler,
dt = 1e-4, 4 s), next to Table 1's three sets and SGN at the paper's gains on the same batch.

    .venv/bin/python tuning/pareto.py [--weights 8] [--steps 40] [--lr 0.15] [--train-dt 1e-3]

Writes tuning/results/pareto.{json,md,png}. The helpers :func:`load_problems`, :func:`make_loss`
and :func:`plain_metrics` are shared with tuning/baselines.py and tuning/gradient_study.py.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import platform
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import optax  # noqa: E402

from fosmc_jax import config as _config  # noqa: E402
from fosmc_jax import paper, simulate_batch  # noqa: E402
from fosmc_jax import search as fs  # noqa: E402
from fosmc_jax.io import save_figure, write_text  # noqa: E402

HERE = pathlib.Path(__file__).parent
OUT = HERE / "results"
CONFIG = HERE / "configs" / "arm_set2.toml"


def log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)


def load_problems(config=CONFIG, train_dt: float | None = 1e-3, t_final: float | None = None):
    """(plain, train) :class:`fosmc_jax.search.Problem` of a config, as ``fosmc tune`` builds
    them (``train`` uses ``train_dt``; ``t_final`` overrides both horizons), and p0."""
    cfg = _config.load(config)
    if t_final is not None:
        cfg = _config.replace(cfg, sim={"t_final": t_final})
    built = _config.build(cfg)
    plain = fs.Problem(built.plants, built.base, built.reference, built.X0s, built.dt,
                       dict(built.options, save_every=0))  # fmt: skip
    tcfg = _config.replace(cfg, sim={"dt": train_dt}) if train_dt else cfg
    tb = _config.build(tcfg)
    train = fs.Problem(tb.plants, tb.base, tb.reference, tb.X0s, tb.dt,
                       dict(tb.options, save_every=0, checkpoint_every=cfg["tune"]["remat_steps"]))  # fmt: skip
    p0 = fs.Tunable(built.base.delta, built.base.gamma, built.base.poles)
    return plain, train, p0


def rollout_metrics(problem: fs.Problem, p: fs.Tunable, switching: str | None = None):
    """(rms_error, chattering, diverged) per rollout, (B, 3), (B, 3), (B,), traced-friendly."""
    ctrl = problem.base._replace(delta=p.delta, gamma=p.gamma, poles=p.poles)
    opts = {k: v for k, v in problem.options.items() if not (k == "checkpoint_every" and switching)}
    if switching:
        opts["switching"] = switching
    r = simulate_batch(problem.plants, ctrl, problem.reference, problem.X0s, problem.dt, **opts)
    return r.metrics.rms_error, r.metrics.chattering, r.diverged


def refs(train: fs.Problem, p0: fs.Tunable) -> tuple[float, float]:
    """The objective's scales: batch means of rms error and chattering at p0 (training sim)."""
    e, c, _ = jax.jit(lambda p: rollout_metrics(train, p))(p0)
    return float(jnp.mean(e)), float(jnp.mean(c))


def make_loss(train: fs.Problem, e_ref: float, c_ref: float):
    """loss(u, w_c) -> mean_i J_i with the library's rollout_costs; u in internal coordinates."""

    def loss(u: fs.Tunable, w_c):
        e, c, div = rollout_metrics(train, fs.to_physical(u, train.base))
        metrics = type("M", (), {"rms_error": e, "chattering": c})
        obj = fs.Objective(1.0, w_c, e_ref, c_ref, scale="linear", chattering_metric="chattering")  # as committed
        J, _, _ = fs.rollout_costs(metrics, div, obj)
        return jnp.mean(J)

    return loss


def plain_metrics(plain: fs.Problem, params: fs.Tunable, switching: str | None = None) -> dict:
    """Plain-simulator metrics of a stack of parameter sets (leading axis K), vmapped:
    mean over rollouts and joints of rms_error (rad) and chattering (V/s), per joint too."""
    f = jax.jit(jax.vmap(lambda p: rollout_metrics(plain, p, switching)))
    e, c, d = (np.asarray(x) for x in f(params))
    return {
        "rms_error": e.mean(axis=(1, 2)).tolist(),
        "chattering": c.mean(axis=(1, 2)).tolist(),
        "rms_error_per_joint": e.mean(axis=1).tolist(),
        "chattering_per_joint": c.mean(axis=1).tolist(),
        "diverged": d.sum(axis=1).tolist(),
    }


def stack(ps: list[fs.Tunable]) -> fs.Tunable:
    return jax.tree.map(lambda *x: jnp.stack(x), *ps)


def tune_vmapped(loss, u0: fs.Tunable, weights, steps: int, lr: float, clip: float = 1.0):
    """Adam (cosine schedule, global-norm clipping) on every weight at once, vmapped.
    Returns final internal parameters (K, ...) and the loss history (steps, K)."""
    opt = optax.chain(optax.clip_by_global_norm(clip), optax.adam(optax.cosine_decay_schedule(lr, steps, 0.1)))
    K = weights.shape[0]
    u = jax.tree.map(lambda x: jnp.broadcast_to(x, (K,) + x.shape), u0)
    state = jax.vmap(opt.init)(u)

    @jax.jit
    def step(u, state):
        value, grad = jax.vmap(jax.value_and_grad(loss))(u, weights)
        grad = jax.tree.map(lambda g: jnp.where(jnp.isfinite(g), g, 0.0), grad)
        updates, state = jax.vmap(opt.update)(grad, state, u)
        return optax.apply_updates(u, updates), state, value, jax.vmap(optax.tree.norm)(grad)

    history, step_s, t0 = [], [], time.perf_counter()
    for k in range(steps):
        t1 = time.perf_counter()
        u, state, value, gnorm = jax.block_until_ready(step(u, state))
        step_s.append(time.perf_counter() - t1)
        history.append(np.asarray(value).tolist())
        if k == 0 or (k + 1) % 5 == 0 or k + 1 == steps:
            log(f"step {k + 1:3d}/{steps}  loss {np.array2string(np.asarray(value), precision=3)}  "
                f"|grad| max {float(jnp.max(gnorm)):.2e}  {time.perf_counter() - t0:6.1f} s")  # fmt: skip
    return u, history, float(np.median(step_s[1:] or step_s))


def non_dominated(x, y) -> list[bool]:
    """True where no other point is at least as good in both and better in one."""
    x, y = np.asarray(x), np.asarray(y)
    return [not np.any((x <= x[i]) & (y <= y[i]) & ((x < x[i]) | (y < y[i]))) for i in range(len(x))]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--weights", type=int, default=8)
    ap.add_argument("--wmin", type=float, default=1e-3)
    ap.add_argument("--wmax", type=float, default=10.0)
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--lr", type=float, default=0.15)
    ap.add_argument("--train-dt", type=float, default=1e-3)
    args = ap.parse_args()
    t_start = time.perf_counter()
    plain, train, p0 = load_problems(CONFIG, args.train_dt)
    e_ref, c_ref = refs(train, p0)
    log(f"scales at p0 (training sim): e_ref {e_ref:.4g} rad, c_ref {c_ref:.4g} V/s")
    weights = jnp.asarray(np.logspace(np.log10(args.wmin), np.log10(args.wmax), args.weights))
    loss = make_loss(train, e_ref, c_ref)
    u0 = fs.to_internal(p0, train.base)

    # vmap or loop? one weight's value_and_grad against a step of the vmapped loop (all weights)
    one = jax.jit(jax.value_and_grad(loss))
    jax.block_until_ready(one(u0, weights[0]))
    t0 = time.perf_counter()
    jax.block_until_ready(one(u0, weights[0]))
    timing = {"one": time.perf_counter() - t0}
    log(f"one value_and_grad: {timing['one']:.2f} s")
    t_tune = time.perf_counter()
    u, history, timing["vmapped"] = tune_vmapped(loss, u0, weights, args.steps, args.lr)
    t_tune = time.perf_counter() - t_tune
    log(
        f"vmapped step (all {len(weights)} weights): {timing['vmapped']:.2f} s = "
        f"{timing['vmapped'] / (len(weights) * timing['one']):.2f} of a loop over weights"
    )
    tuned = jax.vmap(lambda v: fs.to_physical(v, train.base))(u)

    log("plain-simulator evaluation (Euler, dt = 1e-4, 4 s)")
    front = plain_metrics(plain, tuned)
    tables = plain_metrics(plain, stack([p0._replace(delta=jnp.asarray(d)) for d in paper.DELTA_SETS]))
    sgn = plain_metrics(plain, stack([p0]), switching="sign")
    nd = non_dominated(front["rms_error"], front["chattering"])
    dominated_by = []
    for k in range(3):
        e, c = tables["rms_error"][k], tables["chattering"][k]
        dominated_by.append([i for i in range(len(weights))
                             if front["rms_error"][i] < e and front["chattering"][i] < c])  # fmt: skip
    result = {
        "command": "python tuning/pareto.py " + " ".join(f"--{k.replace('_', '-')} {v}" for k, v in vars(args).items()),
        "config": str(CONFIG.relative_to(HERE.parent)),
        "batch": "arm, payloads 0 and 10 kg",
        "train": f"euler, dt = {args.train_dt} s, 4 s",
        "plain": "euler, dt = 1e-4 s, 4 s, float64",
        "objective_scales": {"e_ref_rad": e_ref, "c_ref_V_per_s": c_ref},
        "weights_chattering": np.asarray(weights).tolist(),
        "timing_s": {**timing, "tuning": t_tune, "total": time.perf_counter() - t_start},
        "strategy": "vmap over weights",
        "tuned": {
            "params": {k: np.asarray(v).tolist() for k, v in tuned._asdict().items()},
            **front,
            "non_dominated": nd,
        },  # fmt: skip
        "table1": tables,
        "sgn": sgn,
        "table1_dominated_by_tuned": dominated_by,
        "front_dominates_table1": all(len(d) > 0 for d in dominated_by),
        "history_loss": history,
        "machine": f"{platform.machine()} CPU, jax {jax.__version__}",
    }
    OUT.mkdir(parents=True, exist_ok=True)
    write_text(OUT / "pareto.json", json.dumps(result, indent=1))
    write_md(result)
    plot(result)
    log(f"wrote {OUT}/pareto.{{json,md,png}} in {time.perf_counter() - t_start:.0f} s")


def write_md(r: dict) -> None:
    lines = [
        "# Pareto front: tracking error vs chattering (generated by tuning/pareto.py)", "",
        f"Command: `{r['command']}`; batch: {r['batch']}; trained on {r['train']}, evaluated on the plain "
        f"simulator ({r['plain']}); every weight starts from the paper's gains (36), poles (33) and "
        f"Table 1 set 2; tuned: delta, gamma, poles. Strategy: {r['strategy']} (one value_and_grad "
        f"{r['timing_s']['one']:.2f} s, one optimizer step of all {len(r['weights_chattering'])} weights vmapped "
        f"{r['timing_s']['vmapped']:.2f} s, median). Tuning {r['timing_s']['tuning']:.0f} s, total "
        f"{r['timing_s']['total']:.0f} s on {r['machine']} (2 shared cores).", "",
        "Metrics: mean over the 2 rollouts and 3 joints of the plain-simulator rms error (rad) and "
        "chattering (total variation rate of U, V/s).", "",
        "| point | w_c | rms error (rad) | chattering (V/s) | non-dominated | diverged |",
        "|---|---|---|---|---|---|",
    ]  # fmt: skip
    t = r["tuned"]
    for i, w in enumerate(r["weights_chattering"]):
        lines.append(f"| tuned {i} | {w:.3g} | {t['rms_error'][i]:.4g} | {t['chattering'][i]:.4g} | "
                     f"{'yes' if t['non_dominated'][i] else 'no'} | {t['diverged'][i]} |")  # fmt: skip
    for k in range(3):
        lines.append(f"| Table 1 set {k + 1} | - | {r['table1']['rms_error'][k]:.4g} | "
                     f"{r['table1']['chattering'][k]:.4g} | - | {r['table1']['diverged'][k]} |")  # fmt: skip
    lines.append(f"| SGN, paper gains | - | {r['sgn']['rms_error'][0]:.4g} | {r['sgn']['chattering'][0]:.4g} | - | "
                 f"{r['sgn']['diverged'][0]} |")  # fmt: skip
    lines += ["", "Table 1 sets dominated (lower error and lower chattering) by tuned points: "
              + "; ".join(f"set {k + 1}: {d if d else 'none'}" for k, d in enumerate(r["table1_dominated_by_tuned"]))
              + f". Front dominates all of Table 1: **{'yes' if r['front_dominates_table1'] else 'no'}**.", ""]  # fmt: skip
    write_text(OUT / "pareto.md", "\n".join(lines))


def plot(r: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = r["tuned"]
    fig, ax = plt.subplots(figsize=(7, 5))
    c, e = np.asarray(t["chattering"]), np.asarray(t["rms_error"])
    nd = np.asarray(t["non_dominated"])
    order = np.argsort(c)
    ax.plot(c[order], e[order], "-", color="0.7", zorder=1)
    sc = ax.scatter(c, e, c=np.log10(r["weights_chattering"]), cmap="viridis", s=40, zorder=2,
                    edgecolors=np.where(nd, "k", "none"))  # fmt: skip
    fig.colorbar(sc, ax=ax, label="log10 chattering weight w_c")
    for k, m in zip(range(3), ("s", "D", "^")):
        ax.scatter(r["table1"]["chattering"][k], r["table1"]["rms_error"][k], marker=m, color="tab:red", s=60,
                   label=f"Table 1 set {k + 1} (ratio)")  # fmt: skip
    ax.scatter(r["sgn"]["chattering"][0], r["sgn"]["rms_error"][0], marker="*", color="tab:orange", s=120,
               label="SGN, paper gains")  # fmt: skip
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("chattering, mean total variation rate of U (V/s)")
    ax.set_ylabel("rms tracking error, mean (rad)")
    ax.set_title("Arm, payloads 0 and 10 kg; plain Euler dt = 1e-4 s, 4 s")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    save_figure(fig, OUT / "pareto.png")


if __name__ == "__main__":
    main()
