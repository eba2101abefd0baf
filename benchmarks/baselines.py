"""Baselines for benchmarks/bench.py: the same closed loop (linear plant (3), FOSMC (14), (23)
with the ratio switching (28), zero-order hold, fixed-step Euler or RK4) written without JAX.

(a) ``numpy_loop``: plain Python/NumPy, one rollout at a time; (b) ``numpy_vectorised``:
NumPy over the batch, a Python loop in time; (c) ``scipy_ivp``: scipy.integrate.solve_ivp
per rollout (RK45, max_step = dt, control recomputed at every evaluation: the continuous
closed loop, a different and dearer algorithm, timed on a short horizon); (d) ``numba_prange``:
Numba, parallel over rollouts (optional: ``pip install numba``). Each returns the mean RMS
tracking error, to check that every baseline simulates the same thing.
"""

from __future__ import annotations

import numpy as np

from fosmc_jax import paper


def design(dtype=np.float64):
    """Nominal-model quantities of the controller: C, S = C(A + BK), (CB)^-1, K, gamma, delta."""
    a, b = paper.A_ROWS, paper.B_ROWS
    target = np.zeros((3, 9))
    for j in range(3):
        target[j, 3 * j : 3 * j + 3] = -np.real(np.poly(paper.POLES[j]))[::-1][:3]
    K = np.linalg.solve(b, target - a)
    A, B = paper.full_A(a), paper.full_B(b)
    C = paper.C
    S = C @ (A + B @ K)
    cast = lambda x: np.asarray(x, dtype)
    return tuple(map(cast, (C, S, np.linalg.inv(C @ B), np.linalg.inv(b), a, paper.GAMMA, paper.DELTA_SETS[0])))


def reference(t, dtype=np.float64):
    """(30) and derivatives at times t (T,): (T, 4, 3)."""
    start, end, tau = paper.THETA_START, paper.THETA_END, paper.TAU
    t = np.asarray(t, np.float64)[:, None]
    d, w = end - start, 2 * np.pi / tau
    tc = np.clip(t, 0, tau)
    inside = (t >= 0) & (t < tau)
    out = np.stack([start + d / (2 * np.pi) * (w * tc - np.sin(w * tc)),
                    np.where(inside, d / tau * (1 - np.cos(w * tc)), 0),
                    np.where(inside, d * w / tau * np.sin(w * tc), 0),
                    np.where(inside, d * w**2 / tau * np.cos(w * tc), 0)], axis=1)  # fmt: skip
    return out.astype(dtype)


def _tables(n, dt, dtype):
    """X_d (n+1, 9), Omega (n+1, 3) at t_k, and X_d at the half steps (for RK4)."""
    C, S, CB_inv, B_inv, a_nom, gamma, delta = design(dtype)
    t = np.arange(n + 1) * dt
    r = reference(t, dtype)
    X_d = np.transpose(r[:, :3], (0, 2, 1)).reshape(-1, 9)
    Omega = (r[:, 3] - X_d @ a_nom.T) @ B_inv.T
    rh = reference(t + dt / 2, dtype)
    X_h = np.transpose(rh[:, :3], (0, 2, 1)).reshape(-1, 9)
    return X_d, Omega, X_h


