"""The linearised Ziegler column (reference, section 3.3, eq. ZieglerEquations).

Two massless rigid links of length l, point masses m1 and m2, rotational springs c1 and c2, a
tangential follower force P at the tip. Its dual forms are those of `forms.linear` with

    M = l^2 [[m1 + m2, m2], [m2, m2]],      K = [[c1 + c2 - P l, P l - c2], [-c2, c2]],

K non-symmetric (K12 - K21 = P l: a curl force). The defaults of H are the remark's A = I, B = M^2,
which make the principal part of the dual Euler-Lagrange system the identity.
"""
from __future__ import annotations

import numpy as np

from fem_dual.forms import linear_forms_on_use

# its dual forms are those of forms.linear, loaded on first use: the scene's matrices validate
# input without importing UFL
__getattr__ = linear_forms_on_use(__name__)

__all__ = ["mass_matrix", "stiffness_matrix", "force", "aux_potential", "dtp_map",
           "dtp"]


def mass_matrix(m1: float, m2: float, l: float) -> np.ndarray:
    return l**2 * np.array([[m1 + m2, m2], [m2, m2]], dtype=float)


def stiffness_matrix(c1: float, c2: float, l: float, P: float) -> np.ndarray:
    return np.array([[c1 + c2 - P * l, P * l - c2], [-c2, c2]], dtype=float)
