"""curl2d by quadratic lifting (reference, remark "Quadratic lifting" of section 3.1).

Auxiliary primal r = y^2, s = x^2 make the force quadratic, F(x, r, s) = -k (x r, x s); multipliers
lambda, mu (extra dual fields) pair with the constraints y^2 - r = 0, x^2 - s = 0. With
H_a = alpha/2 (|x - xbar|^2 + (r - rbar)^2 + (s - sbar)^2) + beta/2 |v - vbar|^2 around the base
state (rbar = ybar^2, sbar = xbar^2), stationarity of the augmented pre-dual Lagrangian is the
linear system of eq. (AugmentedDualToPrimal) shifted by the base state, solved in closed form:

    x^ = [alpha (alpha xbar - xi'_x) + k eta_x (alpha rbar - lambda) + k eta_y (alpha sbar - mu)]
         / [alpha (alpha - 2 mu) - k^2 |eta|^2],
    y^ = (alpha ybar - xi'_y) / (alpha - 2 lambda),
    r^ = (alpha rbar - lambda + k eta_x x^) / alpha,   s^ = (alpha sbar - mu + k eta_y x^) / alpha,
    v^ = vbar - (m eta' + xi) / beta.
"""
from __future__ import annotations

from ufl import as_vector, dot

__all__ = ["dtp", "extra_dual", "force", "dtp_map", "lagrangian"]

dtp = "explicit"
extra_dual = 2  # lambda, mu


def force(x, c):
    """The original force of x alone (for the reference and the Hamiltonian of the motion)."""
    return -c["k"] * as_vector([x[0] * x[1] ** 2, x[0] ** 3])


def _lifted_base(xbar):
    return xbar[1] ** 2, xbar[0] ** 2


def dtp_map(xi, eta, dxi, deta, xbar, vbar, c, extra):
    k, a = c["k"], c["alpha"]
    lam, mu = extra[0], extra[1]
    rbar, sbar = _lifted_base(xbar)
    x = ((a * (a * xbar[0] - dxi[0]) + k * eta[0] * (a * rbar - lam)
          + k * eta[1] * (a * sbar - mu)) / (a * (a - 2 * mu) - k**2 * dot(eta, eta)))
    y = (a * xbar[1] - dxi[1]) / (a - 2 * lam)
    r = (a * rbar - lam + k * eta[0] * x) / a
    s = (a * sbar - mu + k * eta[1] * x) / a
    vhat = vbar - (c["m"] * deta + xi) / c["beta"]
    return as_vector([x, y]), vhat, as_vector([r, s])


def lagrangian(xhat, vhat, lifted, xi, eta, dxi, deta, extra, xbar, vbar, c):
    """The augmented pre-dual Lagrangian L_a at (x^, v^, r^, s^)."""
    k, a, b, m = c["k"], c["alpha"], c["beta"], c["m"]
    x, y = xhat[0], xhat[1]
    r, s = lifted[0], lifted[1]
    rbar, sbar = _lifted_base(xbar)
    lam, mu = extra[0], extra[1]
    dx, dv = xhat - xbar, vhat - vbar
    H_a = 0.5 * a * (dot(dx, dx) + (r - rbar) ** 2 + (s - sbar) ** 2) + 0.5 * b * dot(dv, dv)
    return (-dot(xhat, dxi) - m * dot(vhat, deta) - dot(xi, vhat)
            + k * eta[0] * x * r + k * eta[1] * x * s + lam * (y**2 - r) + mu * (x**2 - s) - H_a)
