"""How good are the pathwise (AD) gradients the tuner follows? float64 throughout.

1. AD against central finite differences: reverse (value_and_grad) and forward (jacfwd) mode
   gradients of the mean rms error (rad) and the mean chattering (V/s) with respect to the 15
   internal parameters u = (log delta, log gamma, log(-poles)), against central differences
   (step h in u), on the nominal linear plant, Euler dt = 1e-3 s, for delta = Table 1 set 1
   scaled by 1 and 0.01 and horizons 0.5 s and 2 s.
2. Growth with horizon and shrinkage with delta: per-rollout gradients (jacfwd, one row per
   rollout) over 32 plants drawn uniformly in the Appendix box (seed 0), switching "ratio",
   horizons 0.5, 1, 2, 4 s and delta = Table 1 set 1 x {1, 0.3, 0.1, 0.03, 0.01}; reported: the
   norm of the batch-mean gradient and the batch spread sqrt(mean_i ||g_i - mean g||^2), for
   the rms error and the chattering separately.

    .venv/bin/python tuning/gradient_study.py [--samples 32] [--dt 1e-3]

Writes tuning/results/gradients.{json,png} (the report tuning/results/gradients.md is written by
hand from them).
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

from fosmc_jax import config as _config  # noqa: E402
from fosmc_jax import paper, simulate_batch  # noqa: E402
from fosmc_jax import search as fs  # noqa: E402
from fosmc_jax.io import save_figure, write_text  # noqa: E402

OUT = pathlib.Path(__file__).parent / "results"
SCALES = (1.0, 0.3, 0.1, 0.03, 0.01)
HORIZONS = (0.5, 1.0, 2.0, 4.0)


def log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)


def build(t_final: float, dt: float, samples: int):
    user = {"sim": {"integrator": "euler", "dt": dt, "t_final": t_final},
            "plant": {"uncertainty": "sample" if samples else "none", "samples": max(samples, 1), "seed": 0}}  # fmt: skip
    b = _config.build(_config.resolve(user))
    return b, dict(b.options, save_every=0, checkpoint_every=100)


def per_rollout(b, opts):
    """f(u, delta) -> (rms error (B,), chattering (B,)): means over the joints, per rollout."""

    def f(u, delta):
        p = fs.to_physical(u, b.base)
        ctrl = b.base._replace(delta=delta * jnp.exp(u.delta - jnp.log(b.base.delta)),
                                     gamma=p.gamma, poles=p.poles)  # fmt: skip
        r = simulate_batch(b.plants, ctrl, b.reference, b.X0s, b.dt, **opts)
        return jnp.mean(r.metrics.rms_error, -1), jnp.mean(r.metrics.chattering, -1)

    return f


def flat(g: fs.Tunable) -> np.ndarray:
    """(..., 15) from a Tunable of gradients with leading batch axes."""
    return np.concatenate([np.asarray(x).reshape(np.shape(x)[: np.ndim(x) - np.ndim(u)] + (-1,))
                           for x, u in zip(g, U_SHAPES)], axis=-1)  # fmt: skip


U_SHAPES = (np.zeros(3), np.zeros(3), np.zeros((3, 3)))


def fd_check(dt: float, h: float) -> list[dict]:
    rows = []
    for t_final in (0.5, 2.0):
        b, opts = build(t_final, dt, 0)
        f = per_rollout(b, opts)
        u0 = fs.to_internal(fs.Tunable(b.base.delta, b.base.gamma, b.base.poles), b.base)
        scalar = lambda u, d, k: f(u, d)[k][0]
        rev = jax.jit(jax.grad(scalar), static_argnums=2)
        fwd = jax.jit(jax.jacfwd(scalar), static_argnums=2)
        val = jax.jit(scalar, static_argnums=2)
        x0 = flat(u0)
        unflat = lambda x: fs.Tunable(jnp.asarray(x[:3]), jnp.asarray(x[3:6]), jnp.asarray(x[6:]).reshape(3, 3))
        for scale in (1.0, 0.01):
            d = jnp.asarray(paper.DELTA_SETS[0] * scale)
            for k, name in enumerate(("rms_error", "chattering")):
                gr, gf = flat(rev(u0, d, k)), flat(fwd(u0, d, k))
                fd = np.array([(float(val(unflat(x0 + h * e), d, k)) - float(val(unflat(x0 - h * e), d, k))) / (2 * h)
                               for e in np.eye(x0.size)])  # fmt: skip
                rel = lambda a: float(np.linalg.norm(a - fd) / max(np.linalg.norm(fd), 1e-300))
                rows.append({"t_final": t_final, "delta_scale": scale, "metric": name, "norm_fd": float(np.linalg.norm(fd)),
                             "rel_err_reverse": rel(gr), "rel_err_forward": rel(gf),
                             "rev_vs_fwd": float(np.linalg.norm(gr - gf) / max(np.linalg.norm(gf), 1e-300))})  # fmt: skip
                log(f"FD check T={t_final} s delta x{scale} {name}: |g_fd| {rows[-1]['norm_fd']:.3e} rel err reverse "
                    f"{rows[-1]['rel_err_reverse']:.2e} forward {rows[-1]['rel_err_forward']:.2e}")  # fmt: skip
    return rows


def sweep(dt: float, samples: int) -> list[dict]:
    rows = []
    for t_final in HORIZONS:
        b, opts = build(t_final, dt, samples)
        f = per_rollout(b, opts)
        u0 = fs.to_internal(fs.Tunable(b.base.delta, b.base.gamma, b.base.poles), b.base)
        jac = jax.jit(jax.jacfwd(f))
        t0 = time.perf_counter()
        for scale in SCALES:
            d = jnp.asarray(paper.DELTA_SETS[0] * scale)
            (ge, gc), (e, c) = jac(u0, d), jax.jit(f)(u0, d)
            for name, g, v in (("rms_error", flat(ge), e), ("chattering", flat(gc), c)):
                g = g[np.all(np.isfinite(g), axis=1)]
                mean = g.mean(axis=0)
                rows.append({"t_final": t_final, "delta_scale": scale, "metric": name,
                             "value_mean": float(np.mean(v)), "grad_norm_of_mean": float(np.linalg.norm(mean)),
                             "batch_spread": float(np.sqrt(np.mean(np.sum((g - mean) ** 2, axis=1)))),
                             "per_rollout_norm_median": float(np.median(np.linalg.norm(g, axis=1))),
                             "finite_rollouts": int(g.shape[0])})  # fmt: skip
            log(f"T={t_final} s delta x{scale}: |grad rms| {rows[-2]['grad_norm_of_mean']:.3e} spread "
                f"{rows[-2]['batch_spread']:.3e}; |grad chat| {rows[-1]['grad_norm_of_mean']:.3e} spread "
                f"{rows[-1]['batch_spread']:.3e}  ({time.perf_counter() - t0:.0f} s)")  # fmt: skip
    return rows


def plot(rows: list[dict]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 2, figsize=(11, 8))
    for col, (name, unit) in enumerate((("rms_error", "rad"), ("chattering", "V/s"))):
        for scale in SCALES:
            r = [x for x in rows if x["metric"] == name and x["delta_scale"] == scale]
            T_ = [x["t_final"] for x in r]
            axes[0, col].plot(T_, [x["grad_norm_of_mean"] for x in r], "o-", label=f"delta = set 1 x {scale}")
            axes[1, col].plot(T_, [x["batch_spread"] for x in r], "o-", label=f"delta = set 1 x {scale}")
        axes[0, col].set_ylabel(f"|d mean {name} / du| ({unit} per unit of u)")
        axes[1, col].set_ylabel(f"batch spread of d {name}_i / du ({unit} per unit of u)")
        for ax in axes[:, col]:
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_xlabel("horizon (s)")
            ax.grid(True, which="both", alpha=0.3)
        axes[0, col].set_title(f"{name}: norm of the batch-mean gradient")
        axes[1, col].set_title(f"{name}: spread over 32 box plants")
    axes[0, 0].legend(fontsize=8)
    fig.suptitle("switching ratio, gains (36), Euler dt = 1e-3 s; u = (log delta, log gamma, log(-poles))")
    fig.tight_layout()
    save_figure(fig, OUT / "gradients.png")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--samples", type=int, default=32)
    ap.add_argument("--dt", type=float, default=1e-3)
    ap.add_argument("--h", type=float, default=1e-5)
    ap.add_argument("--skip-fd", action="store_true")
    args = ap.parse_args()
    t0 = time.perf_counter()
    result = {"command": f"python tuning/gradient_study.py --samples {args.samples} --dt {args.dt} --h {args.h}",
              "machine": f"{platform.machine()} CPU, jax {jax.__version__}"}  # fmt: skip
    OUT.mkdir(parents=True, exist_ok=True)
    if not args.skip_fd:
        result["fd_check"] = fd_check(args.dt, args.h)
        write_text(OUT / "gradients.json", json.dumps(result, indent=1))
    result["sweep"] = sweep(args.dt, args.samples)
    result["total_s"] = time.perf_counter() - t0
    write_text(OUT / "gradients.json", json.dumps(result, indent=1))
    plot(result["sweep"])
    log(f"wrote {OUT}/gradients.{{json,png}} in {result['total_s']:.0f} s")


if __name__ == "__main__":
    main()
