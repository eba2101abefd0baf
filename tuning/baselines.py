"""Gradient tuning against derivative-free baselines at an equal budget of rollouts.

The objective is the one of ``fosmc tune --config tuning/configs/arm_set2.toml``: arm, payloads 0
and 10 kg, Euler surrogate dt = 1e-3 s, 4 s, J = mean_i [rms_i / e_ref + chattering_i / c_ref]
(both weights 1; the scales are the batch means at the start, so J = 2 there), in the
unconstrained coordinates u of :mod:`fosmc_jax._tuning` (log delta, log gamma, log(-poles):
15 numbers), starting from the paper's gains and Table 1 set 2.

Methods:
- ``gradient``: the history of the ``fosmc tune`` run in tuning/results/tune_arm/result.json
  (Adam, lr 0.1, cosine, 60 steps, reverse mode). One step = one value_and_grad of the 2-rollout
  batch, counted as 2 rollouts times a factor: 1 (forward rollouts only) and the measured time
  ratio of value_and_grad to the forward loss (printed, both are reported).
- ``random``: u0 + sigma N(0, I), sigma = 1, best so far.
- ``cma``: CMA-ES (numpy, Hansen's tutorial defaults), lambda = 16, sigma0 = 1 from u0.
Candidates are evaluated ``vmap``-ed through simulate_batch (16 candidates x 2 payloads per call).
A candidate costs 2 rollouts.

    .venv/bin/python tuning/baselines.py [--budget 1000] [--seed 0]

Writes tuning/results/baselines.{json,md,png}.
"""

from __future__ import annotations

import argparse
import json
import platform
import time

import jax
import jax.numpy as jnp
import numpy as np
from pareto import CONFIG, OUT, load_problems, log, make_loss, plain_metrics

from fosmc_jax import _tuning as T
from fosmc_jax._io import write_text
from fosmc_jax._plots import save_figure

POP = 16


def flatten(u: T.Tunable) -> np.ndarray:
    return np.concatenate([np.ravel(np.asarray(x)) for x in u])


def unflatten(x, like: T.Tunable) -> T.Tunable:
    out, i = [], 0
    for leaf in like:
        n = int(np.size(leaf))
        out.append(jnp.reshape(x[..., i : i + n], x.shape[:-1] + np.shape(leaf)))
        i += n
    return T.Tunable(*out)


