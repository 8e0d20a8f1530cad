"""Primal recovery at the vertices of the time mesh: the primal state (x, v), the auxiliary dual
Hamiltonian, and (when output asks for them) the dual fields.

The primal state is read from the momenta of the dual Lagrangian, not from the DtP formula.
By stationarity of the pre-dual Lagrangian in (x, v) (the envelope theorem),
dL_d/dxi' = -x^ and dL_d/deta' = -M v^. Testing the action of one cell with the Lagrange basis
function of one of its end vertices and integrating by parts gives that momentum at the vertex:

    r = int_cell (dL_d/dw . phi + dL_d/dw' . phi') dt = -/+ dL_d/dw'(vertex)   (exact solution),

so x(vertex) = +r_xi (left end of the cell) or -r_xi (right end), M v(vertex) = +/- r_eta.
For the Galerkin solution this cell residual is a superconvergent flux (Wheeler's trick): the
vertex values converge at order 2p instead of the order p of the DtP formula evaluated with
the derivatives xi', eta', which jump at the vertices. The slab end value, which starts the next
slab, is as accurate as the interior ones. `recovery="dtp"` keeps the DtP formula (for
comparison). The two one-sided values at an interior vertex agree to the solver tolerance (their
sum is the residual at the vertex), and the value used is their average.

In parallel every rank evaluates its owned cells at both ends; rank 0 gathers and averages. Each
cell is owned by exactly one rank, so every vertex gets exactly its incident cells, once.
"""
from __future__ import annotations

from typing import Optional

import numpy as np
import ufl

from dolfinx import fem
from petsc4py import PETSc

from fem_dual.compat import (CellPointEvaluator, compile_form, destroy_petsc, vector_space,
                             vector_space_dg1)
from fem_dual.errors import SolveError
from fem_dual.slab.pointwise_dtp import PointwiseDtP
from fem_dual.mpi import gather_rows
from fem_dual.slab.problem import SlabProblem

__all__ = ["VertexValues", "VertexSampler", "CellMomenta", "RECOVERIES", "times_last"]

from fem_dual.choices import RECOVERIES  # noqa: E402 -- validated in config
from fem_dual.slab.values import VertexValues, times_last  # noqa: E402,F401 -- light, re-exported


class CellMomenta:
    """The momenta (x^, M v^) at both ends of every owned cell, from the cell residuals of the
    action tested with a discontinuous space of the same degree (see the module docstring)."""

    def __init__(self, problem: SlabProblem):
        self.problem = problem
        msh, n = problem.mesh.msh, problem.n
        bs = problem.W.dofmap.index_map_bs
        space = vector_space(msh, problem.degree, bs, "DG")
        residual = ufl.derivative(problem.L_d * problem.dt * problem.dx, problem.w,
                                  ufl.TestFunction(space))
        self._form = compile_form(residual)
        self._vec = fem.petsc.create_vector(self._form)
        cells = msh.topology.index_map(1).size_local
        ends = space.dofmap.list.array.reshape(-1, problem.degree + 1)[:cells, :2]
        self._index = ends[:, :, None] * bs + np.arange(2 * n)  # (cells, end, component)
        vertices = msh.geometry.dofmap.array.reshape(-1, 2)[:cells]
        s = msh.geometry.x[vertices, 0]
        left_first = (s[:, 0] < s[:, 1])[:, None]
        self._sign = np.where(left_first, [1.0, -1.0], [-1.0, 1.0])[:, :, None]

    def close(self) -> None:
        """Destroy the PETSc vector (collective)."""
        destroy_petsc(self._vec)

    def __call__(self) -> np.ndarray:
        """(cells, 2, 2n): x^ then M v^ at reference points 0 and 1 of each owned cell."""
        pointwise = self.problem.pointwise
        if pointwise is not None:  # the quadrature-point DtP of the current dual state
            message = pointwise.solve(self.problem.comm)
            if message:
                raise SolveError(message)
        with self._vec.localForm() as local:
            local.set(0.0)
        fem.petsc.assemble_vector(self._vec, self._form)
        self._vec.ghostUpdate(PETSc.InsertMode.ADD, PETSc.ScatterMode.REVERSE)
        return self._sign * self._vec.array_r[self._index]


