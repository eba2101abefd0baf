"""A batch to simulate with parameters: what a config describes (:func:`fosmc_jax.build`),
and what the tuner and the front search run (``fosmc_jax.config.tuning_problems``), one class."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .._controllers.kind import SPACES
from .._plants.arm import Arm
from .rollout import simulate_batch
from .sharding import simulate_split


class Problem(NamedTuple):
    """A config's batch: the plants (leading axis P), the initial states ``X0s`` (O, 9), the
    noise ``keys`` (R, 2) of a digital loop (None: the ideal loop), the reference, the step
    ``dt``, :func:`fosmc_jax.simulate_batch`'s ``options``, and the controller's fixed parts:
    ``base``, the object whose fields the ``kind``'s tunable parameters are (the FOSMC's
    :class:`fosmc_jax.FOSMCParams`; another kind's law), and ``make``, base -> the controller
    of the loop (None: ``base`` itself).

    ``problem.simulate(params)`` runs the batch with the kind's parameters replaced; it is a
    pure function of ``params``, so ``jax.jit``, ``jax.grad`` and ``jax.vmap`` of a function
    that calls it work (close over the problem, differentiate the parameters)::

        problem = fosmc_jax.build("realistic_arm")
        loss = lambda delta: problem.simulate({"delta": delta}).mean().rms_error.mean()
        jax.grad(loss)(problem.params()["delta"])
    """

    plants: Any
    base: Any
    reference: Any
    X0s: Any
    dt: Any
    options: dict
    keys: Any = None
    make: Callable[[Any], Any] | None = None
    kind: str = "fosmc"

    def params(self) -> dict:
        """The kind's tunable parameters as the problem holds them, by the names ``result.json``
        and ``front.json`` use (the FOSMC's ``delta``, ``gamma``, ``poles``)."""
        return {name: getattr(self.base, name) for name in SPACES[self.kind].names}

    def controller(self, p: Any = None) -> Any:
        """The controller simulated with parameters ``p``: a dict by the kind's parameter names
        (a subset: the others stay), the kind's ``Space.values`` NamedTuple, or None (``base``
        as it is). Names, shapes and, where the values are concrete, finiteness are checked
        here; the simulator checks the rest (signs, ranges)."""
        params = self.base
        if p is not None:
            new = _checked(self.kind, self.base, p if isinstance(p, Mapping) else p._asdict())
            params = dataclasses.replace(params, **new) if dataclasses.is_dataclass(params) else params._replace(**new)
        return params if self.make is None else self.make(params)

    def with_arm(self, changes: Mapping) -> Problem:
        """The problem with the arm's physical parameters ``changes`` ({field of
        :class:`fosmc_jax.ArmParams`: value}, e.g. ``{"F": F}``; each value of the field's own
        shape, () or (3,)) in every plant of the batch (sampled arms lose that field's spread);
        differentiable in them::

            loss = lambda F: problem.with_arm({"F": F}).simulate(fast=False).mean().rms_error.mean()
            jax.grad(loss)(problem.arm_params()["F"])
        """
        if not isinstance(self.plants, Arm):
            raise ValueError(f"with_arm: the problem's plants are {type(self.plants).__name__}, not the arm")
        fields = self.plants.params
        unknown = sorted(set(changes) - set(fields._fields))
        if unknown:
            raise ValueError(f"with_arm: unknown arm parameter(s) {', '.join(map(repr, unknown))} "
                             f"(ArmParams: {', '.join(fields._fields)})")  # fmt: skip
        new = {}
        for name, value in changes.items():
            old = getattr(fields, name)  # (P, ...) : one row per plant
            value = jnp.asarray(value, old.dtype)
            if value.shape != old.shape[1:]:
                raise ValueError(f"with_arm: arm.{name}: expected shape {old.shape[1:]}, got {value.shape}")
            new[name] = jnp.broadcast_to(value, old.shape)
        return self._replace(plants=self.plants._replace(params=fields._replace(**new)))

    def arm_params(self) -> dict:
        """The arm's physical parameters, by :class:`fosmc_jax.ArmParams` field: the first
        plant's (every plant of a config's batch shares them, unless ``[arm.uncertainty]``
        samples arms)."""
        return {name: value[0] for name, value in self.plants.params._asdict().items()}

    @property
    def args(self) -> tuple:
        """``simulate_batch``'s positional arguments with the base parameters."""
        return self.plants, self.controller(), self.reference, self.X0s, self.dt

    @property
    def rollouts(self) -> int:
        """The batch's size: plants x offsets (paired: plants) x noise realizations."""
        P = _leading(self.plants)
        R = 1 if self.keys is None else self.keys.shape[0]
        return P * R if self.options.get("pairing") == "paired" else P * self.X0s.shape[0] * R

    def simulate(self, params: Any = None, split: bool = False, **options):
        """The batch's :class:`fosmc_jax.Result` (leading axis: the rollouts, in plant, offset,
        realization order) with ``params`` (see :meth:`controller`; None: the problem's own);
        ``split``: over this process's devices (:func:`fosmc_jax._simulator.sharding.simulate_split`,
        the tuner's loss). ``options`` override the problem's ``simulate_batch`` options."""
        run = simulate_split if split else simulate_batch
        ctrl = self.controller(params)
        return run(
            self.plants, ctrl, self.reference, self.X0s, self.dt, keys=self.keys, **dict(self.options, **options)
        )


def _leading(tree) -> int:
    return jax.tree.leaves(tree)[0].shape[0]


def _checked(kind: str, base: Any, p: Mapping) -> dict:
    """``p``'s entries as arrays of ``base``'s dtype and shape, named by the kind's parameters;
    one-line ``ValueError``s naming the entry otherwise."""
    space = SPACES[kind]
    unknown = sorted(set(p) - set(space.names))
    if unknown:
        raise ValueError(f"params: unknown name(s) {', '.join(map(repr, unknown))} for controller kind '{kind}' "
                         f"(its parameters: {', '.join(space.names)})")  # fmt: skip
    out = {}
    for param in space.params:
        if param.name not in p:
            continue
        old = getattr(base, param.name)
        value = p[param.name]
        try:
            value = jnp.asarray(value, jnp.result_type(old))
        except TypeError:
            raise ValueError(f"params.{param.name}: expected numbers, got {type(value).__name__}") from None
        if value.shape != old.shape:
            raise ValueError(f"params.{param.name}: expected shape {old.shape}, got {value.shape}")
        concrete = _concrete(value)
        if concrete is not None and not np.all(np.isfinite(concrete)):
            raise ValueError(f"params.{param.name}: expected finite numbers, got {concrete.tolist()}")
        out[param.name] = value
    return out


def _concrete(x) -> np.ndarray | None:
    """``x``'s values where they are known now (not under ``jit``, ``grad`` or ``vmap``)."""
    if isinstance(x, jax.core.Tracer):
        return None
    return np.asarray(x)
