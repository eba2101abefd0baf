"""Writing results as the commands do: whole or not at all (a killed run never leaves a
half-written file), JSON from arrays and NamedTuples, figures through matplotlib's Agg backend."""

from __future__ import annotations

from pathlib import Path

from ._io import atomic_write, jsonable, write_text

__all__ = ["atomic_write", "jsonable", "save_figure", "write_text"]


def save_figure(fig, path: str | Path) -> None:
    """Write a matplotlib figure atomically and close it. matplotlib (and its Agg backend) is
    imported here, on first use, not when ``fosmc_jax`` is: importing the package never
    changes a user's plotting backend."""
    from ._app.plots import save_figure as save

    save(fig, path)
