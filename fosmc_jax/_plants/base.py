"""The plant interface the simulator runs (:func:`fosmc_jax.simulate`): a pytree with three
methods, the state's layout its own (the linear plant's is X itself, the arm's joint angles,
rates and winding currents)."""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

from jax import Array


@runtime_checkable
class Plant(Protocol):
    """init(X0) -> state from X0 (9,) = [theta, theta', theta''] per joint; observe(state) -> X
    (9,); derivative(state, U) -> d state/dt under the voltages U (3,) (V). :class:`LinearPlant`
    and :class:`Arm` are plants."""

    def init(self, X0: Array) -> Any: ...

    def observe(self, state: Any) -> Array: ...

    def derivative(self, state: Any, U: Array) -> Any: ...


def check_plant(plant: Any) -> None:
    """A one-line TypeError unless ``plant`` has the :class:`Plant` methods."""
    if not isinstance(plant, Plant):
        raise TypeError(f"plant: {type(plant).__name__} is not a plant (needs init(X0), observe(state) and "
                        "derivative(state, U); see fosmc_jax.Plant)")  # fmt: skip
