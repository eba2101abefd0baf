"""The digital loop: a sampled controller between sensors and an actuator.

:class:`DigitalLoop` composes, around any sampled controller (e.g.
:class:`fosmc_jax.DiscreteFOSMC`), the pieces a real servo loop has, each a small pure
function: :func:`measure` (encoder quantization, Gaussian noise, and optionally velocity and
acceleration from backward differences), a computation delay of ``delay`` samples, and the
amplifier's limit (:func:`saturate`). The controller runs every ``sample_steps`` = m
simulation steps, i.e. with period T = m dt. At sample j (t_j = j T):

    Y_j = measure(X(t_j))                                   (sensors)
    U_j, state = law.update(state, Y_j, X_d(t_j), t_j)      (the controller)
    V_j = clip(U_{j-d}, -u_max, u_max) for j >= d, 0 for j < d   (delay, actuator)

and V_j is held over [t_j, t_{j+1}). Gradients: noise is reparameterised (the key is an input
of the rollout, never a traced parameter), rounding passes the gradient straight through
(d round(x) / dx := 1), clipping keeps its natural subgradient.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from jax import Array

from .._controllers.base import ContinuousLaw, HasSlidingVariable

#: ``measured``: theta', theta'' read directly; ``difference``: backward differences of theta.
DERIVATIVES = ("measured", "difference")


@functools.partial(jax.tree_util.register_dataclass, data_fields=["counts", "noise_std"], meta_fields=["derivatives"])
@dataclasses.dataclass(frozen=True)
class Sensors:
    """Encoders and derivative estimation.

    Fields: ``counts`` (3,) encoder counts per revolution (0: no quantization), ``noise_std``
    (9,) standard deviations of the Gaussian noise on [theta_1, theta_1', theta_1'', theta_2,
    ...] (rad, rad/s, rad/s^2), or None for no noise (nothing is drawn); ``derivatives``
    (static): one of :data:`DERIVATIVES`. With ``difference`` only the angles' noise is used.
    """

    counts: Array
    noise_std: Array | None = None
    derivatives: str = "measured"

    def noise_size(self) -> int:
        """How many standard normal draws :func:`measure` takes per sample (static)."""
        return 0 if self.noise_std is None else 9 if self.derivatives == "measured" else 3


class SensorMemory(NamedTuple):
    """What the difference estimator remembers: the last measured angles and rates (3,)."""

    theta: Array
    dtheta: Array


def quantize(theta: Array, counts: Array) -> Array:
    """q round(theta / q), q = 2 pi / counts (identity where counts = 0), with the
    straight-through gradient: the derivative of the rounding is taken as 1."""
    on = counts > 0
    q = 2 * jnp.pi / jnp.where(on, counts, 1)
    rounded = jnp.where(on, q * jnp.round(theta / q), theta)
    return theta + jax.lax.stop_gradient(rounded - theta)


def measure(sensors: Sensors, X: Array, memory: SensorMemory, noise: Array, period: Array):
    """The measurement Y (9,) of the true state X (9,) and the estimator's next memory.

    ``noise``: ``sensors.noise_size()`` standard normal draws, scaled here by ``noise_std``.
    With ``measured`` derivatives, Y = [quantize(theta), theta', theta''] + noise. With
    ``difference``, theta_m = quantize(theta + noise_theta), theta'_m = (theta_m -
    memory.theta) / T and theta''_m = (theta'_m - memory.dtheta) / T.
    """
    if sensors.noise_size() == 9:
        X = X + sensors.noise_std * noise
    theta = X[0::3] + (sensors.noise_std[0::3] * noise if sensors.noise_size() == 3 else 0)
    theta = quantize(theta, sensors.counts)
    if sensors.derivatives == "measured":
        dtheta, ddtheta = X[1::3], X[2::3]
    else:
        dtheta = (theta - memory.theta) / period
        ddtheta = (dtheta - memory.dtheta) / period
    Y = jnp.stack([theta, dtheta, ddtheta], axis=1).reshape(9)
    return Y, SensorMemory(theta, dtheta)


def saturate(U: Array, u_max: Array) -> Array:
    """The applied voltage clip(U, -u_max, u_max) (u_max = inf: no limit)."""
    return jnp.clip(U, -u_max, u_max)


class LoopState(NamedTuple):
    law: Any  # the controller's own state
    memory: SensorMemory
    pending: Array  # (d, 3) computed controls not yet applied, oldest first
    j: Array  # sample index
    key: Array


@functools.partial(
    jax.tree_util.register_dataclass,
    data_fields=["law", "sensors", "u_max", "period"],
    meta_fields=["sample_steps", "delay"],
)
@dataclasses.dataclass(frozen=True)
class DigitalLoop:
    """A sampled controller ``law`` with sensors, delay and actuator limit, as a controller
    for :func:`fosmc_jax.simulate` (see the module docstring for the exact semantics).

    Fields: ``law`` (a controller without continuous-time state), ``sensors``
    (:class:`Sensors`), ``u_max`` (3,) V (inf: no limit), ``period`` T = m dt (s), traced;
    ``sample_steps`` m >= 1 and ``delay`` d >= 0 (samples), static.
    """

    law: Any
    sensors: Sensors
    u_max: Array
    period: Array
    sample_steps: int = 1
    delay: int = 0

    def __post_init__(self):
        if isinstance(self.law, ContinuousLaw):
            raise TypeError("DigitalLoop: the law must be a sampled controller (no continuous-time state)")

    def init(self, X0: Array, r0: Array, key=None) -> LoopState:
        """The exact initial state seeds the difference estimator (its first rates are true)."""
        key = jax.random.PRNGKey(0) if key is None else key
        if jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
            key = jax.random.key_data(key)  # raw uint32: the simulator's divergence guard selects on it
        memory = SensorMemory(X0[0::3], X0[1::3])
        pending = jnp.zeros((self.delay, 3), X0.dtype)
        return LoopState(self.law.init(X0, r0, key), memory, pending, jnp.zeros((), jnp.int32), key)

    def update(self, state: LoopState, X: Array, r: Array, t: Array) -> tuple[Array, LoopState]:
        """One sample: measure the true X (9,), run the law, delay, saturate."""
        size = self.sensors.noise_size()
        noise = jax.random.normal(jax.random.fold_in(state.key, state.j), (size,), X.dtype) if size else None
        Y, memory = measure(self.sensors, X, state.memory, noise, self.period)
        if self.sensors.derivatives == "difference":
            # j = 0 reads the true rates (the estimator starts from the exact initial state)
            first = state.j == 0
            Y = jnp.where(jnp.tile(jnp.array([False, True, True]), 3) & first, X, Y)
            memory = memory._replace(dtheta=jnp.where(first, X[1::3], memory.dtheta))
        U, law = self.law.update(state.law, Y, r, t)
        if self.delay:
            applied = state.pending[0]
            pending = jnp.concatenate([state.pending[1:], U[None]])
        else:
            applied, pending = U, state.pending
        return saturate(applied, self.u_max), LoopState(law, memory, pending, state.j + 1, state.key)

    def without_clock(self, state: LoopState) -> LoopState:
        """``state`` without its sample index and key (None there): on a rollout that has not
        diverged they are functions of the step and of the batch's key (:meth:`with_clock`), so
        that the generated kernel takes them, and the noise's draws, from its table of time
        values instead of carrying them per rollout."""
        return state._replace(j=None, key=None)

    def with_clock(self, state: LoopState, k: Array, key: Array) -> LoopState:
        """``state`` (from :meth:`without_clock`) at the start of simulation step ``k`` of a
        rollout that has not diverged: j = floor(k / m) + 1 samples taken (t = 0 and every m-th
        step since), the rollout's raw ``key``. A diverged rollout's frozen state differs, but
        nothing it computes is kept (the simulator's guard)."""
        j = (jnp.asarray(k, jnp.int32) // self.sample_steps + 1).astype(jnp.int32)
        return state._replace(j=j, key=key)

    def sliding_variable(self, state: LoopState) -> Array:
        """The law's sliding variable at the last sample (NaN if it has none)."""
        if isinstance(self.law, HasSlidingVariable):
            return self.law.sliding_variable(state.law)
        return jnp.full(3, jnp.nan, state.memory.theta.dtype)
