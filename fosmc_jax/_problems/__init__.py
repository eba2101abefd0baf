"""The config layer, between the simulator and the search: a config resolved once into typed
values (:mod:`.schema`, :mod:`.tables`, :mod:`.resolve`), the model the controller is designed
on (:mod:`.design`), the draws (:mod:`.draws`), the batch's memory (:mod:`.memory`) and
the problems a config describes (:mod:`.build`, :mod:`.front_problems`)."""

from . import memory as memory
from .build import (
    GRADIENT_GUARD as GRADIENT_GUARD,
)
from .build import (
    GRADIENT_WINDOW as GRADIENT_WINDOW,
)
from .build import (
    arm_params_of as arm_params_of,
)
from .build import (
    build as build,
)
from .build import (
    chattering_floor as chattering_floor,
)
from .build import (
    controller_of as controller_of,
)
from .build import (
    fallback_problem as fallback_problem,
)
from .build import (
    gradient_window as gradient_window,
)
from .build import (
    keys_of as keys_of,
)
from .build import (
    n_steps as n_steps,
)
from .build import (
    plain_problem as plain_problem,
)
from .build import (
    problem_of as problem_of,
)
from .build import (
    reference_of as reference_of,
)
from .build import (
    rough_loop as rough_loop,
)
from .build import (
    sample_steps as sample_steps,
)
from .build import (
    tracking_voltages as tracking_voltages,
)
from .build import (
    training_config as training_config,
)
from .build import (
    tuning_problems as tuning_problems,
)
from .design import (
    DesignModel as DesignModel,
)
from .design import (
    box_of as box_of,
)
from .design import (
    design_model as design_model,
)
from .design import (
    design_summary as design_summary,
)
from .draws import arm_samples as arm_samples
from .draws import arm_varies as arm_varies
from .draws import draws as draws
from .front_problems import FrontProblems as FrontProblems
from .front_problems import front_problems as front_problems
from .front_problems import held_out_batch as held_out_batch
from .front_problems import held_out_config as held_out_config
from .resolve import PRESETS as PRESETS
from .resolve import as_config as as_config
from .resolve import load as load
from .resolve import replace as replace
from .resolve import resolve as resolve
from .resolve import with_params as with_params
from .schema import (
    BOX_KEYS as BOX_KEYS,
)
from .schema import (
    SCHEMA as SCHEMA,
)
from .schema import (
    ConfigError as ConfigError,
)
from .schema import (
    check_horizon as check_horizon,
)
from .schema import (
    defaults as defaults,
)
from .tables import Config as Config
