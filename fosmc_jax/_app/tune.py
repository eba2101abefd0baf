"""``fosmc tune`` as a function: one controller tuned on the config's batch."""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Any, NamedTuple

import jax
import numpy as np

from .. import _problems as problems
from .._controllers import KINDS
from .._io import jsonable, stamped, write_text
from .._problems import ConfigError
from .._simulator import sharding
from .._simulator.metrics import UNITS
from .distributed import JOIN_TIMEOUT_S, Processes, agreeing, digest, join
from .shared import (
    ConfigInput,
    Log,
    _fresh_out,
    _is_real,
    _quiet,
    _warn_one_plant,
    _with_x64,
    config_of,
    metric_label,
)


@_with_x64
def run_tune(
    config: ConfigInput = None,
    *,
    steps: int | None = None,
    out: str | Path | None = None,
    resume: bool = False,
    force: bool = False,
    budget: float | None = None,
    started: float | None = None,
    log: Log = _quiet,
    distributed: bool = False,
    coordinator: str | None = None,
    num_processes: int | None = None,
    process_id: int | None = None,
    join_timeout: float = JOIN_TIMEOUT_S,
) -> dict[str, Any]:
    """``fosmc tune``: gradient-based tuning (optax) of the ``[tune] params`` of the config's
    ``controller.kind`` (every kind is tunable, each with its own parameters: the FOSMC's
    delta, gamma, poles; SMC's k, phi; super-twisting's k1, k2; default: all of them) on the
    training simulation (``tune.train_dt``, ``tune.train_t_final``), with the objective's
    scales taken at the config's parameters, the optional global stage
    (``tune.global_candidates``) and, for a kind the gamma bounds are for (``Kind.gamma_bounds``:
    the FOSMC), gamma floor (24)-(26) (``tune.keep_gamma_bound``); initial and final parameters
    evaluated on the plain ``[sim]`` simulation.

    ``steps`` overrides ``tune.steps``. ``budget``: seconds of wall time from ``started`` (a
    ``time.perf_counter()`` value; the CLI passes its process's start; None: this call's),
    compilation included, which the global stage and the gradient steps share (:func:`plan`,
    planned once the gradient is compiled; the held-out evaluation compiled before and the
    files' time kept back): the steps are as many as fit, ``FILL`` x ``tune.steps`` at most
    (``steps`` at most where given). ``out``: folder for ``result.json``, ``tuning.png``
    and ``checkpoint.npz`` (None: nothing written; ``tuning.png`` draws the kind's
    parameters); ``resume`` continues from its checkpoint. Returns what
    ``result.json`` holds: ``{"fosmc_jax": {"version", "metrics_version"}, "initial":
    {"params", "metrics", ...}, "start": {"params", "global_candidates"}, "final": {...},
    "held_out": {"metrics", ...}, "held_out_batch", "objective", "history", "config"}``
    (``held_out``: the final parameters on :func:`fosmc_jax._problems.held_out_config`'s
    batch, fresh payloads, sampled arms and draws, as ``fosmc front`` evaluates its points),
    ``params`` by the kind's names (e.g. ``{"k": [...], "phi": [...]}``). On a batch of one
    plant (:func:`one_plant`: the default config's nominal model) it warns (``UserWarning``)
    that the optimum holds for that plant only. Its ``log`` lines start with ``tune:``; its
    step lines name the objective's metrics.

    Across processes (``distributed`` or ``coordinator``, ``num_processes``, ``process_id``,
    ``join_timeout``: as :func:`fosmc_jax._app.front.run_front`'s), the global stage's candidates
    and the training batch's rollouts (where their count divides among the devices) are split
    over every process's devices; every process returns the same result, process 0 alone logs
    and writes ``out``.
    """
    from . import study

    started = time.perf_counter() if started is None else started
    across = join(Processes(distributed, coordinator, num_processes, process_id, join_timeout))
    lead = not across or sharding.leads()
    log = log if lead else _quiet
    with agreeing(across) as agree:
        cfg, out = _checked_tune(config, steps, out, resume, force, budget, lead)
        files = (out / "checkpoint.npz", out / "result.json") if resume and out is not None else ()
        agree(digest({"command": "tune", "config": cfg.as_dict(), "out": out, "resume": resume, "force": force,
                      "budget": budget}, files))  # fmt: skip
    if out is not None:
        if resume and (done := study.finished(out, "result.json", cfg, "tune", log)) is not None:
            return done
        if not resume:
            study.start_afresh(out, "result.json", "checkpoint.npz")
    if lead:
        _warn_one_plant(cfg, "tune")
    return _tune(cfg, out, resume, budget, started, lead, log, fill=budget is not None and steps is None)


