"""Gradient-based tuning of a controller kind's parameters (optax), robust over a batch of rollouts.

Each ``[controller] kind`` has its own tunable parameter set, a :class:`Space` in
:data:`SPACES` (declared with the kind, :mod:`fosmc_jax._controllers.kind`): the FOSMC's delta,
gamma and poles (:class:`Tunable`), conventional SMC's k and phi (:class:`SMCGains`),
super-twisting's k1 and k2 (:class:`STGains`). Each parameter holds one row per joint and names
its config key, its sign and the log10 box of the scale factors that ``fosmc front`` searches
(:mod:`fosmc_jax._search.front`).

Parameters live in unconstrained coordinates: x = exp(u) for a positive parameter, x =
-exp(u) for a negative one (the poles: real, negative, repeats allowed); the FOSMC's gamma can
instead be gamma = g_min(poles) + exp(u_gamma) to keep it above the bounds (24)-(26), which
move with K and hence with the poles.

Objective (unit-free). Per rollout i, with the plain metrics of :mod:`fosmc_jax._simulator.metrics`,
E_i = mean_j of the ``error_metric`` (``rms_error`` or ``max_abs_error``) and C_i = mean_j of
the ``chattering_metric`` (``chattering_hf`` by default: the switching part of the control;
``chattering``, the total variation, also counts the smooth motion the trajectory needs), and
with g(x, ref) = log(x / ref) (``scale = "log"``: errors span decades) or x / ref
(``"linear"``), the ``form``:

    weighted          J_i = w_e g(E_i, e_ref) + w_c g(C_i, c_ref)
    error_bound       J_i = g(C_i, c_ref) + rho relu(log(E_i / error_bound))^2
                      (the smoothest control whose error stays under the bound)
    chattering_bound  J_i = g(E_i, e_ref) + rho relu(log(C_i / chattering_bound))^2
                      (the best tracking whose chattering stays under the bound)

where e_ref and c_ref are the batch means at the initial parameters and rho =
``bound_weight``. The loss is mean_i J_i, plus ``worst_weight`` times max_i J_i
(``worst_case = "max"``) or the CVaR, the mean of the worst ``1 - cvar_alpha`` fraction
(``"cvar"``). A diverged rollout contributes the finite ``penalty`` with no gradient. The
training objective uses the metrics of the training simulation (its step and horizon); every
reported result is re-evaluated with the plain simulator (:func:`evaluate`).
"""

from __future__ import annotations

import json
import re
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from .._controllers.fosmc import FOSMCParams
from .._controllers.fosmc import Tunable as Tunable  # the kinds' parameter sets, re-exported for the tuner's users
from .._controllers.kind import SPACES, Space
from .._controllers.kind import Param as Param
from .._controllers.smc import SMCGains as SMCGains
from .._controllers.super_twisting import STGains as STGains
from .._design.gains import gain_from_poles, gamma_bounds
from .._io import atomic_write
from .._problems.schema import (  # the config's vocabulary of the tuner's choices
    CHATTERING_METRICS as CHATTERING_METRICS,
)
from .._problems.schema import (
    ERROR_METRICS as ERROR_METRICS,
)
from .._problems.schema import (
    FORMS as FORMS,
)
from .._problems.schema import (
    MODES as MODES,
)
from .._problems.schema import (
    OPTIMIZERS as OPTIMIZERS,
)
from .._problems.schema import (
    SCALES as SCALES,
)
from .._problems.schema import (
    WORST_CASE as WORST_CASE,
)
from .._problems.tables import Tune
from .._simulator import sharding
from .._simulator.metrics import mean_over_survivors
from .._simulator.problem import Problem
from .._simulator.sharding import replicated

#: The FOSMC's tunable parameters (a kind's are ``SPACES[kind].names``).
PARAM_NAMES = ("delta", "gamma", "poles")


#: A kind's parameter set (its :class:`Space`'s ``values``: the FOSMC's :class:`Tunable`, SMC's
#: :class:`SMCGains`, super-twisting's :class:`STGains`, a registered kind's own), physical or
#: unconstrained coordinates, with leading batch axes in fronts.
Params = Any


def space_of(p: Params) -> Space:
    """The :class:`Space` of a parameter set (its type is the space's ``values``)."""
    for s in SPACES.values():
        if type(p) is s.values:
            return s
    raise TypeError(f"not a tunable parameter set: {type(p).__name__}")


class GammaFloor(NamedTuple):
    """Keep gamma >= the bounds (24)-(26) of ``convention`` for the given alpha, beta."""

    alpha: float
    beta: float
    convention: str = "paper"


