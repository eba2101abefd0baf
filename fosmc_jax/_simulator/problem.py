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
from .._plants.arm import ARM_PARAMS, PARAM_RULES, Arm, ArmParams, centre_error
from .rollout import simulate_batch
from .sharding import simulate_split


class Problem(NamedTuple):
    """A config's batch: the plants (leading axis P), the initial states ``X0s`` (O, 9), the
    noise ``keys`` (R, 2) of a digital loop (None: the ideal loop), the reference, the step
    ``dt``, :func:`fosmc_jax.simulate_batch`'s ``options``, and the controller's fixed parts:
    ``base``, the object whose fields the ``kind``'s tunable parameters are (the FOSMC's
    :class:`fosmc_jax.FOSMCParams`; another kind's law), and ``make``, base -> the controller
    of the loop (None: ``base`` itself). For an arm's batch, ``arm`` is the nominal
    :class:`fosmc_jax.ArmParams` (the config's ``[arm]``; sampled arms are drawn around it),
    which :meth:`with_arm` and :meth:`arm_params` work from (None: plants made by hand).

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
    arm: Any = None

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
            if not (isinstance(p, Mapping) or hasattr(p, "_asdict")):
                space = SPACES[self.kind]
                raise TypeError(f"params: expected a dict of the parameters of controller kind '{self.kind}' by name "
                                f"({', '.join(space.names)}) or a {space.values.__name__}, got "
                                f"{type(p).__name__}")  # fmt: skip
            new = _checked(self.kind, self.base, p if isinstance(p, Mapping) else p._asdict())
            params = dataclasses.replace(params, **new) if dataclasses.is_dataclass(params) else params._replace(**new)
        return params if self.make is None else self.make(params)

    def with_arm(self, changes: Mapping) -> Problem:
        """The problem with the arm's nominal physical parameters ``changes`` ({field of
        :class:`fosmc_jax.ArmParams`: value}, e.g. ``{"F": F}``, or an ``ArmParams``; each value
        of the field's own shape, () or (3,)); differentiable in them::

            loss = lambda F: problem.with_arm({"F": F}).simulate(fast=False).mean().rms_error.mean()
            jax.grad(loss)(problem.arm_params()["F"])

        Sampled arms (``[arm.uncertainty]``) keep their spread: each plant's entry is scaled by
        value / nominal (the relative draws of the config), so ``with_arm(arm_params())`` is the
        same problem; an entry whose nominal is 0 (never drawn: a zero stays zero) becomes the
        value in every plant. Without a nominal (:attr:`arm` None: plants made by hand) a field
        must be the same in every plant to be changed."""
        fields, nominal = self._arm_fields("with_arm")
        if isinstance(changes, ArmParams):
            changes = {k: v for k, v in changes._asdict().items() if v is not None}
        if not isinstance(changes, Mapping):
            raise ValueError(f"with_arm: expected a dict of arm parameters or an ArmParams, got "
                             f"{type(changes).__name__}")  # fmt: skip
        unknown = sorted(set(changes) - set(ArmParams._fields))
        if unknown:
            raise ValueError(f"with_arm: unknown arm parameter(s) {', '.join(map(repr, unknown))} "
                             f"(ArmParams: {', '.join(ArmParams._fields)})")  # fmt: skip
        plant_fields, new_nominal = {}, {}
        for name, value in changes.items():
            old = getattr(fields, name)  # (P, ...): one row per plant; None: a term left out
            nom = getattr(nominal, name)
            shape = np.shape(getattr(ARM_PARAMS, name))
            dtype = jnp.result_type(self.dt) if old is None else old.dtype
            try:
                value = jnp.asarray(value, dtype)
            except (TypeError, ValueError):
                raise ValueError(f"with_arm: arm.{name}: expected numbers of shape {shape}, got {value!r}") from None
            if value.shape != shape:
                raise ValueError(f"with_arm: arm.{name}: expected shape {shape}, got {value.shape}")
            _, rule, what = PARAM_RULES[name]  # a real arm's range, as the config's [arm]
            if not isinstance(value, jax.core.Tracer) and not np.all(rule(np.asarray(value))):
                raise ValueError(f"with_arm: arm.{name}: expected {what}, got {np.asarray(value).tolist()}")
            P = _leading(self.plants)
            if old is None:  # a term left out: zero in every plant
                old = jnp.zeros((P, *shape), dtype)
            if self.arm is None and not _concretely_equal_rows(old):
                raise ValueError(f"with_arm: arm.{name} differs between the plants and the problem has no nominal arm "
                                 "to scale them from (Problem.arm); build it from a config")  # fmt: skip
            nom = old[0] if self.arm is None else jnp.asarray(nom, dtype)
            safe = jnp.where(nom == 0, 1, nom)
            plant_fields[name] = jnp.where(nom == 0, value, old * (value / safe))
            new_nominal[name] = value
        arm = None if self.arm is None else self.arm._replace(**new_nominal)
        for j in (2, 3) if arm is not None else ():
            c, length = getattr(arm, f"c{j}"), getattr(arm, f"l{j}")
            if not isinstance(c, jax.core.Tracer) and not isinstance(length, jax.core.Tracer):
                if error := centre_error(float(c), float(length), j):
                    raise ValueError(f"with_arm: {error}")
        plants = self.plants._replace(params=fields._replace(**plant_fields))
        return self._replace(plants=plants, arm=arm)

    def arm_params(self) -> dict:
        """The arm's nominal physical parameters, by :class:`fosmc_jax.ArmParams` field: the
        configured ``[arm]`` (:attr:`arm`; sampled arms are drawn around it), or, for plants
        made by hand, the first plant's."""
        return self._arm_fields("arm_params")[1]._asdict()

    def _arm_fields(self, what: str) -> tuple[ArmParams, ArmParams]:
        """The plants' (P, ...) parameters and the nominal's (or the first plant's)."""
        if not isinstance(self.plants, Arm):
            raise ValueError(f"{what}: the problem's plants are {type(self.plants).__name__}, not the arm")
        fields = self.plants.params
        if self.arm is not None:
            return fields, self.arm
        first = ArmParams(*(None if x is None else x[0] for x in fields))
        return fields, first

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


def _concretely_equal_rows(x) -> bool:
    """Whether every row of ``x`` (P, ...) is the first (False for traced values: unknown)."""
    if isinstance(x, jax.core.Tracer):
        return False
    a = np.asarray(x)
    return bool(np.all(a == a[:1]))


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
        except (TypeError, ValueError):
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