def _checked_tune(config, steps, out, resume, force, budget, lead) -> tuple[dict, Path | None]:
    """``run_tune``'s checks of its inputs (one-line :class:`ConfigError` s): the resolved
    config with ``steps`` in it, and the output folder (probed by process 0 alone, the one that
    writes)."""
    from .._search import tune as tuner

    if resume and force:
        raise ConfigError("--resume: continues the run in --out, --force starts it afresh: give one of them")
    if budget is not None and not (_is_real(budget) and math.isfinite(budget) and budget > 0):
        raise ConfigError(f"--budget: expected a positive, finite number of seconds, got {budget}")
    cfg = config_of(config)
    if steps is not None:
        if steps < 1:
            raise ConfigError(f"--steps: expected a positive integer, got {steps}")
        cfg = problems.replace(cfg, tune={"steps": steps})
    tcfg = cfg.tune
    kind = cfg.controller.kind
    names = tuner.SPACES[kind].names
    if not set(tcfg.params) <= set(names):
        raise ConfigError(f"tune.params: expected names drawn from {', '.join(names)} (the parameters of "
                          f"controller.kind = '{kind}'), got {list(tcfg.params)}")  # fmt: skip
    if tcfg.keep_gamma_bound and not KINDS[kind].gamma_bounds:
        held = " or ".join(f"'{k.name}'" for k in KINDS.values() if k.gamma_bounds)
        raise ConfigError(f"tune.keep_gamma_bound: applies to controller.kind = {held} only (the gamma bounds "
                          f"(24)-(26)), got kind = '{kind}'")  # fmt: skip
    if out is not None:
        out = _fresh_out(out, force or resume, "use --resume or --force") if lead else Path(out)
    return cfg, out


#: With ``--budget``: the global stage's least share of the time left once the gradient is compiled
#: (it takes more where ``tune.steps`` steps need less), and the seconds kept back for writing
#: ``result.json`` and the process's exit (JAX's teardown), which the budget counts as a stopwatch
#: does, beside the drawing of ``tuning.png`` (measured: :func:`_drawing_seconds`).
GLOBAL_SHARE, EXIT_SECONDS = 0.3, 2.0

#: With ``--budget`` and no ``--steps``: the gradient steps fill the budget, at most ``FILL`` x
#: ``tune.steps`` of them (the cosine schedule spans those that fit). On the realistic preset a
#: step costs a few hundredths of a second and the loss still falls after ``tune.steps`` of them
#: (BENCHMARKS.md, "fosmc tune --budget").
FILL = 10

#: The CMA-ES stage (``tune.cma_generations``; with ``--budget`` and no ``--steps`` ``FILL`` times as
#: many at most, as the steps): candidates a generation, the first steps' size in the internal
#: coordinates (0.3: a factor 1.35; ahead of 0.1 on most configs of tuning/results/tune_vs_cma.md,
#: behind it on the five of tune_vs_cma_polish_one_start_more.md),
#: and with ``--budget`` its share of the time the global stage leaves (it hands over earlier where
#: pycma stops it; tuning/results/tune_vs_cma_polish.md measured 0.5)
CMA_POPSIZE, CMA_SIGMA, CMA_SHARE = 16, 0.3, 0.5

#: The global stage's candidates per evaluation (the config's parameters are evaluated by the
#: same program, for the objective's scales)
CHUNK = 16


