"""Writing results as the commands do: whole or not at all (a killed run never leaves a
half-written file), JSON from arrays and NamedTuples, figures through matplotlib's Agg backend."""

from ._app.plots import save_figure
from ._io import atomic_write, jsonable, write_text

__all__ = ["atomic_write", "jsonable", "save_figure", "write_text"]
