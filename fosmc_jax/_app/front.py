"""``fosmc front`` as a function: the trade-off front of the config's batch."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

from .._problems import ConfigError
from .._simulator import sharding
from .distributed import JOIN_TIMEOUT_S, Processes, agreeing, digest, join
from .shared import (
    ConfigInput,
    Log,
    _fresh_out,
    _is_integer,
    _is_real,
    _quiet,
    _warn_one_plant,
    _with_x64,
    config_of,
)

#: The largest ``fosmc front --seed``: its CMA-ES runs seed NumPy's legacy generator with
#: ``seed * 1_000_003 + 700_000 + run`` (``fosmc_jax._search.front``), which must stay below 2^32.
MAX_FRONT_SEED = (2**32 - 1 - 700_000 - 1_000) // 1_000_003


@_with_x64
def run_front(
    config: ConfigInput = None,
    *,
    out: str | Path | None = None,
    points: int | None = None,
    budget: float = 300.0,
    candidates: int | None = None,
    steps: int | None = None,
    seed: int = 0,
    gradient_share: float = 0.25,
    gradient_on: str = "train",
    plain_share: float = 0.25,
    search: str | None = None,
    population: int = 256,
    generations: int | None = None,
    compare: tuple[str | Path, ...] | list[str | Path] = (),
    force: bool = False,
    resume: bool = False,
    replay: str | Path | None = None,
    started: float | None = None,
    log: Log = _quiet,
    distributed: bool = False,
    coordinator: str | None = None,
    num_processes: int | None = None,
    process_id: int | None = None,
    join_timeout: float = JOIN_TIMEOUT_S,
) -> dict[str, Any]:
    """``fosmc front``: the Pareto front of mean ``rms_error`` against mean
    ``chattering_hf`` over the config's batch within ``budget`` seconds of wall time, over the
    parameters of the config's ``controller.kind`` (every kind is tunable: the FOSMC's delta,
    gamma, poles; SMC's k, phi; super-twisting's k1, k2; per-joint log scale factors in the
    kind's box, ``fosmc_jax._search.tune.SPACES``), by ``fosmc_jax._app.study.study``: ``points``
    parents per local round, default 8; ``candidates``, ``steps``: the global stage's size and
    the local rounds, default from the budget; ``seed``: of the search's draws;
    ``gradient_share``: with sizes from the budget, the share of the search time spent at the end
    on gradient steps that refine the front's points (:func:`fosmc_jax._search.front._gradient`;
    0: none; default 0.25); ``gradient_on``: the problem they descend, "plain" or "train" (with a
    training surrogate its cheaper gradient, the points reached evaluated on the plain problem;
    the default; without one the two are the same).
    ``plain_share``: with a training surrogate and sizes from the budget, the share of the
    search time the gradient steps leave that goes to local rounds on the plain problem around
    the re-evaluated training front (0: none, the re-evaluation only; default 0.25).
    ``search``: the derivative-free search, "nsga2" (pymoo's NSGA-II of
    ``population``, ``generations`` from the budget unless given) or "staged" (global stage,
    CMA-ES, local rounds: ``candidates``, ``steps``); None: "staged" where ``candidates`` or
    ``steps`` are given, else "nsga2". ``out``: folder for ``front.json``,
    ``front.png`` (with the ``compare`` files' points drawn beside) and the checkpoint (None:
    nothing written); ``resume`` continues from its checkpoint. The budget counts from
    ``started`` (a ``time.perf_counter()`` value; the CLI passes its process's start; None:
    this call). ``replay``: a front.json whose recorded work (``stages.replay``) is redone with
    its config, seed and sizes, without a clock: bit for bit the same front on the same machine
    and device count (``config``, ``points``, ``candidates``, ``steps`` not given).

    Returns what ``front.json`` holds: ``{"fosmc_jax": {"version", "metrics_version"},
    "axes", "points": [{params, metrics, held_out, held_out_diverged, diverged}], "stages", "references",
    "held_out_batch", "config"}``, ``params`` by the kind's names, ``references`` the paper's
    FOSMC (Table 1's sets, SGN) whatever the kind. With ``candidates`` and ``steps`` given the
    result is deterministic except ``stages.wall_time_s``. On a batch of one plant
    (:func:`one_plant`) it warns as ``run_tune`` does. Its ``log`` lines start with ``front:``.

    Across processes (:mod:`fosmc_jax._app.distributed`): ``distributed`` (``jax.distributed.initialize()``
    finds SLURM or Open MPI), or ``coordinator`` ``"HOST:PORT"``, ``num_processes`` and this
    ``process_id``, all joined within ``join_timeout`` s, before JAX computes anything in this
    process (a :class:`ConfigError` otherwise). Each process runs this call with the same
    config and options (checked before any work); the candidates are split over every
    process's devices; every process returns the same result, process 0 alone logs and writes
    ``out`` (``resume`` reads the checkpoint every process sees there: the same file).
    """
    from .._search import front as search_front
    from . import study

    across = join(Processes(distributed, coordinator, num_processes, process_id, join_timeout))
    lead = not across or sharding.leads()
    log = log if lead else _quiet
    with agreeing(across) as agree:
        cfg, out = _checked_front(config, out, points, budget, candidates, steps, seed, compare, force, resume, replay,
                                  lead)  # fmt: skip
        if not (_is_real(gradient_share) and 0 <= gradient_share < 1):
            raise ConfigError(f"--gradient-share: expected a number in [0, 1), got {gradient_share}")
        if not (_is_real(plain_share) and 0 <= plain_share < 1):
            raise ConfigError(f"--plain-share: expected a number in [0, 1), got {plain_share}")
        if gradient_on not in search_front.GRADIENT_ON:
            raise ConfigError(
                f"--gradient-on: expected one of {', '.join(search_front.GRADIENT_ON)}, got {gradient_on!r}"
            )
        search = _checked_search(search, population, generations, candidates, steps, replay)
        files = (*compare, replay, *((out / "checkpoint.npz", out / "front.json") if resume and out else ()))
        agree(digest({"command": "front", "config": cfg.as_dict(), "out": out, "points": points, "budget": budget,
                      "candidates": candidates, "steps": steps, "seed": seed, "gradient_share": gradient_share,
                      "gradient_on": gradient_on, "plain_share": plain_share, "search": search,
                      "population": population,
                      "generations": generations,
                      "compare": list(compare),
                      "force": force, "resume": resume, "replay": replay}, files))  # fmt: skip
    if lead:
        _warn_one_plant(cfg, "front")
    if out is not None and lead:
        out.mkdir(parents=True, exist_ok=True)
    settings = search_front.Settings(points=points or 8, budget=budget, candidates=candidates or 0,
                                     steps=steps or 0, seed=seed, gradient_share=gradient_share,
                                     gradient_on=gradient_on, polish_share=plain_share, search=search,
                                     population=population, generations=generations or 0)  # fmt: skip
    if replay is not None:
        settings = study.replayed(replay)[1]._replace(budget=budget)
    return study.study(cfg, settings, out=out, resume=resume, compare=tuple(compare), started=started, log=log)


def _checked_search(search, population, generations, candidates, steps, replay) -> str:
    """The search a front runs (``run_front``'s ``search``), its sizes checked (one-line
    :class:`ConfigError` s)."""
    from .._search import front as search_front

    staged_sizes = [n for n, v in (("--candidates", candidates), ("--steps", steps)) if v is not None]
    given = [n for n, v in (("--search", search), ("--generations", generations)) if v is not None]
    if replay is not None and given:
        raise ConfigError(f"--replay: takes the search and sizes from its front.json: leave out {', '.join(given)}")
    if search is None:  # the staged search's sizes choose it
        search = "staged" if staged_sizes else search_front.Settings._field_defaults["search"]
    if search not in search_front.SEARCHES:
        raise ConfigError(f"--search: expected one of {', '.join(search_front.SEARCHES)}, got {search!r}")
    if search == "nsga2" and staged_sizes:
        raise ConfigError(f"{', '.join(staged_sizes)}: sizes of the staged search; NSGA-II's is --generations")
    if search == "staged" and generations is not None:
        raise ConfigError("--generations: NSGA-II's size (--search nsga2); the staged search's are --candidates, "
                          "--steps")  # fmt: skip
    if generations is not None and not (_is_integer(generations) and generations >= 1):
        raise ConfigError(f"--generations: expected a positive integer, got {generations}")
    if not (_is_integer(population) and population >= 4):
        raise ConfigError(f"--population: expected an integer of 4 or more, got {population}")
    return search


def _checked_front(config, out, points, budget, candidates, steps, seed, compare, force, resume, replay,
                   lead) -> tuple[dict, Path | None]:  # fmt: skip
    """``run_front``'s checks of its inputs (one-line :class:`ConfigError` s): the resolved
    config and the output folder (probed by process 0 alone, the one that writes)."""
    from . import study

    if resume and force:
        raise ConfigError("--resume: continues the run in --out, --force starts it afresh: give one of them")
    if replay is not None:
        given = [n for n, v in (("--config", config), ("--points", points), ("--candidates", candidates),
                                ("--steps", steps)) if v is not None]  # fmt: skip
        if given:
            raise ConfigError(f"--replay: takes the config and sizes from its front.json: leave out {', '.join(given)}")
        cfg = study.replayed(replay)[0]
    else:
        cfg = config_of(config)
    if out is not None:
        out = _fresh_out(out, force or resume, "use --resume or --force") if lead else Path(out)
    for name, value in (("--points", points), ("--candidates", candidates), ("--steps", steps)):
        if value is not None and not (_is_integer(value) and value >= (1 if name == "--points" else 0)):
            raise ConfigError(f"{name}: expected a {'positive' if name == '--points' else 'non-negative'} "
                              f"integer, got {value}")  # fmt: skip
    if not (_is_real(budget) and math.isfinite(budget) and budget > 0):
        raise ConfigError(f"--budget: expected a positive, finite number of seconds, got {budget}")
    if not (_is_integer(seed) and 0 <= seed <= MAX_FRONT_SEED):
        raise ConfigError(f"--seed: expected an integer in [0, {MAX_FRONT_SEED}], got {seed}")
    for path in compare:
        try:
            json.loads(Path(path).read_text())
        except (OSError, ValueError) as e:
            raise ConfigError(f"--compare: cannot read {path}: {e}") from None
    return cfg, out
