"""The N-link follower-load column (Ziegler's column generalised; large N approaches Beck's and
Pflueger's continuous column), linearised about the straight configuration.

N massless rigid links of length l, point masses m_j at the joints and the tip (j = 1..N, joint j
at the top of link j), rotational springs c_j (c_1 at the base, c_j between links j-1 and j),
joint dampers d_j likewise, and a tangential follower force P at the tip. With absolute link
angles q_j:

    M_ab = l^2 sum_{j >= max(a, b)} m_j                    (kinetic energy of the point masses)
    K_e, D: tridiagonal from 1/2 sum c_j (q_j - q_{j-1})^2  (q_0 = 0), likewise for d_j
    Q_i = P l sin(q_i - q_N) ~ P l (q_i - q_N)              (virtual work of the follower force)
    K = K_e - K_f,  K_f = P l (I - e e_N^T) with the last row zero.

N = 2 gives eq. (ZieglerEquations). The dual forms are those of forms.linear.
"""
from __future__ import annotations

import numpy as np

from fem_dual.forms import linear_forms_on_use

# its dual forms are those of forms.linear, loaded on first use: the scene's matrices validate
# input without importing UFL
__getattr__ = linear_forms_on_use(__name__)

__all__ = ["mass_matrix", "joint_matrix", "follower_matrix", "force", "aux_potential",
           "dtp_map", "dtp"]


def mass_matrix(masses: np.ndarray, l: float) -> np.ndarray:
    n = len(masses)
    tail = np.cumsum(np.asarray(masses, dtype=float)[::-1])[::-1]  # sum_{j >= k} m_j
    idx = np.maximum.outer(np.arange(n), np.arange(n))
    return l**2 * tail[idx]


def joint_matrix(values: np.ndarray) -> np.ndarray:
    """Tridiagonal matrix of 1/2 sum_j v_j (q_j - q_{j-1})^2 with q_0 = 0 (springs or dampers)."""
    v = np.asarray(values, dtype=float)
    n = len(v)
    out = np.zeros((n, n))
    for j in range(n):
        out[j, j] += v[j]
        if j > 0:
            out[j - 1, j - 1] += v[j]
            out[j - 1, j] -= v[j]
            out[j, j - 1] -= v[j]
    return out


def follower_matrix(n: int, l: float, P: float) -> np.ndarray:
    Kf = P * l * np.eye(n)
    Kf[:, -1] -= P * l
    return Kf
