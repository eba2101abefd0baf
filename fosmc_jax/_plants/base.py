"""The plant interface the simulator runs (:func:`fosmc_jax.simulate`): a pytree with three
methods, the state's layout its own (the linear plant's is X itself, the arm's joint angles,
rates and winding currents).

Time. A plant's dynamics may depend on time (an exogenous input, such as the arm's external
torque): such a plant says so with a class attribute ``time_varying = True``, and the
simulator then calls ``observe(state, t)`` and ``derivative(state, U, t)`` with the time t (s)
of the sample or of the integrator's stage, the reference's own clock (t_k = k dt,
t_k + dt/2, ...). Every other plant (:class:`LinearPlant`, a user's plant) keeps the
two-argument ``observe(state)`` and ``derivative(state, U)``: :func:`observe_at` and
:func:`derivative_at` call whichever the plant has. ``init(X0)`` is at t = 0.

Optionally, ``derivative_observed(state, X, U[, t])``: the derivative given the observation X of
the same state and time, for a plant whose observation holds part of its derivative (the arm's
theta''): the simulator then reuses each step's observation in the next step's first stage
(:func:`reuses_observation`); the values are those of ``derivative``.
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

from jax import Array


@runtime_checkable
class Plant(Protocol):
    """init(X0) -> state from X0 (9,) = [theta, theta', theta''] per joint; observe(state) -> X
    (9,); derivative(state, U) -> d state/dt under the voltages U (3,) (V); with a class
    attribute ``time_varying = True``, observe(state, t) and derivative(state, U, t) instead
    (see the module's docstring). :class:`LinearPlant` and :class:`Arm` (time-varying) are
    plants."""

    def init(self, X0: Array) -> Any: ...

    def observe(self, state: Any) -> Array: ...

    def derivative(self, state: Any, U: Array) -> Any: ...


def time_varying(plant: Any) -> bool:
    """Whether ``plant``'s ``observe`` and ``derivative`` take the time t."""
    return bool(getattr(plant, "time_varying", False))


def observe_at(plant: Any, state: Any, t: Array) -> Array:
    """X (9,) of ``plant`` in ``state`` at time ``t`` (s): ``plant.observe(state, t)`` for a
    time-varying plant, ``plant.observe(state)`` otherwise."""
    return plant.observe(state, t) if time_varying(plant) else plant.observe(state)


def derivative_at(plant: Any, state: Any, U: Array, t: Array) -> Any:
    """d state/dt of ``plant`` under ``U`` at time ``t`` (s): ``plant.derivative(state, U, t)``
    for a time-varying plant, ``plant.derivative(state, U)`` otherwise."""
    return plant.derivative(state, U, t) if time_varying(plant) else plant.derivative(state, U)


def reuses_observation(plant: Any) -> bool:
    """Whether ``plant`` has ``derivative_observed(state, X, U[, t])``: its derivative given its
    observation X = ``observe(state[, t])`` at the same time, for a plant whose observation
    holds part of its derivative (the arm's theta''). The simulator then carries each step's
    observation into the next step's first stage, where it would otherwise be computed again."""
    return callable(getattr(plant, "derivative_observed", None))


def derivative_observed_at(plant: Any, state: Any, X: Array, U: Array, t: Array) -> Any:
    """:func:`derivative_at` from the observation ``X`` of ``state`` at ``t``
    (:func:`reuses_observation`)."""
    return plant.derivative_observed(state, X, U, t) if time_varying(plant) else plant.derivative_observed(state, X, U)


def check_plant(plant: Any) -> None:
    """A one-line TypeError unless ``plant`` has the :class:`Plant` methods."""
    if not isinstance(plant, Plant):
        raise TypeError(f"plant: {type(plant).__name__} is not a plant (needs init(X0), observe(state) and "
                        "derivative(state, U); see fosmc_jax.Plant)")  # fmt: skip
