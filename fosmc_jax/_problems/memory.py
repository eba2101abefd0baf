"""Memory as a resource, like time: a resolved config's batch estimated before anything is drawn
or compiled (:func:`estimate`), held against what this process may use (:func:`limit`), and a
batch that cannot fit refused in one line naming the key to change (:func:`refusal`).

The estimate is a lower bound: it counts the arrays a run certainly holds (the drawn plants in
float64 and in the run's precision, each rollout's state, metric accumulators and metrics, a
trace where ``[sim] save_every`` keeps one), not XLA's temporaries or the command line's
records. A batch refused here would certainly not fit; one that passes may still be too large.

``fosmc simulate`` runs a batch in chunks instead (:func:`plan`): what the whole run holds
(the drawn plants and initial states, every rollout's metrics, their records) must fit with one
chunk; the chunk is as many rollouts as fit beside it and the runtime's reserve, each counted
at :data:`WORK_FACTOR` times its working set, so that XLA's temporaries fit too.
"""

from __future__ import annotations

import math
import os
from typing import Any, NamedTuple

import numpy as np

from .._simulator.metrics import METRIC_NAMES
from .tables import Config

#: Floats of one rollout's working set and outputs: its plant state (9) and metric accumulators
#: (3 per metric) while it runs, then its metrics (3 per metric) with ``diverged`` and
#: ``diverged_at``, twice (the device's result and the NumPy copy a command reads).
ROLLOUT_FLOATS = 9 + 3 * len(METRIC_NAMES) + 2 * (3 * len(METRIC_NAMES) + 2)
#: Floats of one sample of a trace: t, X (9), X_d (9), U (3), s (3).
TRACE_FLOATS = 1 + 9 + 9 + 3 + 3
#: Entries of one linear plant: rows 3, 6, 9 of A (3 x 9) and of B (3 x 3).
LINEAR_ENTRIES = 27 + 9

# What fosmc simulate holds, run in chunks (plan)
#: Bytes of one rollout's outputs (beside its floats in the run's precision: 3 per metric and
#: ``diverged_at``) kept for the whole run however it is chunked: ``diverged`` and six int64
#: arrays (plant, offset, realization and arm indices, and the temporaries that make them).
OUTPUT_EXTRA_BYTES = 1 + 6 * 8
#: Floats of one rollout while its chunk runs: its plant state (9), metric accumulators (3 per
#: metric), the device's metrics and ``diverged_at``, and its initial state (9).
WORK_FLOATS = 9 + 3 * len(METRIC_NAMES) + 3 * len(METRIC_NAMES) + 1 + 9
#: How many times :data:`WORK_FLOATS` (with a plant's entries) a chunk is sized at: XLA's
#: temporaries and the generated kernel's per-rollout rows and carries, with room over the peak
#: resident memory seen (BENCHMARKS.md, "Figures behind the code"; 2 until the linear batch moved
#: onto the generated kernel, whose 500,000-rollout chunk then ran out of a 4 GB address space).
WORK_FACTOR = 6
#: Bytes of one rollout's record (``run_simulate(records=True)``: a dict of ints and of metric
#: rows), rounded up from tracemalloc's count (BENCHMARKS.md, "Figures behind the code").
RECORD_BYTES = 1700
#: Bytes per number of the draws ``run_simulate`` returns as lists (``sampled``), and per
#: sampled arm (``arms``: a dict of lists of the arm's 52 entries), each twice tracemalloc's
#: count, for ``--json``'s copy and text (BENCHMARKS.md, "Figures behind the code").
SAMPLED_BYTES, ARM_RECORD_BYTES = 80, 6400
#: What compiling and running take beyond the process that plans (its JAX backend started),
#: above the most an arm's noisy digital loop compiled afresh was seen to take
#: (BENCHMARKS.md, "Figures behind the code").
RESERVE = 0.75e9
#: The fewest rollouts worth a chunk.
MIN_CHUNK = 64


class Estimate(NamedTuple):
    """A batch's memory (bytes, a lower bound), its size in words, and the config key whose
    count dominates it (the one to change)."""

    bytes: int
    batch: str
    key: str


#: What to do with the dominating key (default: lower it).
ADVICE = {
    "sim.save_every": "raise sim.save_every (fewer trace samples; 0: none)",
    "arm.uncertainty.sampling": "set arm.uncertainty.samples to fewer corners, or sampling = 'uniform'",
    "plant.payloads": "list fewer plant.payloads",
    "sim.initial_offset": "list fewer sim.initial_offset rows",
}