def gamma_floor(floor: GammaFloor | None, base: FOSMCParams, poles) -> Any:
    """The lower bound on gamma for these poles (0 without a floor)."""
    if floor is None:
        return jnp.zeros_like(base.gamma)
    K = gain_from_poles(base.a_rows, base.b_rows, poles)
    return gamma_bounds(floor.alpha, floor.beta, base.C, base.b_rows, K, floor.convention)


def to_internal(p: Params, base: Any, floor: GammaFloor | None = None) -> Params:
    """Unconstrained coordinates of physical parameters (inverse of :func:`to_physical`):
    u = log(sign x); with a ``floor`` (the FOSMC only) u_gamma = log(gamma - floor)."""
    if floor is not None:
        excess = p.gamma - gamma_floor(floor, base, p.poles)
        if np.any(np.asarray(excess) <= 0):
            raise ValueError("tune: initial gamma must exceed the gamma bounds when keep_gamma_bound is on")
        p = p._replace(gamma=excess)
    return type(p)(*(jnp.log(x if q.sign > 0 else -x) for q, x in zip(space_of(p).params, p)))


def to_physical(u: Params, base: Any, floor: GammaFloor | None = None) -> Params:
    """Physical parameters from unconstrained ones: each of its sign (FOSMC: delta > 0, poles
    < 0, gamma > 0), gamma > floor with a ``floor``."""
    p = type(u)(*(jnp.exp(v) if q.sign > 0 else -jnp.exp(v) for q, v in zip(space_of(u).params, u)))
    if floor is not None:
        p = p._replace(gamma=gamma_floor(floor, base, p.poles) + p.gamma)
    return p


class Objective(NamedTuple):
    """Form, weights, metrics and scales of the objective (see module docstring)."""

    weight_error: float = 1.0
    weight_chattering: float = 1.0
    error_ref: float = 1.0
    chattering_ref: float = 1.0
    worst_case: str = "none"
    worst_weight: float = 0.0
    cvar_alpha: float = 0.9
    penalty: float = 100.0
    form: str = "weighted"
    scale: str = "log"
    error_metric: str = "rms_error"
    chattering_metric: str = "chattering_hf"
    error_bound: float = 0.0
    chattering_bound: float = 0.0
    bound_weight: float = 100.0


def objective_of(tune: Tune, metrics: dict) -> Objective:
    """The :class:`Objective` of a resolved config's ``[tune]`` table (``cfg.tune``), its scales
    the batch means of ``metrics`` (a dict of per-joint means, as :func:`evaluate` returns) at
    the start."""
    return Objective(
        tune.weight_error, tune.weight_chattering,
        float(np.mean(metrics[tune.error_metric])), float(np.mean(metrics[tune.chattering_metric])),
        tune.worst_case, tune.worst_weight, tune.cvar_alpha, tune.penalty, tune.objective,
        tune.scale, tune.error_metric, tune.chattering_metric, tune.error_bound,
        tune.chattering_bound, tune.bound_weight,
    )  # fmt: skip


def rollout_costs(metrics, diverged, obj: Objective):
    """Per-rollout J_i (B,) and its error and chattering parts; diverged rollouts get ``penalty``."""
    E = jnp.mean(getattr(metrics, obj.error_metric), axis=-1)
    C = jnp.mean(getattr(metrics, obj.chattering_metric), axis=-1)
    g = (lambda x, ref: jnp.log(x / ref)) if obj.scale == "log" else (lambda x, ref: x / ref)
    over = lambda x, bound: obj.bound_weight * jax.nn.relu(jnp.log(x / bound)) ** 2
    if obj.form == "weighted":
        e, c = obj.weight_error * g(E, obj.error_ref), obj.weight_chattering * g(C, obj.chattering_ref)
    elif obj.form == "error_bound":
        e, c = over(E, obj.error_bound), g(C, obj.chattering_ref)
    elif obj.form == "chattering_bound":
        e, c = g(E, obj.error_ref), over(C, obj.chattering_bound)
    else:
        raise ValueError(f"form must be one of {FORMS}, got {obj.form!r}")
    J = jnp.where(diverged | ~jnp.isfinite(e + c), jax.lax.stop_gradient(obj.penalty), e + c)
    return J, e, c


def aggregate(J, obj: Objective):
    """mean(J) plus the optional worst-case term."""
    loss = jnp.mean(J)
    if obj.worst_case == "max":
        loss = loss + obj.worst_weight * jnp.max(J)
    elif obj.worst_case == "cvar":
        k = max(1, int(round((1 - obj.cvar_alpha) * J.shape[0])))
        loss = loss + obj.worst_weight * jnp.mean(jax.lax.top_k(J, k)[0])
    return loss


def make_loss(problem: Problem, obj: Objective, floor: GammaFloor | None):
    """loss(u) -> (loss, (mean error part, mean chattering part)) in unconstrained coordinates."""

    def loss(u: Params):
        r = problem.simulate(to_physical(u, problem.base, floor), split=True)
        J, e, c = rollout_costs(r.metrics, r.diverged, obj)
        return aggregate(J, obj), (jnp.mean(e), jnp.mean(c))

    return loss


