"""Plain metrics of tuned parameters on the training batch and on a held-out batch.

The held-out batch is :func:`fosmc_jax._front.held_out_config`'s: arm payloads the training did
not use (1, 3, 5, 7, 9 kg; 2.5, 5, 7.5 kg for the committed results), fresh box samples for
the linear model, fresh noise seeds.

    .venv/bin/python tuning/held_out.py --config tuning/configs/arm_ideal_set2.toml \\
        --params tuning/results/tune_arm_default/result.json

Prints one Markdown table (means over rollouts; per joint).
"""

from __future__ import annotations

import argparse

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from fosmc_jax import _config  # noqa: E402
from fosmc_jax import _front as F  # noqa: E402
from fosmc_jax import _tuning as T  # noqa: E402


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--config", required=True)
    ap.add_argument("--params", required=True, help="a fosmc tune result.json or a fosmc front front.json")
    ap.add_argument("--point", type=int, help="with a front.json: the point")
    args = ap.parse_args(argv)
    cfg = _config.with_params(_config.load(args.config), args.params, args.point)
    rows = []
    for label, c in (("training batch", cfg), ("held-out batch", F.held_out_config(cfg))):
        plain, _, p = _config.tuning_problems(c)
        m = T.evaluate(plain, p)
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


if __name__ == "__main__":
    main()
