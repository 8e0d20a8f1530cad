"""Linear second-order systems M q'' + D q' + K q = 0 with a quadratic H (reference, section 3.3
and its closing remark).

F(q) = -K q with K not necessarily symmetric (a curl force when K != K^T), any damping D,
H(dq, dv) = 1/2 dq.A dq + 1/2 dv.B dv with A, B symmetric positive definite. Stationarity of the
pre-dual Lagrangian (with the damping term eta.(D v)) gives the explicit dual-to-primal map around
the base state (eq. ZieglerDualToPrimal, shifted by the base state, plus damping):

    q^ = qbar + A^-1 (K^T eta - xi'),     v^ = vbar + B^-1 (D^T eta - M eta' - xi).

The reduced dual Lagrangian is quadratic in (xi, eta): one symmetric positive-definite linear
system per slab. The constants `c` are fem.Constants named M, K, D, A, B, Ainv, Binv.
"""
from __future__ import annotations

from typing import Mapping

import ufl
from ufl import dot

__all__ = ["dtp", "force", "aux_potential", "dtp_map"]

dtp = "explicit"


def force(q, c: Mapping):
    return -dot(c["K"], q)


def aux_potential(dq, dv, c: Mapping):
    return 0.5 * dot(dq, dot(c["A"], dq)) + 0.5 * dot(dv, dot(c["B"], dv))


def dtp_map(xi, eta, dxi, deta, xbar, vbar, c: Mapping):
    """Explicit DtP map: stationarity of the pre-dual Lagrangian in (q, v)."""
    qhat = xbar + dot(c["Ainv"], dot(ufl.transpose(c["K"]), eta) - dxi)
    vhat = vbar + dot(c["Binv"], dot(ufl.transpose(c["D"]), eta) - dot(c["M"], deta) - xi)
    return qhat, vhat
