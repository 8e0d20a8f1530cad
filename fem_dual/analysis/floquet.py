"""Floquet multipliers of a periodic orbit, two ways: the monodromy of fem-dual's own slab maps
along the orbit (SlabFlow, with the degree p + 1 companion's as its error estimate), and, as an
independent check, DOP853 on the motion and its variational equation (monodromy), which also
gives the closure of the orbit and its states at T/k (a k-fold orbit closes there already).
"""
from __future__ import annotations

import signal
from typing import Optional, Tuple

import numpy as np
from mpi4py import MPI

from fem_dual import faults
from fem_dual.errors import SolveError

__all__ = ["CHECK_TOL", "SlabFlow", "monodromy", "nontrivial", "multiplier_distance",
           "stop_if_asked", "floquet_multipliers", "vector_field", "MULTIPLIER_TOL", "MAX_FOLD"]

MAX_FOLD = 12  # an orbit closing after T/k is a k-fold cover, checked for k up to this or the
# orbit's nodes (cells x degree), whichever is larger: no mesh resolves more turns than nodes
MULTIPLIER_TOL = 1e-6  # multipliers' estimate or check above this (relative): not vouched for


def _rhs_and_jacobian(scene, length: float = 0.0):
    """(f, J): z' = f(z) for the undamped scene's motion, and its Jacobian: exact where the
    scene knows the force's (its own formula, or a force expression differentiated in forward
    mode), else fourth-order central differences of size 1e-3 times `length`, the size of the
    motion, or of x (their truncation error would be a check's error of its own)."""
    n = scene.n
    M = scene.mass_matrix()
    if scene.linear:
        from fem_dual.reference import first_order_matrix

        A = first_order_matrix(M, scene.stiffness_matrix(), scene.damping_matrix())
        return (lambda z: A @ z), (lambda z: A)
    Minv = np.linalg.inv(M)

    def f(z):
        return np.concatenate([z[n:], Minv @ scene.force_numpy(z[:n])])

    def jac(z):
        x = z[:n]
        exact = scene.force_jacobian_numpy(x)
        if exact is not None:
            A = np.zeros((2 * n, 2 * n))
            A[:n, n:] = np.eye(n)
            A[n:, :n] = Minv @ exact
            return A
        DF = np.empty((n, n))
        for j in range(n):  # fourth-order central differences (exact for cubic forces)
            h = 1e-3 * (length if length > 0 else max(1.0, abs(x[j])))
            h = (x[j] + h) - x[j]  # the step as rounded, so that x + h is exact
            e = np.zeros(n)
            e[j] = h
            DF[:, j] = (8 * (scene.force_numpy(x + e) - scene.force_numpy(x - e))
                        - (scene.force_numpy(x + 2 * e) - scene.force_numpy(x - 2 * e))) / (12 * h)
        A = np.zeros((2 * n, 2 * n))
        A[:n, n:] = np.eye(n)
        A[n:, :n] = Minv @ DF
        return A

    return f, jac


#: DOP853's rtol and atol in the check of an orbit (its motion and variational equation)
CHECK_TOL = 1e-13


def monodromy(scene, z0: np.ndarray, T: float, folds: int = MAX_FOLD, length: float = 0.0
              ) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(z(T), Phi(T), z(T/k) for k = 2 .. folds): DOP853 at rtol = atol = 1e-13 on the motion
    and its variational equation from z0 over [0, T] (its dense output at T/k); `length`: the
    size of the motion in x, to which the force's difference steps are relative."""
    from scipy.integrate import solve_ivp

    f, jac = _rhs_and_jacobian(scene, length)
    m = len(z0)

    def rhs(_t, y):
        z, Phi = y[:m], y[m:].reshape(m, m)
        return np.concatenate([f(z), (jac(z) @ Phi).ravel()])

    y0 = np.concatenate([z0, np.eye(m).ravel()])
    sol = solve_ivp(rhs, (0.0, T), y0, method="DOP853", rtol=CHECK_TOL, atol=CHECK_TOL,
                    dense_output=True)
    if not sol.success:
        raise SolveError(f"the check of the orbit by DOP853 failed: {sol.message}")
    y = sol.y[:, -1]
    parts = sol.sol(T / np.arange(2, max(folds, 2) + 1))[:m].T
    return y[:m], y[m:].reshape(m, m), parts