def numpy_vectorised(a_rows, b_rows, X0, dt, n, integrator="euler"):
    """a_rows (N, 3, 9), b_rows (N, 3, 3), X0 (N, 9): N rollouts in lockstep."""
    dtype = X0.dtype
    C, S, CB_inv, B_inv, a_nom, gamma, delta = design(dtype)
    X_d, Omega, X_h = _tables(n, dt, dtype)
    nX = np.linalg.norm(X_d, axis=1) * gamma[1] + np.linalg.norm(Omega, axis=1) * gamma[2]
    X, w = X0.copy(), np.zeros((X0.shape[0], 3), dtype)
    sum_e2 = np.zeros((X0.shape[0], 3), dtype)

    def control(k, X, w):
        Z = X - X_d[k]
        s = Z @ C.T - w
        rho = gamma[0] * np.linalg.norm(Z, axis=1) + nX[k]
        return Omega[k] - (rho[:, None] * s / (np.abs(s) + delta)) @ CB_inv.T

    def f(X, Xd, U):
        dX = np.empty_like(X)
        dX[:, [0, 1, 3, 4, 6, 7]] = X[:, [1, 2, 4, 5, 7, 8]]
        dX[:, 2::3] = np.einsum("nij,nj->ni", a_rows, X) + np.einsum("nij,nj->ni", b_rows, U)
        return dX, (X - Xd) @ S.T

    U = control(0, X, w)
    for k in range(n):
        if integrator == "euler":
            dX, dw = f(X, X_d[k], U)
            X, w = X + dt * dX, w + dt * dw
        else:
            k1 = f(X, X_d[k], U)
            k2 = f(X + dt / 2 * k1[0], X_h[k], U)
            k3 = f(X + dt / 2 * k2[0], X_h[k], U)
            k4 = f(X + dt * k3[0], X_d[k + 1], U)
            X = X + dt / 6 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0])
            w = w + dt / 6 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1])
        U = control(k + 1, X, w)
        sum_e2 += (X[:, ::3] - X_d[k + 1, ::3]) ** 2
    return float(np.sqrt(sum_e2 / (n + 1)).mean())


def numpy_loop(a_rows, b_rows, X0, dt, n, integrator="euler"):
    """One rollout at a time, plain Python loop in time (NumPy on 9-vectors)."""
    return float(np.mean([numpy_vectorised(a_rows[i : i + 1], b_rows[i : i + 1], X0[i : i + 1], dt, n, integrator)
                          for i in range(X0.shape[0])]))  # fmt: skip


def scipy_ivp(a_rows, b_rows, X0, dt, t_final):
    """solve_ivp (RK45, max_step = dt) per rollout on the continuous closed loop."""
    from scipy.integrate import solve_ivp

    C, S, CB_inv, B_inv, a_nom, gamma, delta = design()
    out = []
    for i in range(X0.shape[0]):
        A, B = paper.full_A(a_rows[i]), paper.full_B(b_rows[i])

        def rhs(t, y):
            r = reference(np.array([t]))[0]
            X_d = r[:3].T.reshape(9)
            Omega = B_inv @ (r[3] - a_nom @ X_d)
            X, w = y[:9], y[9:]
            Z = X - X_d
            s = C @ Z - w
            rho = gamma[0] * np.linalg.norm(Z) + gamma[1] * np.linalg.norm(X_d) + gamma[2] * np.linalg.norm(Omega)
            U = Omega - CB_inv @ (rho * s / (np.abs(s) + delta))
            return np.concatenate([A @ X + B @ U, S @ Z])

        sol = solve_ivp(rhs, (0, t_final), np.concatenate([X0[i], np.zeros(3)]), method="RK45", max_step=dt)
        out.append(sol.y[0, -1])
    return float(np.mean(out))


def numba_prange(a_rows, b_rows, X0, dt, n, integrator="euler"):
    """Numba, parallel over rollouts, Euler only; None if numba is not installed."""
    try:
        import numba
    except ImportError:
        return None
    kernel = _numba_kernel(numba)
    dtype = X0.dtype
    C, S, CB_inv, B_inv, a_nom, gamma, delta = design(dtype)
    X_d, Omega, _ = _tables(n, dt, dtype)
    nX = (np.linalg.norm(X_d, axis=1) * gamma[1] + np.linalg.norm(Omega, axis=1) * gamma[2]).astype(dtype)
    rms = kernel(a_rows, b_rows, X0, dtype.type(dt), n, C, S, CB_inv, X_d, Omega, nX, gamma, delta)
    return float(rms.mean())


_KERNEL = None


