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