FLOW_CELLS = 4  # cells per slab of fem-dual's own flow over one period (the monodromy)
FLOW_HALVINGS = 6  # a flow slab whose Newton fails is solved as two halves, this many times
# The flow starts with as many cells as the orbit (at most FLOW_START_CELLS) and doubles them
# while the multipliers' estimate exceeds FLOW_TARGET (relative), up to FLOW_MAX_CELLS.
FLOW_START_CELLS = 64
FLOW_TARGET = 1e-10
FLOW_MAX_CELLS = 1024


class SlabFlow:
    """The motion over one period by fem-dual's own slabs and the tangents of their slab maps:
    the monodromy is the product of the slab maps' Jacobians in the start state (exact for linear
    scenes, central differences of relative size 1e-5 for nonlinear ones). Fixed slabs of
    FLOW_CELLS cells at the orbit's degree p, as many cells in all as the orbit has; the error
    companion (degree p + 1, same slabs, Newton from the answer) gives a second monodromy, whose
    multipliers estimate the error of the first. One compiled simulation for every orbit."""

    def __init__(self, degree: int):
        self.degree, self.sim = degree, None
        self._counted = 0.0  # the simulation's set-up seconds already reported

    def new_setup_s(self) -> float:
        """Seconds of set-up (form compilation) since the last call."""
        total = self.sim.setup_s if self.sim is not None else 0.0
        new, self._counted = total - self._counted, total
        return new

    def __call__(self, scene, z0: np.ndarray, T: float, cells: int,
                 other_z0: Optional[np.ndarray] = None, other_T: Optional[float] = None,
                 scale: Optional[float] = None):
        """(z(T), Phi, Phi_companion) from z0 over [0, T] (the companion from other_z0 over
        [0, other_T], the degree p + 1 orbit, when given); `scale`: the size of the motion
        (the orbit's extent), to which the tangents' difference steps are relative, not to
        the size of the state (an orbit far from the origin). Raises SolveError."""
        from fem_dual.config import RunConfig
        from fem_dual.integrate.simulation import Simulation

        n = scene.n
        slabs = max(1, -(-cells // FLOW_CELLS))
        config = RunConfig.create(scene, T=T, x0=z0[:n], v0=z0[n:], cells=FLOW_CELLS,
                                  degree=self.degree, slabs=slabs, base="start",
                                  reference="none")
        if self.sim is None:
            self.sim = Simulation.for_config(config, MPI.COMM_SELF)
        self.sim.begin(config)
        self.sim.companion.begin(config)
        dt, z = T / slabs, np.array(z0, dtype=float)
        dt_c = (T if other_T is None else other_T) / slabs
        z_c = np.array(z0 if other_z0 is None else other_z0, dtype=float)
        Phi = Phi_c = np.eye(2 * n)
        for k in range(slabs):
            stop_if_asked("the monodromy")
            z, z_c, psi, psi_c = self._slab(z, z_c, k * dt, k * dt_c, dt, dt_c, FLOW_HALVINGS,
                                               scale)
            Phi, Phi_c = psi @ Phi, psi_c @ Phi_c
        if not (np.isfinite(Phi).all() and np.isfinite(Phi_c).all()):
            raise SolveError("fem-dual's flow along the orbit blew up")
        return z, Phi, Phi_c

    def _slab(self, z, z_c, t0: float, t0_c: float, dt: float, dt_c: float, halvings: int,
              scale: Optional[float]):
        """(end state, companion's, slab map Jacobian, companion's) of the slab [t0, t0 + dt]
        (the companion's: [t0_c, t0_c + dt_c]), solved as two halves when Newton fails (slabs
        from a constant base state cannot be as long as the orbit's cells, whose base state is
        the guess); `scale`: the size of the motion, to which the tangents' steps are relative."""
        sim, unit = self.sim, np.eye(len(z))
        companion = sim.companion
        try:
            values = sim.solve_slab(z, t0, dt)
            psi = np.column_stack([sim.tangent(z, e, t0, dt, values, central=True,
                                               scale=scale)[-1] for e in unit])
            other = companion.solve_slab(z_c, t0_c, dt_c, start=sim)
            psi_c = np.column_stack([companion.tangent(z_c, e, t0_c, dt_c, other, central=True,
                                                       scale=scale)[-1] for e in unit])
        except faults.Interrupted:  # a signal is no failure to work around
            raise
        except SolveError as exc:
            if halvings == 0:
                raise SolveError(f"fem-dual's flow along the orbit failed at t = {t0:.6g}: "
                                 f"{exc}") from None
            z, z_c, psi, psi_c = self._slab(z, z_c, t0, t0_c, dt / 2, dt_c / 2, halvings - 1,
                                            scale)
            z, z_c, second, second_c = self._slab(z, z_c, t0 + dt / 2, t0_c + dt_c / 2,
                                                  dt / 2, dt_c / 2, halvings - 1, scale)
            return z, z_c, second @ psi, second_c @ psi_c
        return (np.concatenate([values.x[-1], values.v[-1]]),
                np.concatenate([other.x[-1], other.v[-1]]), psi, psi_c)

    def close(self) -> None:
        if self.sim is not None:
            self.sim.close()


def stop_if_asked(what: str) -> None:
    """Raise faults.Interrupted when SIGINT/SIGTERM asked to stop (fem-dual orbit arms them):
    an orbit stops between Newton iterations, flow slabs and guess slabs."""
    signum = faults.requested()
    if signum:
        raise faults.Interrupted(f"interrupted by {signal.Signals(signum).name} in {what}",
                                 signum)


def nontrivial(lam: np.ndarray) -> np.ndarray:
    """The multipliers without the two nearest 1 (the flow's direction and the family's)."""
    return np.array(sorted(lam, key=lambda z: abs(z - 1))[2:])


def vector_field(scene):
    """z' = f(z) of the undamped scene's motion: f, whose value at an orbit's start is the
    flow's direction, the eigenvector of the monodromy for the multiplier 1."""
    return _rhs_and_jacobian(scene)[0]


def floquet_multipliers(Phi: np.ndarray, direction: np.ndarray
                        ) -> Tuple[np.ndarray, np.ndarray]:
    """(trivial pair, nontrivial multipliers) of the monodromy Phi of an orbit whose vector
    field at its start is `direction`. The flow's direction u is an eigenvector (multiplier 1)
    and, in a family of orbits, the family's tangent completes a Jordan block at 1, whose raw
    eigenvalues move by the square root of Phi's error (measured: 2.8 and 0.36 for a pair that
    DOP853 puts within 2e-4 of 1, an orbit near a separatrix). So u is deflated: with V an
    orthonormal complement of u, Phi is block triangular in (u, V) and the other multipliers
    are the eigenvalues of V^T Phi V, where the family's is simple again. Trivial pair: u^T Phi
    u and the eigenvalue of V^T Phi V nearest 1. The nontrivial ones are Phi's own eigenvalues
    (those matched to the rest of V^T Phi V): far from 1 they are well conditioned, while V^T
    Phi V also carries the error of u as an eigenvector (measured: 1.3e-11 against 1e-12)."""
    m = len(Phi)
    norm = float(np.linalg.norm(direction))
    if not (norm > 0 and np.isfinite(norm)):
        lam = np.linalg.eigvals(Phi)
        order = np.argsort(np.abs(lam - 1))
        return lam[order[:2]], lam[order[2:]]
    u = np.asarray(direction, float) / norm
    Q, _ = np.linalg.qr(np.column_stack([u, np.eye(m)]))
    V = Q[:, 1:m]
    rest = np.linalg.eigvals(V.T @ Phi @ V)
    k = int(np.argmin(np.abs(rest - 1)))
    trivial, rest = np.array([complex(u @ Phi @ u), rest[k]]), np.delete(rest, k)
    if len(rest):
        from scipy.optimize import linear_sum_assignment

        raw = np.linalg.eigvals(Phi)
        _, cols = linear_sum_assignment(np.abs(rest[:, None] - raw[None, :]))
        rest = raw[cols]
    return trivial, rest


def multiplier_distance(a: np.ndarray, b: np.ndarray) -> float:
    """The largest distance between matched multipliers of two sets (relative to 1 + |a|),
    matched by least total distance."""
    if len(a) == 0:
        return 0.0
    from scipy.optimize import linear_sum_assignment

    cost = np.abs(a[:, None] - b[None, :])
    rows, cols = linear_sum_assignment(cost)
    return float((cost[rows, cols] / (1.0 + np.abs(a[rows]))).max())
