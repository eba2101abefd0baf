"""The comparison the paper implies: fronts of tracking error against chattering for the FOSMC,
conventional sliding mode with a boundary layer (SMC) and super-twisting, on one config
(by default the realistic preset: the arm at 0 and 10 kg in the sampled, quantized, delayed,
saturating loop), each searched with the same budget and the same method, then re-evaluated
on held-out payloads.

    .venv/bin/python tuning/compare_controllers.py --config tuning/configs/realistic_arm.toml \\
        --evaluations 256 --out tuning/results/compare_controllers

The search, the same for every kind: ``--evaluations`` parameter sets, each the kind's default
parameters (the config's) scaled per joint by 10^z, z log factors over the kind's box
(:data:`BOXES`): the defaults themselves, a grid of common factors (the same z for the three
joints) with about half the budget, the rest per-joint log-uniform draws. Every set runs on the
whole training batch (vmapped chunks); the non-dominated sets in (mean rms_error, mean
chattering_hf) form the kind's front, and each front point is re-run on
:func:`fosmc_jax._front.held_out_config`'s batch (payloads 2.5, 5 and 7.5 kg, fresh noise seeds).
This is a global search, not ``fosmc front`` (which now tunes every kind, each over the same
boxes, fosmc_jax._tuning.SPACES, with local rounds after its global stage): the same method for
the three laws keeps the comparison fair.

Writes ``DIR.json`` (every front point: parameters, training and held-out metrics), ``DIR.md``
(the tables and who wins where) and ``DIR.png`` (the three fronts, log-log).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from fosmc_jax import _config  # noqa: E402
from fosmc_jax import _front as F  # noqa: E402
from fosmc_jax._io import write_text  # noqa: E402
from fosmc_jax._metrics import METRIC_NAMES  # noqa: E402
from fosmc_jax._simulator import simulate_batch  # noqa: E402

#: Per kind, the tunable fields and the log10 range of their scale factors around the config's
#: values. FOSMC: the front's box (fosmc_jax._front.RANGES). SMC: the switching gain k (default
#: 1000) and the layer width phi (10), four and five decades. Super-twisting: k1 (50) and k2
#: (1000), four and five decades.
BOXES = {
    "fosmc": {"delta": (-3.0, 1.5), "gamma": (-0.5, 0.5), "poles": (0.0, 2.0)},
    "smc": {"k": (-2.0, 2.0), "phi": (-3.0, 2.0)},
    "super_twisting": {"k1": (-2.0, 2.0), "k2": (-2.0, 3.0)},
}
LABELS = {"fosmc": "FOSMC (delta, gamma, poles)", "smc": "SMC (k, phi)", "super_twisting": "super-twisting (k1, k2)"}
AXES = ("rms_error", "chattering_hf")


def get_field(ctrl, name: str):
    """The field ``name`` anywhere in a controller (dataclasses and named tuples, depth first)."""
    for child in _children(ctrl):
        if child[0] == name:
            return child[1]
        found = get_field(child[1], name)
        if found is not None:
            return found
    return None


def set_fields(ctrl, values: dict):
    """``ctrl`` with the named fields replaced wherever they sit (see :func:`get_field`)."""
    changes = {}
    for name, value in _children(ctrl):
        changes[name] = values[name] if name in values else set_fields(value, values)
    if dataclasses.is_dataclass(ctrl):
        return dataclasses.replace(ctrl, **{f.name: changes[f.name] for f in dataclasses.fields(ctrl) if f.init})
    if isinstance(ctrl, tuple) and hasattr(ctrl, "_fields"):
        return ctrl._replace(**changes)
    return ctrl


def _children(obj):
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return [(f.name, getattr(obj, f.name)) for f in dataclasses.fields(obj)]
    if isinstance(obj, tuple) and hasattr(obj, "_fields"):
        return list(obj._asdict().items())
    return []


def factors(kind: str, n: int, seed: int) -> np.ndarray:
    """``n`` log factors (n, 3 * fields): 0, a grid of common factors with about n / 2 points,
    per-joint log-uniform draws for the rest."""
    box = BOXES[kind]
    lo = np.repeat([b[0] for b in box.values()], 3)
    hi = np.repeat([b[1] for b in box.values()], 3)
    g = int((n / 2) ** (1 / len(box)) + 1e-9)
    axes = [np.linspace(a, b, g) for a, b in box.values()]
    grid = np.repeat(np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, len(box)), 3, axis=1)
    draws = np.random.default_rng(seed).uniform(lo, hi, size=(n - 1 - len(grid), len(lo)))
    return np.concatenate([np.zeros((1, len(lo))), grid, draws])


def values_of(kind: str, base: dict, z: np.ndarray) -> dict:
    """The fields' values (leading axis n) for log factors z: base value x 10^z per joint (the
    poles' three per joint share their joint's factor)."""
    out = {}
    for i, name in enumerate(BOXES[kind]):
        f = 10.0 ** z[:, 3 * i : 3 * i + 3]
        x = np.asarray(base[name])
        out[name] = jnp.asarray(x[None] * f.reshape(f.shape + (1,) * (x.ndim - 1)), x.dtype)
    return out


def evaluator(problem: _config.Problem):
    """values (leading axis) -> mean metrics over the non-diverged rollouts, and diverged counts."""

    @jax.jit
    def run(values):
        def one(v):
            r = simulate_batch(problem.plants, set_fields(problem.controller, v), problem.reference, problem.X0s,
                               problem.dt, keys=problem.keys, **dict(problem.options, save_every=0))  # fmt: skip
            ok = ~r.diverged
            mean = lambda x: jnp.sum(jnp.where(ok[:, None], x, 0), 0) / jnp.maximum(jnp.sum(ok), 1)
            out = {k: jnp.where(jnp.any(ok), mean(getattr(r.metrics, k)), jnp.nan) for k in METRIC_NAMES}
            return dict(out, diverged=jnp.sum(r.diverged))

        return jax.vmap(one)(values)

    def evaluate(values: dict, chunk: int, what: str) -> dict:
        n = len(next(iter(values.values())))
        parts, t0 = [], time.perf_counter()
        for i in range(0, n, chunk):
            part = {k: v[i : i + chunk] for k, v in values.items()}
            size = len(next(iter(part.values())))
            part = {k: jnp.concatenate([v, jnp.repeat(v[-1:], chunk - size, 0)]) for k, v in part.items()}
            parts.append({k: np.asarray(v)[:size] for k, v in run(part).items()})
            print(f"{what}: {min(i + chunk, n)}/{n}  {time.perf_counter() - t0:6.1f} s", flush=True)
        return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}

    return evaluate


def study(cfg: dict, kind: str, n: int, chunk: int, seed: int) -> dict:
    """One kind's search, front and held-out re-evaluation."""
    cfg = dict(cfg, controller=dict(cfg["controller"], kind=kind))
    train = _config.build(_config.resolve(cfg))
    base = {name: np.asarray(get_field(train.controller, name)) for name in BOXES[kind]}
    z = factors(kind, n, seed)
    t0 = time.perf_counter()
    m = evaluator(train)(values_of(kind, base, z), chunk, f"{kind} search")
    wall = time.perf_counter() - t0
    e, c = (np.nanmean(m[a], axis=1) for a in AXES)
    keep = np.flatnonzero(F.nondominated(e, c))
    keep = keep[np.argsort(c[keep])]
    held = _config.build(_config.resolve(F.held_out_config(cfg)))
    values = values_of(kind, base, z[keep])
    mh = evaluator(held)(values, chunk, f"{kind} held out")
    points = [{"params": {k: np.asarray(v[j]).tolist() for k, v in values.items()},
               "metrics": {k: np.asarray(m[k][i]).tolist() for k in METRIC_NAMES},
               "held_out": {k: np.asarray(mh[k][j]).tolist() for k in METRIC_NAMES},
               "diverged": int(m["diverged"][i]), "held_out_diverged": int(mh["diverged"][j])}
              for j, i in enumerate(keep)]  # fmt: skip
    default = {k: np.asarray(m[k][0]).tolist() for k in METRIC_NAMES}
    return {"kind": kind, "evaluations": n, "search_wall_s": wall, "diverged_sets": int(np.sum(m["diverged"] > 0)),
            "default": {"params": {k: v.tolist() for k, v in base.items()}, "metrics": default},
            "points": points}  # fmt: skip


