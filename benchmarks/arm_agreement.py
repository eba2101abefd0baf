"""How closely the arm's kernel (generated from the JAX model: fosmc_jax/_simulator/generated.py; the
hand-written arm_kernel.cc before its retirement) agrees with vmap of simulate, and how
far float32 digital loops are from float64: the figures BENCHMARKS.md ("Issue 21") and docs/performance.md
quote, in one command:

    python benchmarks/arm_agreement.py            # about 2 minutes on 2 cores

Cases: the paper's arm case in the ideal loop (Table 1 set 1, payloads 0, 5, 10 kg x 2
offsets, 0.2 s), and the realistic preset (fosmc_jax/_problems/presets/realistic_arm.toml: the digital
loop, 0.3 s, 2 offsets) with the FOSMC, SMC and super-twisting, and its float32 variants. Per
case: the largest difference of any metric between the kernel and vmap(simulate), relative to
that metric's largest |value| over the batch; for float32 digital loops also each path's
largest relative distance from the float64 loop (the "truth" both approximate).
"""

from __future__ import annotations

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

import fosmc_jax as fj  # noqa: E402
from fosmc_jax import config as _config  # noqa: E402

PRESET = "fosmc_jax/_problems/presets/realistic_arm.toml"
IDEAL = {"controller.sample_period": 0.0, "controller.delay_samples": 0, "sensors.encoder_counts": [0, 0, 0],
         "sensors.derivatives": "measured", "actuator.u_max": None}  # fmt: skip


def build(base: str | None, t_final: float, **changes):
    cfg = _config.load(base) if base else _config.resolve({"plant": {"kind": "arm", "payloads": [0.0, 5.0, 10.0]}})
    cfg = cfg.as_dict()
    cfg["sim"]["t_final"] = t_final
    cfg["sim"]["initial_offset"] = [[0.0] * 9, [0.01, 0, 0, -0.02, 0, 0, 0.03, 0, 0]]
    for key, value in changes.items():
        section, name = key.split(".")
        cfg[section][name] = value
        if value is None:
            del cfg[section][name]
    b = _config.build(cfg)
    opts = {k: v for k, v in b.options.items() if k not in ("switching", "law", "save_every")}
    return lambda fast: fj.simulate_batch(b.plants, b.controller(), b.reference, b.X0s, b.dt, keys=b.keys, fast=fast,
                                          **opts).metrics  # fmt: skip


def worst(a, b) -> float:
    """The largest |a - b| over every metric, relative to that metric's largest |b|."""
    out = 0.0
    for name in a._fields:
        x, y = np.asarray(getattr(a, name), np.float64), np.asarray(getattr(b, name), np.float64)
        scale = np.max(np.abs(y))
        if scale > 0:
            out = max(out, float(np.max(np.abs(x - y)) / scale))
    return out


def main() -> None:
    cases = {
        "ideal FOSMC, RK4, float64": (None, 0.2, {}),
        "ideal FOSMC, Euler, float64": (None, 0.2, {"sim.integrator": "euler"}),
        "ideal FOSMC, RK4, float32": (None, 0.2, {"sim.precision": "float32"}),
        "digital FOSMC (the preset), float64": (PRESET, 0.3, {}),
        "digital SMC, float64": (PRESET, 0.3, {"controller.kind": "smc"}),
        "digital super-twisting, float64": (PRESET, 0.3, {"controller.kind": "super_twisting"}),
        "ideal SMC, float64": (PRESET, 0.3, dict(IDEAL, **{"controller.kind": "smc"})),
        "ideal super-twisting, float64": (PRESET, 0.3, dict(IDEAL, **{"controller.kind": "super_twisting"})),
        "digital FOSMC, exact angles, measured rates, float32": (PRESET, 0.3, {
            "sensors.encoder_counts": [0, 0, 0], "sensors.derivatives": "measured", "sim.precision": "float32"}),
        "digital FOSMC, exact angles, differenced rates, float32": (PRESET, 0.3, {
            "sensors.encoder_counts": [0, 0, 0], "sim.precision": "float32"}),
        "digital FOSMC (the preset), float32": (PRESET, 0.3, {"sim.precision": "float32"}),
        "digital FOSMC, 65,536 counts, float32": (PRESET, 0.3, {
            "sensors.encoder_counts": [65536] * 3, "sim.precision": "float32"}),
    }  # fmt: skip
    print("| case | kernel vs vmap(simulate) | kernel vs float64 | vmap(simulate) vs float64 |")
    print("|---|---|---|---|")
    for name, (base, t_final, changes) in cases.items():
        run = build(base, t_final, **changes)
        fast, slow = run(True), run(False)
        row = [f"{worst(fast, slow):.1e}", "", ""]
        if changes.get("sim.precision") == "float32" and base:
            truth = build(base, t_final, **dict(changes, **{"sim.precision": "float64"}))(False)
            row[1:] = [f"{worst(fast, truth):.1e}", f"{worst(slow, truth):.1e}"]
        print(f"| {name} | {' | '.join(row)} |", flush=True)


if __name__ == "__main__":
    main()