def _numba_kernel(numba):
    global _KERNEL
    if _KERNEL is not None:
        return _KERNEL

    @numba.njit(parallel=True, fastmath=False, cache=False)
    def kernel(a_rows, b_rows, X0, dt, n, C, S, CB_inv, X_d, Omega, nX, gamma, delta):
        N = X0.shape[0]
        rms = np.zeros((N, 3), X0.dtype)
        for r in numba.prange(N):
            X = X0[r].copy()
            w = np.zeros(3, X0.dtype)
            U = np.zeros(3, X0.dtype)
            Z = np.zeros(9, X0.dtype)
            s = np.zeros(3, X0.dtype)
            dX = np.zeros(9, X0.dtype)
            acc = np.zeros(3, X0.dtype)
            for k in range(n + 1):
                nz = 0.0
                for i in range(9):
                    Z[i] = X[i] - X_d[k, i]
                    nz += Z[i] * Z[i]
                rho = gamma[0] * np.sqrt(nz) + nX[k]
                for i in range(3):
                    v = -w[i]
                    for j in range(9):
                        v += C[i, j] * Z[j]
                    s[i] = rho * v / (abs(v) + delta[i])
                for i in range(3):
                    U[i] = Omega[k, i] - (CB_inv[i, 0] * s[0] + CB_inv[i, 1] * s[1] + CB_inv[i, 2] * s[2])
                    acc[i] += Z[3 * i] * Z[3 * i]
                if k == n:
                    break
                for i in range(3):
                    jerk = 0.0
                    for j in range(9):
                        jerk += a_rows[r, i, j] * X[j]
                    for j in range(3):
                        jerk += b_rows[r, i, j] * U[j]
                    dX[3 * i], dX[3 * i + 1], dX[3 * i + 2] = X[3 * i + 1], X[3 * i + 2], jerk
                    dw = 0.0
                    for j in range(9):
                        dw += S[i, j] * Z[j]
                    w[i] += dt * dw
                for i in range(9):
                    X[i] += dt * dX[i]
            for i in range(3):
                rms[r, i] = np.sqrt(acc[i] / (n + 1))
        return rms

    _KERNEL = kernel
    return kernel


# ---------------------------------------------------------------------------- arm (NumPy)
# How it is built: the kinematics of fosmc_jax._plants.arm._frames rewritten in NumPy over the batch;
# the link Jacobians J_v in closed form (geometric Jacobian: column i = axis_i x (p - o_i),
# exact for this chain); G = g sum m J_v[z] (exact, = dV/dq); C from the Christoffel symbols of
# M with dM/dq by central finite differences of the NumPy M (h = 1e-4, in float64 whatever the
# run's dtype: float32 differences would lose the term). The JAX arm uses autodiff instead.


def _arm_M(p, payload, theta):
    """M (N, 3, 3) and the z rows of J_v of p2, p3, tool (3 x (N, 3)) for theta (N, 3)."""
    c, s = np.cos(theta), np.sin(theta)
    N, z0 = theta.shape[0], np.zeros(theta.shape[0], theta.dtype)
    o = np.ones_like(z0)
    R1 = np.stack([np.stack([c[:, 0], -s[:, 0], z0], 1), np.stack([s[:, 0], c[:, 0], z0], 1),
                   np.stack([z0, z0, o], 1)], 1)  # fmt: skip
    Ry = lambda j: np.stack([np.stack([c[:, j], z0, s[:, j]], 1), np.stack([z0, o, z0], 1),
                             np.stack([-s[:, j], z0, c[:, j]], 1)], 1)  # fmt: skip
    R2 = R1 @ Ry(1)
    R3 = R2 @ Ry(2)
    y1, zax = R1[:, :, 1], np.broadcast_to(np.array([0.0, 0.0, 1.0], theta.dtype), (N, 3))
    down2, down3 = -R2[:, :, 2], -R3[:, :, 2]
    shoulder = p["d1"] * zax + p["d2"] * y1
    elbow = shoulder + p["l2"] * down2 + p["d3"] * y1
    p2, p3, tool = shoulder + p["c2"] * down2, elbow + p["c3"] * down3, elbow + p["l3"] * down3
    jac = lambda q, third: np.stack([np.cross(zax, q), np.cross(y1, q - shoulder),
                                     np.cross(y1, q - elbow) if third else np.zeros_like(q)], 2)  # fmt: skip
    J2, J3, Jt = jac(p2, False), jac(p3, True), jac(tool, True)
    JtJ = lambda J: np.einsum("nki,nkj->nij", J, J)
    Jw2 = np.stack([zax, y1, np.zeros_like(y1)], 2)
    Jw3 = np.stack([zax, y1, y1], 2)
    rot = lambda R, I, Jw: (lambda A: np.einsum("nki,k,nkj->nij", A, I, A))(np.swapaxes(R, 1, 2) @ Jw)
    M = p["m2"] * JtJ(J2) + p["m3"] * JtJ(J3) + payload[:, None, None] * JtJ(Jt)
    M = M + rot(R2, p["I2"], Jw2) + rot(R3, p["I3"], Jw3)
    M = M + np.diag(p["Jm"] + np.array([p["I1"], 0.0, 0.0]))
    return (M + np.swapaxes(M, 1, 2)) / 2, (J2[:, 2], J3[:, 2], Jt[:, 2])


