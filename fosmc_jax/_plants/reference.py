"""Reference trajectories and the feed-forward Omega(t) of assumption (10).

A reference is any callable ``ref(t) -> Array[4, 3]`` returning, per joint, the desired angle
and its first three time derivatives: rows theta_d, theta_d', theta_d'', theta_d''' (rad,
rad/s, rad/s^2, rad/s^3). :class:`Cycloid` is the paper's (30); :class:`Sinusoid` is the
simplest smooth alternative. Both are NamedTuples, hence pytrees whose fields can be traced,
vmapped and differentiated. Users can plug in their own callable with the same signature.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
from jax import Array

from .._design.linalg import solve3


class Cycloid(NamedTuple):
    """The paper's rest-to-rest reference (30).

    theta_d(t) = theta(0) + Delta / (2 pi) [2 pi t / tau - sin(2 pi t / tau)] for 0 <= t < tau,
    theta(tau) afterwards (and theta(0) before 0), Delta = theta(tau) - theta(0).
    The third derivative jumps by Delta (2 pi)^2 / tau^3 at t = 0 and t = tau (docs/paper.md).

    Fields: ``start`` (3,) rad, ``end`` (3,) rad, ``duration`` tau (s, scalar).
    """

    start: Array
    end: Array
    duration: Array

    def __call__(self, t: Array) -> Array:
        tau = self.duration
        delta = self.end - self.start
        w = 2 * jnp.pi / tau
        tc = jnp.clip(t, 0.0, tau)
        inside = (t >= 0) & (t < tau)
        theta = self.start + delta / (2 * jnp.pi) * (w * tc - jnp.sin(w * tc))
        d1 = jnp.where(inside, delta / tau * (1 - jnp.cos(w * tc)), 0.0)
        d2 = jnp.where(inside, delta * w / tau * jnp.sin(w * tc), 0.0)
        d3 = jnp.where(inside, delta * w**2 / tau * jnp.cos(w * tc), 0.0)
        return jnp.stack([theta, d1, d2, d3])


class Sinusoid(NamedTuple):
    """theta_d(t) = offset + amplitude sin(frequency t + phase), per joint.

    Fields: ``offset`` (3,) rad, ``amplitude`` (3,) rad, ``frequency`` (3,) rad/s,
    ``phase`` (3,) rad.
    """

    offset: Array
    amplitude: Array
    frequency: Array
    phase: Array

    def __call__(self, t: Array) -> Array:
        a, w = self.amplitude, self.frequency
        x = w * t + self.phase
        s, c = jnp.sin(x), jnp.cos(x)
        return jnp.stack([self.offset + a * s, a * w * c, -a * w**2 * s, -a * w**3 * c])


def desired_state(derivatives: Array) -> Array:
    """X_d (9,) of (6), ordered joint by joint, from a reference's (4, 3) output."""
    return derivatives[:3].T.reshape(9)


def feedforward(a_rows: Array, b_rows: Array, derivatives: Array) -> Array:
    """Omega(t) of (10), shape (3,): the input under which the nominal model follows X_d.

    Rows 1, 2, 4, 5, 7, 8 of (10) hold for any smooth X_d; rows 3, 6, 9 give
    theta_d''' = A_r X_d + B_bar Omega, so Omega = B_bar^-1 (theta_d''' - A_r X_d).
    """
    return solve3(b_rows, derivatives[3] - a_rows @ desired_state(derivatives))
