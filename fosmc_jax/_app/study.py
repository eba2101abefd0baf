"""The study behind fosmc front: a resolved config's training, plain and held-out problems
built once, the search of :mod:`fosmc_jax._search.front` run on them, every front point
evaluated on the held-out batch, the paper's references beside it, and front.json / front.png
written; what ``--resume`` finds in an output folder (:func:`finished`, :func:`start_afresh`)
and what ``--replay`` redoes (:func:`replayed`)."""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .. import _problems as problems
from .._design import paper
from .._io import jsonable, write_text
from .._search import tune as tuner
from .._search.front import Evaluator, Settings, front_search, point_of, replay_settings
from .._simulator import sharding

#: A front point holds on the held-out batch where its mean rms_error there is within this share
#: of its training one (tuning/held_out_arms.py's measure).
HOLDS = 0.25


def held_out_summary(points: list[dict]) -> str:
    """One line on how the front's points hold on the held-out batch: how many are within
    :data:`HOLDS` of their training mean rms_error, and the worst ratio (a point with a diverged
    held-out rollout counts as not holding)."""
    mean = lambda m: float(np.mean([np.nan if x is None else x for x in m["rms_error"]]))
    ratio = np.array([mean(p["held_out"]) / mean(p["metrics"]) for p in points])
    ratio[[p.get("held_out_diverged", 0) > 0 for p in points]] = np.nan
    holds = int(np.sum(np.abs(ratio - 1) <= HOLDS))
    worst = int(np.nanargmax(ratio)) if np.isfinite(ratio).any() else None
    diverged = int(np.sum(np.isnan(ratio)))
    return (f"front: held out: {holds} of {len(points)} points within {100 * HOLDS:.0f}% of their training rms_error"
            + (f", the worst {ratio[worst]:.3g}x (point {worst})" if worst is not None else "")
            + (f", {diverged} with a diverged held-out rollout" if diverged else "")
            + " (fosmc select judges a point on the larger of both)")  # fmt: skip


def references(front: problems.FrontProblems, chunk: int, plain: Evaluator) -> dict[str, dict]:
    """Plain mean metrics of the paper's FOSMC, whatever the config's kind: Table 1's three
    sets (the config's switching) and SGN, with the config's gamma and poles, on the config's
    batch (``front.references``); Table 1's through ``plain`` (the config's plain problem, its
    evaluator compiled once for the study) when the config's kind is the FOSMC."""
    out = {}
    for label, sets in (("Table 1", (0, 1, 2)), ("SGN", (0,))):
        reference = front.references[label]
        problem = plain if reference is None else Evaluator(reference)
        base = problem.problem.base
        p0 = tuner.Tunable(*(getattr(base, k) for k in tuner.PARAM_NAMES))
        ps = tuner.Tunable(jnp.stack([jnp.asarray(paper.DELTA_SETS[k], p0.delta.dtype) for k in sets]),
                       jnp.stack([p0.gamma] * len(sets)), jnp.stack([p0.poles] * len(sets)))  # fmt: skip
        m = problem(ps, chunk if problem is plain else len(sets), log=lambda _: None)
        for i, k in enumerate(sets):
            out[f"{label} set {k + 1}" if label == "Table 1" else label] = point_of(
                jax.tree.map(lambda x, i=i: x[i], ps), m, i)  # fmt: skip
    return out


def finished(
    out: Path | None, name: str, cfg: problems.Config, command: str, log: Callable[[str], None]
) -> dict | None:
    """What ``--resume`` finds in ``out`` when the run there is complete: its final file
    ``name`` (``front.json``, ``result.json``; written last, and removed when a run starts
    afresh, :func:`start_afresh`), returned as it is after one line saying so; None when there
    is none (the run resumes from its checkpoint, or starts). A complete run of another config
    is refused (``ConfigError`` naming ``--resume``): resuming it would mix two studies."""
    path = None if out is None else Path(out) / name
    if path is None or not path.exists():
        return None
    try:
        done = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise problems.ConfigError(f"--resume: cannot read {path}: {e}") from None
    if done.get("config") != json.loads(json.dumps(jsonable(cfg.as_dict()))):
        raise problems.ConfigError(f"--resume: {path} is a complete run of another config: give its config, or "
                                  "--force to start afresh")  # fmt: skip
    log(f"{command}: {path} is complete (nothing to resume): left as it is; --force starts afresh")
    return done


def start_afresh(out: Path | None, *names: str) -> None:
    """Remove a previous run's final file and checkpoint ``names`` from ``out`` (a run started
    over it with ``--force``), so that a final file in a folder always belongs to its last
    run, and a checkpoint never to another run."""
    for name in names if out is not None and sharding.leads() else ():  # process 0 alone writes
        (Path(out) / name).unlink(missing_ok=True)


