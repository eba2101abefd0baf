"""fosmc_jax: a differentiable, batched JAX simulator of the full-order sliding mode tracking
controller (FOSMC) of "A Full Order Sliding Mode Tracking Controller For A Class of Uncertain
Dynamical System", for a 3-DOF direct-drive arm."""

from ._app.bench import identification_log
from ._app.certify import certify
from ._app.commands import (
    run_bounds,
    run_certify,
    run_export,
    run_front,
    run_identify,
    run_reproduce,
    run_simulate,
    run_tune,
)
from ._certificate.hitting import Certificate
from ._controllers.base import ContinuousLaw, ControlLaw, HasSlidingVariable, SampledLoop
from ._controllers.fosmc import (
    FOSMC,
    LAWS,
    SWITCHING,
    DiscreteFOSMC,
    FOSMCParams,
    FOSMCState,
    control_law,
    safe_norm,
    sliding_surface,
    switch,
)
from ._controllers.smc import SMC
from ._controllers.super_twisting import ContinuousSuperTwisting, SuperTwisting
from ._controllers.surface import SurfaceParams
from ._design import paper
from ._design.gains import (
    CONVENTIONS,
    BoxBound,
    DesignError,
    box_norm_bound,
    check_design,
    check_matching,
    closed_loop_matrix,
    gain_from_poles,
    gamma_bounds,
    input_matrix_product,
    matching_condition,
    stable_step,
    summarize,
)
from ._loop.digital import DERIVATIVES, DigitalLoop, Sensors, measure, quantize, saturate
from ._plants.arm import (
    ARM_PARAMS,
    PAYLOAD_RANGE,
    Arm,
    ArmParams,
    arm_box,
    arm_sweep,
    third_order_rows,
    tracking_voltage,
    without_idle_terms,
)
from ._plants.base import Plant
from ._plants.linear import UNCERTAINTY, LinearPlant, uncertain_plants
from ._plants.reference import Cycloid, Sinusoid, desired_state, feedforward
from ._problems import ConfigError, build
from ._simulator.cache import use_compilation_cache
from ._simulator.metrics import CHATTERING_CUTOFF, METRIC_NAMES, UNITS, Metrics, mean_over_survivors
from ._simulator.native import available as kernel_available
from ._simulator.problem import Problem
from ._simulator.rollout import INTEGRATORS, Result, Trace, simulate, simulate_batch
from ._simulator.sharding import simulate_sharded, use_all_cores, use_host_devices

__all__ = [
    # a config (path, preset name, dict) to the batch it describes: problem.simulate(params)
    "build",
    "Problem",
    # one function per `fosmc` command: a config in, the command's data out (fosmc_jax._app.commands)
    "run_bounds",
    "run_certify",
    "run_front",
    "run_reproduce",
    "run_simulate",
    "run_tune",
    "run_export",
    "run_identify",
    # the log of an experiment from a simulation, in fosmc identify's layout
    "identification_log",
    "ARM_PARAMS",
    "PAYLOAD_RANGE",
    "Arm",
    "ArmParams",
    "Certificate",
    "ConfigError",
    "arm_box",
    "arm_sweep",
    "certify",
    "simulate_sharded",
    "stable_step",
    "summarize",
    "third_order_rows",
    "tracking_voltage",
    "without_idle_terms",
    "config",
    "io",
    "search",
    "use_all_cores",
    "use_compilation_cache",
    "kernel_available",
    "use_host_devices",
    "CHATTERING_CUTOFF",
    "SMC",
    "ContinuousSuperTwisting",
    "SuperTwisting",
    "SurfaceParams",
    "CONVENTIONS",
    "DERIVATIVES",
    "DigitalLoop",
    "DiscreteFOSMC",
    "FOSMC",
    "FOSMCState",
    "Sensors",
    "UNITS",
    "measure",
    "quantize",
    "saturate",
    "INTEGRATORS",
    "LAWS",
    "METRIC_NAMES",
    "mean_over_survivors",
    "SWITCHING",
    "UNCERTAINTY",
    "BoxBound",
    "FOSMCParams",
    "ControlLaw",
    "ContinuousLaw",
    "HasSlidingVariable",
    "SampledLoop",
    "Plant",
    "Cycloid",
    "DesignError",
    "LinearPlant",
    "Metrics",
    "Result",
    "Sinusoid",
    "Trace",
    "box_norm_bound",
    "check_design",
    "check_matching",
    "closed_loop_matrix",
    "control_law",
    "desired_state",
    "feedforward",
    "gain_from_poles",
    "gamma_bounds",
    "input_matrix_product",
    "matching_condition",
    "paper",
    "safe_norm",
    "simulate",
    "simulate_batch",
    "sliding_surface",
    "switch",
    "uncertain_plants",
]
from . import config, io, search  # noqa: E402  (the public namespaces, after the names they build on)
from ._io import __version__ as __version__  # noqa: E402  (the installed distribution's metadata)

#: Old public names, kept for one release: name -> (new name, what it is now).
_DEPRECATED = {
    "tuning": ("fosmc_jax.search", lambda: _tune_module()),
    "Controller": ("fosmc_jax.FOSMCParams (the name Controller is the interface's, fosmc_jax.ControlLaw)",
                   lambda: FOSMCParams),
}  # fmt: skip


def _tune_module():
    from ._search import tune

    return tune


def __getattr__(name: str):
    if name in _DEPRECATED:
        import warnings

        new, get = _DEPRECATED[name]
        warnings.warn(f"fosmc_jax.{name} is deprecated: use {new}", DeprecationWarning, stacklevel=2)
        return get()
    raise AttributeError(f"module 'fosmc_jax' has no attribute {name!r}")