def _box_vertices(cfg: Config) -> float:
    """How many vertices the linear box has (2^m, m its entries of non-zero width)."""
    box = cfg.plant.box
    pairs = ((box.A_lower, box.A_upper), (box.B_lower, box.B_upper))
    m = sum(int(np.sum(np.asarray(upper) > np.asarray(lower))) for lower, upper in pairs)
    return 2.0**m


def _arms(cfg: Config) -> tuple[int, str]:
    """How many sampled arms ``[arm.uncertainty]`` draws (1: none), and the key that sets it."""
    unc = cfg.arm.uncertainty
    live = sum(int(np.sum(np.broadcast_to(np.asarray(w, float), np.shape(x)) > 0))
               for w, x in zip(unc.widths, cfg.arm.params))  # fmt: skip
    if not live:
        return 1, "arm.uncertainty.samples"
    if unc.sampling == "uniform":
        return unc.samples, "arm.uncertainty.samples"
    corners = 2**live
    if not unc.samples or unc.samples >= corners:
        return corners, "arm.uncertainty.sampling"  # every corner of the varying entries
    return unc.samples, "arm.uncertainty.samples"


class Batch(NamedTuple):
    """A resolved config's batch in counts: ``rollouts``, ``plants``, initial states
    (``offsets``), ``arms`` sampled by ``[arm.uncertainty]`` (0: none), numbers ``sampled`` by
    ``[sample]``, floats per rollout of a ``trace`` (0: none), ``entries`` per plant, the
    run's float size ``item``, the bytes of the float64 arm draws (``drawn``), the key whose
    count dominates (``key``) and the batch in words (``words``)."""

    rollouts: float
    plants: float
    offsets: float
    arms: float
    sampled: float
    trace: int
    entries: int
    item: int
    drawn: float
    key: str
    words: str


