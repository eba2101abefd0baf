"""What each ``fosmc`` command computes, as one Python function per command: the index of the
commands' modules (``simulate.py``, ``bounds.py``, ``reproduce.py``, ``certify.py``, ``tune.py``,
``front.py``, ``export.py``, ``identify.py``; what they share in ``shared.py``).

``run_simulate``, ``run_bounds``, ``run_reproduce``, ``run_certify``, ``run_tune`` and
``run_front`` take a config (a TOML path, a user dict, an already resolved config, or
``None`` for the paper's defaults) and the command's options as keyword arguments, and return
the data the command writes: the dict that ``--json`` prints (``simulate``, ``bounds``,
``certify``), that ``result.json`` / ``front.json`` hold (``tune``, ``front``), or the tables
that ``reproduce`` writes. The dicts hold NumPy arrays where the JSON has lists;
``fosmc_jax._io.jsonable`` of a result is exactly the command's JSON. The ``fosmc`` command
line (``fosmc_jax._app.cli``) only parses arguments, prints and maps errors to exit codes.

Naming: ``run_<command>`` says "what ``fosmc <command>`` does" and keeps these config-level
entry points apart from the library functions they call (``simulate``, ``certify`` take
plants, controllers and arrays, not configs). Errors are :class:`ConfigError` with the
command line's one-line message; an option is named as the command line spells it
(``--steps: expected a positive integer, got 0``), so both surfaces say the same thing.

Every function runs with float64 available (``jax.enable_x64`` inside the call, as the
command line enables it globally); the config's ``[sim] precision`` picks the dtype. ``log``
receives the progress lines the command prints on stderr (default: silent). ``tune``,
``front`` and ``reproduce`` write their files only when given ``out``, refusing a non-empty
folder without ``force`` (or ``resume``) as the command does.
"""

from __future__ import annotations

from .bounds import run_bounds
from .certify import run_certify
from .export import run_export
from .front import MAX_FRONT_SEED, run_front
from .identify import run_identify
from .reproduce import run_reproduce
from .shared import config_of, metric_label, one_plant, writable
from .simulate import rollout_records, run_simulate
from .tune import run_tune

__all__ = ["run_simulate", "run_bounds", "run_reproduce", "run_certify", "run_tune", "run_front", "run_export",
           "run_identify", "config_of", "metric_label", "one_plant", "writable", "rollout_records",
           "MAX_FRONT_SEED"]  # fmt: skip