def evaluate(problem: Problem, p: Params) -> dict[str, Any]:
    """Plain-simulator metrics of physical parameters ``p``, averaged over the non-diverged
    rollouts of the batch; plus the number of diverged rollouts."""
    r = problem.simulate(p, checkpoint_every=0)
    diverged = np.asarray(r.diverged)
    out = {name: mean_over_survivors(np.asarray(v), diverged).tolist() for name, v in r.metrics._asdict().items()}
    return {"metrics": out, "diverged": int(diverged.sum()), "rollouts": int(diverged.size)}


# ---------------------------------------------------------------------------- optimizer loop


class Settings(NamedTuple):
    steps: int = 100
    learning_rate: float = 0.05  # Adam's (learning_rate, schedule and clip: Adam's only)
    schedule: str = "cosine"  # or "constant"
    clip: float = 1.0  # global-norm clipping of the gradient in internal coordinates
    mode: str = "auto"  # "reverse", "forward" or "auto" (time both, keep the faster)
    free: tuple[str, ...] | None = None  # the parameters tuned (None: all), the rest frozen
    checkpoint_every: int = 10  # optimizer steps between checkpoints (0: none)
    optimizer: str = "adam"  # or "lbfgs": L-BFGS directions with a backtracking line search


#: L-BFGS's line search: Armijo's sufficient decrease, the step's factor after a rejected trial
#: and after an accepted step, the trials per step, the longest step (2-norm in u: a factor e on
#: one parameter) and the curvature pairs kept
ARMIJO, SHRINK, GROW, TRIALS, MAX_STEP, MEMORY = 1e-4, 0.3, 2.0, 10, 1.0, 10


def learning_rate(rate: float, rough: bool) -> float:
    """``[tune] learning_rate``, 0 meaning automatic: 0.05, or 0.01 on a rough loop (a digital loop
    that quantizes or differences its measurements, :func:`fosmc_jax._problems.rough_loop`): on
    the realistic preset 0.05's steps left the tracking region within 10 steps (tuning/README.md)."""
    return rate or (0.01 if rough else 0.05)


def make_optimizer(s: Settings, labels: Params) -> optax.GradientTransformation:
    lr = s.learning_rate
    if s.schedule == "cosine":
        lr = optax.cosine_decay_schedule(s.learning_rate, max(1, s.steps), alpha=0.1)
    adam = optax.chain(optax.clip_by_global_norm(s.clip), optax.adam(lr))
    return optax.multi_transform({"free": adam, "frozen": optax.set_to_zero()}, labels)


def value_and_grad(loss, mode: str):
    if mode == "reverse":
        return jax.jit(jax.value_and_grad(loss, has_aux=True))

    def fwd(u):
        grad, out = jax.jacfwd(lambda v: (lambda o: (o[0], o))(loss(v)), has_aux=True)(u)
        return out, grad

    return jax.jit(fwd)


def _on_adjoint_kernel(loss, u) -> bool:
    """Whether ``loss``'s reverse mode runs the generated adjoint kernel (traced, not compiled).
    Then ``auto`` need not time forward mode: with 15 parameters a gradient costs a few forwards
    there, while forward mode runs 15 tangents through a ``lax.scan`` whose compilation alone took
    over a minute on the realistic preset."""
    program = str(jax.make_jaxpr(jax.grad(lambda v: loss(v)[0]))(u))
    return re.search(r"fosmc_gen_\w*?_(?:adj|\w*Adjoint)\b", program) is not None


def _step_function(loss, u, mode: str, log: Callable[[str], None]) -> tuple[Callable, str]:
    """The compiled value and gradient of ``loss`` and its gradient mode: ``mode``, or for
    ``"auto"`` reverse where the program runs the generated adjoint kernel, else the faster of
    reverse and forward, each timed at ``u`` (the timed function is returned: no second
    compilation)."""
    if mode == "auto" and _on_adjoint_kernel(loss, u):
        mode = "reverse"
        log("tune: gradient mode reverse (the generated adjoint kernel)")
    candidates = ("reverse", "forward") if mode == "auto" else (mode,)
    compiled = {m: value_and_grad(loss, m) for m in candidates}
    if mode == "auto":
        timings = {}
        for m, f in compiled.items():
            jax.block_until_ready(f(u))  # compile
            t0 = time.perf_counter()
            jax.block_until_ready(f(u))
            timings[m] = sharding.first(time.perf_counter() - t0)  # process 0's: the same choice everywhere
        mode = min(timings, key=timings.get)
        log(f"tune: gradient mode {mode} (one evaluation: reverse {timings['reverse']:.3f} s, "
            f"forward {timings['forward']:.3f} s)")  # fmt: skip
    return compiled[mode], mode


