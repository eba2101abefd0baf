"""The chattering the trajectory alone needs: the total variation of the exact tracking voltage.

A controller that tracks a reference closely puts out about the voltage under which the arm
follows it exactly (:func:`fosmc_jax.tracking_voltage`: the inverse dynamics through the
motors); the total variation of that voltage over the run, the ``chattering`` metric of a
perfect tracker (:func:`fosmc_jax.config.chattering_floor`), is a floor under every tuned
point's ``chattering``. A bound on ``chattering``
below it (``[tune] chattering_bound`` with ``chattering_metric = "chattering"``) cannot be met
at a small error. Per config: the floor (mean over the batch's arms and the joints, per joint),
the largest tracking voltage against the config's voltage limit, and the config's bound.

    .venv/bin/python tuning/tracking_floor.py            # the arm configs with a TV bound and their twins

The voltage is taken on the controller's sampling grid (every ``sim.dt``, or every
``controller.sample_period`` on a digital loop), as the metric counts the jumps of the
applied voltage. Writes ``tuning/results/tracking_floor.md`` and ``.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import subprocess
import sys

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import fosmc_jax as fj  # noqa: E402
from fosmc_jax.io import write_text  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parent
CONFIGS = ["arm_ideal_set2", "arm_ideal_set2_tv_bound", "unseen_ideal_payloads", "unseen_ideal_payloads_tv_bound",
           "unseen_ideal_set3", "unseen_ideal_set3_tv_bound", "realistic_arm"]  # fmt: skip


def floor(config: str) -> dict:
    """The tracking voltage's total variation rate (V/s) and peak (V) on a config's arms."""
    cfg = fj.config.load(config)
    if cfg.plant.kind != "arm":
        raise SystemExit(f"tracking_floor: {config}: plant.kind is {cfg.plant.kind!r}, not 'arm'")
    tv = fj.config.chattering_floor(cfg)  # (arms, 3)
    U = fj.config.tracking_voltages(cfg)  # (arms, samples, 3): the peak voltage (computed again: 1 s)
    tune = cfg.tune
    bound = (
        tune.chattering_bound
        if tune.objective == "chattering_bound" and tune.chattering_metric == "chattering"
        else None
    )
    return {"config": config, "arms": int(U.shape[0]), "samples": int(U.shape[1]), "tv_floor": float(tv.mean()),
            "tv_floor_per_joint": tv.mean(axis=0).tolist(), "peak_voltage": np.abs(U).max(axis=(0, 1)).tolist(),
            "u_max": list(cfg.actuator.u_max) if cfg.actuator.u_max else None, "tv_bound": bound}  # fmt: skip


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--configs", nargs="*", default=CONFIGS, help="names in tuning/configs or paths")
    ap.add_argument("--out", default=str(ROOT / "results"))
    ap.add_argument("--stem", default="tracking_floor")
    args = ap.parse_args(argv)
    rows, data = [], []
    for name in args.configs:
        path = name if name.endswith(".toml") else str(ROOT / "configs" / f"{name}.toml")
        print(f"tracking_floor: {name} ...", flush=True)
        r = floor(path)
        r["config"] = name
        data.append(r)
        bound = "" if r["tv_bound"] is None else f"{r['tv_bound']:g} ({r['tv_bound'] / r['tv_floor']:.2f})"
        limit = "" if r["u_max"] is None else " / " + ", ".join(f"{u:g}" for u in r["u_max"])
        rows.append(f"| {name} | {r['arms']} | {r['tv_floor']:.3f} | " + ", ".join(f"{x:.3f}" for x in r["tv_floor_per_joint"])
                    + " | " + ", ".join(f"{x:.2f}" for x in r["peak_voltage"]) + limit + f" | {bound} |")  # fmt: skip
    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=ROOT
    ).stdout.strip()
    command = " ".join([".venv/bin/python tuning/tracking_floor.py", *(argv if argv is not None else sys.argv[1:])])
    text = "\n".join([
        "# The chattering the trajectory alone needs",
        "",
        f"`{command}` at {commit} (load average {os.getloadavg()[0]:.1f} at the end). The exact tracking "
        "voltage `fosmc_jax.tracking_voltage` on each config's arms (payloads, sampled arms) along its reference, "
        "on the controller's sampling grid; its total variation over the run per second, the `chattering` "
        "metric (V/s) of a perfect tracker: the mean over arms and joints, and per joint; its largest magnitude "
        "(V) per joint against the config's limit; the config's bound on `chattering` (`[tune] chattering_bound`), "
        "with its ratio to the floor (below 1: no point tracks closely within it).",
        "",
        "| config | arms | TV floor, V/s | per joint, V/s | peak voltage, V (/ limit) | TV bound, V/s (/ floor) |",
        "|---|---|---|---|---|---|",
        *rows,
        "",
    ])  # fmt: skip
    write_text(pathlib.Path(args.out) / f"{args.stem}.md", text)
    write_text(pathlib.Path(args.out) / f"{args.stem}.json", json.dumps(data, indent=1))
    print(text)


if __name__ == "__main__":
    main()