class Plan(NamedTuple):
    """A ``--budget``'s deadlines, ``time.perf_counter()`` values counted from the process's start
    (None: no budget): the global stage's, and the gradient steps' (the evaluations and files
    after them kept back at their measured cost)."""

    global_stage: float | None = None
    steps: float | None = None


def _drawing_seconds() -> float:
    """What drawing ``tuning.png`` costs, measured by a first drawing into a scratch folder after
    matplotlib's import (both, under load, take seconds; done now, the real drawing then finds
    them done)."""
    import tempfile

    from .plots import plot_tuning

    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        plot_tuning({"loss": [1.0], "error": [1.0], "chattering": [1.0]}, [{"x": [1.0]}], Path(tmp) / "tuning.png")
    return time.perf_counter() - t0


def plan(end: float | None, step_seconds: float, steps: int, fallback_seconds: float, now: float) -> Plan:
    """The deadlines of a run whose steps must end by ``end`` (None: no budget), planned at ``now``
    with the gradient and the global stage's evaluation compiled (a step: ``step_seconds``). The
    global stage gets what ``steps`` steps and ``fallback_seconds`` (a second compilation, where
    the gradient at the start may fall back to another loss's; the steps get it where it does
    not) do not need, ``GLOBAL_SHARE`` of the time left at least (it evaluates one chunk of
    candidates even past its deadline)."""
    if end is None:
        return Plan()
    left = max(0.0, end - now - fallback_seconds)
    share = max(GLOBAL_SHARE * left, left - (steps + 3) * step_seconds)  # + the steps' timing calls
    return Plan(now + share, end)


def _start(tcfg, problem, obj, p0, floor, checkpoint: Path | None, deadline: float | None, log: Log):
    """Where the gradient steps start: a resumed run's first start (kept in its ``checkpoint``),
    else the best of the global stage's candidates (``tune.global_candidates``, those evaluated
    before ``deadline``, on ``problem``, a problem or its :class:`fosmc_jax._search.front.Evaluator`),
    else the config's parameters ``p0``; and with ``tune.starts`` above 1 the best ``starts`` of
    those candidates (a leading axis; None otherwise)."""
    from .._search import front
    from .._search import tune as tuner

    kept = tuner.checkpoint_extra(checkpoint) if checkpoint is not None else None
    if kept and "start" in kept:
        return type(p0)(*(jax.numpy.asarray(kept["start"][k], x.dtype) for k, x in zip(p0._fields, p0))), None
    if not tcfg.global_candidates or floor is not None or checkpoint is not None:
        return p0, None
    starts, scores = front.global_starts(problem, obj, p0, tcfg.global_candidates, tcfg.starts, chunk=CHUNK,
                                         free=tuple(tcfg.params), log=log, deadline=deadline)  # fmt: skip
    which = "the best candidate" if deadline else f"the best of {tcfg.global_candidates} candidates"
    log(f"tune: global stage: {which} scores {scores[0]:.4f} (the config's parameters score about 0 with the log "
        "scale)" + (f"; the best {len(scores)} start the gradient steps" if tcfg.starts > 1 else ""))  # fmt: skip
    return jax.tree.map(lambda x: x[0], starts), starts if len(scores) > 1 else None