def _means(p: dict, where: str = "metrics") -> tuple[float, float]:
    return float(np.mean(p[where][AXES[0]])), float(np.mean(p[where][AXES[1]]))


def best_error_below(points: list[dict], chattering: float) -> float:
    """The lowest mean rms_error among front points with mean chattering_hf <= ``chattering``."""
    ok = [e for e, c in map(_means, points) if c <= chattering]
    return min(ok) if ok else np.inf


def markdown(res: dict) -> str:
    kinds = res["kinds"]
    lines = [f"**The three controllers' fronts ({res['config']})**", "",
             f"Command: `{res['command']}` ({res['wall_s']:.0f} s in all, compilations and held-out runs included). "
             f"{res['evaluations']} evaluations per kind, load average "
             f"{res['load_before']} before and {res['load_after']} after; jax {res['jax']}.", "",
             "| kind | search wall s | front points | diverged sets | default: rms_error (rad) / chattering_hf (V) | "
             "lowest rms_error on the front (rad) | lowest chattering_hf on the front (V) | "
             "held-out / training rms_error (range over front points) |",
             "|---|---:|---:|---:|---|---:|---:|---|"]  # fmt: skip
    for k in kinds:
        r = res["results"][k]
        pts = r["points"]
        e = [_means(p)[0] for p in pts]
        c = [_means(p)[1] for p in pts]
        ratio = [_means(p, "held_out")[0] / _means(p)[0] for p in pts]
        d = _means(r["default"])
        lines.append(f"| {LABELS[k]} | {r['search_wall_s']:.0f} | {len(pts)} | {r['diverged_sets']} | "
                     f"{d[0]:.3g} / {d[1]:.3g} | {min(e):.3g} | {min(c):.3g} | "
                     f"{min(ratio):.2f}-{max(ratio):.2f} |")  # fmt: skip
    levels = res["chattering_levels"]
    lines += ["", "Best mean rms_error (rad) on each front at a chattering budget (mean chattering_hf <= level):", "",
              "| chattering_hf <= (V) | " + " | ".join(LABELS[k] for k in kinds) + " | best |",
              "|---:|" + "---:|" * (len(kinds) + 1)]  # fmt: skip
    for lv in levels:
        best = {k: best_error_below(res["results"][k]["points"], lv) for k in kinds}
        win = min(best, key=best.get)
        cells = " | ".join("-" if not np.isfinite(best[k]) else f"{best[k]:.3g}" for k in kinds)
        lines.append(f"| {lv:g} | {cells} | {LABELS[win] if np.isfinite(best[win]) else '-'} |")
    lines += ["", "Front points of each kind dominated by a point of another kind's front:", ""]
    for k in kinds:
        mine = [_means(p) for p in res["results"][k]["points"]]
        others = [_means(p) for o in kinds if o != k for p in res["results"][o]["points"]]
        dom = sum(any(oe <= e and oc <= c and (oe < e or oc < c) for oe, oc in others) for e, c in mine)
        lines.append(f"- {LABELS[k]}: {dom} of {len(mine)}")
    return "\n".join(lines) + "\n"


