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

    M(q) q'' + C(q, q') q' + G(q) + F q' + Fc tanh(q'/v_c) = tau + tau_ext(t),

M from the link Jacobians (sum of m J_v^T J_v + J_w^T R I R^T J_w: symmetric positive
definite by construction), C from the Christoffel symbols of M (so dM/dt - 2C is
skew-symmetric), G = dV/dq from the potential energy V. F q' is viscous friction,
Fc tanh(q'/v_c) Coulomb friction smoothed over the velocity scale v_c (:func:`coulomb_friction`),
tau_ext(t) an external torque per joint, constant + step + sinusoid (:func:`external_torque`):
the disturbances of docs/arm.md, all zero in :data:`ARM_PARAMS`. The external torque depends
on time, so the arm is a time-varying plant (``Arm.time_varying``: the simulator passes t to
``observe`` and ``derivative``, :mod:`fosmc_jax._plants.base`).

Motors, per joint: L di/dt = u - R i - Kb q', tau = Kt i. The plant's internal state is
(q, q', i) (:class:`ArmState`); the controller sees X = [q1, q1', q1'', q2, ...] with q''
computed from that state, as in the paper's third-order model (1)-(2). Units: U in volts,
i in amperes, angles in radians, SI elsewhere.

Every parameter lives in :class:`ArmParams`; the calibrated defaults :data:`ARM_PARAMS` are
the output of ``tuning/calibrate_arm.py`` (docs/paper.md: the paper's B_bar reads as
M^-1 diag(Kt/L), its ddtheta coefficients as -R/L), pasted here as literals.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from .._design import paper as _paper
from .._design.gains import BoxBound, box_norm_bound
from .._design.linalg import solve3
from .reference import Cycloid, desired_state

#: Payload range of the paper's simulations (kg): "no load (0 kg) and maximum load (10 kg)".
PAYLOAD_RANGE = (0.0, 10.0)


# The disturbances' defaults (read-only: shared by every ArmParams that takes them).
_ZEROS, _ONES = np.zeros(3), np.ones(3)
_ZEROS.flags.writeable = _ONES.flags.writeable = False

#: Default smoothing scale v_c (rad/s) of the Coulomb term Fc tanh(q'/v_c): the friction
#: reaches 99.5% of Fc at 3 v_c = 0.03 rad/s, under 2% of the paper's reference's peak rates
#: (1.8, 1.7, 1.7 rad/s), so the motion sees nearly ideal Coulomb friction; near rest it acts as
#: a viscous slope Fc/v_c (100 N m s/rad per N m of Fc), a mode of at most 0.37 Fc/v_c = 37 /s
#: per N m (M^-1's largest eigenvalue over the paper's envelope is 0.37 /(kg m^2)), inside RK4's
#: stability interval (2.78/dt) for Fc up to 75 N m at dt = 1e-3 s (docs/arm.md, "Friction and
#: disturbances").
V_COULOMB = 0.01


class ArmParams(NamedTuple):
    """Physical parameters of the arm (a pytree; every leaf may be traced).

    Source of the values in :data:`ARM_PARAMS`: calibrated by ``tuning/calibrate_arm.py``
    against the paper's (29) and Appendix box, except ``d1`` and ``g`` (fixed) and the
    trailing Coulomb friction and external torques (none; their fields have defaults). The
    external torque adds to the motors' Kt i on each joint (positive: along the joint's angle).
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
    # Friction beyond F and external disturbances (docs/arm.md); defaults: none, so that the
    # calibrated arm and every construction from the 19 fields above stay as they were.
    # The amplitudes Fc, tau_bias, tau_step and tau_sin may be None: the term left out (at no cost).
    Fc: Array = _ZEROS  # (3,) N m, Coulomb friction level: Fc tanh(q'/v_coulomb)
    v_coulomb: Array = V_COULOMB  # rad/s, the Coulomb term's smoothing velocity scale (> 0)
    tau_bias: Array = _ZEROS  # (3,) N m, constant external torque
    tau_step: Array = _ZEROS  # (3,) N m, external torque step, on from t = t_step
    t_step: Array = 1.0  # s, time of the step
    tau_sin: Array = _ZEROS  # (3,) N m, amplitude of the sinusoidal external torque
    f_sin: Array = _ONES  # (3,) Hz, its frequency: tau_sin sin(2 pi f_sin t)


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


def coulomb_friction(params: ArmParams, dtheta: Array) -> Array:
    """Coulomb friction torques Fc tanh(theta'/v_coulomb) (3,), N m, for rates ``dtheta`` (3,)."""
    p = cast_params(params, dtheta.dtype)
    return jnp.zeros_like(dtheta) if p.Fc is None else p.Fc * jnp.tanh(dtheta * (1 / p.v_coulomb))


def external_torque(params: ArmParams, t: Array) -> Array:
    """The external torque on each joint at time ``t`` (s), (3,) N m:
    tau_bias + tau_step [t >= t_step] + tau_sin sin(2 pi f_sin t)."""
    t = jnp.asarray(t)
    dtype = t.dtype if jnp.issubdtype(t.dtype, jnp.floating) else jnp.result_type(float)
    d = _external(cast_params(params, dtype), t)
    return jnp.zeros(3, dtype) if d is None else jnp.stack(d)


def _external(p: ArmParams, t: Array) -> tuple[Array, Array, Array] | None:
    """:func:`external_torque` as three scalars, None where every part is absent (None); ``p``
    cast."""
    if p.tau_bias is None and p.tau_step is None and p.tau_sin is None:
        return None
    t = jnp.asarray(t, p.t_step.dtype)
    d = [jnp.zeros((), t.dtype)] * 3 if p.tau_bias is None else [p.tau_bias[j] for j in range(3)]
    if p.tau_step is not None:
        on = t >= p.t_step
        d = [d[j] + jnp.where(on, p.tau_step[j], 0) for j in range(3)]
    if p.tau_sin is not None:
        w = (2 * np.pi) * p.f_sin
        d = [d[j] + p.tau_sin[j] * jnp.sin(w[j] * t) for j in range(3)]
    return tuple(d)


#: The external torque's fields: outside the dynamics' rows (:func:`third_order_rows`), an input.
EXOGENOUS = ("tau_bias", "tau_step", "t_step", "tau_sin", "f_sin")


#: The optional terms, by the field of their amplitude: None there (:func:`without_idle_terms`)
#: leaves the term out of the dynamics, at no cost.
OPTIONAL_TERMS = ("Fc", "tau_bias", "tau_step", "tau_sin")


def without_idle_terms(plant):
    """``plant`` with each optional term (:data:`OPTIONAL_TERMS`) whose amplitude is concretely
    zero (in every arm of a batch) set to None, in every :class:`ArmParams` the plant holds (an
    :class:`Arm`'s, or a user's plant built on them): the same dynamics, without evaluating the
    zero term (3 tanh or sin per evaluation of the accelerations, which every path would pay at
    every stage of every step; what that costs: BENCHMARKS.md, "Figures behind the code"). The
    simulator does this before it compiles (:func:`fosmc_jax.simulate`,
    :func:`fosmc_jax.simulate_batch`); traced amplitudes (a derivative in them) stay."""

    def prune(params):
        if not isinstance(params, ArmParams):
            return params
        idle = {}
        for name in OPTIONAL_TERMS:
            x = getattr(params, name)
            if x is not None and not isinstance(x, jax.core.Tracer) and not np.any(np.asarray(x)):
                idle[name] = None
        return params._replace(**idle) if idle else params

    return jax.tree.map(prune, plant, is_leaf=lambda x: isinstance(x, ArmParams))


_finite = np.isfinite
_positive = lambda a: np.isfinite(a) & (a > 0)
_non_negative = lambda a: np.isfinite(a) & (a >= 0)
# a link's principal moments: positive, each at most the sum of the other two (last axis)
_principal = lambda a: _positive(a) & (2 * a <= np.sum(a, axis=-1, keepdims=True) * (1 + 1e-12))

#: What a real arm's parameters may be, by :class:`ArmParams` field: (shape, a test of the
#: concrete values, NumPy in, booleans out, NaN failing; what is expected). One source for the
#: config's ``[arm]`` keys and ``Problem.with_arm`` (with :func:`centre_error`). The simulator's
#: input checks accept the wider domain of the equations (e.g. R = 0, Kb = 0: ideal motors).
PARAM_RULES: dict = {
    "d1": ((), _finite, "a number (m)"),
    "d2": ((), _finite, "a number (m)"),
    "d3": ((), _finite, "a number (m)"),
    "l2": ((), _positive, "a positive length (m)"),
    "l3": ((), _positive, "a positive length (m)"),
    "c2": ((), _non_negative, "a non-negative distance (m; at most arm.l2)"),
    "c3": ((), _non_negative, "a non-negative distance (m; at most arm.l3)"),
    "m2": ((), _positive, "a positive mass (kg)"),
    "m3": ((), _positive, "a positive mass (kg)"),
    "I1": ((), _positive, "a positive inertia (kg m^2)"),
    "I2": ((3,), _principal, "3 positive principal inertias (kg m^2), each at most the sum of the other two"),
    "I3": ((3,), _principal, "3 positive principal inertias (kg m^2), each at most the sum of the other two"),
    "Jm": ((3,), _positive, "3 positive rotor inertias (kg m^2)"),
    "F": ((3,), _non_negative, "3 non-negative viscous friction coefficients (N m s/rad)"),
    "g": ((), _non_negative, "a non-negative number (m/s^2)"),
    "R": ((3,), _positive, "3 positive resistances (ohm)"),
    "L": ((3,), _positive, "3 positive inductances (H)"),
    "Kt": ((3,), _positive, "3 positive torque constants (N m/A)"),
    "Kb": ((3,), _positive, "3 positive back-EMF constants (V s/rad)"),
    "Fc": ((3,), _non_negative, "3 non-negative Coulomb friction levels (N m)"),
    "v_coulomb": ((), _positive, "a positive velocity scale (rad/s)"),
    "tau_bias": ((3,), _finite, "3 numbers (N m)"),
    "tau_step": ((3,), _finite, "3 numbers (N m)"),
    "t_step": ((), _non_negative, "a non-negative time (s)"),
    "tau_sin": ((3,), _finite, "3 numbers (N m)"),
    "f_sin": ((3,), _non_negative, "3 non-negative frequencies (Hz)"),
}


def centre_error(c: float, length: float, j: int) -> str | None:
    """The error when link ``j``'s centre of mass ``c`` lies beyond its length (None: within)."""
    if c <= length:
        return None
    within = f"within the link, at most arm.l{j} = {length:g} m"
    return f"arm.c{j}: expected the centre of mass of link {j} {within}, got {c:g}"


def forward_dynamics(params: ArmParams, payload: Array, theta: Array, dtheta: Array, tau: Array) -> Array:
    """theta'' = M^-1 (tau - C theta' - G - F theta' - Fc tanh(theta'/v_coulomb)), rad/s^2, for
    joint torques ``tau`` (N m; the motors' and the external ones)."""
    p = cast_params(params, theta.dtype)
    M = mass_matrix(p, payload, theta)
    n = coriolis_matrix(p, payload, theta, dtheta) @ dtheta + gravity(p, payload, theta) + p.F * dtheta
    return solve3(M, tau - (n + coulomb_friction(p, dtheta)))


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
#
# Everything is written on scalar entries (tuples), not on stacked (3, 3) arrays: under
# ``vmap`` a matrix product becomes one small batched dot per call, while scalar expressions
# fuse into a few elementwise loops over the batch (the structure-of-arrays layout that
# ``_simulator._linear_batch`` writes by hand). Symmetric matrices are the tuples
# (m11, m12, m13, m22, m23, m33).


def _point_masses(p: ArmParams, payload: Array) -> tuple:
    """(mass, a, b, y) of link 2, link 3 and the payload (see the comment above); b = 0 for
    link 2 is left out of the expressions (``None``)."""
    y3 = p.d2 + p.d3
    return (p.m2, p.c2, None, p.d2), (p.m3, p.l2, p.c3, y3), (payload, p.l2, p.l3, y3)


def _inertia(p: ArmParams, payload: Array, theta: tuple) -> tuple[tuple, tuple, tuple, tuple]:
    """Entries of M, dM/dq2, dM/dq3 (M does not depend on q1) and G, in closed form.

    ``p`` already cast, ``theta`` three scalars. Returns M (6 entries, upper triangle by rows),
    dM/dq2 (a11, a12, a13: its other entries vanish), dM/dq3 (b11, b12, b13, b22, b23: b33
    vanishes) and G (G2, G3: G1 vanishes); units kg m^2 (per rad) and N m."""
    s2, c2 = jnp.sin(theta[1]), jnp.cos(theta[1])
    s3, c3 = jnp.sin(theta[2]), jnp.cos(theta[2])
    s23, c23 = s2 * c3 + c2 * s3, c2 * c3 - s2 * s3
    I2, I3, Jm = p.I2, p.I3, p.Jm
    m11 = p.I1 + Jm[0] + I2[0] * s2 * s2 + I2[2] * c2 * c2 + I3[0] * s23 * s23 + I3[2] * c23 * c23
    m22, m23, m33 = Jm[1] + I2[1] + I3[1], I3[1], Jm[2] + I3[1]
    b11 = 2 * (I3[0] - I3[2]) * s23 * c23
    a11 = 2 * (I2[0] - I2[2]) * s2 * c2 + b11
    m12 = m13 = a12 = a13 = b12 = b22 = b23 = g2 = g3 = 0.0
    for m, a, b, y in _point_masses(p, payload):
        if b is None:  # link 2: its mass on the shoulder's axis only
            x, dx2 = a * s2, a * c2
            m11, a11 = m11 + m * (x * x + y * y), a11 + 2 * m * x * dx2
            m12, a12 = m12 + m * y * dx2, a12 - m * y * x
            m22 = m22 + m * a * a
            g2 = g2 + m * x
            continue
        bs, bc = b * s23, b * c23
        x, dx2, dx3 = a * s2 + bs, a * c2 + bc, bc
        mx, my, mab = m * x, m * y, m * a * b
        m11, a11, b11 = m11 + m * (x * x + y * y), a11 + 2 * mx * dx2, b11 + 2 * mx * dx3
        m12, a12, b12 = m12 + my * dx2, a12 - my * x, b12 - my * bs
        m13, a13 = m13 + my * dx3, a13 - my * bs
        m22, b22 = m22 + m * (a * a + b * b) + 2 * mab * c3, b22 - 2 * mab * s3
        m23, b23 = m23 + m * b * b + mab * c3, b23 - mab * s3
        m33 = m33 + m * b * b
        g2, g3 = g2 + mx, g3 + m * bs
    # d/dq3 of M13 equals d/dq2 of M13 and d/dq3 of M12 (all -m y b sin q23): b13 = a13 = b12.
    return (m11, m12, m13, m22, m23, m33), (a11, a12, a13), (b11, b12, a13, b22, b23), (p.g * g2, p.g * g3)


def _coriolis(M2: tuple, M3: tuple, w: tuple) -> tuple:
    """C theta' = M' theta' - 1/2 d/dq (theta'^T M theta'), M' = dM/dq2 q2' + dM/dq3 q3', for
    the entries of :func:`_inertia` and the rates ``w`` (three scalars); three scalars, N m."""
    a11, a12, a13 = M2
    b11, b12, b13, b22, b23 = M3
    w1, w2, w3 = w
    e11, e12, e13 = a11 * w2 + b11 * w3, a12 * w2 + b12 * w3, a13 * w2 + b13 * w3
    e22, e23 = b22 * w3, b23 * w3
    h2 = w1 * (a11 * w1 / 2 + a12 * w2 + a13 * w3)
    h3 = w1 * (b11 * w1 / 2 + b12 * w2 + b13 * w3) + w2 * (b22 * w2 / 2 + b23 * w3)
    return (
        e11 * w1 + e12 * w2 + e13 * w3,
        e12 * w1 + e22 * w2 + e23 * w3 - h2,
        e13 * w1 + e23 * w2 - h3,
    )


def _solve_sym(M: tuple, r: tuple) -> tuple:
    """x with M x = r for a symmetric 3x3 M given by its entries (adjugate over determinant)."""
    m11, m12, m13, m22, m23, m33 = M
    A, B, C = m22 * m33 - m23 * m23, m13 * m23 - m12 * m33, m12 * m23 - m13 * m22
    E, F, I = m11 * m33 - m13 * m13, m12 * m13 - m11 * m23, m11 * m22 - m12 * m12
    inv_det = 1 / (m11 * A + m12 * B + m13 * C)
    r1, r2, r3 = r
    return (
        (A * r1 + B * r2 + C * r3) * inv_det,
        (B * r1 + E * r2 + F * r3) * inv_det,
        (C * r1 + F * r2 + I * r3) * inv_det,
    )


def _sym(M: tuple) -> Array:
    m11, m12, m13, m22, m23, m33 = (jnp.asarray(m) for m in M)
    m11, m12, m13, m22, m23, m33 = jnp.broadcast_arrays(m11, m12, m13, m22, m23, m33)
    return jnp.stack([jnp.stack([m11, m12, m13]), jnp.stack([m12, m22, m23]), jnp.stack([m13, m23, m33])])


def _closed(params: ArmParams, payload: Array, theta: Array) -> tuple:
    p = cast_params(params, theta.dtype)
    return _inertia(p, jnp.asarray(payload, theta.dtype), tuple(theta))


def mass_matrix_closed(params: ArmParams, payload: Array, theta: Array) -> Array:
    """:func:`mass_matrix` (3, 3) in closed form (equal to rounding), kg m^2."""
    return _sym(_closed(params, payload, theta)[0])


def gravity_closed(params: ArmParams, payload: Array, theta: Array) -> Array:
    """:func:`gravity` (3,) in closed form, N m."""
    g2, g3 = _closed(params, payload, theta)[3]
    return jnp.stack([jnp.zeros_like(g2), g2, g3])


def coriolis_closed(params: ArmParams, payload: Array, theta: Array, dtheta: Array) -> Array:
    """C(theta, theta') theta' (3,), N m, in closed form (:func:`coriolis_matrix` @ theta')."""
    _, M2, M3, _ = _closed(params, payload, theta)
    return jnp.stack(_coriolis(M2, M3, tuple(dtheta)))


# ---------------------------------------------------------------------------- the plant


class ArmState(NamedTuple):
    """Internal state of :class:`Arm`: joint angles (rad), rates (rad/s), motor currents (A),
    each a tuple of three scalars (joints 1, 2, 3) rather than a (3,) array, so that under
    ``vmap`` every entry is one array over the batch and the closed form runs as elementwise
    loops over it (no strided slices of (batch, 3) arrays in the time loop)."""

    theta: tuple[Array, Array, Array]
    dtheta: tuple[Array, Array, Array]
    current: tuple[Array, Array, Array]


class Arm(NamedTuple):
    """The arm as a plant for :func:`fosmc_jax.simulate` (``init``, ``observe``, ``derivative``).

    Fields: ``params`` (:class:`ArmParams`), ``payload`` (kg, scalar; traced, so ``vmap`` and
    ``grad`` reach it). Batched arms carry a leading axis on every leaf (see :func:`arm_sweep`).
    The time loop uses the closed form (:func:`_inertia`); :func:`mass_matrix`,
    :func:`coriolis_matrix` and :func:`gravity` are the same dynamics by autodiff.

    A time-varying plant (``time_varying``): ``observe`` and ``derivative`` take the time t (s)
    of the external torque (:func:`external_torque`; t = 0 when left out), which the simulator
    passes (:func:`fosmc_jax._plants.base.observe_at`).
    """

    params: ArmParams
    payload: Array
    #: The external torque depends on t: the simulator passes t to observe and derivative.
    time_varying = True

    def init(self, X0: Array) -> ArmState:
        """State with [theta, theta', theta''] = ``X0`` (9,) at t = 0: the currents are solved
        from Kt i = M theta'' + C theta' + G + F theta' + Fc tanh(theta'/v_coulomb) - tau_ext(0)."""
        theta, dtheta, ddtheta = tuple(X0[0::3]), tuple(X0[1::3]), tuple(X0[2::3])
        p = cast_params(self.params, X0.dtype)
        torque = _motor_torque(p, self.payload, theta, dtheta, ddtheta, jnp.zeros((), X0.dtype))
        return ArmState(theta, dtheta, tuple(t / p.Kt[j] for j, t in enumerate(torque)))

    def accelerations(self, state: ArmState, t: Array = 0.0) -> Array:
        """theta'' (3,) from the state at time ``t`` (s): M^-1 (Kt i + tau_ext(t) - C theta' - G -
        F theta' - Fc tanh(theta'/v_coulomb)), in closed form."""
        return jnp.stack(_accelerations(self.params, self.payload, state, t))

    def observe(self, state: ArmState, t: Array = 0.0) -> Array:
        """X (9,) = [theta_1, theta_1', theta_1'', theta_2, ...] at time ``t`` (s)."""
        acc = _accelerations(self.params, self.payload, state, t)
        return jnp.stack([x for j in range(3) for x in (state.theta[j], state.dtheta[j], acc[j])])

    def derivative(self, state: ArmState, U: Array, t: Array = 0.0) -> ArmState:
        """Time derivative of the state under motor voltages ``U`` (3,), V, at time ``t`` (s)."""
        return self._derivative(state, _accelerations(self.params, self.payload, state, t), U)

    def derivative_observed(self, state: ArmState, X: Array, U: Array, t: Array = 0.0) -> ArmState:
        """:meth:`derivative` with theta'' read from ``X`` = :meth:`observe` of ``state`` at ``t``
        (the closed form, the step's dearest part, once per step instead of twice with Euler)."""
        return self._derivative(state, (X[2], X[5], X[8]), U)

    def _derivative(self, state: ArmState, ddtheta: tuple, U: Array) -> ArmState:
        p = cast_params(self.params, state.theta[0].dtype)
        di = tuple((U[j] - p.R[j] * state.current[j] - p.Kb[j] * state.dtheta[j]) / p.L[j] for j in range(3))
        return ArmState(state.dtheta, ddtheta, di)


def tracking_voltage(arm: Arm, derivatives: Array, t: Array = 0.0) -> Array:
    """The motor voltages U (3,), V, under which ``arm`` follows a reference exactly at time
    ``t`` (s); ``derivatives`` is the reference's (4, 3) output there (theta_d and its first three
    derivatives, :mod:`fosmc_jax._plants.reference`). With the torque the motion needs,
    tau = M theta_d'' + C theta_d' + G + F theta_d' + Fc tanh(theta_d'/v_c) - tau_ext(t), the
    current i = tau / Kt and the motor's equation give U = L i' + R i + Kb theta_d', with i' the
    derivative of tau along the reference (its fourth row: theta_d''') over Kt.

    A controller that tracks closely puts out about this voltage, so its total variation over a
    run is a floor under the ``chattering`` metric that no tuning passes (``tuning/tracking_floor.py``)."""
    p = cast_params(arm.params, derivatives.dtype)
    x = tuple(tuple(derivatives[k]) for k in range(3))  # theta_d, theta_d', theta_d'': three scalars each
    dx = tuple(tuple(derivatives[k]) for k in range(1, 4))
    t = jnp.asarray(t, derivatives.dtype)
    torque = lambda x, t: jnp.stack(_motor_torque(p, arm.payload, *x, t))
    tau, dtau = jax.jvp(torque, (x, t), (dx, jnp.ones_like(t)))
    return p.L * dtau / p.Kt + p.R * tau / p.Kt + p.Kb * derivatives[1]


def _motor_torque(p: ArmParams, payload: Array, theta: tuple, dtheta: tuple, ddtheta: tuple, t: Array) -> tuple:
    """The motors' torques (three scalars) that give the arm the accelerations ``ddtheta`` at
    (``theta``, ``dtheta``) and time ``t``: M theta'' + C theta' + G + F theta' + Fc tanh(theta'/v_c)
    - tau_ext(t); ``p`` cast."""
    (m11, m12, m13, m22, m23, m33), n = _terms(p, payload, theta, dtheta)
    a1, a2, a3 = ddtheta
    torque = (
        m11 * a1 + m12 * a2 + m13 * a3 + n[0],
        m12 * a1 + m22 * a2 + m23 * a3 + n[1],
        m13 * a1 + m23 * a2 + m33 * a3 + n[2],
    )
    d = _external(p, t)
    return torque if d is None else tuple(torque[j] - d[j] for j in range(3))


def _terms(p: ArmParams, payload: Array, theta: tuple, dtheta: tuple) -> tuple[tuple, tuple]:
    """Entries of M and the torques C theta' + G + F theta' + Fc tanh(theta'/v_coulomb) (three
    scalars); ``p`` cast."""
    M, M2, M3, (g2, g3) = _inertia(p, jnp.asarray(payload, theta[0].dtype), theta)
    c1, c2, c3 = _coriolis(M2, M3, dtheta)
    n = (c1 + p.F[0] * dtheta[0], c2 + g2 + p.F[1] * dtheta[1], c3 + g3 + p.F[2] * dtheta[2])
    if p.Fc is None:
        return M, n
    inv_v = 1 / p.v_coulomb  # one division: of the arm's parameters alone, the generated kernel hoists it
    return M, tuple(n[j] + p.Fc[j] * jnp.tanh(dtheta[j] * inv_v) for j in range(3))


# Rematerialised under reverse mode: the closed form is a few hundred cheap elementwise
# operations, and saving each of their results for the backward pass (at every step of a
# checkpointed block) costs more than recomputing them from the nine state entries
# (BENCHMARKS.md, "Figures behind the code").
# prevent_cse=False: it runs inside scan, where there is no CSE across steps to prevent.
@functools.partial(jax.checkpoint, prevent_cse=False)
def _accelerations(params: ArmParams, payload: Array, state: ArmState, t: Array) -> tuple[Array, Array, Array]:
    p = cast_params(params, state.theta[0].dtype)
    M, n = _terms(p, payload, state.theta, state.dtheta)
    r = tuple(p.Kt[j] * state.current[j] - n[j] for j in range(3))
    d = _external(p, t)
    return _solve_sym(M, r if d is None else tuple(r[j] + d[j] for j in range(3)))


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

    With h := M q'' + C q' + F q' + G + f_c(q'), f_c = Fc tanh(q'/v_c) the Coulomb friction,
    the arm is Kt i = h - tau_ext(t). Differentiating it along L i' = u - R i - Kb q' gives
    M q''' + (dh/dt - M q''') = diag(Kt/L) u - diag(R/L) h - diag(Kt Kb/L) q' + e(t), which is
    factored as

      b       = M^-1 diag(Kt/L)                                                (B_bar)
      a[:, q''] = -M^-1 (diag(R/L) M + dM/dt + d(Cq')/dq' + F + diag(Fc/v_c sech^2(q'/v_c)))
      a[:, q' ] = -M^-1 (diag(R/L) (C + F + diag(phi)) + diag(Kt Kb/L) + d(Cq')/dq + dG/dq)
      a[:, q  ] = -M^-1 diag(R/L) G_bar,   G_bar = int_0^1 dG/dq(s q) ds,

    so that G_bar q = G(q) (exact because G(0) = 0; 12-point Gauss-Legendre) and
    diag(phi) q' = f_c(q'), phi = Fc tanh(q'/v_c)/q' (Fc/v_c at q' = 0): the Coulomb term
    factored exactly, as G is. Every block is evaluated at X (C, dM/dt, the derivatives of C q'
    and the friction depend on q', so the factoring is one choice among many; it is exact:
    a X + b U is the true theta''' of the arm without external torque).

    The external torque (:func:`external_torque`) is outside the rows: a matched exogenous
    input, e(t) = diag(R/L) tau_ext(t) + tau_ext'(t) adds M^-1 e(t) = b (R tau_ext + L
    tau_ext')/Kt to theta''' (a disturbance voltage in the input channel; the step's
    derivative is an impulse at t_step).

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
    x = dq / p.v_coulomb
    slope = jnp.zeros(3, X.dtype) if p.Fc is None else p.Fc / p.v_coulomb
    phi = jnp.diag(slope * _tanh_over(x))  # phi q' = Fc tanh(q'/v_c)
    dphi = jnp.diag(slope * (1 - jnp.tanh(x) ** 2))  # d/dq' of Fc tanh(q'/v_c)
    a_q = -solve3(M, r[:, None] * G_bar)
    a_dq = -solve3(M, r[:, None] * (C + F + phi) + jnp.diag(kb) + dc_dq + dG(p, m, q))
    a_ddq = -solve3(M, r[:, None] * M + Mdot + dc_ddq + F + dphi)
    b = solve3(M, jnp.diag(k))
    a = jnp.stack([a_q, a_dq, a_ddq], axis=2).reshape(3, 9)
    return a, b


def _tanh_over(x: Array) -> Array:
    """tanh(x)/x, 1 at x = 0 (below |x| = 1e-4 its series 1 - x^2/3, off by under
    2 x^4/15 < 2e-17), with finite derivatives everywhere (the double where)."""
    small = jnp.abs(x) < 1e-4
    safe = jnp.where(small, 1.0, x)
    return jnp.where(small, 1 - x * x / 3, jnp.tanh(safe) / safe)


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
    in the layout of :mod:`fosmc_jax._design.paper` (A: (3, 9), B: (3, 3))."""

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