def _tune(cfg: problems.Config, out: Path | None, resume: bool, budget: float | None, started: float, lead: bool,
          log: Log, fill: bool = False) -> dict[str, Any]:  # fmt: skip
    """``run_tune``'s work, its inputs checked: the evaluations at the config's parameters
    (:func:`_evaluations`), the budget's end (:func:`_end`), the gradient compiled and the
    deadlines planned, the global stage (:func:`_start`), the gradient steps, and the final and
    held-out evaluations with the files (:func:`_result`)."""
    from .._search import tune as tuner

    tcfg = cfg.tune
    plain, problem, p0 = problems.tuning_problems(cfg)
    if out is not None and lead:
        out.mkdir(parents=True, exist_ok=True)
    floor = None
    if tcfg.keep_gamma_bound:  # alpha, beta of the design model the controller is built on
        d = problems.design_summary(cfg)
        floor = tuner.GammaFloor(d.alpha.value, d.beta.value, tcfg.gamma_bound_convention)
    log(f"tune: {problem.rollouts} rollouts x {problem.options['n_steps']} steps (dt = {float(problem.dt)} s) "
        f"per training evaluation; free parameters: {', '.join(tcfg.params)}")  # fmt: skip
    checkpoint = None if out is None else out / "checkpoint.npz"
    resuming = resume and checkpoint is not None and checkpoint.exists()
    searching = bool(tcfg.global_candidates) and floor is None
    evaluator, evaluate_plain, m = _evaluations(cfg, plain, problem, p0, searching)
    initial = evaluate_plain(p0)
    held = problems.held_out_config(cfg)
    held_problem = problems.tuning_problems(held)[0]
    end = None if budget is None else _end(held_problem, p0, started + budget, out is not None and lead)
    obj = tuner.objective_of(tcfg, m)
    log(f"tune: objective {obj.form} ({obj.scale} scale) of {metric_label(obj.error_metric)} and "
        f"{metric_label(obj.chattering_metric)}, each relative to its value at the config's parameters on the training "
        f"simulation ({obj.error_ref:.4e} {UNITS[obj.error_metric]}, {obj.chattering_ref:.4e} "
        f"{UNITS[obj.chattering_metric]}): the terms below are unit-free")  # fmt: skip
    tv_floor = _tv_floor(cfg, obj, log)
    try:
        u_p0 = tuner.to_internal(p0, plain.base, floor)
    except ValueError as e:
        raise ConfigError(str(e)) from None
    lr = tuner.learning_rate(tcfg.learning_rate, problems.rough_loop(cfg))
    fallback = _fallback(cfg, problem, obj, floor, log)
    loss = tuner.make_loss(problem, obj, floor)
    # compiled before the global stage: a budget then plans with the gradient's measured cost
    K = tcfg.starts if searching and not resuming else 1  # a resumed run continues its one start
    grid = u_p0 if K == 1 else jax.tree.map(lambda x: jax.numpy.broadcast_to(x, (K, *x.shape)), u_p0)
    stepper = tuner.prepare(loss, grid, tcfg.mode, starts=K > 1, log=log)
    # the fallback's compilation, where the start needs it: the adjoint kernel's build and most of
    # the tracing, the larger part of the first compilation, are not repeated
    again = 0.0 if fallback is None else 0.5 * stepper.compile_seconds
    now = time.perf_counter()
    deadlines = plan(end, stepper.step_seconds, tcfg.steps, again, now)
    if end is not None:
        log(f"tune: --budget {budget:g} s: the gradient compiled in {stepper.compile_seconds:.1f} s, "
            f"{stepper.step_seconds:.3f} s a step; "
            + ("no global stage" if not searching or resuming
               else "one chunk of the global stage" if deadlines.global_stage <= now
               else f"the global stage until {deadlines.global_stage - started:.1f} s")
            + f", the steps until {end - started:.1f} s from the process's start")  # fmt: skip
    start_params, starts = _start(tcfg, evaluator, obj, p0, floor, checkpoint if resuming else None,
                                  deadlines.global_stage, log)  # fmt: skip
    cma = (tuner.checkpoint_extra(checkpoint) or {}).get("cma") if resuming else None  # the first run's record
    if tcfg.cma_generations and searching and not resuming:
        now = time.perf_counter()
        until = None if end is None else now + CMA_SHARE * (end - now)
        generations = tcfg.cma_generations * (FILL if fill else 1)
        start_params, cma = _cma(tcfg, loss, start_params, plain.base, generations, until, log)
        if starts is not None:  # the starts, each at its own rate, from CMA-ES's best
            starts = jax.tree.map(lambda x, s: jax.numpy.broadcast_to(x, s.shape), start_params, starts)
    u0 = tuner.to_internal(start_params, plain.base, floor)
    settings = tuner.Settings(tcfg.steps * (FILL if fill else 1), lr, tcfg.schedule, tcfg.clip, tcfg.mode,
                              tuple(tcfg.params), tcfg.checkpoint_every, tcfg.optimizer)  # fmt: skip
    terms = (f"{obj.error_metric} term", f"{obj.chattering_metric} term")
    found = {k: np.asarray(v).tolist() for k, v in zip(p0._fields, start_params)}
    # a resumed run's start (its global stage's or CMA-ES's best) and the CMA-ES stage's record
    keep = None if start_params is p0 else {"start": found, **({} if cma is None else {"cma": cma})}
    if end is not None and time.perf_counter() > end:
        log(f"tune: --budget {budget:g} s: passed before the gradient steps (compilation included); one step runs")
    if starts is None:
        u, history = tuner.run(loss, u0, settings, checkpoint=checkpoint, resume=resume, terms=terms, extra=keep,
                               deadline=end, fallback=fallback, guard=problems.GRADIENT_GUARD,
                               stepper=stepper if K == 1 else None, log=log)  # fmt: skip
    else:  # the starts at once; no checkpoint (a resumed run starts afresh)
        U0 = jax.vmap(lambda p: tuner.to_internal(p, plain.base, None))(starts)
        u, history = tuner.run_starts(loss, U0, settings, rates=tuner.rates_of(lr, len(jax.tree.leaves(starts)[0])),
                                      deadline=end, fallback=fallback, guard=problems.GRADIENT_GUARD, terms=terms,
                                      stepper=stepper, log=log)  # fmt: skip
    # on the host: the parameters as p0's (not placed on the gradient's devices), so the final
    # evaluation runs the program that evaluated p0 instead of compiling another
    u = jax.device_get(u)
    final_params = tuner.to_physical(u, plain.base, floor)
    return _result(cfg, obj, (p0, start_params, final_params), initial, evaluate_plain(final_params), history,
                   (held, held_problem), lambda p: tuner.to_physical(p, plain.base, floor), out if lead else None,
                   log, tv_floor, cma)  # fmt: skip