def batch(cfg: Config) -> Batch:
    """:class:`Batch` of a resolved config (counts only: nothing is drawn)."""
    item = np.dtype(cfg.sim.precision).itemsize
    plant, sample, sim = cfg.plant, cfg.sample, cfg.sim
    plant_factors: dict[str, float] = {}  # key -> the count of plants it sets
    arms = 0
    if plant.kind == "arm":
        entries = sum(int(np.size(x)) for x in cfg.arm.params)
        arms, arm_key = _arms(cfg)
        plant_factors[arm_key] = arms
        plant_factors["sample.count" if sample.payloads else "plant.payloads"] = (
            sample.count if sample.payloads else len(plant.payloads)
        )
        drawn = 2 * arms * entries * 8  # the draws and the sampled arms, float64
    else:
        entries, drawn = LINEAR_ENTRIES, 0
        samples = plant.samples if plant.uncertainty in ("sample", "vertices") else 1
        vertices = plant.uncertainty == "vertices"
        plant_factors["plant.samples"] = min(samples, _box_vertices(cfg)) if vertices else samples
    offsets = sample.count if any(sample.offsets) else len(np.atleast_2d(sim.initial_offset))
    offset_key = "sample.count" if any(sample.offsets) else "sim.initial_offset"
    realizations = cfg.sensors.realizations if cfg.controller.sample_period else 1
    if sim.pairing == "paired":  # the i-th plant with the i-th initial state
        plants = max(*plant_factors.values(), offsets)
        rollouts = plants * realizations
    else:
        plants = math.prod(plant_factors.values())
        rollouts = plants * offsets * realizations
    factors = {**plant_factors, offset_key: max(offsets, plant_factors.get(offset_key, 0)),
               "sensors.realizations": realizations}  # fmt: skip
    n_steps = max(1, round(sim.t_final / sim.dt))
    trace = TRACE_FLOATS * (n_steps // sim.save_every + 1) if sim.save_every else 0
    key = max(factors, key=lambda k: factors[k])
    if trace and rollouts * trace > rollouts * ROLLOUT_FLOATS + plants * entries:
        key = "sim.save_every"
    words = f"{rollouts:.4g} rollout(s) of {plants:.4g} plant(s)" + (f", a trace of {trace // TRACE_FLOATS} samples"
                                                                       if trace else "")  # fmt: skip
    sampled = sample.count * ((1 if sample.payloads else 0) + (9 if any(sample.offsets) else 0))
    return Batch(rollouts, plants, offsets, arms, sampled, trace, entries, item, drawn, key, words)


def estimate(cfg: Config) -> Estimate:
    """The memory a resolved config's batch needs at least (see the module's docstring), from
    its plants (P), initial states (O), noise realizations (R), horizon and trace."""
    b = batch(cfg)
    total = b.drawn + b.plants * b.entries * (8 + b.item) + b.rollouts * (ROLLOUT_FLOATS + b.trace) * b.item
    return Estimate(int(min(total, 2**62)), b.words, b.key)


def held(cfg: Config, *, records: bool = False, draws: bool = False) -> float:
    """Bytes ``fosmc simulate`` holds for a resolved config's whole batch, however it is run in
    chunks: the drawn arms, plants and initial states (float64 and the run's precision), every
    rollout's outputs, and with ``records`` their records, with ``draws`` the draws as lists
    (``run_simulate``'s ``rollouts``, ``sampled`` and ``arms``)."""
    b = batch(cfg)
    total = b.drawn + b.plants * b.entries * (8 + b.item) + b.offsets * 9 * (8 + 2 * b.item)
    total += b.rollouts * ((3 * len(METRIC_NAMES) + 1) * b.item + OUTPUT_EXTRA_BYTES + (RECORD_BYTES if records else 0))
    if draws:  # drawn again for the lists
        total += b.sampled * (8 + SAMPLED_BYTES) + b.arms * (2 * b.entries * 8 + ARM_RECORD_BYTES)
    return total


def plan(cfg: Config, *, records: bool = False, draws: bool = False,
         available: tuple[int | None, str] | None = None) -> tuple[int, str | None]:  # fmt: skip
    """(rollouts per chunk, None) for ``fosmc simulate`` on a resolved config: the whole batch
    where it fits in :func:`limit` (or ``available``) less :data:`RESERVE` and what the run
    :func:`held`, else as many rollouts as that room holds at :data:`WORK_FACTOR` times their
    working set (:data:`MIN_CHUNK` at least); (0, the one-line refusal) where what the run
    holds and :data:`MIN_CHUNK` rollouts exceed the limit (the reserve, an estimate, left out:
    a batch is refused only where it cannot fit). A batch that keeps a trace (``[sim]
    save_every``) is not chunked (the trace is an output): :func:`refusal`'s check. Nothing is
    drawn."""
    b = batch(cfg)
    room, what = limit() if available is None else available
    if b.trace:
        too_large = refusal(cfg, (room, what))
        return (0, too_large) if too_large else (int(b.rollouts), None)
    if room is None:
        return int(b.rollouts), None
    keep = held(cfg, records=records, draws=draws)
    work = WORK_FACTOR * (WORK_FLOATS + b.entries) * b.item
    fewest = min(MIN_CHUNK, b.rollouts)
    if keep + fewest * work > room:
        advice = ADVICE.get(b.key, f"lower {b.key}")
        return 0, (f"{b.key}: the batch needs at least {_gb(keep + fewest * work)} ({b.words}; its draws and "
                   f"outputs, kept whole however it is chunked), more than the {_gb(room)} this process may use "
                   f"({what}): {advice}")  # fmt: skip
    return int(min(b.rollouts, max(fewest, (room - RESERVE - keep) // work))), None


def _meminfo(field: str) -> int | None:
    """A field of /proc/meminfo in bytes (Linux); None elsewhere."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith(field + ":"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def _mapped() -> int:
    """The address space this process maps now (VmSize, bytes; 0 where unknown)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmSize:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return 0


def limit() -> tuple[int | None, str]:
    """(bytes, what they are): the memory this process may still use, the smaller of the
    machine's available memory and, where ``ulimit -v`` sets one, its address-space limit less
    what the process maps already; (None, ...) where neither is known."""
    found = []
    available = _meminfo("MemAvailable")
    if available is None:
        try:
            available = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        except (ValueError, OSError, AttributeError):
            available = None
    if available is not None:
        found.append((available, "the machine's available memory"))
    try:
        import resource

        soft = resource.getrlimit(resource.RLIMIT_AS)[0]
        if soft != resource.RLIM_INFINITY:
            found.append((max(0, soft - _mapped()), "the address-space limit (ulimit -v) less what this process maps"))
    except (ImportError, OSError, ValueError):
        pass
    return min(found) if found else (None, "unknown")


def refusal(cfg: Config, available: tuple[int | None, str] | None = None) -> str | None:
    """The one-line refusal of a batch whose :func:`estimate` exceeds :func:`limit` (or
    ``available``), naming the key to lower first; None when it fits (or no limit is known)."""
    need = estimate(cfg)
    room, what = limit() if available is None else available
    if room is None or need.bytes <= room:
        return None
    advice = ADVICE.get(need.key, f"lower {need.key}")
    return (f"{need.key}: the batch needs at least {_gb(need.bytes)} ({need.batch}), more than the {_gb(room)} this "
            f"process may use ({what}): {advice}")  # fmt: skip


def _gb(n: Any) -> str:
    return f"{n / 1e9:.3g} GB"