class VertexSampler:
    """Evaluates the DtP image at the vertices of the slab mesh.

    Args:
        problem: the slab problem.
        with_dual: also sample xi and eta (for XDMF output); off when no output is asked for.
        recovery: "momentum" (superconvergent, the default) or "dtp" (the DtP formula).
        momenta: what gives the momenta at the cell ends (a callable returning (cells, 2, 2n),
            the pointwise assembly's `LocalAction.momenta`); by default CellMomenta.
    """

    def __init__(self, problem: SlabProblem, with_dual: bool = False,
                 recovery: str = "momentum", momenta=None):
        if recovery not in RECOVERIES:
            raise ValueError(f"recovery={recovery!r} is not one of {RECOVERIES}")
        self.problem = problem
        self.with_dual = with_dual
        self.momenta = None
        if recovery == "momentum":
            self.momenta = momenta if momenta is not None else CellMomenta(problem)
        n = problem.n
        msh = problem.mesh.msh
        ends = np.array([0.0, 1.0])
        cells = msh.topology.index_map(1).size_local
        self.vertex_dtp: Optional[PointwiseDtP] = None
        self._state: Optional[tuple] = None  # DG1 functions holding the recovered x, v
        xhat, vhat, hamiltonian = problem.xhat, problem.vhat, problem.hamiltonian
        if self.momenta is not None and problem.extra is None:
            # H_d of the recovered state and the nodal duals: as accurate as the state
            space = vector_space_dg1(msh, n)
            xhat, vhat = fem.Function(space), fem.Function(space)
            dofs = space.dofmap.list.array.reshape(-1, 2)[:cells]
            flat = (dofs[..., None] * n + np.arange(n)).ravel()  # (cell, end, component)
            self._state = (xhat.x.array, vhat.x.array, flat)
            hamiltonian = problem.hamiltonian_of(xhat, vhat)
        elif problem.pointwise is not None:  # implicit DtP: solve G = 0 at the cell ends
            space = vector_space_dg1(msh, n)
            self.vertex_dtp = PointwiseDtP(space, ends, problem.position_equations, problem.time)
            xhat = self.vertex_dtp.X
            hamiltonian = problem.hamiltonian_of(xhat, vhat)
        parts = [ufl.SpatialCoordinate(msh)[0], *xhat, *vhat, hamiltonian]
        if with_dual:
            parts += [*problem.xi, *problem.eta]
        self._eval = CellPointEvaluator(ufl.as_vector(parts), ends)
        self._cells = np.arange(problem.mesh.msh.topology.index_map(1).size_local, dtype=np.int32)
        self._n = n
        self._ends: Optional[tuple] = None  # the rows of each vertex, found once
        self._minv: Optional[tuple] = None  # (M, M^-1)

    def close(self) -> None:
        """Destroy the PETSc objects of the momenta (collective)."""
        close = getattr(self.momenta, "close", None)
        if close is not None:
            close()

    def __call__(self) -> Optional[VertexValues]:
        """Sample the current dual solution; the result lives on rank 0 (None elsewhere).

        Raises:
            SolveError: the implicit DtP map cannot be solved at a vertex.
        """
        rows = self.rows()
        return None if rows is None else self.average(rows)

    def rows(self) -> Optional[np.ndarray]:
        """One-sided values at both ends of every cell, gathered on rank 0 (None elsewhere):
        columns s, x^ (n), v^ (n), H_d, then xi (n) and eta (n) when sampled."""
        if self.vertex_dtp is not None:
            self.vertex_dtp.reset(self.problem.x0.value)  # the slab's start: near every vertex
            message = self.vertex_dtp.solve(self.problem.comm)
            if message:
                raise SolveError(message)
        if self._state is not None:  # x, v from the momenta into DG1, then evaluate
            n = self._n
            momenta = self.momenta()  # (cells, end, 2n)
            X, V, flat = self._state
            X[flat] = momenta[..., :n].ravel()
            V[flat] = (momenta[..., n:] @ self._mass_inverse().T).ravel()
            local = self._eval(self._cells).reshape(-1, self._eval.value_size)
        else:
            local = self._eval(self._cells).reshape(-1, self._eval.value_size)
            if self.momenta is not None:  # a lifted scene: H_d through its own Legendre map
                n = self._n
                momenta = self.momenta().reshape(-1, 2 * n)
                local[:, 1:1 + n] = momenta[:, :n]
                local[:, 1 + n:1 + 2 * n] = momenta[:, n:] @ self._mass_inverse().T
        return gather_rows(self.problem.comm, local)

    def _mass_inverse(self) -> np.ndarray:
        """M^-1, computed again when M changes (a scene's parameters)."""
        scene = self.problem.scene  # (a new scene object for new parameters)
        if self._minv is None or self._minv[0] is not scene:
            self._minv = (scene, np.linalg.inv(self.problem.c["M"].value))
        return self._minv[1]

    def average(self, rows: np.ndarray) -> VertexValues:
        """Vertex values from the one-sided rows (rows, columns): the mean of the rows that
        share a vertex. Rows of many slabs (slabs, rows, columns) give values with a leading
        slab axis."""
        flat = rows if rows.ndim == 2 else rows[0]
        if self._ends is None or self._ends[2] != len(flat):  # the rows' order never changes
            _, inverse, count = np.unique(flat[:, 0], return_inverse=True, return_counts=True)
            if count.max(initial=0) > 2:
                raise RuntimeError("a vertex of the time mesh has more than two cells")
            grouped = np.argsort(inverse, kind="stable")
            starts = np.concatenate([[0], np.cumsum(count)[:-1]])
            self._ends = (grouped[starts], grouped[starts + count - 1], len(flat))
        first, last, _ = self._ends  # the one or two rows of each vertex (x/2 is exact)
        mean = 0.5 * rows.take(first, axis=-2) + 0.5 * rows.take(last, axis=-2)
        s = mean[..., 0] if rows.ndim == 2 else mean[0, :, 0]
        n = self._n
        values = VertexValues(s=s, x=mean[..., 1:1 + n], v=mean[..., 1 + n:1 + 2 * n],
                              hamiltonian=mean[..., 1 + 2 * n], z=mean[..., 1:1 + 2 * n],
                              block=mean)
        if self.with_dual:
            values.xi = mean[..., 2 + 2 * n:2 + 3 * n]
            values.eta = mean[..., 2 + 3 * n:2 + 4 * n]
        return values
