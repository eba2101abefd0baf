"""A numerical certificate of the hitting condition (20): s^T ds/dt / ||s|| < 0 away from s = 0.

Theorem 4.1 claims that the control (23) with gamma above the bounds (24)-(26) makes (20) hold
for every plant in the box. docs/paper.md explains why the bounds cannot be taken on trust (norm
conventions, (1 + beta) where the usual argument needs (1 - beta)); this module checks (20)
itself, at sampled points, and reports the worst one.

Algebra. With Z = X - X_d, s = C Z - w (14) and w' = (CA + CBK) Z, (17) is
ds/dt = C Z' - C (A + BK) Z. Rows other than 3, 6, 9 of A, B are the same integrator chains in
the true and the nominal model, and X_d' = A X_d + B Omega (10) holds with the chains exactly,
so the chain parts cancel and only rows 3, 6, 9 are left:

    ds/dt = C_r ( a X + b U - theta_d''' - (A_r + B_bar K) Z ),     C_r = C[:, (3, 6, 9)],

with (a, b) the true rows 3, 6, 9 (a box vertex, or the arm's third_order_rows at X) and
U = Omega - (CB)^-1 rho f(s) [+ K Z] (23), rho = gamma_1 ||Z|| + gamma_2 ||X_d|| + gamma_3 ||Omega||.
Because w is a free integral state, the direction of s is independent of Z: both are sampled.

The box. For fixed (t, Z, s) the control does not depend on the plant, so s^T ds/dt is affine
in the entries of (a, b): its maximum over the box is at the vertex that sets each entry to the
bound that makes its term w_i X_j a_ij (resp. w_i U_j b_ij, w = C_r^T s) largest. The linear
certificate therefore covers *all* 2^m vertices (indeed the whole box) exactly, in closed form;
``vertices=N`` instead evaluates N explicit vertices (seeded sample, or all of them if fewer),
which the tests use to cross-check the closed form.
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from .._controllers.fosmc import Derived, FOSMCParams, derive, safe_norm, switch, switching_gain
from .._design import paper as _paper
from .._plants.arm import Arm, third_order_rows
from .._plants.reference import desired_state, feedforward

# ---------------------------------------------------------------------------- array level


class Terms(NamedTuple):
    """What ds/dt needs at one (t, Z), independent of s and of the true plant."""

    X: Array  # (9,) true state X_d + Z
    rho: Array  # scalar, gamma_1 ||Z|| + gamma_2 ||X_d|| + gamma_3 ||Omega||
    U0: Array  # (3,) the control without its switching part: Omega [+ K Z]
    r: Array  # (3,) theta_d''' + (A_r + B_bar K) Z


def terms(ctrl: FOSMCParams, derived: Derived, derivatives: Array, Z: Array, law: str = "paper") -> Terms:
    """:class:`Terms` at reference ``derivatives`` (4, 3) (a reference's output at t) and
    tracking error ``Z`` (9,), with the controller's nominal model for Omega (10)."""
    X_d = desired_state(derivatives)
    Omega = feedforward(ctrl.a_rows, ctrl.b_rows, derivatives)
    rho = switching_gain(ctrl.gamma, safe_norm(Z), safe_norm(X_d), safe_norm(Omega))
    U0 = Omega + derived.K @ Z if law == "equivalent" else Omega
    r = derivatives[3] + (ctrl.a_rows + ctrl.b_rows @ derived.K) @ Z
    return Terms(X_d + Z, rho, U0, r)


def control(ctrl: FOSMCParams, derived: Derived, tm: Terms, s: Array, switching: str = "sign") -> Array:
    """U (3,) of (23) at sliding variable ``s`` (3,), volts."""
    return tm.U0 - derived.CB_inv @ (tm.rho * switch(s, ctrl.delta, switching))


def hitting(
    ctrl: FOSMCParams,
    derivatives: Array,
    Z: Array,
    s: Array,
    a_true: Array,
    b_true: Array,
    switching: str = "sign",
    law: str = "paper",
) -> Array:
    """s^T ds/dt / ||s|| of (20) for the true rows ``a_true`` (3, 9), ``b_true`` (3, 3) (units of
    s per second). ``derivatives`` (4, 3) is the reference at t, ``Z`` (9,), ``s`` (3,) non-zero.
    (20) holds at this point where the value is negative."""
    derived = derive(ctrl)
    tm = terms(ctrl, derived, derivatives, Z, law)
    U = control(ctrl, derived, tm, s, switching)
    w = ctrl.C[:, list(_paper.ROWS)].T @ s
    return w @ (a_true @ tm.X + b_true @ U - tm.r) / jnp.linalg.norm(s)


def box_max_hitting(
    ctrl: FOSMCParams,
    derivatives: Array,
    Z: Array,
    s: Array,
    box: tuple[Array, Array, Array, Array],
    switching: str = "sign",
    law: str = "paper",
) -> tuple[Array, Array, Array]:
    """max over the whole box (A_lower, A_upper, B_lower, B_upper) of :func:`hitting`, exact
    (closed form: the function is affine in the box entries). Returns the value and the rows
    (3, 9), (3, 3) of a maximising vertex."""
    derived = derive(ctrl)
    tm = terms(ctrl, derived, derivatives, Z, law)
    U = control(ctrl, derived, tm, s, switching)
    w = ctrl.C[:, list(_paper.ROWS)].T @ s
    A_lo, A_hi, B_lo, B_hi = box
    ca, cb = jnp.outer(w, tm.X), jnp.outer(w, U)
    a = jnp.where(ca > 0, A_hi, A_lo)
    b = jnp.where(cb > 0, B_hi, B_lo)
    value = (jnp.sum(ca * a) + jnp.sum(cb * b) - w @ tm.r) / jnp.linalg.norm(s)
    return value, a, b


# ---------------------------------------------------------------------------- sampling


def s_directions(n_random: int, rng: np.random.Generator) -> np.ndarray:
    """Unit directions of s, (26 + n_random, 3): the 26 sign patterns in {-1, 0, 1}^3 \\ {0}
    (axes +-, the 12 edge diagonals, the 8 orthant diagonals), normalised, then random ones."""
    grid = np.array(np.meshgrid([-1, 0, 1], [-1, 0, 1], [-1, 0, 1], indexing="ij")).reshape(3, -1).T
    grid = grid[np.any(grid != 0, axis=1)].astype(float)
    rand = rng.standard_normal((n_random, 3))
    out = np.concatenate([grid, rand])
    return out / np.linalg.norm(out, axis=1, keepdims=True)


def z_samples(n_random: int, scales: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Tracking errors Z, (1 + 18 + n_random, 9): Z = 0, the 18 axis points +-scales_i e_i, and
    n_random points scales * r u, u uniform on the unit sphere of R^9, r uniform in [0, 1]."""
    axes = np.concatenate([np.diag(scales), -np.diag(scales)])
    u = rng.standard_normal((n_random, 9))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    rand = scales * rng.uniform(0.0, 1.0, (n_random, 1)) * u
    return np.concatenate([np.zeros((1, 9)), axes, rand])


# ---------------------------------------------------------------------------- certificate


class Certificate(NamedTuple):
    """Outcome of :func:`certify`.

    ``max_hitting``: the largest s^T ds/dt / ||s|| found (units of s per second); (20) holds at
    every point checked iff it is negative (``holds``). ``points_checked``: (t, Z, s, plant)
    points covered; for the linear plant with ``vertices = "all"`` each (t, Z, s) covers all
    2^m vertices exactly (``evaluations`` counts the closed-form maxima computed). ``where``:
    the worst point: t (s), Z (9,), s (3,) unit, and the vertex (its code and rows) or the
    payload (kg). ``vertices``: which plants were checked, in words.
    """

    max_hitting: float
    holds: bool
    points_checked: int
    evaluations: int
    where: dict[str, Any]
    vertices: str
    plant: str
    envelope: dict[str, Any]


_STATIC = ("switching", "law")


@functools.partial(jax.jit, static_argnames=_STATIC)
def box_values(ctrl, derivs, Zs, S, box, switching, law):
    """box_max_hitting over the grid derivs (T, 4, 3) x Zs (nZ, 9) x S (nS, 3): (T, nZ, nS)."""
    one = lambda d, Z, s: box_max_hitting(ctrl, d, Z, s, box, switching, law)[0]
    return jax.lax.map(lambda d: jax.vmap(lambda Z: jax.vmap(lambda s: one(d, Z, s))(S))(Zs), derivs)


@functools.partial(jax.jit, static_argnames=_STATIC)
def vertex_values(ctrl, derivs, Zs, S, Va, Vb, switching, law):
    """hitting at every vertex (Va (V, 3, 9), Vb (V, 3, 3)) x the grid: (V, T, nZ, nS)."""
    one = lambda d, Z, s, a, b: hitting(ctrl, d, Z, s, a, b, switching, law)
    per_v = lambda a, b: jax.lax.map(
        lambda d: jax.vmap(lambda Z: jax.vmap(lambda s: one(d, Z, s, a, b))(S))(Zs), derivs
    )
    return jax.lax.map(lambda ab: per_v(*ab), (Va, Vb))


@functools.partial(jax.jit, static_argnames=_STATIC)
def arm_values(ctrl, derivs, Zs, S, params, payloads, switching, law):
    """hitting on the arm (rows third_order_rows at X_d + Z) per payload x the grid: (P, T, nZ, nS)."""

    def per_payload(mass):
        arm = Arm(params, mass)

        def at(d, Z):
            a, b = third_order_rows(arm, desired_state(d) + Z)
            return jax.vmap(lambda s: hitting(ctrl, d, Z, s, a, b, switching, law))(S)

        return jax.lax.map(lambda d: jax.vmap(lambda Z: at(d, Z))(Zs), derivs)

    return jax.lax.map(per_payload, payloads)


@jax.jit
def argmax(v: Array) -> tuple[Array, Array]:
    k = jnp.argmax(v)
    return v.ravel()[k], k
