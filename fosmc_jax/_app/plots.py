"""Figures (matplotlib, no numerics): every axis labelled with units."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.backend_bases import FigureCanvasBase
from matplotlib.figure import Figure

from .._io import atomic_write

JOINTS = ("joint 1", "joint 2", "joint 3")


def check_figure_path(path: str | Path) -> None:
    """A one-line ``ValueError`` unless ``path`` ends in a format :func:`save_figure` writes
    (the extension matplotlib's Agg canvas knows: png, pdf, svg, ...), checked before the work
    whose figure it is."""
    formats = FigureCanvasBase.get_supported_filetypes()
    suffix = Path(path).suffix[1:].lower()
    if suffix not in formats:
        got = f"'.{suffix}'" if suffix else "no extension"
        raise ValueError(f"expected a file name ending in a figure format ({', '.join(sorted(formats))}), got {got}")


def save_figure(fig, path: str | Path) -> None:
    """Write ``fig`` atomically (see :func:`fosmc_jax._io.atomic_write`); a pyplot figure (a
    user's) is closed after. The package's own figures are :class:`matplotlib.figure.Figure`
    objects outside pyplot's registry, so that threads may draw them at once (``fosmc reproduce``
    draws its figures while other cases compile)."""
    try:
        atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=110, bbox_inches="tight", format=Path(path).suffix[1:]))
    finally:
        if fig.canvas.manager is not None:
            import matplotlib.pyplot as plt

            plt.close(fig)


def plot_rollouts(t, X, X_d, U, labels, path: str | Path, title: str = "") -> None:
    """Desired and actual angles, tracking errors and controls of a few rollouts.

    ``t`` (m,) s; ``X``, ``X_d`` (B, m, 9); ``U`` (B, m, 3) V; ``labels``: B legend entries.
    """
    X, X_d, U = (np.asarray(a) for a in (X, X_d, U))
    fig = Figure(figsize=(14, 9))
    axes = fig.subplots(3, 3, sharex=True, squeeze=False)
    for j in range(3):
        ax_th, ax_e, ax_u = axes[j]
        ax_th.plot(t, X_d[0, :, 3 * j], "k--", lw=1.5, label="desired")
        for b, label in enumerate(labels):
            ax_th.plot(t, X[b, :, 3 * j], lw=1, label=label)
            ax_e.plot(t, X[b, :, 3 * j] - X_d[b, :, 3 * j], lw=1)
            ax_u.plot(t, U[b, :, j], lw=0.8)
        ax_th.set_ylabel(f"{JOINTS[j]}\nangle (rad)")
        ax_e.set_ylabel("tracking error (rad)")
        ax_u.set_ylabel("control U (V)")
        for ax in axes[j]:
            ax.grid(alpha=0.3)
    for ax in axes[-1]:
        ax.set_xlabel("time (s)")
    if len(labels) <= 12:
        axes[0, 0].legend(fontsize=8, loc="best")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    save_figure(fig, path)


def plot_histograms(arrays: dict, names, units: dict, path: str | Path, title: str = "") -> None:
    """A Monte-Carlo batch's distribution: one histogram per joint (columns) of each metric in
    ``names`` (rows), over the rollouts that did not diverge, with the 5th, 50th and 95th
    percentiles marked. ``arrays``: {name: (N, 3)} and ``diverged`` (N,)."""
    ok = ~np.asarray(arrays["diverged"], bool)
    fig = Figure(figsize=(13, 3.4 * len(names)))
    axes = fig.subplots(len(names), 3, squeeze=False)
    for i, name in enumerate(names):
        v = np.asarray(arrays[name])[ok]
        for j in range(3):
            ax = axes[i, j]
            if len(v):
                ax.hist(v[:, j], bins=min(40, max(5, len(v) // 5)), color="C0", alpha=0.8)
                for q, style, label in ((5, ":", "5th, 95th percentiles"), (50, "-", "median"), (95, ":", None)):
                    ax.axvline(np.percentile(v[:, j], q), color="k", ls=style, lw=1, label=label)
            ax.set_xlabel(f"{name} ({units[name]})")
            ax.set_ylabel("rollouts")
            ax.set_title(JOINTS[j])
            ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=8, loc="best")
    fig.suptitle(f"{title}{'; ' if title else ''}{ok.sum()} of {ok.size} rollouts (diverged left out)")
    fig.tight_layout()
    save_figure(fig, path)


def plot_joint_series(series, ylabel: str, path: str | Path, title: str, *, logy: bool = False,
                      styles=None, xlim=None) -> None:  # fmt: skip
    """One panel per joint, several labelled time series in each.

    ``series``: list of (label, t (m,) s, Y (m, 3)); ``ylabel`` names the quantity and its unit.
    ``logy`` plots |Y| on a log axis.
    """
    fig = Figure(figsize=(9, 8))
    axes = fig.subplots(3, 1, sharex=True)
    for i, (label, t, Y) in enumerate(series):
        Y = np.asarray(Y)
        style = (styles or {}).get(label, {})
        for j, ax in enumerate(axes):
            y = np.abs(Y[:, j]) if logy else Y[:, j]
            ax.plot(t, y, lw=style.get("lw", 1.0), ls=style.get("ls", "-"), color=style.get("color", f"C{i}"),
                    marker=style.get("marker"), ms=3, drawstyle=style.get("drawstyle", "default"),
                    label=label if j == 0 else None)  # fmt: skip
    for j, ax in enumerate(axes):
        ax.set_ylabel(f"{JOINTS[j]}\n{'|' + ylabel + '|' if logy else ylabel}")
        ax.grid(alpha=0.3)
        if logy:
            ax.set_yscale("log")
            # exact zeros (e.g. s(0) = 0) would stretch the axis over many empty decades
            values = np.concatenate([np.abs(np.asarray(Y)[:, j]) for _, _, Y in series])
            positive = values[values > 0]
            if positive.size:
                ax.set_ylim(bottom=np.percentile(positive, 0.5) / 10)
        if xlim is not None:
            ax.set_xlim(*xlim)
    axes[-1].set_xlabel("time (s)")
    fig.legend(loc="upper center", ncol=min(len(series), 5), bbox_to_anchor=(0.5, 1.0), fontsize=9, frameon=False)
    fig.suptitle(title, y=1.04)
    fig.tight_layout()
    save_figure(fig, path)


#: Axis labels of the tunable parameters of every controller kind (fosmc_jax._search.tune.SPACES).
_PARAM_LABELS = {
    "delta": "delta (same unit as s)",
    "gamma": "gamma (gains of (23))",
    "poles": "-pole (1/s)",
    "k": "SMC k (unit of ds/dt)",
    "phi": "SMC phi (same unit as s)",
    "k1": "super-twisting k1 (s^1/2 / s)",
    "k2": "super-twisting k2 (s / s^2)",
}


def plot_tuning(history: dict, params: list[dict], path: str | Path) -> None:
    """Loss and its two parts, and each tunable parameter (per joint; the FOSMC's delta,
    gamma, poles, SMC's k, phi, super-twisting's k1, k2), against the optimizer step."""
    steps = np.arange(1, len(history["loss"]) + 1)
    names = list(params[0])
    rows = (len(names) + 2) // 2
    fig = Figure(figsize=(12, 4 * rows))
    axes = fig.subplots(rows, 2, squeeze=False)
    axes = axes.ravel()
    ax = axes[0]
    curves = {key: np.asarray(history[key], float) for key in ("loss", "error", "chattering")}
    for key, y in curves.items():
        ax.plot(steps, y, label=key if key == "loss" else f"{key} part")
    ax.set_ylabel("objective (unit-free)")
    ax.set_yscale("log" if all(np.all(y > 0) for y in curves.values()) else "linear")  # log objectives go < 0
    ax.legend()
    for ax, key in zip(axes[1:], names):
        v = np.array([p[key] for p in params]).reshape(len(params), -1)
        v = -v if key == "poles" else v
        for i in range(v.shape[1]):
            label = f"joint {i // 3 + 1}, pole {i % 3 + 1}" if key == "poles" else f"joint {i + 1}"
            ax.plot(steps, v[:, i], label=label)
        ax.set_ylabel(_PARAM_LABELS.get(key, key))
        ax.set_yscale("log")
        ax.legend(fontsize=7, ncol=3 if key == "poles" else 1)
    for ax in axes[len(names) + 1 :]:
        ax.set_visible(False)
    for ax in axes[: len(names) + 1]:
        ax.set_xlabel("optimizer step")
        ax.grid(alpha=0.3)
    fig.tight_layout()
    save_figure(fig, path)


def plot_tradeoff(sweeps, path: str | Path, title: str) -> None:
    """Tracking error and chattering against each swept parameter, in both loops.

    ``sweeps``: list of objects with ``name``, ``values`` (n,), and ``ideal``, ``realistic``
    metrics whose fields are (n, 3) arrays; each panel shows the mean over the joints."""
    rows = (("rms_error", "mean RMS tracking error (rad)"), ("chattering_hf", "mean chattering_hf (V)"),
            ("chattering", "mean total variation rate (V/s)"))  # fmt: skip
    fig = Figure(figsize=(5.5 * len(sweeps), 3.2 * len(rows)))
    axes = fig.subplots(len(rows), len(sweeps), squeeze=False)
    for c, sw in enumerate(sweeps):
        for r, (metric, label) in enumerate(rows):
            ax = axes[r, c]
            for loop, style in (("ideal", "o-"), ("realistic", "s-")):
                y = np.mean(np.asarray(getattr(getattr(sw, loop), metric)), axis=-1)
                ax.plot(sw.values, y, style, label=f"{loop} loop")
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_ylabel(label)
            ax.grid(alpha=0.3, which="both")
            if r == len(rows) - 1:
                ax.set_xlabel(sw.name + (" (x Table 1 set 1)" if "delta" in sw.name else " (x poles (33))"))
        axes[0, c].legend(fontsize=9)
    fig.suptitle(title)
    fig.tight_layout()
    save_figure(fig, path)


def plot_front(front: dict, compare: list, path: str | Path) -> None:
    """A front (``fosmc front``'s result) on log-log axes of its two metrics (means over
    rollouts and joints), with its held-out evaluation, its references (Table 1's sets, SGN)
    and any ``compare`` = [(label, front or tune result dict)]."""
    ex, ey = front["axes"]
    xy = lambda m: (np.mean(m[ey]), np.mean(m[ex]))
    fig = Figure(figsize=(8, 6))
    ax = fig.subplots()
    pts = np.array([xy(p["metrics"]) for p in front["points"]])
    ax.plot(pts[:, 0], pts[:, 1], "o-", color="C0", label="front (training batch)")
    held = [xy(p["held_out"]) for p in front["points"] if "held_out" in p]
    if held:
        held = np.array(held)
        ax.plot(held[:, 0], held[:, 1], "o--", mfc="none", color="C0", label="front, held-out batch")
    for i, (label, ref) in enumerate(front.get("references", {}).items()):
        ax.plot(*xy(ref["metrics"]), "s" if label != "SGN" else "X", ms=9, color=f"C{i + 1}", label=label)
    for j, (label, other) in enumerate(compare):
        if "points" in other:
            o = np.array([xy(p["metrics"]) for p in other["points"]])
            ax.plot(o[:, 0], o[:, 1], "^:", color=f"C{j + 6}", label=label)
        else:
            ax.plot(*xy(other["final"]["metrics"]), "^", ms=9, color=f"C{j + 6}", label=label)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel(f"mean {ey} (V)" if ey == "chattering_hf" else f"mean {ey} (V/s)")
    ax.set_ylabel(f"mean {ex} (rad)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    ax.set_title("Pareto front: tracking error against chattering")
    fig.tight_layout()
    save_figure(fig, path)