class Stepper(NamedTuple):
    """A loss's compiled value and gradient, ``fn(u) -> ((value, aux), grad)`` (vmapped over a
    leading axis of starts for :func:`run_starts`), its gradient mode, and what it cost
    (:func:`prepare`): a budget knows what the gradient steps cost before the global stage takes
    its share."""

    fn: Callable
    mode: str
    compile_seconds: float  # the tracing, the kernel's build and the compilation, with one call
    step_seconds: float  # one call, compiled


def prepare(loss, u: Params, mode: str = "auto", *, starts: bool = False,
            log: Callable[[str], None] = print) -> Stepper:  # fmt: skip
    """The :class:`Stepper` of ``loss`` at ``u`` (internal coordinates; with ``starts``, K of them
    on a leading axis, the program of :func:`run_starts`, reverse mode): compiled and timed, for
    :func:`run`'s and :func:`run_starts`' ``stepper``. The compiled program depends on ``u``'s
    shapes only, so any point of the same shape (the config's parameters before the global stage
    has found the start) compiles it."""
    u = replicated(u)  # as run and run_starts place their parameters: the same program
    t0 = time.perf_counter()
    if starts:
        fn, mode = jax.jit(jax.vmap(jax.value_and_grad(loss, has_aux=True))), "reverse"
    else:
        fn, mode = _step_function(loss, u, mode, log)
    jax.block_until_ready(fn(u))
    t1 = time.perf_counter()
    jax.block_until_ready(fn(u))
    t2 = time.perf_counter()
    return Stepper(fn, mode, sharding.first(t1 - t0), sharding.first(t2 - t1))  # process 0's: one plan everywhere


def _save(path: Path, header: dict, arrays: dict[str, Any]) -> None:
    """Atomically write a checkpoint: a NumPy .npz of named arrays and a JSON ``header``; by
    process 0 alone in a run across processes (the others hold the same state)."""
    if not sharding.leads():
        return
    if "header" in arrays:
        raise ValueError("a checkpoint array may not be named 'header'")
    text = np.frombuffer(json.dumps(header).encode(), np.uint8)
    atomic_write(path, lambda tmp: np.savez(tmp, header=text, **{k: np.asarray(x) for k, x in arrays.items()}))


def _load(path: Path) -> tuple[dict, dict[str, np.ndarray]]:
    """(header, arrays by name) of a checkpoint written by :func:`_save`."""
    with np.load(path) as z:
        return json.loads(bytes(z["header"]).decode()), {k: z[k] for k in z.files if k != "header"}


def checkpoint_extra(path: Path) -> dict | None:
    """The ``extra`` JSON a :func:`run` wrote into its checkpoint ``path`` (None: none, or no
    checkpoint)."""
    return _load(path)[0].get("extra") if Path(path).exists() else None


def _named(tree) -> dict[str, Any]:
    """A pytree's leaves by their paths (``jax.tree_util.keystr``), in leaf order."""
    return {jax.tree_util.keystr(path): x for path, x in jax.tree_util.tree_flatten_with_path(tree)[0]}


def _norm(tree) -> float:
    """The global 2-norm of a pytree without overflow (entries above 1e154 square to inf): inf
    only where an entry is, NaN where one is."""
    g = np.concatenate([np.ravel(np.asarray(x, float)) for x in jax.tree.leaves(tree)])
    scale = np.max(np.abs(g)) if g.size else 0.0
    if not np.isfinite(scale) or scale == 0:
        return float(scale)
    return float(scale * np.linalg.norm(g / scale))


