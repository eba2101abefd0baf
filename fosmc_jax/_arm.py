"""The physical plant: a 3-DOF revolute direct-drive arm with one BLDC motor per joint.

The paper simulates its controller on an "integrated model" of such an arm, loaded with 0 kg
and 10 kg, but does not print it. This module builds one, so that a sweep over payloads is a
sweep over physics.

Mechanics. Joint 1 (base yaw) turns about the vertical z axis. Joints 2 (shoulder) and 3
(elbow) pitch about the horizontal axis y1 that turns with joint 1. At theta_2 = theta_3 = 0
both links hang straight down (so gravity vanishes at theta = 0, see :func:`third_order_rows`).
Link 2 is displaced along the shoulder axis by ``d2`` and link 3 along the elbow axis by
``d3``: these offsets couple joint 1 to joints 2 and 3 in M. Each link has its centre of mass
on its own axis and a diagonal inertia tensor in its own frame; a point payload of mass
``payload`` (kg) sits at the tool, the far end of link 3. The rotor inertias ``Jm`` of the
direct-drive motors add to the diagonal of M. With q = theta,

    M(q) q'' + C(q, q') q' + G(q) + F q' = tau,

M from the link Jacobians (sum of m J_v^T J_v + J_w^T R I R^T J_w: symmetric positive
definite by construction), C from the Christoffel symbols of M (so dM/dt - 2C is
skew-symmetric), G = dV/dq from the potential energy V.

Motors, per joint: L di/dt = u - R i - Kb q', tau = Kt i. The plant's internal state is
(q, q', i) (:class:`ArmState`); the controller sees X = [q1, q1', q1'', q2, ...] with q''
computed from that state, as in the paper's third-order model (1)-(2). Units: U in volts,
i in amperes, angles in radians, SI elsewhere.

Every parameter lives in :class:`ArmParams`; the calibrated defaults :data:`ARM_PARAMS` are
the output of ``tuning/calibrate_arm.py`` (NOTES.md item 6: the paper's B_bar reads as
M^-1 diag(Kt/L), its ddtheta coefficients as -R/L), pasted here as literals.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from . import _paper
from ._design import BoxBound, box_norm_bound
from ._linalg import solve3
from ._reference import Cycloid, desired_state

#: Payload range of the paper's simulations (kg): "no load (0 kg) and maximum load (10 kg)".
PAYLOAD_RANGE = (0.0, 10.0)


class ArmParams(NamedTuple):
    """Physical parameters of the arm (a pytree; every leaf may be traced).

    Source of the values in :data:`ARM_PARAMS`: calibrated by ``tuning/calibrate_arm.py``
    against the paper's (29) and Appendix box, except ``d1`` and ``g`` (fixed).
    Vectors (3,) are per joint 1, 2, 3; link tensors are (xx, yy, zz) principal moments about
    the link's centre of mass, in the link frame (z along the link, y along the joint axis).
    """

    d1: Array  # m, height of the shoulder above the base (kinematics only)
    d2: Array  # m, shoulder offset of link 2 along the joint-2 axis
    d3: Array  # m, elbow offset of link 3 along the joint-3 axis
    l2: Array  # m, length of link 2 (shoulder to elbow)
    l3: Array  # m, length of link 3 (elbow to tool)
    c2: Array  # m, distance shoulder -> centre of mass of link 2, along the link
    c3: Array  # m, distance elbow -> centre of mass of link 3, along the link
    m2: Array  # kg, mass of link 2
    m3: Array  # kg, mass of link 3
    I1: Array  # kg m^2, inertia of link 1 about the vertical axis
    I2: Array  # (3,) kg m^2, principal inertias of link 2 about its centre of mass
    I3: Array  # (3,) kg m^2, principal inertias of link 3 about its centre of mass
    Jm: Array  # (3,) kg m^2, motor rotor inertias (added to the diagonal of M)
    F: Array  # (3,) N m s/rad, viscous friction
    g: Array  # m/s^2, gravity
    R: Array  # (3,) ohm, winding resistance
    L: Array  # (3,) H, winding inductance
    Kt: Array  # (3,) N m/A, torque constant
    Kb: Array  # (3,) V s/rad, back-EMF constant (= Kt in SI for an ideal motor)


# Calibrated by tuning/calibrate_arm.py (paste its output here).
ARM_PARAMS = ArmParams(
    d1=0.5,
    d2=0.0012273,
    d3=0.0101301,
    l2=0.278527,
    l3=0.205152,
    c2=0.222754,
    c3=0.00270167,
    m2=50.8742,
    m3=43.9056,
    I1=1.85309,
    I2=np.array([3.61426, 6.68737, 4.42477]),
    I3=np.array([2.09596, 3.49843, 2.00212]),
    Jm=np.array([0.388901, 0.783712, 0.0855265]),
    F=np.array([0.195137, 0.0218947, 0.0476432]),
    g=9.81,
    R=np.array([0.15339, 0.0408162, 0.00333548]),
    L=np.array([0.0123151, 0.00482401, 0.000423062]),
    Kt=np.array([2.82869, 2.78674, 0.218529]),
    Kb=np.array([2.82869, 2.78674, 0.218529]),
)


def cast_params(params: ArmParams, dtype) -> ArmParams:
    """``params`` with every leaf as a JAX array of ``dtype`` (the dtype of the state in use)."""
    return jax.tree.map(lambda p: jnp.asarray(p, dtype), params)


# ---------------------------------------------------------------------------- kinematics


def _rot_z(a: Array) -> Array:
    c, s = jnp.cos(a), jnp.sin(a)
    o, z = jnp.ones_like(a), jnp.zeros_like(a)
    return jnp.stack([jnp.stack([c, -s, z]), jnp.stack([s, c, z]), jnp.stack([z, z, o])])


def _rot_y(a: Array) -> Array:
    c, s = jnp.cos(a), jnp.sin(a)
    o, z = jnp.ones_like(a), jnp.zeros_like(a)
    return jnp.stack([jnp.stack([c, z, s]), jnp.stack([z, o, z]), jnp.stack([-s, z, c])])


class _Frames(NamedTuple):
    p2: Array  # (3,) centre of mass of link 2
    p3: Array  # (3,) centre of mass of link 3
    tool: Array  # (3,) payload position
    R2: Array  # (3, 3) orientation of link 2
    R3: Array  # (3, 3) orientation of link 3


def _frames(p: ArmParams, theta: Array) -> _Frames:
    R1 = _rot_z(theta[0])
    R2 = R1 @ _rot_y(theta[1])
    R3 = R2 @ _rot_y(theta[2])
    down = jnp.array([0.0, 0.0, -1.0], theta.dtype)  # each link points down at theta = 0
    y1 = R1[:, 1]  # the pitch axis of joints 2 and 3
    shoulder = jnp.stack([jnp.zeros_like(p.d1), jnp.zeros_like(p.d1), p.d1]) + p.d2 * y1
    elbow = shoulder + p.l2 * (R2 @ down) + p.d3 * y1
    return _Frames(
        shoulder + p.c2 * (R2 @ down),
        elbow + p.c3 * (R3 @ down),
        elbow + p.l3 * (R3 @ down),
        R2,
        R3,
    )


def tool_position(params: ArmParams, theta: Array) -> Array:
    """Cartesian position (3,) of the tool (the payload), m, for joint angles ``theta`` (3,)."""
    return _frames(cast_params(params, theta.dtype), theta).tool


# ---------------------------------------------------------------------------- dynamics


def mass_matrix(params: ArmParams, payload: Array, theta: Array) -> Array:
    """Inertia matrix M(theta) (3, 3), kg m^2: symmetric positive definite by construction.

    sum over bodies of m J_v^T J_v + J_w^T R I R^T J_w, plus payload J_tool^T J_tool and the
    rotor inertias on the diagonal. ``payload`` in kg (scalar, may be traced).
    """
    p = cast_params(params, theta.dtype)
    payload = jnp.asarray(payload, theta.dtype)
    jac = jax.jacfwd(lambda q: _frames(p, q)[:3])(theta)  # J_v of p2, p3, tool, each (3, 3)
    f = _frames(p, theta)
    z = jnp.array([0.0, 0.0, 1.0], theta.dtype)
    y1 = f.R2[:, 1]
    zero = jnp.zeros(3, theta.dtype)
    Jw2 = jnp.stack([z, y1, zero], axis=1)  # angular-velocity Jacobians, (3, 3)
    Jw3 = jnp.stack([z, y1, y1], axis=1)
    rot = lambda R, I, Jw: (R.T @ Jw).T @ (I[:, None] * (R.T @ Jw))
    M = (
        p.m2 * jac[0].T @ jac[0]
        + p.m3 * jac[1].T @ jac[1]
        + payload * jac[2].T @ jac[2]
        + rot(f.R2, p.I2, Jw2)
        + rot(f.R3, p.I3, Jw3)
    )
    M = M + jnp.diag(p.Jm + jnp.stack([p.I1, jnp.zeros_like(p.I1), jnp.zeros_like(p.I1)]))
    return (M + M.T) / 2


def potential_energy(params: ArmParams, payload: Array, theta: Array) -> Array:
    """Gravitational potential energy V(theta), J (zero height at the base)."""
    p = cast_params(params, theta.dtype)
    f = _frames(p, theta)
    return p.g * (p.m2 * f.p2[2] + p.m3 * f.p3[2] + jnp.asarray(payload, theta.dtype) * f.tool[2])


def gravity(params: ArmParams, payload: Array, theta: Array) -> Array:
    """Gravity torques G(theta) = dV/dtheta (3,), N m."""
    return jax.grad(potential_energy, argnums=2)(params, payload, theta)


def coriolis_matrix(params: ArmParams, payload: Array, theta: Array, dtheta: Array) -> Array:
    """Coriolis/centrifugal matrix C(theta, theta') (3, 3) from the Christoffel symbols of M:
    C_ij = sum_k 1/2 (dM_ij/dq_k + dM_ik/dq_j - dM_jk/dq_i) q'_k, so dM/dt - 2C is skew."""
    dM = jax.jacfwd(mass_matrix, argnums=2)(params, payload, theta)  # [i, j, k] = dM_ij/dq_k
    gamma = (dM + jnp.swapaxes(dM, 1, 2) - jnp.transpose(dM, (2, 0, 1))) / 2
    return gamma @ dtheta


def kinetic_energy(params: ArmParams, payload: Array, theta: Array, dtheta: Array) -> Array:
    """1/2 theta'^T M theta', J."""
    return dtheta @ mass_matrix(params, payload, theta) @ dtheta / 2


def forward_dynamics(params: ArmParams, payload: Array, theta: Array, dtheta: Array, tau: Array) -> Array:
    """theta'' = M^-1 (tau - C theta' - G - F theta'), rad/s^2, for joint torques ``tau`` (N m)."""
    p = cast_params(params, theta.dtype)
    M = mass_matrix(p, payload, theta)
    n = coriolis_matrix(p, payload, theta, dtheta) @ dtheta + gravity(p, payload, theta) + p.F * dtheta
    return jnp.linalg.solve(M, tau - n)


# ---------------------------------------------------------------------------- closed form
#
# The same dynamics written out, for the time loop (the autodiff functions above are the
# oracle, tests/test_arm_dynamics.py). Both pitch joints turn about y1, so link 3's orientation
# is R1 Ry(q2 + q3), and in the frame of joint 1 every point mass sits at
#
#     r = (x, y, z),  x = -(a sin q2 + b sin(q2 + q3)),  y const,  z = d1 - a cos q2 - b cos(q2 + q3)
#
# with (a, b, y) = (c2, 0, d2) for link 2, (l2, c3, d2 + d3) for link 3 and (l2, l3, d2 + d3)
# for the payload. Its velocity in that rotating frame is (x' - q1' y, q1' x, z'), so its
# kinetic energy gives M11 = m (x^2 + y^2), M12 = m y (a cos q2 + b cos q23), M13 = m y b cos q23,
# M22 = m (a^2 + b^2 + 2 a b cos q3), M23 = m (b^2 + a b cos q3), M33 = m b^2. A link's body
# angular velocity is (-sin q q1', q', cos q q1') (q = q2, or q23 for link 3), adding
# Ixx sin^2 q + Izz cos^2 q to M11 and Iyy to its pitch block; the rotors add Jm (and link 1,
# I1) on the diagonal. G = dV/dq with V = g sum m z. The derivatives of M by q2 and q3 are
# written out too, for C theta' = M' theta' - 1/2 d/dq (theta'^T M theta').


def _point_masses(p: ArmParams, payload: Array) -> tuple:
    """(mass, a, b, y) of link 2, link 3 and the payload (see the comment above)."""
    y3 = p.d2 + p.d3
    return (p.m2, p.c2, jnp.zeros_like(p.c2), p.d2), (p.m3, p.l2, p.c3, y3), (payload, p.l2, p.l3, y3)


def _sym(m11, m12, m13, m22, m23, m33) -> Array:
    return jnp.stack([jnp.stack([m11, m12, m13]), jnp.stack([m12, m22, m23]), jnp.stack([m13, m23, m33])])


def _inertia(p: ArmParams, payload: Array, theta: Array) -> tuple[Array, Array, Array, Array]:
    """M, dM/dq2, dM/dq3 (M does not depend on q1) and G, in closed form; ``p`` already cast."""
    s2, c2 = jnp.sin(theta[1]), jnp.cos(theta[1])
    s23, c23 = jnp.sin(theta[1] + theta[2]), jnp.cos(theta[1] + theta[2])
    s3, c3 = jnp.sin(theta[2]), jnp.cos(theta[2])
    d2, d3 = 2 * (p.I2[0] - p.I2[2]) * s2 * c2, 2 * (p.I3[0] - p.I3[2]) * s23 * c23
    m11 = p.I1 + p.Jm[0] + p.I2[0] * s2**2 + p.I2[2] * c2**2 + p.I3[0] * s23**2 + p.I3[2] * c23**2
    m12 = m13 = g2 = g3 = jnp.zeros_like(m11)
    m22, m23, m33 = p.Jm[1] + p.I2[1] + p.I3[1], p.I3[1], p.Jm[2] + p.I3[1]
    a11, a12, a13 = d2 + d3, m12, m12  # d/dq2 of M11, M12, M13 (M22, M23, M33 do not depend on q2)
    b11, b12, b13, b22, b23 = d3, m12, m12, m12, m12  # d/dq3 of M11, M12, M13, M22, M23
    for m, a, b, y in _point_masses(p, payload):
        x, dx2, dx3 = a * s2 + b * s23, a * c2 + b * c23, b * c23
        m11, a11, b11 = m11 + m * (x**2 + y**2), a11 + 2 * m * x * dx2, b11 + 2 * m * x * dx3
        m12, a12, b12 = m12 + m * y * dx2, a12 - m * y * x, b12 - m * y * b * s23
        m13, a13, b13 = m13 + m * y * dx3, a13 - m * y * b * s23, b13 - m * y * b * s23
        m22, b22 = m22 + m * (a**2 + b**2 + 2 * a * b * c3), b22 - 2 * m * a * b * s3
        m23, b23 = m23 + m * (b**2 + a * b * c3), b23 - m * a * b * s3
        m33 = m33 + m * b**2
        g2, g3 = g2 + m * x, g3 + m * b * s23
    zero = jnp.zeros_like(m11)
    M = _sym(m11, m12, m13, m22, m23, m33)
    M2 = _sym(a11, a12, a13, zero, zero, zero)
    M3 = _sym(b11, b12, b13, b22, b23, zero)
    return M, M2, M3, p.g * jnp.stack([zero, g2, g3])


def mass_matrix_closed(params: ArmParams, payload: Array, theta: Array) -> Array:
    """:func:`mass_matrix` in closed form (equal to rounding), kg m^2."""
    return _inertia(cast_params(params, theta.dtype), jnp.asarray(payload, theta.dtype), theta)[0]


def gravity_closed(params: ArmParams, payload: Array, theta: Array) -> Array:
    """:func:`gravity` in closed form, N m."""
    return _inertia(cast_params(params, theta.dtype), jnp.asarray(payload, theta.dtype), theta)[3]


def _coriolis(M2: Array, M3: Array, dtheta: Array) -> Array:
    """C theta' = M' theta' - 1/2 d/dq (theta'^T M theta'), with M' = dM/dq2 q2' + dM/dq3 q3'."""
    Mdot = M2 * dtheta[1] + M3 * dtheta[2]
    half = jnp.stack([jnp.zeros_like(dtheta[0]), dtheta @ M2 @ dtheta, dtheta @ M3 @ dtheta]) / 2
    return Mdot @ dtheta - half


def coriolis_closed(params: ArmParams, payload: Array, theta: Array, dtheta: Array) -> Array:
    """C(theta, theta') theta' (3,), N m, in closed form."""
    _, M2, M3, _ = _inertia(cast_params(params, theta.dtype), jnp.asarray(payload, theta.dtype), theta)
    return _coriolis(M2, M3, dtheta)


# ---------------------------------------------------------------------------- the plant


class ArmState(NamedTuple):
    """Internal state of :class:`Arm`: joint angles (rad), rates (rad/s), motor currents (A)."""

    theta: Array
    dtheta: Array
    current: Array


class Arm(NamedTuple):
    """The arm as a plant for :func:`fosmc_jax.simulate` (``init``, ``observe``, ``derivative``).

    Fields: ``params`` (:class:`ArmParams`), ``payload`` (kg, scalar; traced, so ``vmap`` and
    ``grad`` reach it). Batched arms carry a leading axis on every leaf (see :func:`arm_sweep`).
    """

    params: ArmParams
    payload: Array

    def _terms(self, theta: Array, dtheta: Array) -> tuple[ArmParams, Array, Array]:
        """Cast parameters, M, and the torques C theta' + G + F theta' (closed form)."""
        p = cast_params(self.params, theta.dtype)
        M, M2, M3, G = _inertia(p, jnp.asarray(self.payload, theta.dtype), theta)
        return p, M, _coriolis(M2, M3, dtheta) + G + p.F * dtheta

    def init(self, X0: Array) -> ArmState:
        """State with [theta, theta', theta''] = ``X0`` (9,): the currents are solved from
        Kt i = M theta'' + C theta' + G + F theta'."""
        theta, dtheta, ddtheta = X0[0::3], X0[1::3], X0[2::3]
        p, M, n = self._terms(theta, dtheta)
        return ArmState(theta, dtheta, (M @ ddtheta + n) / p.Kt)

    def accelerations(self, state: ArmState) -> Array:
        """theta'' (3,) from the state: M^-1 (Kt i - C theta' - G - F theta'), in closed form."""
        p, M, n = self._terms(state.theta, state.dtheta)
        return solve3(M, p.Kt * state.current - n)

    def observe(self, state: ArmState) -> Array:
        """X (9,) = [theta_1, theta_1', theta_1'', theta_2, ...]."""
        return jnp.stack([state.theta, state.dtheta, self.accelerations(state)], axis=1).reshape(9)

    def derivative(self, state: ArmState, U: Array) -> ArmState:
        """Time derivative of the state under motor voltages ``U`` (3,), V."""
        p = cast_params(self.params, state.theta.dtype)
        di = (U - p.R * state.current - p.Kb * state.dtheta) / p.L
        return ArmState(state.dtheta, self.accelerations(state), di)


def arm_sweep(payloads: Array, params: ArmParams = ARM_PARAMS) -> Arm:
    """A batch of arms, one per payload (P,) kg, every leaf with a leading axis P (for
    :func:`fosmc_jax.simulate_batch`). The dtype of ``payloads`` sets the parameters' dtype."""
    payloads = jnp.asarray(payloads)
    dtype = payloads.dtype if jnp.issubdtype(payloads.dtype, jnp.floating) else jnp.result_type(float)
    n = payloads.shape[0]
    tile = lambda x: jnp.broadcast_to(jnp.asarray(x, dtype), (n,) + jnp.shape(x))
    return Arm(jax.tree.map(tile, params), payloads.astype(dtype))


# ---------------------------------------------------------------------------- third-order rows

_GL_NODES, _GL_WEIGHTS = np.polynomial.legendre.leggauss(12)
_GL_NODES, _GL_WEIGHTS = (_GL_NODES + 1) / 2, _GL_WEIGHTS / 2  # on [0, 1]


def third_order_rows(arm: Arm, X: Array) -> tuple[Array, Array]:
    """Rows 3, 6, 9 of the arm's own third-order model (1) at state X: theta''' = a X + b U.

    Differentiating Kt i = h := M q'' + C q' + F q' + G along L i' = u - R i - Kb q' gives
    M q''' = diag(Kt/L) u - diag(R/L) h - diag(Kt Kb/L) q' - dh/dt, which is factored as

      b       = M^-1 diag(Kt/L)                                                (B_bar)
      a[:, q''] = -M^-1 (diag(R/L) M + dM/dt + d(Cq')/dq' + F)
      a[:, q' ] = -M^-1 (diag(R/L) (C + F) + diag(Kt Kb/L) + d(Cq')/dq + dG/dq)
      a[:, q  ] = -M^-1 diag(R/L) G_bar,   G_bar = int_0^1 dG/dq(s q) ds,

    so that G_bar q = G(q) (exact because G(0) = 0; 12-point Gauss-Legendre). Every block is
    evaluated at X (C, dM/dt and the derivatives of C q' depend on q', so the factoring is one
    choice among many; it is exact: a X + b U is the true theta''').

    Args:
      arm: :class:`Arm` (unbatched).
      X: (9,) state [theta, theta', theta''] per joint.
    Returns:
      ``a_rows`` (3, 9) (units 1/s^k), ``b_rows`` (3, 3) (rad/(s^3 V)).
    """
    q, dq = X[0::3], X[1::3]
    p = cast_params(arm.params, X.dtype)
    m = arm.payload
    M = mass_matrix(p, m, q)
    dM = jax.jacfwd(mass_matrix, argnums=2)(p, m, q)
    Mdot = dM @ dq
    C = coriolis_matrix(p, m, q, dq)
    cq = lambda q_, dq_: coriolis_matrix(p, m, q_, dq_) @ dq_
    dc_dq, dc_ddq = jax.jacfwd(cq, argnums=(0, 1))(q, dq)
    dG = jax.jacfwd(gravity, argnums=2)
    G_bar = jnp.einsum(
        "n,nij->ij",
        jnp.asarray(_GL_WEIGHTS, X.dtype),
        jax.vmap(lambda s: dG(p, m, s * q))(jnp.asarray(_GL_NODES, X.dtype)),
    )
    r, k, kb = p.R / p.L, p.Kt / p.L, p.Kt * p.Kb / p.L
    F = jnp.diag(p.F)
    a_q = -jnp.linalg.solve(M, r[:, None] * G_bar)
    a_dq = -jnp.linalg.solve(M, r[:, None] * (C + F) + jnp.diag(kb) + dc_dq + dG(p, m, q))
    a_ddq = -jnp.linalg.solve(M, r[:, None] * M + Mdot + dc_ddq + F)
    b = jnp.linalg.solve(M, jnp.diag(k))
    a = jnp.stack([a_q, a_dq, a_ddq], axis=2).reshape(3, 9)
    return a, b


# ---------------------------------------------------------------------------- the arm's box


def envelope_samples(n_times: int = 81, dtype=None) -> Array:
    """States X (n_times, 9) along the paper's reference (30) over [0, tau]: the operating
    envelope of the paper's simulations (start/end of (30), tau = 2 s)."""
    dtype = dtype or jnp.result_type(float)
    ref = Cycloid(*(jnp.asarray(x, dtype) for x in (_paper.THETA_START, _paper.THETA_END, _paper.TAU)))
    t = jnp.linspace(0.0, _paper.TAU, n_times, dtype=dtype)
    return jax.vmap(lambda s: desired_state(ref(s)))(t)


class ArmBox(NamedTuple):
    """The arm's uncertainty box on rows 3, 6, 9 and its nominal (the box's midpoint),
    in the layout of :mod:`fosmc_jax._paper` (A: (3, 9), B: (3, 3))."""

    A_lower: np.ndarray
    A_upper: np.ndarray
    B_lower: np.ndarray
    B_upper: np.ndarray
    A_nominal: np.ndarray
    B_nominal: np.ndarray


@jax.jit
def rows_over(params: ArmParams, payloads: Array, X_samples: Array) -> tuple[Array, Array]:
    """:func:`third_order_rows` for every payload (P,) x state (S, 9): (P, S, 3, 9), (P, S, 3, 3)."""
    one = lambda m, X: third_order_rows(Arm(params, m), X)
    return jax.vmap(jax.vmap(one, in_axes=(None, 0)), in_axes=(0, None))(payloads, X_samples)


def arm_box(params: ArmParams, payloads: Array, X_samples: Array) -> ArmBox:
    """The arm's box over payloads (P,) kg x states (S, 9), as the paper built its Appendix:
    elementwise min and max of the instantaneous rows, nominal = midpoint (float64 NumPy)."""
    a, b = rows_over(params, payloads, X_samples)
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    lo_a, hi_a = a.min(axis=(0, 1)), a.max(axis=(0, 1))
    lo_b, hi_b = b.min(axis=(0, 1)), b.max(axis=(0, 1))
    return ArmBox(lo_a, hi_a, lo_b, hi_b, (lo_a + hi_a) / 2, (lo_b + hi_b) / 2)


def box_alpha_beta(box: ArmBox) -> tuple[BoxBound, BoxBound]:
    """alpha, beta of (31) for the arm's own box and nominal (vertex enumeration, exact)."""
    alpha = box_norm_bound(box.A_nominal, box.A_lower, box.A_upper, box.B_nominal)
    beta = box_norm_bound(box.B_nominal, box.B_lower, box.B_upper, box.B_nominal)
    return alpha, beta
