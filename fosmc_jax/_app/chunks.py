"""A batch run in chunks (``fosmc simulate`` on a batch larger than memory holds at once,
:func:`fosmc_jax._problems.memory.plan`): the same compiled program on chunks of one shape, the last
padded, every rollout's metrics written into arrays of the whole batch.

A batch's rollouts are flattened plant, offset, realization (paired: pair, realization) first
(:func:`fosmc_jax.simulate_batch`). A chunk is a contiguous run of them that the simulator can
make itself: a slice of the outermost axis whose inner axes fit, one element of each axis outside
it (:func:`blocks`). So each chunk is a batch of the same kind as the whole (cross or paired,
one key or several), which the simulator runs down the same path.

A run given a checkpoint folder writes each finished chunk there, atomically, and a run resumed
there reads the chunks it finds instead of running them: the chunk is the unit of resume.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import jax
import numpy as np

from .._io import atomic_write
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
    runs the same number of its elements (as few chunks as fit, evened out) with one element of
    each axis outside it."""
    d = next(d for d in range(len(sizes)) if math.prod(sizes[d + 1 :]) <= chunk or d == len(sizes) - 1)
    inner = math.prod(sizes[d + 1 :])
    length = min(sizes[d], max(chunk // inner, 2 if d == len(sizes) - 1 else 1))
    # as many chunks, evened out: the last padded by fewer elements than there are chunks (4.5e6 and
    # 0.5e6 padded to 4.5e6 ran nearly twice the work of two chunks of 2.5e6)
    length = -(-sizes[d] // -(-sizes[d] // length))
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


def chunk_path(checkpoint: Path, i: int) -> Path:
    """The file of chunk ``i`` in a checkpoint folder."""
    return Path(checkpoint) / f"chunk_{i:06d}.npz"


def _save(path: Path, arrays: dict[str, np.ndarray]) -> None:
    def write(tmp):
        with open(tmp, "wb") as f:  # a file object: np.savez would add ".npz" to a name
            np.savez(f, **arrays)

    atomic_write(path, write)


def _load(path: Path, block: Block) -> dict[str, np.ndarray]:
    """A finished chunk's arrays; ValueError where the file is not that chunk's."""
    with np.load(path) as z:
        got = {k: z[k] for k in z.files}
    if set(got) != set(OUTPUTS) or any(len(x) != block.size for x in got.values()):
        raise ValueError(f"{path} is not a chunk of {block.size} rollouts of this run")
    return got


#: The most rollouts per chunk of a run with a checkpoint (each chunk a file, the unit a killed
#: run resumes from; 16 MB of float64 metrics): few enough that a kill loses little, enough
#: that each chunk's overhead (its dispatch, its file) stays small beside its work
CHECKPOINT_CHUNK = 65_536
#: The arrays of each rollout that a chunk gives
OUTPUTS = (*METRIC_NAMES, "diverged", "diverged_at")


def run(simulate: Callable, plants, X0s, keys, paired: bool, chunk: int, log: Callable[[str], None],
        every: float = 10.0, checkpoint: Path | None = None) -> dict[str, np.ndarray]:  # fmt: skip
    """Every rollout of the batch (``plants``, ``X0s``, ``keys``; ``paired`` or crossed) run in
    chunks of at most ``chunk`` rollouts by ``simulate(plants, X0s, keys) -> Result``, each
    chunk's metrics copied into arrays of the whole batch: {metric name: (N, 3), "diverged":
    (N,), "diverged_at": (N,)}. With a ``checkpoint`` folder each finished chunk is written
    there (:func:`chunk_path`, atomically: a killed run leaves whole files), and a chunk whose
    file is there already is read instead of run (a resumed run). ``log`` gets a line after
    the first chunk run (its time counts the compilation) and then at most one per ``every``
    seconds, with the time left."""
    n_keys = 1 if keys is None else keys.shape[0]
    sizes = axes(jax.tree.leaves(plants)[0].shape[0], X0s.shape[0], n_keys, paired)
    todo, total = blocks(sizes, chunk), math.prod(sizes)
    kept = [checkpoint is not None and chunk_path(checkpoint, i).exists() for i in range(len(todo))]
    if any(kept):
        log(f"fosmc: {sum(kept)} of {len(todo)} chunks are in {checkpoint}"
            + (": nothing to run" if all(kept) else f": running the other {len(todo) - sum(kept)}"))  # fmt: skip
    out: dict[str, np.ndarray] = {}
    start = last = time.perf_counter()
    done = ran = 0  # rollouts in the arrays; rollouts run since the compilation's chunk
    compiled = None  # when the first chunk run (with the compilation) ended
    for i, block in enumerate(todo):
        if kept[i]:
            got = _load(chunk_path(checkpoint, i), block)
        else:
            result = simulate(*inputs(plants, X0s, keys, block, paired))
            got = {name: getattr(result.metrics, name) for name in METRIC_NAMES}
            got.update(diverged=result.diverged, diverged_at=result.diverged_at)
            got = {name: np.asarray(x)[: block.size] for name, x in got.items()}
            del result
            if checkpoint is not None:
                _save(chunk_path(checkpoint, i), got)
        for name, x in got.items():
            if name not in out:
                out[name] = np.empty((total,) + x.shape[1:], x.dtype)
            out[name][block.start : block.start + block.size] = x
        del got  # the chunk's buffers freed before the next chunk runs
        done += block.size
        if kept[i]:
            continue
        now = time.perf_counter()
        if compiled is None:  # the compilation's chunk: the rate comes from the others
            log(f"fosmc: chunk {i + 1} of {len(todo)}: {done} of {total} rollouts in {now - start:.1f} s "
                "(compilation included)")  # fmt: skip
            last = compiled = now
            continue
        ran += block.size
        if now - last >= every or i == len(todo) - 1:
            left = (now - compiled) / ran * (total - done)
            log(f"fosmc: chunk {i + 1} of {len(todo)}: {done} of {total} rollouts in {now - start:.1f} s"
                + (f", about {left:.0f} s left" if i < len(todo) - 1 else ""))  # fmt: skip
            last = now
    return out
