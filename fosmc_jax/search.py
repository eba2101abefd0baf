"""Search and tuning, the layer behind ``fosmc tune`` and ``fosmc front``, for research
scripts: tuning problems and objectives, the gradient tuner, the front's search (NSGA-II or staged) and its
pieces, the choice of one point of a front (:func:`select`, ``fosmc select``), the peers it is
compared with (CMA-ES, NSGA-II), and the Pareto indicators a front is judged by. The problems
come from a config: :func:`fosmc_jax.config.tuning_problems`.

    import fosmc_jax.config as fc, fosmc_jax.search as fs
    plain, train, p0 = fc.tuning_problems(fc.load("tuning/configs/realistic_arm.toml"))
    evaluate = fs.Evaluator(plain)  # compiled once, on first use
    m = evaluate(fs.from_factors(p0, fs.global_factors(64, seed=0)), chunk=16)
    e, c = fs.axes(m)  # mean rms_error (rad), chattering_hf (V) per candidate
    front = fs.nondominated(e, c)
"""

from ._controllers import Kind, register, rules
from ._search.front import (
    AXES,
    DIM,
    Evaluator,
    axes,
    bounds,
    cma_stage,
    evaluate_many,
    from_factors,
    front_search,
    global_factors,
    global_stage,
    global_starts,
    grid_factors,
    local_factors,
    pick_starts,
    point_of,
    replay_settings,
    sample_candidates,
    scalarized,
    to_factors,
)
from ._search.front import Plan as FrontPlan
from ._search.front import Settings as FrontSettings
from ._search.pareto import additive_epsilon, dominated_by, epsilon, hypervolume, nondominated
from ._search.peers import cma_es, cma_front, log_grid, nsga2, optuna_nsga2, random_search
from ._search.select import controller_toml, select
from ._search.tune import (
    SPACES,
    GammaFloor,
    Objective,
    Param,
    Params,
    Problem,
    SMCGains,
    Space,
    STGains,
    Tunable,
    aggregate,
    evaluate,
    learning_rate,
    make_loss,
    objective_of,
    rollout_costs,
    space_of,
    to_internal,
    to_physical,
    value_and_grad,
)
from ._search.tune import Settings as TuneSettings
from ._search.tune import run as tune

__all__ = [
    # Pareto indicators (fosmc_jax._search.pareto)
    "additive_epsilon",
    "dominated_by",
    "epsilon",
    "hypervolume",
    "nondominated",
    # controller kinds (fosmc_jax._controllers.kind): a kind is one file and one register() line
    "Kind",
    "register",
    "rules",
    # tuning problems, objectives and the gradient tuner (fosmc_jax._search.tune)
    "SPACES",
    "Param",
    "SMCGains",
    "STGains",
    "GammaFloor",
    "Objective",
    "Params",
    "Problem",
    "Space",
    "Tunable",
    "TuneSettings",
    "aggregate",
    "evaluate",
    "learning_rate",
    "make_loss",
    "objective_of",
    "rollout_costs",
    "space_of",
    "to_internal",
    "to_physical",
    "tune",
    "value_and_grad",
    # the front's search (fosmc_jax._search.front)
    "AXES",
    "DIM",
    "Evaluator",
    "FrontPlan",
    "FrontSettings",
    "axes",
    "bounds",
    "cma_stage",
    "evaluate_many",
    "from_factors",
    "front_search",
    "global_factors",
    "global_stage",
    "global_starts",
    "grid_factors",
    "local_factors",
    "pick_starts",
    "point_of",
    "replay_settings",
    "sample_candidates",
    "scalarized",
    "to_factors",
    # choosing a front point (fosmc_jax._search.select)
    "controller_toml",
    "select",
    # the peers (fosmc_jax._search.peers)
    "cma_es",
    "cma_front",
    "log_grid",
    "nsga2",
    "optuna_nsga2",
    "random_search",
]