def cma_es(f_batch, x0, sigma0, budget_candidates, seed):
    """Minimal CMA-ES (Hansen, 'The CMA Evolution Strategy: A Tutorial', default parameters).
    ``f_batch`` maps (lambda, n) -> (lambda,). Returns (evaluations used, best so far) lists."""
    rng = np.random.default_rng(seed)
    n, lam = x0.size, POP
    mu = lam // 2
    w = np.log(mu + 0.5) - np.log(np.arange(1, mu + 1))
    w /= w.sum()
    mueff = 1 / np.sum(w**2)
    cc, cs = (4 + mueff / n) / (n + 4 + 2 * mueff / n), (mueff + 2) / (n + mueff + 5)
    c1 = 2 / ((n + 1.3) ** 2 + mueff)
    cmu = min(1 - c1, 2 * (mueff - 2 + 1 / mueff) / ((n + 2) ** 2 + mueff))
    damps = 1 + 2 * max(0, np.sqrt((mueff - 1) / (n + 1)) - 1) + cs
    chiN = np.sqrt(n) * (1 - 1 / (4 * n) + 1 / (21 * n**2))
    m, sigma, C = x0.copy(), sigma0, np.eye(n)
    pc, ps = np.zeros(n), np.zeros(n)
    used, best, trace = 0, np.inf, []
    while used + lam <= budget_candidates:
        evals, B = np.linalg.eigh(C)
        D = np.sqrt(np.maximum(evals, 1e-20))
        z = rng.standard_normal((lam, n))
        y = z * D @ B.T
        x = m + sigma * y
        fx = f_batch(x)
        used += lam
        best = min(best, float(np.min(fx)))
        trace.append((used, best))
        idx = np.argsort(fx)[:mu]
        y_w = w @ y[idx]
        m = m + sigma * y_w
        Cinvsqrt = B @ np.diag(1 / D) @ B.T
        ps = (1 - cs) * ps + np.sqrt(cs * (2 - cs) * mueff) * Cinvsqrt @ y_w
        hsig = np.linalg.norm(ps) / np.sqrt(1 - (1 - cs) ** (2 * used / lam)) / chiN < 1.4 + 2 / (n + 1)
        pc = (1 - cc) * pc + hsig * np.sqrt(cc * (2 - cc) * mueff) * y_w
        C = ((1 - c1 - cmu) * C + c1 * (np.outer(pc, pc) + (1 - hsig) * cc * (2 - cc) * C)
             + cmu * (y[idx].T * w) @ y[idx])  # fmt: skip
        sigma *= np.exp((cs / damps) * (np.linalg.norm(ps) / chiN - 1))
    return trace, m


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--budget", type=int, default=960, help="rollouts per derivative-free method")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    t_start = time.perf_counter()
    tune = json.loads((OUT / "tune_arm" / "result.json").read_text())
    obj = tune["objective"]
    plain, train, p0 = load_problems(CONFIG, tune["config"]["tune"]["train_dt"])
    loss = make_loss(train, obj["error_ref"], obj["chattering_ref"])
    u0 = T.to_internal(p0, train.base)
    x0 = flatten(u0)
    per_candidate = jax.tree.leaves(train.plants)[0].shape[0] * train.X0s.shape[0]  # payloads x initial states
    batch_loss = jax.jit(jax.vmap(lambda x: loss(unflatten(x, u0), 1.0)))

    # cost of one gradient relative to one forward evaluation of the same 2-rollout batch
    fwd = jax.jit(lambda u: loss(u, 1.0))
    vag = jax.jit(jax.value_and_grad(lambda u: loss(u, 1.0)))
    timing = {}
    for name, f in (("forward", fwd), ("value_and_grad", vag)):
        jax.block_until_ready(f(u0))
        t0 = time.perf_counter()
        for _ in range(2):
            jax.block_until_ready(f(u0))
        timing[name] = (time.perf_counter() - t0) / 2
    factor = timing["value_and_grad"] / timing["forward"]
    log(f"forward {timing['forward']:.2f} s, value_and_grad {timing['value_and_grad']:.2f} s: factor {factor:.1f}")

    def f_batch(x):
        t0 = time.perf_counter()
        v = np.asarray(batch_loss(jnp.asarray(x)))
        timing.setdefault("batch16", []).append(time.perf_counter() - t0)
        return np.where(np.isfinite(v), v, 1e3)

    n_cand = args.budget // per_candidate
    rng = np.random.default_rng(args.seed)
    rs_trace, best, best_x, used = [], np.inf, x0, 0
    log(f"random search: {n_cand} candidates in batches of {POP}")
    while used + POP <= n_cand:
        x = x0 + rng.standard_normal((POP, x0.size))
        fx = f_batch(x)
        used += POP
        if fx.min() < best:
            best, best_x = float(fx.min()), x[np.argmin(fx)]
        rs_trace.append((used, best))
    log(f"random search best {best:.4f}")
    log("CMA-ES")
    cma_trace, cma_m = cma_es(f_batch, x0, 1.0, n_cand, args.seed)
    log(f"CMA-ES best {cma_trace[-1][1]:.4f}")

    g_loss = np.minimum.accumulate(np.asarray(tune["history"]["loss"]))
    steps = np.arange(1, g_loss.size + 1)
    finals = {
        "gradient": T.Tunable(*(jnp.asarray(tune["final"]["params"][k]) for k in ("delta", "gamma", "poles"))),
        "random": T.to_physical(unflatten(jnp.asarray(best_x), u0), train.base),
        "cma (mean)": T.to_physical(unflatten(jnp.asarray(cma_m), u0), train.base),
    }
    log("plain-simulator evaluation of the three results")
    ev = plain_metrics(plain, jax.tree.map(lambda *a: jnp.stack(a), *finals.values()))
    result = {
        "command": f"python tuning/baselines.py --budget {args.budget} --seed {args.seed}",
        "objective": "fosmc tune objective of tuning/configs/arm_set2.toml, surrogate euler dt = "
        f"{tune['config']['tune']['train_dt']} s; J = 2 at the start",  # fmt: skip
        "rollouts_per_candidate": per_candidate,
        "timing_s": {
            "forward": timing["forward"],
            "value_and_grad": timing["value_and_grad"],
            "batch16_median": float(np.median(timing["batch16"])),
        },  # fmt: skip
        "gradient_cost_factor": factor,
        "gradient": {
            "rollouts_factor1": (steps * per_candidate).tolist(),
            "rollouts_measured": (steps * per_candidate * factor).tolist(),
            "best": g_loss.tolist(),
        },  # fmt: skip
        "random": {"rollouts": [u * per_candidate for u, _ in rs_trace], "best": [b for _, b in rs_trace]},
        "cma": {"rollouts": [u * per_candidate for u, _ in cma_trace], "best": [b for _, b in cma_trace]},
        "plain_final": {k: {m: ev[m][i] for m in ("rms_error", "chattering")} for i, k in enumerate(finals)},
        "total_s": time.perf_counter() - t_start,
        "machine": f"{platform.machine()} CPU, jax {jax.__version__}",
    }
    for name in ("random", "cma"):
        b = result[name]["best"]
        result[name]["final_best"] = b[-1] if b else None
    targets = {}
    for target in (1.8, 1.6, 1.5, 1.4):
        row = {}
        for name, xs, ys in (("gradient (factor 1)", result["gradient"]["rollouts_factor1"], g_loss),
                             ("gradient (measured factor)", result["gradient"]["rollouts_measured"], g_loss),
                             ("random", result["random"]["rollouts"], result["random"]["best"]),
                             ("cma", result["cma"]["rollouts"], result["cma"]["best"])):  # fmt: skip
            hit = [x for x, y in zip(xs, ys) if y <= target]
            row[name] = round(float(hit[0])) if hit else None
        targets[str(target)] = row
    result["rollouts_to_reach"] = targets
    write_text(OUT / "baselines.json", json.dumps(result, indent=1))
    write_md(result)
    plot(result)
    log(f"wrote {OUT}/baselines.{{json,md,png}} in {time.perf_counter() - t_start:.0f} s")


