"""Primal recovery at the vertices of the time mesh: the DtP image (x^, v^), the auxiliary dual
Hamiltonian, and (when output asks for them) the dual fields.

xi' and eta' jump at interior vertices of a C0 Lagrange field, so x^ and v^ are two-valued there.
Rule: the value at a vertex is the average of the one-sided values of the cells that share it
(two inside the slab, one at the slab ends, where the value is one-sided and exact for the cell).

In parallel every rank evaluates its owned cells at both ends; rank 0 gathers and averages. Each
cell is owned by exactly one rank, so every vertex gets exactly its incident cells, once.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
import ufl
from scipy import sparse

from fem_dual.compat import CellPointEvaluator, vector_space_dg1
from fem_dual.errors import SolveError
from fem_dual.pointwise import PointwiseDtP
from fem_dual.mpi import gather_rows
from fem_dual.problem import SlabProblem

__all__ = ["VertexValues", "VertexSampler"]


@dataclass
class VertexValues:
    """Values at the vertices of one slab, sorted by the reference coordinate s in [0, 1]."""

    s: np.ndarray
    x: np.ndarray  # (vertices, n)
    v: np.ndarray
    hamiltonian: np.ndarray
    xi: Optional[np.ndarray] = None
    eta: Optional[np.ndarray] = None

    def finite(self) -> bool:
        arrays = [self.x, self.v, self.hamiltonian] + [a for a in (self.xi, self.eta)
                                                       if a is not None]
        return all(np.isfinite(a).all() for a in arrays)


class VertexSampler:
    """Evaluates the DtP image at the vertices of the slab mesh.

    Args:
        problem: the slab problem.
        with_dual: also sample xi and eta (for XDMF output); off when no output is asked for.
    """

    def __init__(self, problem: SlabProblem, with_dual: bool = False):
        self.problem = problem
        self.with_dual = with_dual
        n = problem.n
        msh = problem.mesh.msh
        ends = np.array([0.0, 1.0])
        self.vertex_dtp: Optional[PointwiseDtP] = None
        xhat, hamiltonian = problem.xhat, problem.hamiltonian
        if problem.pointwise is not None:  # implicit DtP: solve G = 0 at the cell ends (DG1 nodes)
            space = vector_space_dg1(msh, n)
            self.vertex_dtp = PointwiseDtP(space, ends, problem.position_equations, problem.time)
            xhat = self.vertex_dtp.X
            hamiltonian = problem.hamiltonian_of(xhat, problem.vhat)
        parts = [ufl.SpatialCoordinate(msh)[0], *xhat, *problem.vhat, hamiltonian]
        if with_dual:
            parts += [*problem.xi, *problem.eta]
        self._eval = CellPointEvaluator(ufl.as_vector(parts), ends)
        self._cells = np.arange(problem.mesh.msh.topology.index_map(1).size_local, dtype=np.int32)
        self._n = n
        self._mean: Optional[sparse.csr_matrix] = None  # rows -> vertex means, built once

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
            self.vertex_dtp.reset(self.problem.xbar.value)
            message = self.vertex_dtp.solve(self.problem.comm)
            if message:
                raise SolveError(message)
        local = self._eval(self._cells).reshape(-1, self._eval.value_size)
        return gather_rows(self.problem.comm, local)

    def average(self, rows: np.ndarray) -> VertexValues:
        """Vertex values from the one-sided rows: the mean of the rows that share a vertex."""
        if self._mean is None or self._mean.shape[1] != len(rows):  # the rows' order never changes
            s, inverse = np.unique(rows[:, 0], return_inverse=True)
            count = np.bincount(inverse).astype(float)
            self._mean = sparse.csr_matrix((1.0 / count[inverse], (inverse, np.arange(len(rows)))),
                                           shape=(len(s), len(rows)))
        mean = self._mean @ rows
        s = mean[:, 0]
        n = self._n
        values = VertexValues(s=s, x=mean[:, 1:1 + n], v=mean[:, 1 + n:1 + 2 * n],
                              hamiltonian=mean[:, 1 + 2 * n])
        if self.with_dual:
            values.xi = mean[:, 2 + 2 * n:2 + 3 * n]
            values.eta = mean[:, 2 + 3 * n:2 + 4 * n]
        return values