def _cma(tcfg, loss, start, base, generations: int, deadline: float | None, log: Log):
    """The CMA-ES stage (``tune.cma_generations`` above 0): pycma's CMA-ES from the global stage's
    best on the gradient steps' own training loss, in the internal coordinates (log delta,
    log gamma, log(-poles); the parameters not in ``tune.params`` held), ``CMA_POPSIZE``
    candidates a generation in one vmapped call, steps of ``CMA_SIGMA``; until pycma's own
    criteria stop it, ``generations`` are run or the ``deadline`` passes. Returns its best
    point (physical; the start where nothing beat it), the gradient steps' start, and what the
    stage did (``result.json``'s ``start.cma``)."""
    from jax.flatten_util import ravel_pytree

    from .._search import peers
    from .._search import tune as tuner

    flat, unravel = ravel_pytree(tuner.to_internal(start, base, None))
    flat = np.asarray(flat)
    free = np.concatenate([np.full(np.size(x), name in tcfg.params) for name, x in zip(start._fields, start)])
    batched = jax.jit(jax.vmap(lambda x: loss(unravel(x))[0]))
    shown = [time.perf_counter()]

    def objective(X):
        full = np.repeat(flat[None], len(X), 0)
        full[:, free] = X
        return np.asarray(batched(sharding.replicated(jax.numpy.asarray(full))))  # placed as the gradient's input

    def progress(line: str) -> None:
        if time.perf_counter() - shown[0] > 1.0:  # about once a second
            shown[0] = time.perf_counter()
            log(f"tune: CMA-ES stage: {line.removeprefix('cma-es: ')}")

    t0 = time.perf_counter()
    f0 = float(objective(np.repeat(flat[free][None], CMA_POPSIZE, 0))[0])  # the compiled size; pycma never tries x0
    budget = np.inf if deadline is None else sharding.first(deadline - time.perf_counter())  # spent: one generation
    x, f, X, _ = peers.cma_es(objective, flat[free], CMA_SIGMA, budget, CMA_POPSIZE, log=progress,
                              generations=generations)  # fmt: skip
    info = {"generations": len(X) // CMA_POPSIZE, "start_loss": f0, "loss": min(float(f), f0)}  # no clock: one result
    if not f < f0:
        log(f"tune: CMA-ES stage: {info['generations']} generations found nothing below the global stage's best "
            f"(loss {f0:.5f}): the gradient steps start there")  # fmt: skip
        return start, info
    best = flat.copy()
    best[free] = x
    log(f"tune: CMA-ES stage: {info['generations']} generations in {time.perf_counter() - t0:.1f} s: loss "
        f"{f0:.5f} -> {f:.5f}; the gradient steps start there")  # fmt: skip
    return tuner.to_physical(unravel(jax.numpy.asarray(best)), base, None), info


def _tv_floor(cfg: problems.Config, obj, log: Log) -> np.ndarray | None:
    """Where ``chattering_bound`` bounds the total variation (``chattering``) of an arm's
    voltage: the trajectory's own floor under it per joint (:func:`problems.chattering_floor`,
    mean over the batch's arms), with a warning where the bound lies below it (no controller
    then tracks closely within the bound); else None."""
    if obj.form != "chattering_bound" or obj.chattering_metric != "chattering" or cfg.plant.kind != "arm":
        return None
    per_joint = problems.chattering_floor(cfg).mean(axis=0)
    floor, bound = float(per_joint.mean()), obj.chattering_bound
    log(f"tune: the reference's chattering floor (the exact tracking voltage's total variation) is {floor:.4g} V/s; "
        f"the bound {bound:.4g} V/s leaves {bound - floor:.4g} V/s to the switching")  # fmt: skip
    if bound <= floor:
        log(f"tune: warning: [tune] chattering_bound {bound:.4g} V/s is at or below the floor {floor:.4g} V/s of "
            "the reference itself: no controller tracks it closely within the bound")  # fmt: skip
    return per_joint


def _evaluations(cfg: problems.Config, plain, problem, p0, searching: bool):
    """The evaluator of the global stage (``problem``'s :class:`fosmc_jax._search.front.Evaluator`
    where there is one, else ``problem``), the plain evaluation (a function of the parameters),
    and the training metrics at ``p0`` (the objective's scales)."""
    from .._search import front
    from .._search import tune as tuner

    # the objective's scales by the global stage's evaluation where there is one (one program
    # compiled for both); a resumed run, whose global stage is over, computes them by the same
    # program (another one's last bits would move the resumed steps off the uninterrupted run's)
    evaluator = front.Evaluator(problem) if searching else problem
    # where training simulates [sim] itself, that program evaluates the plain results too
    same = searching and problems.training_config(cfg) is cfg

    def evaluate_plain(p) -> dict[str, Any]:
        if not same:
            return tuner.evaluate(plain, p)
        r = evaluator(jax.tree.map(lambda x: jax.numpy.asarray(x)[None], p), CHUNK, log=_quiet)
        metrics = {k: v[0].tolist() for k, v in r.items() if k != "diverged"}
        return {"metrics": metrics, "diverged": int(r["diverged"][0]), "rollouts": plain.rollouts}

    if searching:
        at_p0 = evaluator(jax.tree.map(lambda x: x[None], p0), CHUNK, log=_quiet)
        return evaluator, evaluate_plain, {k: v[0].tolist() for k, v in at_p0.items() if k != "diverged"}
    return evaluator, evaluate_plain, tuner.evaluate(problem, p0)["metrics"]


def _fallback(cfg: problems.Config, problem, obj, floor, log: Log):
    """The loss of truncated windows that the steps follow where the whole horizon's gradient at
    the start is not finite or too large (on a rough loop; None elsewhere)."""
    from .._search import tune as tuner

    truncated = problems.fallback_problem(cfg, problem)
    if truncated is None:
        return None
    log(f"tune: the gradient follows the whole horizon; its fallback, where that gradient's norm at the start "
        f"is above {problems.GRADIENT_GUARD:g} or not finite: {problems.GRADIENT_WINDOW:g} s windows")  # fmt: skip
    return tuner.make_loss(truncated, obj, floor)


def _end(held_problem, p0, deadline: float, drawn: bool) -> float:
    """When the gradient steps must end for the run to end by ``deadline``: the held-out
    evaluation is compiled now and its run timed, and the drawing of ``tuning.png`` (where
    ``drawn``) measured, so that what follows the steps is known before the global stage and the
    steps share the rest (the final evaluation runs the plain program, compiled already, on fewer
    rollouts)."""
    from .._search import tune as tuner

    tuner.evaluate(held_problem, p0)
    t0 = time.perf_counter()
    tuner.evaluate(held_problem, p0)
    evaluations = sharding.first(time.perf_counter() - t0)
    drawing = sharding.first(_drawing_seconds() if drawn else 0.0)  # process 0 draws
    return deadline - EXIT_SECONDS - drawing - 2 * evaluations


def _result(cfg, obj, params, initial, final, history, held, physical, out: Path | None, log: Log,
            tv_floor: np.ndarray | None = None, cma: dict | None = None) -> dict[str, Any]:  # fmt: skip
    """The result (``run_tune``'s return) of a run from ``params`` (p0, the start, the final
    parameters) with plain metrics ``initial`` and ``final``: the final parameters evaluated on
    what training did not see (``held``: the held-out config and its problem: fresh payloads,
    sampled arms, draws); with ``out`` result.json and tuning.png written there (``physical``:
    the history's internal parameters to physical ones). With ``tv_floor`` (:func:`_tv_floor`)
    the result holds it (``chattering_floor``) and the final chattering's share above it; with
    ``cma`` (:func:`_cma`'s record) ``start.cma``."""
    from .._search import tune as tuner

    p0, start_params, final_params = params
    start = time.perf_counter()
    held_out = tuner.evaluate(held[1], final_params)
    log(f"tune: held out ({held_out['rollouts']} rollouts, {held_out['diverged']} diverged): "
        f"{obj.error_metric} {np.mean(held_out['metrics'][obj.error_metric]):.4g}, "
        f"{obj.chattering_metric} {np.mean(held_out['metrics'][obj.chattering_metric]):.4g}")  # fmt: skip
    as_dict = lambda p: {k: np.asarray(v).tolist() for k, v in p._asdict().items()}
    result = stamped({
        "initial": {"params": as_dict(p0), **initial},
        "start": {
            "params": as_dict(start_params),
            "global_candidates": 0 if start_params is p0 else cfg.tune.global_candidates,
            **({} if cma is None else {"cma": cma}),
        },  # fmt: skip
        "final": {"params": as_dict(final_params), **final},
        "held_out": held_out,
        "held_out_batch": problems.held_out_batch(held[0]),
        "objective": obj._asdict(),
        "history": {k: v for k, v in history.items() if k != "params"},
        "config": cfg.as_dict(),
    })  # fmt: skip
    if tv_floor is not None:
        tv = np.mean(final["metrics"]["chattering"], axis=0)
        result["chattering_floor"] = {"per_joint": tv_floor.tolist(), "mean": float(tv_floor.mean()),
                                      "switching": float(tv.mean() - tv_floor.mean())}  # fmt: skip
        log(f"tune: chattering {tv.mean():.4g} V/s: the floor {tv_floor.mean():.4g} V/s and "
            f"{tv.mean() - tv_floor.mean():.4g} V/s of switching")  # fmt: skip
    if out is not None:
        from .plots import plot_tuning

        write_text(out / "result.json", json.dumps(jsonable(result), indent=1))
        params_history = [as_dict(physical(type(p0)(*map(jax.numpy.asarray, p)))) for p in history["params"]]
        plot_tuning(history, params_history, out / "tuning.png")
        log(f"tune: wrote {out}/result.json and {out}/tuning.png in {time.perf_counter() - start:.1f} s")
    return result
