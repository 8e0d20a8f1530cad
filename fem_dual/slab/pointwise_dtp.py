"""The implicit dual-to-primal map, solved pointwise by Newton.

For forces whose DtP map has no closed form (curl2d, user-defined forces), the position part
x^ solves G(x; xi, eta, xi') = 0 with G = xi' + DF(x)^T eta + dH/dx(x - xbar) (stationarity of the
pre-dual Lagrangian in x). It is solved at fixed reference points of every local cell: the
quadrature points where the forms are evaluated, or the cell ends for vertex recovery. The values
live in a Function of a point space (Quadrature, or DG1 whose nodes are the cell ends), so they
enter forms and expressions as coefficients.

G_x = d^2H/dx^2 + sum_i eta_i d^2F_i/dx^2 is symmetric, and positive definite on the branch of
the DtP map that starts at the base state (zero dual state, G_x = d^2H/dx^2): there the pre-dual
Lagrangian has its unique maximum in x. Where the smallest eigenvalue of G_x falls below
BRANCH_TOL times its largest (near the determinant condition of section 3.1), the root is about
to leave that branch, or has left it for another stationary point: the solve stops with a
message naming the time, and the driver retries the slab halved (shorter slabs keep the dual
fields, hence the curvature term, small).
"""
from __future__ import annotations

from typing import Callable, Optional

import numpy as np
import ufl
from dolfinx import fem
from fem_dual.compat import CellPointEvaluator
from fem_dual.mpi import allreduce

__all__ = ["PointwiseDtP", "BRANCH_TOL"]

BRANCH_TOL = 1e-3  # lambda_min / lambda_max of G_x below this: leaving the base state branch
LAST_STEP = 1e-8  # a relative Newton step below this is the last one
MAX_IT = 50  # Newton steps at most
CONVERGED, NOT_FINITE, NOT_CONVERGED = 0, 1, 2  # how the pointwise Newton ended


class PointwiseDtP:
    """Newton on G(x) = 0 at the reference points `points` of every local cell.

    Args:
        space: vector point space (n components) holding x^ at the points.
        points: reference coordinates of the points, in the order of the space's cell dofs.
        equations: G as a UFL function of the position (a ufl.variable).
        time: UFL expression of the physical time (for messages).
        inverse_space: optional tensor point space (n x n) to receive G_x^-1 at the solution,
            for the Newton-linearised DtP map of the global Jacobian.
    """

    def __init__(self, space: fem.FunctionSpace, points: np.ndarray,
                 equations: Callable[[ufl.core.expr.Expr], ufl.core.expr.Expr],
                 time: ufl.core.expr.Expr, inverse_space: Optional[fem.FunctionSpace] = None):
        self.X = fem.Function(space)
        self.points = points
        self.n = n = space.dofmap.index_map_bs
        xv = ufl.variable(self.X)
        G = equations(xv)
        Gx = ufl.diff(G, xv)
        self.equations = equations
        parts = [*G, *[Gx[i, j] for i in range(n) for j in range(n)], time]
        self._eval = CellPointEvaluator(ufl.as_vector(parts), points)
        msh = space.mesh
        imap = msh.topology.index_map(msh.topology.dim)
        self.cells = np.arange(imap.size_local + imap.num_ghosts, dtype=np.int32)
        self.dofs = space.dofmap.list.array.reshape(len(self.cells), len(points))
        self.Ginv = fem.Function(inverse_space) if inverse_space is not None else None
        self.iterations = 0
        self._packed = None  # (the compiled loops, the packed expression, ...), or False: numpy
        self._out = np.zeros((len(self.cells), len(points) * (n + n * n + 1)))
        self._shape = (len(self.cells), len(points), n + n * n + 1)

    @property
    def compiled(self) -> bool:
        """Whether the Newton iteration ran in compiled code (fem_dual.native)."""
        return bool(self._packed)

    def _evaluate(self) -> np.ndarray:
        """(cells, points, G then G_x then t) at the current X."""
        return self._eval.into(self.cells, self._out).reshape(self._shape)

    def reset(self, xbar: np.ndarray) -> None:
        """Start from the base state (the DtP image of the zero dual state)."""
        self.X.x.array.reshape(-1, self.n)[:] = xbar

    def solve(self, comm, max_it: int = MAX_IT) -> Optional[str]:
        """Solve G = 0 at every point; returns None, or a message (the same on every rank).

        The branch test (eigenvalues of G_x) is made at the root and, when Newton fails, at the
        last iterate: a root on another branch is refused, and an iteration that wandered off
        is named by where it went."""
        n = self.n
        values = self.X.x.array.reshape(-1, self.n)
        start = values.copy()
        with np.errstate(all="ignore"):  # NaN steps and ratios count as bad below
            status, out, step, it = self._iterate(max_it)
            Gx = out[..., n:n + n * n].reshape(out.shape[:2] + (n, n))
            problem = self._branch(Gx, out[..., -1])
            if status == NOT_FINITE:
                problem = problem or "the DtP map produced a non-finite state"
            elif status == NOT_CONVERGED and problem is None:
                t = out[..., -1]
                worst = np.unravel_index(np.argmax(np.abs(step).max(axis=-1)), step.shape[:2])
                problem = (f"the DtP map has no solution near t = {t[worst]:.6g} (pointwise "
                           f"Newton did not converge in {max_it} iterations); use smaller "
                           "slabs or larger alpha")
        self.iterations = it
        message = allreduce(comm, problem or "", "max")  # any rank's message, on every rank
        if message:
            values[:] = start  # keep the last good state as the next starting guess
            return message
        if self.Ginv is not None:
            self.Ginv.x.array.reshape(-1, n * n)[self.dofs] = _inverse(Gx).reshape(
                Gx.shape[0], Gx.shape[1], n * n)
        return None

    def _iterate(self, max_it: int):
        """Newton on every point from the current X: (status, the last evaluation (cells,
        points, G then G_x then t), the last step, the last iteration). A step of 1e-8 is the
        last (quadratic convergence: after it the root is exact to round-off, without one more
        evaluation to confirm it; G_x and its inverse are those of the last iterate, 1e-8
        away). In compiled code (fem_dual.native) where it is available."""
        if self._packed is None:
            from fem_dual import native

            if native.library() is None:
                self._packed = False
            else:
                from fem_dual.native.force import PackedExpression

                packed = PackedExpression(self._eval.compiled, self.cells)
                self._packed = (packed,  # X's columns in a cell's row, X's blocks
                                np.ascontiguousarray(packed.slot(self.X), dtype=np.int64),
                                np.ascontiguousarray(self.dofs, dtype=np.int64))
        if self._packed:
            return self._compiled_iterate(max_it)
        n = self.n
        values = self.X.x.array.reshape(-1, self.n)
        for it in range(max_it + 1):
            out = self._evaluate()
            G, Gx = out[..., :n], out[..., n:n + n * n].reshape(out.shape[:2] + (n, n))
            step = _solve(Gx, G)
            if not np.isfinite(step).all():
                return NOT_FINITE, out, step, it
            current = values[self.dofs]
            values[self.dofs] = current - step
            if np.abs(step).max() <= LAST_STEP * (1.0 + np.abs(current).max()):
                return CONVERGED, out, step, it
        return NOT_CONVERGED, out, step, it

    def _compiled_iterate(self, max_it: int):
        """_iterate's loop in compiled code: the same steps, stopping rule and results."""
        from fem_dual.native.dtp import dtp_newton

        packed, xslot, xdofs = self._packed
        step = np.empty((len(self.cells), len(self.points), self.n))
        status, it = dtp_newton(packed.kernel, packed.pack(), xslot, packed.constants(),
                                packed.coords, max_it, LAST_STEP, self._out, step,
                                self.X.x.array, xdofs)
        return status, self._out.reshape(self._shape), step, it

    @staticmethod
    def _branch(Gx: np.ndarray, t: np.ndarray) -> Optional[str]:
        """Why the points' G_x leave the base state's branch (smallest / largest eigenvalue
        below BRANCH_TOL, or not finite), or None."""
        with np.errstate(all="ignore"):
            ratio = _eigenvalue_ratio(Gx)
        if ratio.min() > BRANCH_TOL:  # (False for a NaN among them)
            return None
        bad = ~(ratio > BRANCH_TOL)
        where = np.unravel_index(np.argmin(np.where(np.isnan(ratio), -np.inf, ratio)), bad.shape)
        return (f"the DtP map is near singular at t = {t[where]:.6g} (smallest/largest "
                f"eigenvalue of G_x {ratio[where]:.2g}); use smaller slabs or larger alpha")