class _LineSearch:
    """One L-BFGS step (``optax.scale_by_lbfgs``'s direction) with a backtracking line search on
    Armijo's condition: the first trial is ``GROW`` times the last accepted step length (1 at
    most: the direction's own scale, at most ``MAX_STEP`` long), each rejected one ``SHRINK``
    times shorter; where ``TRIALS`` trials find no decrease, ``TRIALS`` more along the gradient with
    the memory cleared (curvature pairs gathered across the chattering loops' kinks mislead more
    often than the gradient does). A trial is one evaluation of the compiled value and gradient, so
    the accepted one brings the next step's gradient. A trial whose loss is not finite, or is the diverged
    rollouts' flat penalty above the current loss, is rejected like any increase."""

    def __init__(self, step_fn, opt, mask, deadline):
        self.step_fn, self.opt, self.deadline, self.timed_out = step_fn, opt, deadline, False

        @jax.jit
        def direction(u, state, grad):
            g = jax.tree.map(jnp.multiply, grad, mask)  # frozen parameters stay
            d, state = opt.update(g, state, u)
            slope = optax.tree.vdot(g, d)
            # not a descent direction (negative curvature measured): the gradient, memory cleared
            bad = ~(slope > 0)
            d = jax.tree.map(lambda a, b: jnp.where(bad, a, b), g, d)
            state = jax.tree.map(lambda a, b: jnp.where(bad, a, b), opt.init(u), state)
            slope = jnp.where(bad, optax.tree.vdot(g, g), slope)
            scale = jnp.minimum(1.0, MAX_STEP / jnp.maximum(optax.tree.norm(d), 1e-300))
            return jax.tree.map(lambda x: scale * x, d), scale * slope, state

        self.direction = direction
        self.trial = jax.jit(lambda u, d, eta: jax.tree.map(lambda a, b: a - eta * b, u, d))

    def __call__(self, u, state, eta, current):
        (value, _), grad = current
        trials = 0
        # where the L-BFGS direction fails, once more along the gradient with the memory cleared
        for memory, first in ((state, min(1.0, eta * GROW)), (self.opt.init(u), 1.0)):
            d, slope, state = self.direction(u, memory, grad)
            eta = first
            for _ in range(TRIALS):
                trials += 1
                v = self.trial(u, d, eta)
                out = self.step_fn(v)
                f = float(out[0][0])
                if np.isfinite(f) and f <= float(value) - ARMIJO * eta * float(slope) and np.isfinite(_norm(out[1])):
                    return v, state, eta, out, trials
                if self.deadline is not None and sharding.first(time.perf_counter() > self.deadline):
                    self.timed_out = True
                    return None
                eta *= SHRINK
        return None