def write_md(r: dict) -> None:
    names = list(next(iter(r["rollouts_to_reach"].values())))
    lines = [
        "# Gradient tuning vs derivative-free baselines (generated by tuning/baselines.py)", "",
        f"Command: `{r['command']}`; objective: {r['objective']}. A candidate = {r['rollouts_per_candidate']} "
        f"rollouts of 4,000 steps. Forward loss {r['timing_s']['forward']:.2f} s, value_and_grad "
        f"{r['timing_s']['value_and_grad']:.2f} s (reverse mode): a gradient step costs "
        f"{r['gradient_cost_factor']:.1f} forward evaluations by wall time; 16 candidates vmapped "
        f"{r['timing_s']['batch16_median']:.2f} s (median). Total {r['total_s']:.0f} s on {r['machine']}.", "",
        "Rollouts needed to reach a best objective value (lower J is better; J = 2 at the start; - = not reached):", "",
        "| target J | " + " | ".join(names) + " |", "|---|" + "---|" * len(names),
    ]  # fmt: skip
    for t, row in r["rollouts_to_reach"].items():
        lines.append(f"| {t} | " + " | ".join("-" if row[n] is None else str(row[n]) for n in names) + " |")
    lines += ["", "Best J at the end: gradient (60 steps) "
              f"{r['gradient']['best'][-1]:.4f}; random {r['random']['final_best']:.4f}; CMA-ES "
              f"{r['cma']['final_best']:.4f}.", "",
              "Plain-simulator metrics (Euler dt = 1e-4, mean over rollouts and joints) of each method's result:", "",
              "| method | rms error (rad) | chattering (V/s) |", "|---|---|---|"]  # fmt: skip
    for k, v in r["plain_final"].items():
        lines.append(f"| {k} | {v['rms_error']:.4g} | {v['chattering']:.4g} |")
    write_text(OUT / "baselines.md", "\n".join(lines) + "\n")


def plot(r: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    g = r["gradient"]
    ax.plot(g["rollouts_factor1"], g["best"], "-", color="tab:blue", label="gradient (Adam), 1 rollout per rollout")
    ax.plot(g["rollouts_measured"], g["best"], "--", color="tab:blue",
            label=f"gradient, x{r['gradient_cost_factor']:.1f} (measured time ratio)")  # fmt: skip
    ax.plot(r["random"]["rollouts"], r["random"]["best"], "-", color="tab:green", label="random search, sigma = 1")
    ax.plot(r["cma"]["rollouts"], r["cma"]["best"], "-", color="tab:red", label="CMA-ES, lambda = 16")
    ax.set_xscale("log")
    ax.set_xlabel("rollouts used (4 s, Euler dt = 1e-3 s)")
    ax.set_ylabel("best objective J so far (dimensionless; 2 at start)")
    ax.set_title("Arm, payloads 0 and 10 kg, start: paper gains + Table 1 set 2")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    save_figure(fig, OUT / "baselines.png")


if __name__ == "__main__":
    main()
