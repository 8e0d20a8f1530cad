"""Base states of H on a slab (the (xbar, vbar) of forms.predual), beyond the constant ones.

Only the residual of the base state, L zbar = zbar' - f(zbar) with f(z) = (v, M^-1 F(x)), enters
a slab's dual action (issue 14): the constant start state leaves f(z0), an O(omega) forcing that
modes the cells do not resolve turn into growth; zero leaves -f(0), nothing for a linear system
or a force with F(0) = 0, but the dual fields must then carry the whole state through a
nonlinear DtP map. The predictor below is close to the motion and nearly residual-free in every
mode: the linearly implicit Euler step from the start,

    zbar(t) = z0 + t (I - t J)^-1 f(z0),   J = df/dz (z0),

follows the slow motion to first order and, for a mode with |lambda t| >> 1, sits at its
quasi-static state z0 - J^-1 f(z0) (a stiff spring at the position where it balances the other
forces), so unresolved modes are not forced.
"""
from __future__ import annotations

import numpy as np

__all__ = ["Predictor", "force_jacobian", "stiff_at_start", "STIFF_RATIO"]

STIFF_RATIO = 5.0  # fastest linearised frequency / the start's rate beyond which it is stiff


def force_jacobian(force, x: np.ndarray) -> np.ndarray:
    """dF/dx at x by central differences (n force evaluations x 2; F is smooth)."""
    n = len(x)
    J = np.empty((n, n))
    for j in range(n):
        h = 1e-6 * max(1.0, abs(x[j]))
        e = np.zeros(n)
        e[j] = h
        J[:, j] = (force(x + e) - force(x - e)) / (2 * h)
    return J


class Predictor:
    """zbar(t) = z0 + t (I - t J)^-1 f(z0) for a scene (linear: J is its first-order matrix)."""

    def __init__(self, scene):
        self.scene = scene
        self.n = scene.n
        self.Minv = np.linalg.inv(scene.mass_matrix())

    def _rate_and_jacobian(self, z0: np.ndarray):
        n, scene = self.n, self.scene
        if scene.linear:
            J = scene.first_order_matrix()
            return J @ z0, J
        x0, v0 = z0[:n], z0[n:]
        J = np.zeros((2 * n, 2 * n))
        J[:n, n:] = np.eye(n)
        J[n:, :n] = self.Minv @ force_jacobian(scene.force_numpy, x0)
        return np.concatenate([v0, self.Minv @ scene.force_numpy(x0)]), J

    def __call__(self, z0: np.ndarray, t: np.ndarray) -> np.ndarray:
        """(len(t), 2n): the predictor at the times t after the slab's start."""
        f0, J = self._rate_and_jacobian(np.asarray(z0, dtype=float))
        eye = np.eye(len(f0))
        out = np.empty((len(t), len(f0)))
        for i, ti in enumerate(np.asarray(t, dtype=float)):
            out[i] = z0 + ti * np.linalg.solve(eye - ti * J, f0)
        return out


def stiff_at_start(scene, x0: np.ndarray, v0: np.ndarray) -> bool:
    """Whether a nonlinear scene is stiff at its start: the fastest frequency of the force
    linearised there, sqrt |eig(M^-1 dF/dx)|, exceeds STIFF_RATIO times the start's own rate
    (fem_dual.stepper.motion_rate), so that slabs sized by the motion leave modes unresolved."""
    from fem_dual.stepper import motion_rate

    Minv = np.linalg.inv(scene.mass_matrix())
    a0 = Minv @ scene.force_numpy(x0)
    fastest = float(np.sqrt(np.abs(np.linalg.eigvals(Minv @ force_jacobian(scene.force_numpy,
                                                                          x0))).max()))
    rate = motion_rate(x0, v0, a0)
    return fastest > STIFF_RATIO * rate if rate > 0 else False