def plot(res: dict, path: Path) -> None:
    fig, ax = plt.subplots(figsize=(7.5, 5.5))
    for k, mark in zip(res["kinds"], "os^"):
        pts = res["results"][k]["points"]
        e, c = np.array([_means(p) for p in pts]).T
        ax.plot(c, e, marker=mark, ls="-", label=f"{LABELS[k]}: training (0, 10 kg)")
        eh, ch = np.array([_means(p, "held_out") for p in pts]).T
        ax.plot(ch, eh, marker=mark, ls=":", mfc="none", color=ax.lines[-1].get_color(),
                label=f"{LABELS[k]}: held out (2.5, 5, 7.5 kg)")  # fmt: skip
        d = _means(res["results"][k]["default"])
        ax.plot(d[1], d[0], marker="*", ms=14, ls="none", color=ax.lines[-1].get_color(), label=f"{k} defaults")
    ax.set(xscale="log", yscale="log", xlabel="mean chattering_hf (V)", ylabel="mean rms tracking error (rad)",
           title=f"Fronts at {res['evaluations']} evaluations each ({Path(res['config']).name})")  # fmt: skip
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    tmp = path.with_suffix(".tmp.png")
    fig.savefig(tmp, dpi=130)
    plt.close(fig)
    tmp.replace(path)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--config", default="tuning/configs/realistic_arm.toml")
    ap.add_argument("--evaluations", type=int, default=256, help="parameter sets per kind (the budget)")
    ap.add_argument("--chunk", type=int, default=16)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--kinds", nargs="+", default=list(BOXES), choices=list(BOXES))
    ap.add_argument("--out", default="tuning/results/compare_controllers", help="output stem (.json, .md, .png)")
    args = ap.parse_args(argv)
    if args.evaluations < 16:
        ap.error("--evaluations: expected at least 16")
    cfg = _config.load(args.config)
    load = lambda: round(__import__("os").getloadavg()[0], 2)
    res = {"config": args.config, "evaluations": args.evaluations, "kinds": args.kinds, "load_before": load(),
           "command": "python tuning/compare_controllers.py " + " ".join(argv if argv is not None else
                                                                          __import__("sys").argv[1:]),
           "jax": jax.__version__, "machine": platform.machine(),
           "chattering_levels": [0.03, 0.1, 0.3, 1.0, 3.0, 10.0]}  # fmt: skip
    t0 = time.perf_counter()
    res["results"] = {k: study(cfg, k, args.evaluations, args.chunk, args.seed) for k in args.kinds}
    res["load_after"], res["wall_s"] = load(), time.perf_counter() - t0
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_text(out.with_suffix(".json"), json.dumps(res, indent=1))
    write_text(out.with_suffix(".md"), markdown(res))
    plot(res, out.with_suffix(".png"))
    print(markdown(res))


if __name__ == "__main__":
    main()