# Batched small linear algebra: numpy's gufuncs cost 10-40 us a call on these arrays of a few
# dozen 2 x 2 matrices, a third of an implicit scene's run; closed forms for n = 2 (the 2D
# forces) cost a few array operations.

def _solve(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """A^-1 b for stacks of n x n matrices A and n-vectors b."""
    if A.shape[-1] == 2:
        a11, a12, a21, a22 = A[..., 0, 0], A[..., 0, 1], A[..., 1, 0], A[..., 1, 1]
        det = a11 * a22 - a12 * a21
        return np.stack([(a22 * b[..., 0] - a12 * b[..., 1]) / det,
                         (a11 * b[..., 1] - a21 * b[..., 0]) / det], axis=-1)
    return np.linalg.solve(A, b[..., None])[..., 0]


def _inverse(A: np.ndarray) -> np.ndarray:
    if A.shape[-1] == 2:
        det = A[..., 0, 0] * A[..., 1, 1] - A[..., 0, 1] * A[..., 1, 0]
        inv = np.empty_like(A)
        inv[..., 0, 0], inv[..., 1, 1] = A[..., 1, 1] / det, A[..., 0, 0] / det
        inv[..., 0, 1], inv[..., 1, 0] = -A[..., 0, 1] / det, -A[..., 1, 0] / det
        return inv
    return np.linalg.inv(A)


def _eigenvalue_ratio(A: np.ndarray) -> np.ndarray:
    """Smallest eigenvalue over the largest magnitude of the symmetric parts of a stack of
    matrices (NaN where they are not finite)."""
    if A.shape[-1] == 2:  # mean -+ radius: no stacking of the pair
        mean = 0.5 * (A[..., 0, 0] + A[..., 1, 1])
        radius = np.hypot(0.5 * (A[..., 0, 0] - A[..., 1, 1]), 0.5 * (A[..., 0, 1] + A[..., 1, 0]))
        return (mean - radius) / (np.abs(mean) + radius)
    if not np.isfinite(A).all():
        return np.full(A.shape[:-2], np.nan)
    eig = np.linalg.eigvalsh(0.5 * (A + np.swapaxes(A, -1, -2)))  # ascending
    return eig[..., 0] / np.abs(eig).max(axis=-1)
