"""Plain metrics of tuned parameters on the training batch and on a held-out batch.

The held-out batch is :func:`fosmc_jax.config.held_out_config`'s: arm payloads the training did
not use (1, 3, 5, 7, 9 kg; 2.5, 5, 7.5 kg for the committed results), fresh box samples for
the linear model, fresh noise seeds.

    .venv/bin/python tuning/held_out.py --config tuning/configs/arm_ideal_set2.toml \\
        --params tuning/results/tune_arm_default/result.json

Prints one Markdown table (means over rollouts; per joint). With ``--front front.json
--payloads P ...`` instead of ``--params``: every point of an arm front at each payload, the
worst payload's rms_error as a ratio to the point's training one, and the points beyond
1.25x (tuning/README.md, "Three held-out payloads were too few"):

    .venv/bin/python tuning/held_out.py --config tuning/configs/realistic_arm_short_training.toml \
        --front tuning/results/front_realistic_15min_cma/front.json --payloads 0.5 1 1.5 2 3 4 6 8 9 9.5
"""

from __future__ import annotations

import argparse
import json
import pathlib

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from fosmc_jax import config as _config  # noqa: E402
from fosmc_jax import search as fs  # noqa: E402


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--config", required=True)
    ap.add_argument("--params", help="a fosmc tune result.json or a fosmc front front.json")
    ap.add_argument("--point", type=int, help="with a front.json: the point")
    ap.add_argument("--front", help="a fosmc front front.json: every point at --payloads")
    ap.add_argument("--payloads", type=float, nargs="+", help="with --front: arm payloads (kg)")
    args = ap.parse_args(argv)
    if args.front:
        return payload_check(_config.load(args.config), args.front, args.payloads)
    if not args.params:
        ap.error("--params or --front is required")
    cfg = _config.with_params(_config.load(args.config), args.params, args.point)
    rows = []
    for label, c in (("training batch", cfg), ("held-out batch", _config.held_out_config(cfg))):
        plain, _, p = _config.tuning_problems(c)
        m = fs.evaluate(plain, p)
        rows.append((label, c["plant"].get("payloads") if c["plant"]["kind"] == "arm" else c["plant"]["seed"], m))
    print(
        "| batch | payloads (kg) or seed | rms_error (rad) | max_abs_error (rad) | chattering (V/s) | chattering_hf (V) |"
    )
    print("|---|---|---|---|---|---|")
    for label, what, m in rows:
        cells = [" / ".join(f"{v:.3g}" for v in m["metrics"][k]) for k in
                 ("rms_error", "max_abs_error", "chattering", "chattering_hf")]  # fmt: skip
        print(f"| {label} | {what} | " + " | ".join(cells) + " |")
    (a, b) = (np.mean(rows[0][2]["metrics"]["rms_error"]), np.mean(rows[1][2]["metrics"]["rms_error"]))
    print(f"\nmean rms_error held-out / training: {b / a:.2f}")


def payload_check(cfg: dict, front_json: str, payloads: list[float]) -> None:
    """Every point of a front at each of ``payloads`` (one rollout each, the config's loop)."""
    pts = json.loads(pathlib.Path(front_json).read_text())["points"]
    p0 = _config.tuning_problems(cfg)[2]
    params = type(p0)(*(np.array([p["params"][k] for p in pts]) for k in p0._fields))
    trained = np.array([np.mean(p["metrics"]["rms_error"]) for p in pts])
    plain = _config.tuning_problems(_config.replace(cfg, plant={"payloads": payloads}))[0]
    run = jax.jit(jax.vmap(lambda p: plain.simulate(p, checkpoint_every=0)))
    errors, diverged = [], 0
    for i in range(0, len(pts), 16):  # chunks of 16, the last padded: one compilation
        part = jax.tree.map(lambda x, i=i: x[i : i + 16], params)
        n = len(part[0])
        r = run(jax.tree.map(lambda x: np.concatenate([x, np.repeat(x[-1:], 16 - n, 0)]), part))
        errors.append(np.asarray(r.metrics.rms_error)[:n].mean(-1))  # (points, payloads): mean over joints
        diverged += int(np.sum(np.asarray(r.diverged)[:n]))
        print(f"{min(i + 16, len(pts))}/{len(pts)} points", flush=True)
    E = np.concatenate(errors)
    worst = E.max(axis=1) / trained
    print(
        f"{front_json}: {len(pts)} points x payloads {payloads} kg, {diverged} rollouts diverged; worst payload's "
        f"rms_error / training: median {np.median(worst):.2f}, 90% {np.quantile(worst, 0.9):.2f}, max {worst.max():.3g}"
    )
    for i in np.flatnonzero(worst > 1.25):
        c = np.mean(pts[i]["metrics"]["chattering_hf"])
        print(
            f"  point {i} (training {trained[i]:.3g} rad at {c:.3g} V): rms_error by payload "
            + ", ".join(f"{e:.3g}" for e in E[i])
        )


if __name__ == "__main__":
    main()