def run(
    loss,
    u0: Params,
    settings: Settings,
    *,
    checkpoint: Path | None = None,
    resume: bool = False,
    terms: tuple[str, str] = ("error", "chattering"),
    extra: dict | None = None,
    deadline: float | None = None,
    fallback=None,
    guard: float = np.inf,
    stepper: Stepper | None = None,
    log: Callable[[str], None] = print,
) -> tuple[Params, dict[str, list]]:
    """Minimise ``loss(u) -> (value, (error part, chattering part))`` from ``u0`` with Adam, or
    with L-BFGS and a line search (``settings.optimizer``, :class:`_LineSearch`).

    Non-finite losses or gradients skip Adam's step (and say so); L-BFGS stops there, and where
    its line search finds no decrease. Every ``checkpoint_every``
    steps the state is written atomically to ``checkpoint``; ``resume`` continues from it and
    ends where an uninterrupted run would. Returns the best internal parameters, those of the
    lowest finite loss among every step's and the last update's (a step can land where the
    rollouts diverge: a flat penalty with zero gradient that Adam's momentum does not leave),
    and the history (per step: loss, error, chattering, gradient norm, skipped, internal
    params; ``best_step``: the index of the returned parameters, ``steps`` for the last update).
    Every line of ``log`` starts with ``tune:``; ``terms`` names the loss's two parts in its step
    lines (``fosmc tune``: the objective's metrics, e.g. ``rms_error term``). ``extra``: JSON
    the caller keeps in the checkpoint (:func:`checkpoint_extra` reads it back; a resumed run
    keeps the first run's). ``deadline`` (a ``time.perf_counter()`` value): the steps are as many
    as fit before it at the compiled step's measured time (``settings.steps`` at most; the
    schedule spans them; a resumed run keeps the first run's count), and the loop stops at it.
    ``fallback``: a loss to minimise instead where ``loss``'s gradient at ``u0`` is not finite or
    its norm is above ``guard`` (``fosmc tune``: the whole horizon's gradient, and a truncated
    one's where it explodes); a resumed run keeps the first run's choice. ``stepper``: ``loss``'s
    value and gradient already compiled (:func:`prepare`), used unless a resumed run follows the
    fallback or another gradient mode.

    (Long: the loop's checkpoint, resume, budget and fallback read and write one state, the
    parameters, optimizer state, step, mode and history; stages would pass all of it around.)
    """
    if settings.optimizer not in OPTIMIZERS:
        raise ValueError(f"optimizer: expected one of {', '.join(OPTIMIZERS)}, got {settings.optimizer!r}")
    free = u0._fields if settings.free is None else settings.free
    labels = type(u0)(*("free" if n in free else "frozen" for n in u0._fields))
    lbfgs = settings.optimizer == "lbfgs"
    opt = optax.scale_by_lbfgs(memory_size=MEMORY) if lbfgs else make_optimizer(settings, labels)
    u, state, eta = u0, opt.init(u0), 1.0
    history: dict[str, list] = {"loss": [], "error": [], "chattering": [], "grad_norm": [], "skipped": [],
                                "params": []}  # fmt: skip
    start_step = 0
    mode = settings.mode
    fell_back = False
    if resume and checkpoint is not None and checkpoint.exists():
        header, arrays = _load(checkpoint)
        if header.get("optimizer", "adam") != settings.optimizer:
            raise ValueError(f"the checkpoint {checkpoint} is of the {header.get('optimizer', 'adam')} optimizer, "
                             f"not of {settings.optimizer}")  # fmt: skip
        u, state = jax.tree.unflatten(
            jax.tree.structure((u, state)), [jnp.asarray(arrays[k]) for k in _named((u, state))]
        )
        history, start_step, mode = header["history"], header["step"], header["mode"]
        settings = settings._replace(steps=header.get("steps", settings.steps))
        eta = header.get("eta", eta)
        if not lbfgs:
            opt = make_optimizer(settings, labels)  # the schedule of the first run's steps
        extra = header.get("extra", extra)
        fell_back = header.get("fallback", False)
        log(f"tune: resumed from {checkpoint} at step {start_step} (gradient mode {mode})")
    if fell_back and fallback is not None:
        loss = fallback

    u, state = replicated((u, state))  # as the gradients come out: one compilation of each program
    if stepper is not None and not fell_back and mode in ("auto", stepper.mode):
        step_fn, mode = stepper.fn, stepper.mode
    else:
        step_fn, mode = _step_function(loss, u, mode, log)
    if fallback is not None and not fell_back and start_step == 0:
        (value, _), grad = step_fn(u)
        norm = _norm(grad)  # NaN where the gradient is
        if sharding.first(not (np.isfinite(float(value)) and norm <= guard)):  # process 0's: the same everywhere
            fell_back = True
            loss, step_fn = fallback, value_and_grad(fallback, mode)
            log(f"tune: the gradient at the start has norm {norm:.3e} (above {guard:g} or not finite): the "
                "fallback's gradient instead")  # fmt: skip
    if deadline is not None and start_step == 0:
        jax.block_until_ready(step_fn(u))  # compiled (where auto did not)
        t0 = time.perf_counter()
        (value, _), grad = step_fn(u)
        _norm(grad), float(value), [np.asarray(x).tolist() for x in u]  # with a step's work on the host
        per_step = sharding.first(time.perf_counter() - t0)
        # one evaluation more after the steps: the last update's loss (process 0's count, on every process)
        fit = sharding.first(max(1, int((deadline - time.perf_counter()) / per_step) - 1))
        if fit < settings.steps:
            settings = settings._replace(steps=fit)
            if not lbfgs:
                opt = make_optimizer(settings, labels)  # the schedule over the steps that fit; the same state
        log(f"tune: budget: {settings.steps} gradient steps ({per_step:.3f} s each) before the deadline")

    @jax.jit
    def update(u, state, grad):
        updates, state = opt.update(grad, state, u)
        return optax.apply_updates(u, updates), state

    search = None
    if lbfgs:
        mask = jax.tree.map(lambda label, x: jnp.full_like(x, label == "free"), labels, u)
        search = _LineSearch(step_fn, opt, mask, deadline)
    current = step_fn(u) if lbfgs else None  # L-BFGS: the loss and gradient at u, from the accepted trial
    t_start = time.perf_counter()
    for step in range(start_step, settings.steps):
        if deadline is not None and step > start_step and sharding.first(time.perf_counter() > deadline):
            log(f"tune: the budget's deadline passed: {step} of {settings.steps} steps done")
            break
        (value, (err, chat)), grad = current if lbfgs else step_fn(u)
        gnorm = _norm(grad)
        finite = bool(np.isfinite(float(value))) and np.isfinite(gnorm)
        history["params"].append([np.asarray(x).tolist() for x in u])
        note, stop = "", False
        if lbfgs:
            moved = search(u, state, eta, current) if finite else None
            if moved is None:
                stop = True
                why = "non-finite loss or gradient" if not finite else f"no decrease in {2 * TRIALS} trials"
                why = "the budget's deadline passed in its line search" if search.timed_out else why
                log(f"tune: step {step + 1}: {why}: L-BFGS stops")
            else:
                u, state, eta, current, trials = moved
                note = f"  step {eta:.2e} ({trials} evaluations)"
        elif finite:
            u, state = update(u, state, grad)
        else:
            log(f"tune: step {step}: non-finite loss or gradient, step skipped")
        for k, v in (("loss", value), ("error", err), ("chattering", chat), ("grad_norm", gnorm)):
            history[k].append(float(v))
        history["skipped"].append(not finite)
        log(f"tune: step {step + 1:4d}/{settings.steps}  loss {float(value):.5f}  {terms[0]} {float(err):.5f}  "
            f"{terms[1]} {float(chat):.5f}  |grad| {gnorm:.3e}{note}  "
            f"{time.perf_counter() - t_start:7.1f} s")  # fmt: skip
        if stop:
            break
        done = step + 1
        if (
            checkpoint is not None
            and settings.checkpoint_every
            and (done % settings.checkpoint_every == 0 or done == settings.steps)
        ):
            header = {"step": done, "mode": mode, "steps": settings.steps, "history": history, "extra": extra,
                      "optimizer": settings.optimizer, "eta": eta, "fallback": fell_back}  # fmt: skip
            _save(checkpoint, header, _named((u, state)))
    # the last update's point: L-BFGS evaluated it in its line search; Adam's is evaluated with the
    # compiled value_and_grad (one gradient's cost) rather than a jit of the loss alone, which
    # would compile a second program
    (last, _), _ = current if lbfgs else step_fn(u)
    losses = np.asarray(history["loss"] + [float(last)], float)
    best = int(np.argmin(np.where(np.isfinite(losses), losses, np.inf)))
    if best < len(history["params"]):
        u = type(u)(*(jnp.asarray(p, x.dtype) for p, x in zip(history["params"][best], u)))
        log(f"tune: the parameters of step {best + 1} (loss {losses[best]:.5f}) are returned: the lowest loss of the "
            f"run (after the last step: {float(last):.5f})")  # fmt: skip
    return u, dict(history, best_step=best)