def _arm_accel(p, payload, theta, dtheta, current, h=1e-4):
    """theta'' = M^-1 (Kt i - C theta' - G - F theta') (N, 3), and the torque balance."""
    M, (z2, z3, zt) = _arm_M(p, payload, theta)
    G = p["g"] * (p["m2"] * z2 + p["m3"] * z3 + payload[:, None] * zt)
    th64 = theta.astype(np.float64)
    dM = np.stack([(_arm_M(p, payload, th64 + h * e)[0] - _arm_M(p, payload, th64 - h * e)[0]) / (2 * h)
                   for e in np.eye(3)], 3).astype(theta.dtype)  # fmt: skip  # [n, i, j, k] = dM_ij/dq_k
    gamma = (dM + np.swapaxes(dM, 2, 3) - np.transpose(dM, (0, 3, 1, 2))) / 2
    Cm = np.einsum("nijk,nk->nij", gamma, dtheta)
    balance = np.einsum("nij,nj->ni", Cm, dtheta) + G + p["F"] * dtheta
    return np.linalg.solve(M, (p["Kt"] * current - balance)[..., None])[..., 0], M, balance


def numpy_arm(payloads, X0, dt, n):
    """NumPy vectorised over the batch (payloads (N,), X0 (N, 9)), Python loop in time, Euler:
    the arm (fosmc_jax.ARM_PARAMS) under the same controller; returns the mean RMS tracking error."""
    from fosmc_jax import ARM_PARAMS

    dtype = X0.dtype
    p = {k: np.asarray(v, dtype) for k, v in ARM_PARAMS._asdict().items()}
    payload = np.asarray(payloads, dtype)
    C, S, CB_inv, B_inv, a_nom, gamma, delta = design(dtype)
    X_d, Omega, _ = _tables(n, dt, dtype)
    nX = np.linalg.norm(X_d, axis=1) * gamma[1] + np.linalg.norm(Omega, axis=1) * gamma[2]
    theta, dtheta, ddtheta = X0[:, 0::3].copy(), X0[:, 1::3].copy(), X0[:, 2::3]
    _, M, balance = _arm_accel(p, payload, theta, dtheta, np.zeros_like(theta))
    current = (np.einsum("nij,nj->ni", M, ddtheta) + balance) / p["Kt"]
    w = np.zeros((X0.shape[0], 3), dtype)
    sum_e2 = np.zeros((X0.shape[0], 3), dtype)
    acc = _arm_accel(p, payload, theta, dtheta, current)[0]
    for k in range(n + 1):
        X = np.stack([theta, dtheta, acc], 2).reshape(-1, 9)
        Z = X - X_d[k]
        sum_e2 += Z[:, ::3] ** 2
        if k == n:
            break
        s = Z @ C.T - w
        rho = gamma[0] * np.linalg.norm(Z, axis=1) + nX[k]
        U = Omega[k] - (rho[:, None] * s / (np.abs(s) + delta)) @ CB_inv.T
        di = (U - p["R"] * current - p["Kb"] * dtheta) / p["L"]
        theta, dtheta, current, w = theta + dt * dtheta, dtheta + dt * acc, current + dt * di, w + dt * (Z @ S.T)
        acc = _arm_accel(p, payload, theta, dtheta, current)[0]
    return float(np.sqrt(sum_e2 / (n + 1)).mean())
