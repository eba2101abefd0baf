"""Figures (matplotlib, no numerics): every axis labelled with units."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

JOINTS = ("joint 1", "joint 2", "joint 3")


def save_figure(fig, path: str | Path) -> None:
    """Write ``fig`` atomically (temporary file in the same folder, then rename) and close it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    try:
        fig.savefig(tmp, dpi=110, bbox_inches="tight")
        os.replace(tmp, path)
    finally:
        plt.close(fig)
        if os.path.exists(tmp):
            os.remove(tmp)


def plot_rollouts(t, X, X_d, U, labels, path: str | Path, title: str = "") -> None:
    """Desired and actual angles, tracking errors and controls of a few rollouts.

    ``t`` (m,) s; ``X``, ``X_d`` (B, m, 9); ``U`` (B, m, 3) V; ``labels``: B legend entries.
    """
    X, X_d, U = (np.asarray(a) for a in (X, X_d, U))
    fig, axes = plt.subplots(3, 3, figsize=(14, 9), sharex=True, squeeze=False)
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