#: ``[tune] starts``' learning rates span the config's rate / SPREAD .. x SPREAD (:func:`rates_of`)
SPREAD = 4.0


def rates_of(rate: float, n: int, spread: float = SPREAD) -> np.ndarray:
    """Per-start learning rates for :func:`run_starts`: ``n`` rates spaced geometrically from
    ``rate / spread`` to ``rate * spread`` (all ``rate`` for ``spread`` 1 or one start), so that
    the batch tries step sizes the config's rate alone would not."""
    if n == 1 or spread == 1:
        return np.full(n, rate)
    return rate * spread ** np.linspace(-1.0, 1.0, n)


def run_starts(
    loss,
    U0: Params,
    settings: Settings,
    *,
    rates: np.ndarray | None = None,
    deadline: float | None = None,
    fallback=None,
    guard: float = np.inf,
    terms: tuple[str, str] = ("error", "chattering"),
    stepper: Stepper | None = None,
    log: Callable[[str], None] = print,
) -> tuple[Params, dict[str, list]]:
    """Adam from several starts at once: ``U0`` holds K starts on a leading axis (internal
    coordinates), each step is one call of ``jax.vmap`` of ``loss``'s value and gradient over
    them (the generated kernels fold the K candidates into their lanes: BENCHMARKS.md, "gradients
    of a batch of candidates in one call"), and each start follows its own Adam state
    with its own learning rate (``rates``, K of them; default: ``settings.learning_rate`` each)
    on ``settings``' schedule. A start whose loss or gradient is not finite, or whose gradient is
    zero (every rollout diverged: the flat penalty), goes back to its own best point with a fresh
    Adam state and half its rate. ``deadline``: as :func:`run`'s (the steps that fit at the
    batched step's measured time). ``fallback``, ``guard``: as :func:`run`'s, judged at the first
    start (the global stage's best). ``stepper``: ``loss``'s batched value and gradient already
    compiled (:func:`prepare` with ``starts``). Returns the
    internal parameters of the lowest finite loss evaluated, over every start and step, and a
    history shaped as :func:`run`'s, each step's entries those of its best start (``restarts``:
    per step, the starts sent back)."""
    if settings.optimizer != "adam":
        raise ValueError("run_starts: Adam only (settings.optimizer = 'adam')")
    K = int(jax.tree.leaves(U0)[0].shape[0])
    free = U0._fields if settings.free is None else settings.free
    labels = type(U0)(*("free" if n in free else "frozen" for n in U0._fields))
    scale = np.ones(K) if rates is None else np.asarray(rates, float) / settings.learning_rate
    step_fn = stepper.fn if stepper is not None else jax.jit(jax.vmap(jax.value_and_grad(loss, has_aux=True)))
    U = replicated(U0)
    step_fn, settings = _starts_plan(step_fn, U, settings, fallback, guard, deadline, log)
    opt = make_optimizer(settings, labels)
    state = jax.vmap(opt.init)(U)
    update, choose, restart = _starts_updates(opt)
    history: dict[str, list] = {"loss": [], "error": [], "chattering": [], "grad_norm": [], "skipped": [],
                                "params": [], "restarts": []}  # fmt: skip
    best_f = np.full(K, np.inf)
    best_U = U
    t_start = time.perf_counter()
    for step in range(settings.steps + 1):  # the last pass evaluates the last update's points
        (value, (err, chat)), grads = step_fn(U)
        f, err, chat = (np.asarray(x, float) for x in (value, err, chat))  # one transfer each
        rows = np.concatenate([np.asarray(x, float).reshape(K, -1) for x in jax.tree.leaves(grads)], axis=1)
        norms = np.asarray([_norm(row) for row in rows])
        ok = np.isfinite(f) & np.isfinite(norms)
        better = ok & (f < best_f)
        if better.any():
            best_U, best_f = choose(jnp.asarray(better), U, best_U), np.where(better, f, best_f)
        i = int(np.argmin(np.where(ok, f, np.inf))) if ok.any() else 0
        if step == settings.steps:
            history["last"] = float(f[i]) if ok.any() else float("nan")
            break
        history["params"].append([np.asarray(x)[i].tolist() for x in U])
        for k, v in (("loss", f[i]), ("error", err[i]), ("chattering", chat[i]), ("grad_norm", norms[i])):
            history[k].append(float(v))
        history["skipped"].append(not ok.any())
        stuck = ~ok | (norms == 0)
        history["restarts"].append(int(stuck.sum()))
        log(f"tune: step {step + 1:4d}/{settings.steps}  loss {float(f[i]):.5f}  {terms[0]} {float(err[i]):.5f}  "
            f"{terms[1]} {float(chat[i]):.5f}  |grad| {norms[i]:.3e}  (best of {K} starts: {i}; "
            f"{int(stuck.sum())} sent back)  {time.perf_counter() - t_start:7.1f} s")  # fmt: skip
        if deadline is not None and step > 0 and sharding.first(time.perf_counter() > deadline):
            log(f"tune: the budget's deadline passed: {step + 1} of {settings.steps} steps done")
            break
        U, state = update(U, state, grads, jnp.asarray(scale))
        if stuck.any():
            scale = np.where(stuck, scale / 2, scale)
            back = jnp.asarray(stuck)
            U, state = choose(back, best_U, U), choose(back, restart(best_U), state)
    k = int(np.argmin(best_f))
    u = jax.tree.map(lambda x: x[k], best_U)
    history["best_step"] = int(np.argmin(np.where(np.isfinite(history["loss"]), history["loss"], np.inf)))
    log(f"tune: start {k}'s best point (loss {best_f[k]:.5f}) is returned: the lowest loss of the {K} starts")
    return u, history