def replayed(path: str | Path) -> tuple[dict, Settings]:
    """The config and the :class:`fosmc_jax._search.front.Settings` that redo the work of the
    front in ``path`` (``fosmc front --replay``; :func:`fosmc_jax._search.front.replay_settings`);
    ``ConfigError`` naming ``--replay`` for a file that is not such a front."""
    try:
        data = json.loads(Path(path).read_text())
        return problems.as_config(data["config"]), replay_settings(data["stages"])
    except (KeyError, TypeError, AttributeError):
        raise problems.ConfigError(f"--replay: {path} is not a fosmc front front.json (no config or stages)") from None
    except (OSError, ValueError) as e:
        raise problems.ConfigError(f"--replay: {path}: {str(e).splitlines()[0]}") from None


#: Seconds kept at the end of ``fosmc front``'s budget for writing front.json and drawing front.png.
WRITE_S = 1.5


def study(cfg: problems.Config, settings: Settings, *, out: Path | None = None, resume: bool = False,
          compare: tuple = (), started: float | None = None, log: Callable[[str], None] = print
          ) -> dict[str, Any]:  # fmt: skip
    """``fosmc front``: the front of a resolved config's controller kind (its own parameters;
    training and plain problems as ``fosmc tune`` builds them), each point also evaluated on
    :func:`held_out_config`'s batch, the FOSMC's Table 1 sets and SGN beside it. The budget
    counts from ``started`` (a ``time.perf_counter()`` value: the CLI's process start; None:
    now): the held-out evaluator is compiled first and its cost per point kept out of the
    search's time. Writes ``front.json`` and ``front.png`` (and a checkpoint) to ``out`` when
    given; returns what ``front.json`` holds. With ``resume``, a complete run in ``out`` is
    returned as it is (:func:`finished`); without, a previous run's front.json and checkpoint
    there are removed first (:func:`start_afresh`)."""
    t0 = time.perf_counter() if started is None else started
    if resume and (done := finished(out, "front.json", cfg, "front", log)) is not None:
        return done
    if not resume:
        start_afresh(out, "front.json", "checkpoint.npz")
    front = problems.front_problems(cfg)
    train, p0 = front.train, front.p0
    plain = Evaluator(front.plain)  # compiled once: for the references and the search
    refs = references(front, settings.chunk, plain)
    held = Evaluator(front.held_out)
    one = jax.tree.map(lambda x: jnp.broadcast_to(x, (settings.chunk,) + jnp.shape(x)), p0)
    held(one, settings.chunk, log=lambda _: None)  # compiled
    held_s = np.inf
    for _ in range(3):  # the held-out evaluation's cost per front point: the least of three warm chunks
        t = time.perf_counter()
        held(one, settings.chunk, log=lambda _: None)
        held_s = min(held_s, (time.perf_counter() - t) / settings.chunk)
    held_s = sharding.first(float(held_s))  # process 0's: the search's plan is the same on every process
    log(f"front: the held-out evaluation costs {1e3 * held_s:.1f} ms per front point")
    checkpoint = None if out is None else Path(out) / "checkpoint.npz"
    result = front_search(train, plain, p0, settings, checkpoint=checkpoint, resume=resume,
                 deadline=t0 + settings.budget - WRITE_S, reserve_per_point=1.5 * held_s, log=log)  # fmt: skip
    params = type(p0)(*(jnp.asarray(np.array([pt["params"][k] for pt in result["points"]]), x.dtype)
                        for k, x in zip(p0._fields, p0)))  # fmt: skip
    mh = held(params, settings.chunk, log=log, what="held-out evaluation")
    for i, pt in enumerate(result["points"]):
        held_point = point_of(jax.tree.map(lambda x, i=i: x[i], params), mh, i)
        pt["held_out"], pt["held_out_diverged"] = held_point["metrics"], held_point["diverged"]
    log(held_out_summary(result["points"]))
    result["references"] = refs
    result["held_out_batch"] = front.held_out_batch
    result["config"] = cfg.as_dict()
    if out is not None and sharding.leads():
        from .plots import plot_front

        write_text(Path(out) / "front.json", json.dumps(jsonable(result), indent=1))
        plot_front(result, [(Path(c).parent.name or str(c), json.loads(Path(c).read_text())) for c in compare],
                   Path(out) / "front.png")  # fmt: skip
        log(f"front: wrote {out}/front.json and {out}/front.png")
    return result
