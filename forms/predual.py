"""The pre-dual Lagrangian (eq. PreDualLagrangian) and the auxiliary dual Hamiltonian
(eq. DualHamiltonian) of the reference, for any force, mass matrix and auxiliary function H.

The reduced dual Lagrangian of every scene is this pre-dual Lagrangian evaluated at the scene's
dual-to-primal map: L_d(xi, eta, xi', eta') = L(x^, v^, xi, eta, xi', eta'), so the action is the
single source of truth and no reduced Lagrangian is written by hand.
"""
from __future__ import annotations

from typing import Callable

import ufl
from ufl import dot

__all__ = ["predual_lagrangian", "dual_hamiltonian", "boundary_term", "isotropic_quadratic",
           "isotropic_aux"]

Force = Callable[[ufl.core.expr.Expr], ufl.core.expr.Expr]
AuxH = Callable[[ufl.core.expr.Expr, ufl.core.expr.Expr], ufl.core.expr.Expr]


def predual_lagrangian(x, v, xi, eta, dxi, deta, M, F: Force, H: AuxH, xbar, vbar, D=None):
    """L = -x.xi' - (M v).eta' - xi.v - eta.F(x) + eta.(D v) - H(x - xbar, v - vbar).

    The damping term eta.(D v) pairs eta with M v' + D v - F(x) = 0 (the remark closing section
    3.3); D = None is the undamped system of the reference.

    Args:
        x, v: primal position and velocity (n-vectors, UFL).
        xi, eta: dual fields paired with x' = v and with M v' = F(x).
        dxi, deta: their time derivatives.
        M: mass matrix (n x n, UFL).
        F: the force, a function of the position.
        H: the auxiliary function of (x - xbar, v - vbar).
        xbar, vbar: the base state.
    """
    L = (-dot(x, dxi) - dot(dot(M, v), deta) - dot(xi, v) - dot(eta, F(x))
         - H(x - xbar, v - vbar))
    return L if D is None else L + dot(eta, dot(D, v))


def dual_hamiltonian(x, v, xi, eta, F: Force, H: AuxH, xbar, vbar, D=None):
    """H_d = xi.v^ + eta.F(x^) - eta.(D v^) + H(x^ - xbar, v^ - vbar), conserved on each slab
    (eq. DualHamiltonian, with the damping force -D v^ beside F)."""
    Hd = dot(xi, v) + dot(eta, F(x)) + H(x - xbar, v - vbar)
    return Hd if D is None else Hd - dot(eta, dot(D, v))


def boundary_term(xi, eta, M, x0, v0):
    """-x0.xi(0) - (M v0).eta(0): the initial conditions, natural at t = 0 (eq. DualAction)."""
    return -dot(x0, xi) - dot(dot(M, v0), eta)


def isotropic_quadratic(dx, dv, alpha, beta):
    """H = alpha/2 |dx|^2 + beta/2 |dv|^2 (the auxiliary function of sections 3.1 and 3.2)."""
    return 0.5 * alpha * dot(dx, dx) + 0.5 * beta * dot(dv, dv)


def isotropic_aux(dx, dv, c):
    """isotropic_quadratic with the scene constants alpha and beta (a force scene's H)."""
    return isotropic_quadratic(dx, dv, c["alpha"], c["beta"])