def _starts_plan(step_fn, U, settings: Settings, fallback, guard: float, deadline: float | None, log):
    """:func:`run_starts`' value and gradient (``fallback``'s where the first start's gradient is
    not finite or its norm above ``guard``) and its settings (with a ``deadline``: as many steps
    as fit at the batched step's measured time)."""
    K = len(jax.tree.leaves(U)[0])
    if fallback is not None:
        (value, _), grads = step_fn(U)
        norm = _norm(jax.tree.map(lambda x: x[0], grads))
        if sharding.first(not (np.isfinite(float(value[0])) and norm <= guard)):
            step_fn = jax.jit(jax.vmap(jax.value_and_grad(fallback, has_aux=True)))
            log(f"tune: the gradient at the start has norm {norm:.3e} (above {guard:g} or not finite): the "
                "fallback's gradient instead")  # fmt: skip
    if deadline is not None:
        jax.block_until_ready(step_fn(U))  # compiled
        t0 = time.perf_counter()
        jax.block_until_ready(step_fn(U))
        per_step = sharding.first(time.perf_counter() - t0)
        fit = sharding.first(max(1, int((deadline - time.perf_counter()) / per_step) - 1))
        settings = settings._replace(steps=min(settings.steps, fit))
        log(f"tune: budget: {settings.steps} gradient steps of {K} starts ({per_step:.3f} s each) before the deadline")
    return step_fn, settings


def _starts_updates(opt):
    """:func:`run_starts`' compiled pieces: ``update`` (each start's Adam step, scaled by its own
    rate; a non-finite gradient's entries make no step), ``choose(mask, a, b)`` (a's rows where
    ``mask``, b's elsewhere, leaf by leaf) and ``restart`` (fresh Adam states, the schedule from
    the top)."""

    @jax.jit
    def update(U, state, grads, scale):
        def one(u, s, g, k):
            g = jax.tree.map(lambda x: jnp.where(jnp.isfinite(x), x, 0.0), g)  # a non-finite start's: no step
            updates, s = opt.update(g, s, u)
            return optax.apply_updates(u, jax.tree.map(lambda x: k * x, updates)), s

        return jax.vmap(one)(U, state, grads, scale)

    @jax.jit
    def choose(mask, a, b):
        return jax.tree.map(lambda x, y: jnp.where(mask.reshape((-1,) + (1,) * (x.ndim - 1)), x, y), a, b)

    restart = jax.jit(lambda best_U: jax.vmap(opt.init)(best_U))
    return update, choose, restart
