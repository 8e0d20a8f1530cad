"""The three-dimensional curl force F(x) = -(yz, 2xz, xy) (reference, section 3.2).

With H = alpha/2 |x - xbar|^2 + beta/2 |v - vbar|^2 the DtP map is explicit: stationarity in x is
the linear system A(eta) x = alpha xbar - xi' with A(eta) of eq. (3DPositionDualToPrimal), and
v^ = vbar - (m eta' + xi) / beta. Constants: m, alpha, beta and M = m I.
"""
from __future__ import annotations

import ufl
from ufl import as_matrix, as_vector, dot

from forms.predual import isotropic_quadratic

__all__ = ["dtp", "force", "aux_potential", "position_matrix", "dtp_map"]

dtp = "explicit"


def force(x, c):
    return -as_vector([x[1] * x[2], 2 * x[0] * x[2], x[0] * x[1]])


def aux_potential(dx, dv, c):
    return isotropic_quadratic(dx, dv, c["alpha"], c["beta"])


def position_matrix(eta, alpha):
    """A(eta) of eq. (3DPositionDualToPrimal)."""
    return as_matrix([[alpha, -eta[2], -2 * eta[1]],
                      [-eta[2], alpha, -eta[0]],
                      [-2 * eta[1], -eta[0], alpha]])


def dtp_map(xi, eta, dxi, deta, xbar, vbar, c):
    xhat = dot(ufl.inv(position_matrix(eta, c["alpha"])), c["alpha"] * xbar - dxi)
    vhat = vbar - (c["m"] * deta + xi) / c["beta"]
    return xhat, vhat
