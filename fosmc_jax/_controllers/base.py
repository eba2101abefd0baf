"""The controller interface the simulator runs (:func:`fosmc_jax.simulate`), declared once.

A controller is a pytree with ``init`` and ``update`` (:class:`ControlLaw`); what more it
offers is declared by the protocols it also satisfies, each checked once where the simulator
receives it: a continuous-time state integrated with the plant between samples
(:class:`ContinuousLaw`: ``derivative``), a sliding variable for traces
(:class:`HasSlidingVariable`), and the sampling and actuator of a digital loop
(:class:`SampledLoop`: ``sample_steps``, ``u_max``, as :class:`fosmc_jax.DigitalLoop`).
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

from jax import Array


@runtime_checkable
class ControlLaw(Protocol):
    """init(X0, r0, key=None) -> state, from the initial state X0 (9,) and the reference's
    first sample r0 (4, 3); update(state, Y, r, t) -> (U, state) at each controller sample, from
    the measurement Y (9,), the reference r (4, 3) at time t (s): U (3,) volts."""

    def init(self, X0: Array, r0: Array, key: Array | None = None) -> Any: ...

    def update(self, state: Any, Y: Array, r: Array, t: Array) -> tuple[Array, Any]: ...


@runtime_checkable
class ContinuousLaw(ControlLaw, Protocol):
    """A law with continuous-time state: derivative(state, X, r, t) -> d state/dt, integrated
    with the plant between samples (the ideal loop's integral of (14))."""

    def derivative(self, state: Any, X: Array, r: Array, t: Array) -> Any: ...


@runtime_checkable
class HasSlidingVariable(Protocol):
    """sliding_variable(state) -> s (3,) at the last sample, for traces (NaN without one)."""

    def sliding_variable(self, state: Any) -> Array: ...


@runtime_checkable
class SampledLoop(ControlLaw, Protocol):
    """A controller sampled every ``sample_steps`` simulation steps, its output limited to
    |U_i| <= ``u_max`` (3,) V (the chattering metrics report the saturation)."""

    sample_steps: int
    u_max: Array


@runtime_checkable
class PlacedPoles(Protocol):
    """Controller parameters that place the poles of a nominal closed loop: ``a_rows`` (3, 9)
    and ``b_rows`` (3, 3), rows 3, 6, 9 of the nominal A and B, and ``poles`` (3, 3) (1/s), as
    :class:`fosmc_jax.FOSMCParams`. The simulator warns where its step exceeds that loop's
    stable step (:func:`fosmc_jax.stable_step`), for parameters its input rules checked."""

    a_rows: Array
    b_rows: Array
    poles: Array


def check_controller(ctrl: Any) -> None:
    """A one-line TypeError unless ``ctrl`` has the :class:`ControlLaw` methods."""
    if not isinstance(ctrl, ControlLaw):
        raise TypeError(f"controller: {type(ctrl).__name__} is not a controller (needs init(X0, r0, key) and "
                        "update(state, Y, r, t); see fosmc_jax.ControlLaw)")  # fmt: skip
