"""The comparison the paper implies: fronts of tracking error against chattering for the FOSMC,
conventional sliding mode with a boundary layer (SMC) and super-twisting, on one config
(by default the realistic preset with a 2 s training surrogate: the arm at 0 and 10 kg in the
sampled, quantized, delayed, saturating loop), each found by ``fosmc front`` with the same
wall-time budget, each point re-evaluated on held-out payloads.

    .venv/bin/python tuning/compare_controllers.py --config tuning/configs/realistic_arm_short_training.toml \\
        --budget 240 --out tuning/results/compare_controllers

For every kind, one after the other on the same machine: ``fosmc front`` (:func:`fosmc_jax.config.study`)
on the config with ``[controller] kind`` set, over the kind's own parameters
(``fosmc_jax.search.SPACES``: the FOSMC's delta, gamma, poles; SMC's k, phi; super-twisting's
k1, k2; per-joint log factors around the config's values), with ``--budget`` seconds (its
compilations, references and held-out evaluation included); the front's points carry their
held-out metrics (:func:`fosmc_jax.config.held_out_config`: payloads 1, 3, 5, 7 and 9 kg since
849d357, 2.5, 5 and 7.5 kg in the committed study; fresh noise seeds). The kind's defaults
(the config's values) are evaluated beside it.

Writes ``DIR.json`` (every front point: parameters, training and held-out metrics), ``DIR.md``
(the tables and who wins where) and ``DIR.png`` (the three fronts, log-log).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import jax

import fosmc_jax  # noqa: E402

fosmc_jax.use_all_cores()  # every method evaluates its chunks on every core, as `fosmc front` does
jax.config.update("jax_enable_x64", True)

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from fosmc_jax import config as _config  # noqa: E402
from fosmc_jax import search as fs  # noqa: E402
from fosmc_jax.io import jsonable, write_text  # noqa: E402

KINDS = tuple(fs.SPACES)
LABELS = {"fosmc": "FOSMC (delta, gamma, poles)", "smc": "SMC (k, phi)", "super_twisting": "super-twisting (k1, k2)"}
AXES = fs.AXES


def log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)


def study(cfg: dict, kind: str, budget: float, seed: int) -> dict:
    """One kind's ``fosmc front`` (its points with held-out metrics) and its defaults' metrics."""
    cfg = _config.replace(cfg, controller={"kind": kind})
    t0 = time.perf_counter()
    front = _config.study(cfg, fs.FrontSettings(budget=budget, seed=seed), log=lambda s: log(f"{kind}: {s}"))
    wall = time.perf_counter() - t0
    plain, _, p0 = _config.tuning_problems(cfg)
    default = fs.evaluate(plain, p0)
    return {"kind": kind, "evaluations": front["stages"]["evaluations"], "search_wall_s": wall,
            "stages": front["stages"], "diverged_sets": sum(p["diverged"] > 0 for p in front["points"]),
            "default": {"params": {k: np.asarray(v).tolist() for k, v in p0._asdict().items()},
                        "metrics": default["metrics"]},
            "points": [{k: p[k] for k in ("params", "metrics", "held_out", "diverged")} for p in front["points"]]}  # fmt: skip


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
             f"`fosmc front --budget {res['budget_s']:g}` per kind, load average "
             f"{res['load_before']} before and {res['load_after']} after; jax {res['jax']}.", "",
             "| kind | front wall s | front points | diverged sets | default: rms_error (rad) / chattering_hf (V) | "
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
    lines += [
        "",
        "Evaluations per kind (training problem): "
        + ", ".join(f"{LABELS[k]} {res['results'][k]['evaluations']}" for k in kinds)
        + ".",
        "",
    ]
    lines += ["Best mean rms_error (rad) on each front at a chattering budget (mean chattering_hf <= level):", "",
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
                label=f"{LABELS[k]}: held out ({', '.join(f'{p:g}' for p in res['held_out_payloads'])} kg)")  # fmt: skip
        d = _means(res["results"][k]["default"])
        ax.plot(d[1], d[0], marker="*", ms=14, ls="none", color=ax.lines[-1].get_color(), label=f"{k} defaults")
    ax.set(xscale="log", yscale="log", xlabel="mean chattering_hf (V)", ylabel="mean rms tracking error (rad)",
           title=f"fosmc front, {res['budget_s']:g} s each ({Path(res['config']).name})")  # fmt: skip
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    tmp = path.with_suffix(".tmp.png")
    fig.savefig(tmp, dpi=130)
    plt.close(fig)
    tmp.replace(path)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--config", default="tuning/configs/realistic_arm_short_training.toml")
    ap.add_argument("--budget", type=float, default=240.0, help="fosmc front's wall time per kind, s")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--kinds", nargs="+", default=list(KINDS), choices=list(KINDS))
    ap.add_argument("--out", default="tuning/results/compare_controllers", help="output stem (.json, .md, .png)")
    args = ap.parse_args(argv)
    cfg = _config.load(args.config)
    load = lambda: round(os.getloadavg()[0], 2)
    res = {"config": args.config, "budget_s": args.budget, "kinds": args.kinds, "load_before": load(),
           "command": "python tuning/compare_controllers.py " + " ".join(sys.argv[1:] if argv is None else argv),
           "jax": jax.__version__, "machine": platform.machine(),
           "chattering_levels": [0.03, 0.1, 0.3, 1.0, 3.0, 10.0],
           "held_out_payloads": _config.held_out_config(cfg)["plant"]["payloads"]}  # fmt: skip
    t0 = time.perf_counter()
    res["results"] = {k: study(cfg, k, args.budget, args.seed) for k in args.kinds}
    res["load_after"], res["wall_s"] = load(), time.perf_counter() - t0
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_text(out.with_suffix(".json"), json.dumps(jsonable(res), indent=1))
    write_text(out.with_suffix(".md"), markdown(res))
    plot(res, out.with_suffix(".png"))
    print(markdown(res))


if __name__ == "__main__":
    main()
