"""The implicit DtP map of any smooth force, derived by UFL.

For a force F(x), a mass matrix M and a separable auxiliary function H(dx, dv) = H(dx, 0) + H(0, dv)
quadratic in dv with matrix B, stationarity of the pre-dual Lagrangian gives

    G(x) = xi' + DF(x)^T eta + dH/dx(x - xbar, 0) = 0        (position, implicit)
    v^ = vbar - B^-1 (M eta' + xi)                            (velocity, explicit)

G is the UFL derivative of x.xi' + eta.F(x) + H(x - xbar, 0), so a user writes only F and H.
"""
from __future__ import annotations

from types import SimpleNamespace

import ufl
from ufl import dot

__all__ = ["position_equations", "velocity_map", "make"]


def position_equations(force, aux_potential, x, xi, eta, dxi, xbar, c):
    """G(x) by UFL differentiation; `x` must be a ufl.variable."""
    zero_v = ufl.zero(*xbar.ufl_shape)
    phi = dot(x, dxi) + dot(eta, force(x, c)) + aux_potential(x - xbar, zero_v, c)
    return ufl.diff(phi, x)


def velocity_map(xi, deta, vbar, c):
    """v^ for H's velocity part 1/2 dv.B dv: the constants hold M and Binv."""
    return vbar - dot(c["Binv"], dot(c["M"], deta) + xi)


def make(force, aux_potential) -> SimpleNamespace:
    """A forms object for the implicit DtP path from just F(x, c) and H(dx, dv, c)."""

    def equations(x, xi, eta, dxi, xbar, c):
        return position_equations(force, aux_potential, x, xi, eta, dxi, xbar, c)

    return SimpleNamespace(dtp="implicit", force=force, aux_potential=aux_potential,
                           velocity_map=velocity_map, position_equations=equations)
