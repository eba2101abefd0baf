"""The paper's data, in one place.

Every number of "A Full Order Sliding Mode Tracking Controller For A Class of Uncertain
Dynamical System" that this package uses lives here, with its equation number. The Appendix
box is the corrected one of docs/paper.md. Nothing else in the package hard-codes
these values; the design quantities the paper derives from them (K, alpha, beta, gamma
bounds) are *computed* in :mod:`fosmc_jax._design.gains`, and the printed ones are kept here only
to be shown beside the computed ones.

All arrays are float64 NumPy arrays; the numerics cast them to the dtype in use.
Rows of ``A_ROWS``/``B_ROWS`` are the rows 3, 6, 9 (1-based) of A and B in (29): the only rows
that are not integrator chains.
"""

from __future__ import annotations

import numpy as np

#: Indices (0-based) of the rows 3, 6, 9 of the 9-state model: theta''' of each joint.
ROWS = (2, 5, 8)

#: Rows 3, 6, 9 of the nominal A in (29), shape (3, 9), units 1/s^k.
A_ROWS = np.array(
    [
        [0.0, -21.08, -8.78, 15.19, 28.05, 3.23, 0.03, 13.78, 0.99],
        [0.0, 49.56, 4.82, -112.51, -6.52, -8.57, 2.60, 2.27, -0.62],
        [0.0, -0.18, -0.14, 132.64, -32.64, 0.99, -11.44, -18.08, -7.30],
    ]
)

#: Rows 3, 6, 9 of the nominal B in (29) ("B_bar"), shape (3, 3), rad/(s^3 V).
B_ROWS = np.array(
    [
        [20.91, -4.56, 0.16],
        [-5.70, 37.58, -39.11],
        [0.23, -44.67, 175.98],
    ]
)

#: The Appendix box on rows 3, 6, 9 of A (corrected in docs/paper.md), shape (3, 9).
A_LOWER = np.array(
    [
        [0.0, -102.79, -14.33, -4.61, 17.63, 0.22, 0.03, -0.64, -0.52],
        [0.0, 8.27, 3.37, -129.62, -64.26, -10.40, -1.98, -5.82, -1.77],
        [0.0, -0.91, -6.36, 125.08, -91.77, -1.18, -31.88, -26.86, -8.70],
    ]
)
A_UPPER = np.array(
    [
        [0.0, 60.63, -3.22, 34.99, 38.48, 6.23, 0.03, 28.19, 2.50],
        [0.0, 90.85, 6.26, -95.39, 51.22, -6.74, 7.17, 10.36, 0.53],
        [0.0, 0.54, 6.08, 140.20, 26.50, 3.17, 9.00, -9.31, -5.89],
    ]
)

#: The Appendix box on B_bar (docs/paper.md: 15.54..26.28 is B(3,1); 172.95 is B(9,3)'s lower bound).
B_LOWER = np.array(
    [
        [15.54, -10.82, -0.16],
        [-13.52, 35.08, -40.27],
        [-0.23, -46.00, 172.95],
    ]
)
B_UPPER = np.array(
    [
        [26.28, 1.70, 0.49],
        [2.19, 40.07, -37.95],
        [0.69, -43.34, 179.00],
    ]
)

#: Sliding-surface matrix C in (34), shape (3, 9).
C = np.array(
    [
        [2.0, 3.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        [0.0, 0.0, 0.0, 30.0, 20.0, 1.0, 0.0, 0.0, 0.0],
        [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 30.0, 20.0, 1.0],
    ]
)

#: Desired closed-loop poles (33), one row per joint, 1/s.
POLES = np.array(
    [
        [-0.3, -0.31, -3.0],
        [-0.3, -0.31, -3.0],
        [-0.03, -0.031, -0.3],
    ]
)

#: Switching gains (36).
GAMMA = np.array([350.0, 300.0, 30.0])

#: Table 1: boundary-layer constants delta_i of (28), one row per set.
DELTA_SETS = np.array(
    [
        [200.0, 100.0, 60.0],
        [1000.0, 550.0, 250.0],
        [2000.0, 800.0, 600.0],
    ]
)

#: Reference (30): start and end joint angles (rad) and duration tau (s).
THETA_START = np.array([-0.8, -1.5, -0.5])
THETA_END = np.array([1.0, 0.2, 1.2])
TAU = 2.0

#: Simulation horizon of the paper's figures (s) and the payloads it simulates (kg).
T_FINAL = 4.0
PAYLOADS = (0.0, 10.0)

# --- Printed values, kept only to be shown beside the computed ones. ---

#: (31) as printed.
ALPHA_PRINTED = 5.9874
BETA_PRINTED = 0.6200

#: (32) as printed. docs/paper.md: it is for A - BK and, so rounded, not stabilising.
K_PRINTED = np.array(
    [
        [0.01, -0.59, -0.26, 0.07, 1.27, 0.07, 0.0, 0.67, -0.01],
        [0.0, 1.65, 0.09, -2.99, -0.21, -0.21, 0.0, 0.06, -0.11],
        [0.0, 0.42, 0.02, 0.0, -0.24, -0.06, -0.07, -0.08, -0.06],
    ]
)

#: (35) as printed: lower bounds on gamma.
GAMMA_MIN_PRINTED = np.array([76.7962, 66.2157, 6.8566])


def full_A(a_rows: np.ndarray) -> np.ndarray:
    """The 9x9 A of (29) from its rows 3, 6, 9: integrator chains elsewhere."""
    a_rows = np.asarray(a_rows)
    A = np.zeros((9, 9), dtype=a_rows.dtype)
    for j in range(3):
        A[3 * j, 3 * j + 1] = 1.0
        A[3 * j + 1, 3 * j + 2] = 1.0
    A[list(ROWS)] = a_rows
    return A


def full_B(b_rows: np.ndarray) -> np.ndarray:
    """The 9x3 B of (29) from its rows 3, 6, 9 (zeros elsewhere)."""
    b_rows = np.asarray(b_rows)
    B = np.zeros((9, 3), dtype=b_rows.dtype)
    B[list(ROWS)] = b_rows
    return B
