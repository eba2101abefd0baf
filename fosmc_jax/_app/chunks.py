"""A batch run in chunks (``fosmc simulate`` on a batch larger than memory holds at once,
:func:`fosmc_jax._app.memory.plan`): the same compiled program on chunks of one shape, the last
padded, every rollout's metrics written into arrays of the whole batch.

A batch's rollouts are flattened plant, offset, realization (paired: pair, realization) first
(:func:`fosmc_jax.simulate_batch`). A chunk is a contiguous run of them that the simulator can
make itself: a slice of the outermost axis whose inner axes fit, one element of each axis outside
it (:func:`blocks`). So each chunk is a batch of the same kind as the whole (cross or paired,
one key or several), which the simulator runs down the same path.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import numpy as np

from .._simulator.metrics import METRIC_NAMES


class Block(NamedTuple):
    """A chunk: its first rollout in the batch's order (``start``), how many it holds
    (``size``), and per axis of the batch (:func:`axes`) the range ``(a, b)`` of that axis it
    runs; the chunked ``axis`` padded to ``length`` elements by repeating its last."""

    start: int
    size: int
    ranges: tuple[tuple[int, int], ...]
    axis: int
    length: int


def axes(plants: int, offsets: int, realizations: int, paired: bool) -> tuple[int, ...]:
    """The batch's axes, outermost first: (plants, offsets, realizations), or (pairs,
    realizations) with ``paired``."""
    return (plants, realizations) if paired else (plants, offsets, realizations)


def blocks(sizes: tuple[int, ...], chunk: int) -> list[Block]:
    """The chunks of a batch of axes ``sizes`` (outermost first; its rollouts the product) of
    at most ``chunk`` rollouts each, or of the innermost axis' two elements where fewer than two
    fit (a realization axis of one element would take another path, the noise-free one). The
    chunked axis is the outermost whose inner axes hold at most ``chunk`` rollouts; each chunk
    runs as many of its elements as fit (the same number in every chunk) with one element of
    each axis outside it."""
    d = next(d for d in range(len(sizes)) if math.prod(sizes[d + 1 :]) <= chunk or d == len(sizes) - 1)
    inner = math.prod(sizes[d + 1 :])
    length = min(sizes[d], max(chunk // inner, 2 if d == len(sizes) - 1 else 1))
    out = []
    for outer in np.ndindex(*sizes[:d]):
        for a in range(0, sizes[d], length):
            b = min(a + length, sizes[d])
            ranges = tuple((i, i + 1) for i in outer) + ((a, b),) + tuple((0, n) for n in sizes[d + 1 :])
            start = 0
            for (lo, _), n in zip(ranges, sizes):  # the flat index of the block's first rollout
                start = start * n + lo
            out.append(Block(start, (b - a) * inner, ranges, d, length))
    return out


def _take(x, lo: int, hi: int, length: int):
    """Rows ``lo`` to ``hi`` of ``x`` (leading axis), repeating row ``hi - 1`` up to ``length``."""
    if hi - lo == length:
        return x[lo:hi]
    return x[np.minimum(np.arange(lo, lo + length), hi - 1)]


def inputs(plants, X0s, keys, block: Block, paired: bool) -> tuple[Any, Any, Any]:
    """The plants, initial states and keys (None: none) of ``block``'s chunk."""

    def part(x, axis: int):
        a, b = block.ranges[axis]
        return _take(x, a, b, block.length if axis == block.axis else b - a)

    last = len(block.ranges) - 1
    return (jax.tree.map(lambda x: part(x, 0), plants), part(X0s, 0 if paired else 1),
            None if keys is None else part(keys, last))  # fmt: skip


def run(simulate: Callable, plants, X0s, keys, paired: bool, chunk: int,
        log: Callable[[str], None], every: float = 10.0) -> dict[str, np.ndarray]:  # fmt: skip
    """Every rollout of the batch (``plants``, ``X0s``, ``keys``; ``paired`` or crossed) run in
    chunks of at most ``chunk`` rollouts by ``simulate(plants, X0s, keys) -> Result``, each
    chunk's metrics copied into arrays of the whole batch: {metric name: (N, 3), "diverged":
    (N,), "diverged_at": (N,)}. ``log`` gets a line after the first chunk (its time counts
    the compilation) and then at most one per ``every`` seconds, with the time left."""
    n_keys = 1 if keys is None else keys.shape[0]
    sizes = axes(jax.tree.leaves(plants)[0].shape[0], X0s.shape[0], n_keys, paired)
    todo, total = blocks(sizes, chunk), math.prod(sizes)
    out: dict[str, np.ndarray] = {}
    start = last = time.perf_counter()
    done = first = 0
    for i, block in enumerate(todo):
        result = simulate(*inputs(plants, X0s, keys, block, paired))
        got = {name: getattr(result.metrics, name) for name in METRIC_NAMES}
        got.update(diverged=result.diverged, diverged_at=result.diverged_at)
        for name, x in got.items():
            x = np.asarray(x)[: block.size]
            if name not in out:
                out[name] = np.empty((total,) + x.shape[1:], x.dtype)
            out[name][block.start : block.start + block.size] = x
        done += block.size
        now = time.perf_counter()
        if i == 0:  # the compilation's chunk: the rate comes from the others
            log(f"fosmc: chunk 1 of {len(todo)}: {done} of {total} rollouts in {now - start:.1f} s (compilation "
                "included)")  # fmt: skip
            first, last, compiled = done, now, now
        elif now - last >= every or i == len(todo) - 1:
            left = (now - compiled) / (done - first) * (total - done)
            log(f"fosmc: chunk {i + 1} of {len(todo)}: {done} of {total} rollouts in {now - start:.1f} s"
                + (f", about {left:.0f} s left" if i < len(todo) - 1 else ""))  # fmt: skip
            last = now
    return out
