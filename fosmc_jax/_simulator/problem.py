"""A batch to simulate with parameters: what a config describes (``fosmc_jax.config.build``)
and what the tuner and the front search (``fosmc_jax.config.tuning_problems``), one class."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, NamedTuple

from .rollout import simulate_batch
from .sharding import simulate_split


class Problem(NamedTuple):
    """The batch (plants with a leading axis P, initial states X0s (O, 9), noise ``keys``
    (R, 2) of a digital loop or None), the reference, the step ``dt``, ``simulate_batch``'s
    ``options``, and the controller's fixed parts: ``base``, whose fields the parameters
    replace (the FOSMC's :class:`fosmc_jax.FOSMCParams`, or another kind's law), and ``make``,
    base -> the controller of the loop (None: ``base`` itself)."""

    plants: Any
    base: Any
    reference: Any
    X0s: Any
    dt: Any
    options: dict
    keys: Any = None
    make: Callable[[Any], Any] | None = None

    def controller(self, p: Any = None) -> Any:
        """The controller simulated with parameters ``p`` (a NamedTuple: ``base``'s fields of
        those names replaced; None: ``base`` as it is)."""
        params = self.base
        if p is not None:
            if dataclasses.is_dataclass(params):  # a kind's law (SMC, super-twisting, ...)
                params = dataclasses.replace(params, **p._asdict())
            else:
                params = params._replace(**p._asdict())
        return params if self.make is None else self.make(params)

    @property
    def args(self) -> tuple:
        """``simulate_batch``'s positional arguments with the base parameters."""
        return self.plants, self.controller(), self.reference, self.X0s, self.dt

    def simulate(self, p: Any = None, split: bool = False, **options):
        """The batch's rollouts with parameters ``p`` (None: the base ones); ``split``: over
        this process's devices (:func:`fosmc_jax._simulator.sharding.simulate_split`, the
        tuner's loss). ``options`` override the problem's."""
        run = simulate_split if split else simulate_batch
        ctrl = self.controller(p)
        return run(
            self.plants, ctrl, self.reference, self.X0s, self.dt, keys=self.keys, **dict(self.options, **options)
        )
