"""The controller interface the simulator runs (:func:`fosmc_jax.simulate`), declared once.

A controller is a pytree with ``init`` and ``update`` (:class:`ControlLaw`); what more it
offers is declared by the protocols it also satisfies, each checked once where the simulator
receives it: a continuous-time state integrated with the plant between samples
(:class:`ContinuousLaw`: ``derivative``), a sliding variable for traces
(:class:`HasSlidingVariable`), and the sampling and actuator of a digital loop
(:class:`SampledLoop`: ``sample_steps``, ``u_max``, as :class:`fosmc_jax.DigitalLoop`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple, Protocol, runtime_checkable

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


class KernelLaw(NamedTuple):
    """What the arm's hand-written kernel (``arm_kernel.cc``, :mod:`fosmc_jax._simulator.arm_native`)
    needs of a law it runs: its ``surface`` (C, a_rows, b_rows), its lane ``rows`` (in the
    kernel's order, 96 numbers in all), its ``period`` (0 in the ideal loop), the indices of its
    ``switching`` function and ``law`` (0 where it has none), and ``memory``: its state -> the
    integral it carries from sample to sample (3,) (None: it carries none)."""

    surface: tuple[Array, Array, Array]
    rows: tuple[Any, ...]
    period: Any
    switching: int
    law: int
    memory: Callable[[Any], Array] | None


@runtime_checkable
class ArmKernelLaw(Protocol):
    """A controller the arm's kernel runs. ``arm_kernel_code(sampled)``: its law's code in
    ``arm_kernel.cc`` (h.kind: 0 the FOSMC, 1 SMC, 2 super-twisting) in the ideal loop
    (``sampled`` False: the controller itself) or sampled inside a
    :class:`fosmc_jax.DigitalLoop` (True: the loop's law); None where the kernel does not run it
    there. ``arm_kernel_law()``: its :class:`KernelLaw`."""

    def arm_kernel_code(self, sampled: bool) -> int | None: ...

    def arm_kernel_law(self) -> KernelLaw: ...


def check_controller(ctrl: Any) -> None:
    """A one-line TypeError unless ``ctrl`` has the :class:`ControlLaw` methods."""
    if not isinstance(ctrl, ControlLaw):
        raise TypeError(f"controller: {type(ctrl).__name__} is not a controller (needs init(X0, r0, key) and "
                        "update(state, Y, r, t); see fosmc_jax.ControlLaw)")  # fmt: skip
