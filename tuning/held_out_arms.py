"""Held-out arms against training arms on a front tuned over sampled arms (issue 25).

For each config, ``fosmc front --budget B`` tunes over its sampled arms (corners of the
ranges) x payloads and evaluates every front point on the held-out batch (other corners, the
next ``[arm.uncertainty] seed``, and payloads at 0.1, 0.3, ..., 0.9 of ``arm.payload_range``);
this script reads both and reports, per front, the held-out mean rms_error as a ratio to the
training one, point by point, and the same ratio of chattering_hf (the comparison is at the
same chattering where that ratio is near 1). Writes ``tuning/results/held_out_arms.md`` and
``.json`` and the fronts under ``tuning/results/held_out_arms/``.

    .venv/bin/python tuning/held_out_arms.py                # both configs, --budget 120
    .venv/bin/python tuning/held_out_arms.py --budget 60 --configs small_arm

``--fronts`` reads front.json files already made (by ``fosmc front``, which evaluates the held-out
batch beside the training one) instead of running fronts; ``--stem`` names the report:

    .venv/bin/python tuning/held_out_arms.py --stem held_out_arms_realistic_robust \
        --fronts tuning/results/reference/realistic_arm_robust/front900_s{0,1,2}/front/front.json
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import sys

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import fosmc_jax as fj  # noqa: E402
from fosmc_jax.io import write_text  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parent
CONFIGS = {"small_arm": "small_arm", "realistic_arm_uncertain": str(ROOT / "configs/realistic_arm_uncertain.toml"),
           "arm_ideal_robust": str(ROOT / "configs/arm_ideal_robust.toml")}  # fmt: skip


def ratios(front: dict) -> dict:
    """Per point: held-out / training mean rms_error and chattering_hf (diverged: NaN)."""
    mean = lambda m, k: np.nan if m[k][0] is None else float(np.mean(m[k]))
    out = {}
    for k in ("rms_error", "chattering_hf"):
        out[k] = np.array([mean(p["held_out"], k) / mean(p["metrics"], k) for p in front["points"]])
    return out


LEVELS = (0.5, 1.0, 2.0, 4.0, 8.0)  # V, chattering_hf levels at which the fronts are compared


def best_error(front: dict, level: float) -> float:
    """The front's least training mean rms_error (rad) among its points with mean
    chattering_hf at most ``level`` (V); NaN where none is that smooth."""
    pts = [p["metrics"] for p in front["points"] if np.mean(p["metrics"]["chattering_hf"]) <= level]
    return min((float(np.mean(m["rms_error"])) for m in pts), default=np.nan)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--budget", type=float, default=120.0)
    ap.add_argument("--configs", nargs="*", default=["small_arm", "realistic_arm_uncertain"], choices=list(CONFIGS))
    ap.add_argument("--fronts", nargs="*", default=[], metavar="FRONT_JSON", help="report on these instead of running")
    ap.add_argument("--stem", default="held_out_arms", help="the report's name in --out")
    ap.add_argument("--out", default=str(ROOT / "results"))
    args = ap.parse_args(argv)
    out = pathlib.Path(args.out)
    rows, levels, data = [], [], {}
    made = {str(pathlib.Path(f).parent): f for f in args.fronts}  # a front by its folder
    for name in made or args.configs:
        if made:
            front = json.loads(pathlib.Path(made[name]).read_text())
        else:
            print(f"held_out_arms: {name}, fosmc front --budget {args.budget:g} ...", flush=True)
            front = fj.run_front(CONFIGS[name], out=out / "held_out_arms" / name, budget=args.budget, force=True,
                                 log=lambda s: print(s, flush=True) if not s.startswith("point") else None)  # fmt: skip
        r = ratios(front)
        e, c = r["rms_error"], r["chattering_hf"]
        within = float(np.mean(np.abs(e - 1) <= 0.25))
        best = [best_error(front, level) for level in LEVELS]
        data[name] = {"points": len(e), "rms_error_ratio": e.tolist(), "chattering_hf_ratio": c.tolist(),
                      "within_25_percent": within, "held_out_batch": front["held_out_batch"],
                      "best_rms_error_at_chattering_hf": dict(zip(map(str, LEVELS), best))}  # fmt: skip
        levels.append(f"| {name} | " + " | ".join(f"{b:.3g}" for b in best) + " |")
        rows.append(f"| {name} | {len(e)} | {np.nanmin(e):.3f} / {np.nanmedian(e):.3f} / {np.nanmax(e):.3f} | "
                    f"{np.nanmin(c):.3f} / {np.nanmedian(c):.3f} / {np.nanmax(c):.3f} | {100 * within:.0f}% |")  # fmt: skip
    load = os.getloadavg()[0]
    command = " ".join([".venv/bin/python tuning/held_out_arms.py", *(argv if argv is not None else sys.argv[1:])])
    text = "\n".join([
        "# Held-out arms against training arms",
        "",
        f"`{command}` (load average {load:.1f} at the end, "
        f"{os.cpu_count()} cores). Per front point: the held-out batch's mean over rollouts divided by the training "
        "batch's; min / median / max over the front's points.",
        "",
        "| config | points | rms_error held-out / training | chattering_hf held-out / training | points within 25% |",
        "|---|---|---|---|---|",
        *rows,
        "",
        "The fronts side by side: the least training mean rms_error (rad) among each front's points whose mean "
        "chattering_hf is at most the column's (V); nan: no point that smooth.",
        "",
        "| config | " + " | ".join(f"<= {level:g} V" for level in LEVELS) + " |",
        "|---|" + "---|" * len(LEVELS),
        *levels,
        "",
    ])  # fmt: skip
    write_text(out / f"{args.stem}.md", text)
    write_text(out / f"{args.stem}.json", json.dumps(data, indent=1))
    print(text)


if __name__ == "__main__":
    main()
