"""The two-dimensional curl force F(x, y) = -k (x y^2, x^3) (reference, section 3.1).

With H = alpha/2 |x - xbar|^2 + beta/2 |v - vbar|^2 the velocity part of the DtP map is explicit,
v^ = vbar - (m eta' + xi) / beta (eq. v-hat-Ex1), and the position part is implicit: G(x^) = 0 with
G of the reference (eqs. BerryDualToPrimal a, b), shifted by the base state:

    G(x, y) = [alpha (x - xbar) + xi'_x - k eta_x y^2 - 3 k eta_y x^2,
               alpha (y - ybar) + xi'_y - 2 k eta_x x y].

Constants: k, m, alpha, beta and M = m I.
"""
from __future__ import annotations

from ufl import as_vector

from fem_dual.forms.predual import isotropic_aux

__all__ = ["dtp", "force", "aux_potential", "velocity_map", "position_equations"]

dtp = "implicit"


def force(x, c):
    return -c["k"] * as_vector([x[0] * x[1] ** 2, x[0] ** 3])


aux_potential = isotropic_aux


def velocity_map(xi, deta, vbar, c):
    return vbar - (c["m"] * deta + xi) / c["beta"]


def position_equations(x, xi, eta, dxi, xbar, c):
    """G(x) of eqs. (BerryDualToPrimal) a and b, hand-derived."""
    k, a = c["k"], c["alpha"]
    return as_vector([a * (x[0] - xbar[0]) + dxi[0] - k * eta[0] * x[1] ** 2
                      - 3 * k * eta[1] * x[0] ** 2,
                      a * (x[1] - xbar[1]) + dxi[1] - 2 * k * eta[0] * x[0] * x[1]])
