"""The three-dimensional curl force F(x) = -(yz, 2xz, xy) (reference, section 3.2), optionally on
a linear spring: F(x) = -K x - (yz, 2xz, xy) (K = 0 in the reference; a stiff K makes the stiff
nonlinear case of the stress suite).

With H = 1/2 (x - xbar).A (x - xbar) + beta/2 |v - vbar|^2 (A = alpha I in the reference) the DtP
map is explicit: stationarity in x is the linear system A(eta) x = A xbar - xi' + K^T eta with
A(eta) of eq. (3DPositionDualToPrimal) (alpha I replaced by A), and v^ = vbar - (m eta' + xi) /
beta. Constants: m, beta, K, A and M = m I.
"""
from __future__ import annotations

import ufl
from ufl import as_matrix, as_vector, dot

__all__ = ["dtp", "force", "aux_potential", "position_matrix", "dtp_map"]

dtp = "explicit"


def force(x, c):
    return -dot(c["K"], x) - as_vector([x[1] * x[2], 2 * x[0] * x[2], x[0] * x[1]])


def aux_potential(dx, dv, c):
    return 0.5 * dot(dx, dot(c["A"], dx)) + 0.5 * c["beta"] * dot(dv, dv)


def position_matrix(eta, A):
    """A(eta) of eq. (3DPositionDualToPrimal), with H's position matrix A for alpha I."""
    return A - as_matrix([[0, eta[2], 2 * eta[1]],
                          [eta[2], 0, eta[0]],
                          [2 * eta[1], eta[0], 0]])


def dtp_map(xi, eta, dxi, deta, xbar, vbar, c):
    A = c["A"]
    rhs = dot(A, xbar) - dxi + dot(ufl.transpose(c["K"]), eta)
    xhat = dot(ufl.inv(position_matrix(eta, A)), rhs)
    vhat = vbar - (c["m"] * deta + xi) / c["beta"]
    return xhat, vhat
