"""Ablation of ``fosmc tune``'s settings on the tune target's problem (issue 11, item 1).

Each variant is the config ``tuning/configs/arm_ideal_set2.toml`` (ideal loop, arm at 0 and
10 kg, from Table 1 set 2, plain Euler dt = 1e-4 s, 4 s) with one ``[tune]`` key changed from
its default, tuned one after the other in this process with every core (as the CLI does);
every metric is the plain simulator's (``result.json``'s ``final``: the step of lowest training
loss, its number in the last column, steps + 1 for the point after the last update), means over the two
payloads and the three joints, beside the wall time of the whole ``run_tune`` call
(compilation included: each variant compiles its own problems).

    .venv/bin/python tuning/tune_ablation.py [--only NAME ...]

(``--only``: rerun those variants and replace their rows in the written table.)

Writes tuning/results/tune_ablation.{json,md}.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import time

import fosmc_jax as fj

fj.use_all_cores()

import numpy as np  # noqa: E402

from fosmc_jax import config as _config  # noqa: E402
from fosmc_jax.io import jsonable, write_text  # noqa: E402

HERE = pathlib.Path(__file__).parent
#: name -> the [tune] keys changed from the defaults (the default: none)
VARIANTS = {
    "default": {},
    "learning_rate 0.02": {"learning_rate": 0.02},
    "learning_rate 0.15": {"learning_rate": 0.15},
    "no global stage": {"global_candidates": 0},
    "global stage of 256": {"global_candidates": 256},
    "trained on the first 2 s": {"train_t_final": 2.0},
}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--only", nargs="+", choices=list(VARIANTS), help="run these variants only")
    args = ap.parse_args(argv)
    base = _config.load(HERE / "configs" / "arm_ideal_set2.toml")
    out = HERE / "results" / "tune_ablation.json"
    rows = json.loads(out.read_text()) if args.only and out.exists() else {}  # --only: replace those rows
    for name in args.only or VARIANTS:
        cfg = _config.replace(base, tune=VARIANTS[name])
        load, t0 = os.getloadavg()[0], time.perf_counter()
        r = fj.run_tune(_config.resolve(cfg), log=lambda msg: print(f"{name}: {msg}", flush=True))
        wall = time.perf_counter() - t0
        m = r["final"]["metrics"]
        rows[name] = {"changed": VARIANTS[name], "wall_s": wall, "load": [load, os.getloadavg()[0]],
                      "rms_error": float(np.mean(m["rms_error"])), "chattering": float(np.mean(m["chattering"])),
                      "chattering_hf": float(np.mean(m["chattering_hf"])), "last_loss": r["history"]["loss"][-1],
                      "best_step": r["history"]["best_step"], "final": r["final"]}  # fmt: skip
        print(f"{name}: rms_error {rows[name]['rms_error']:.3g} rad, chattering {rows[name]['chattering']:.3g} V/s, "
              f"{wall:.0f} s", flush=True)  # fmt: skip
    rows = {name: rows[name] for name in VARIANTS if name in rows}  # the table's order
    lines = ["| variant | `[tune]` change | wall s | load start / end | mean rms_error (rad) | mean chattering, total "
             "variation (V/s) | mean chattering_hf (V) | training loss at the last step | step returned |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|"]  # fmt: skip
    for name, r in rows.items():
        change = ", ".join(f"{k} = {v}" for k, v in r["changed"].items()) or "-"
        lines.append(f"| {name} | {change} | {r['wall_s']:.0f} | {r['load'][0]:.1f} / {r['load'][1]:.1f} | "
                     f"{r['rms_error']:.3g} | {r['chattering']:.3g} | {r['chattering_hf']:.3g} | {r['last_loss']:.3g} | "
                     f"{r['best_step'] + 1} |")  # fmt: skip
    write_text(out, json.dumps(jsonable(rows), indent=1))
    write_text(HERE / "results" / "tune_ablation.md", "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
