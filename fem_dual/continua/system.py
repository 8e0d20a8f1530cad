"""The spatial operators of a continuum for the method of lines.

For a function space V (scalar, blocked or mixed), homogeneous Dirichlet conditions on some of
its dofs and bilinear forms m(u, w), k(u, w) and optionally d(u, w) (k and d may be
non-symmetric), the semi-discrete equations of motion are

    M q'' + D q' + K q = 0,   M_ij = m(phi_j, phi_i), K_ij = k(phi_j, phi_i), D_ij = d(phi_j, phi_i)

for i, j over the *free* dofs (not constrained), q the vector of the free dofs' values. M, K, D
are distributed PETSc AIJ matrices: each form is assembled by ``fem.petsc.assemble_matrix`` over
all dofs, then restricted with ``createSubMatrix`` on the index set of the owned free dofs (no
Dirichlet rows: the constrained dofs are simply absent). Without d, D is an empty AIJ matrix.

Free-dof order (rows of M, K, D; entries of every free vector): rank by rank, and on each rank
the owned free dofs by increasing local unrolled index (``Function.x.array`` index; for a
blocked space component c of node j is ``bs * j + c``). A *free vector* is a numpy array of this
rank's owned free values in that order; :meth:`SpatialSystem.gather` and
:meth:`SpatialSystem.scatter` pass between it and the global vector on rank 0.
"""
from __future__ import annotations

import os
from typing import Dict, Iterable, Mapping, Optional, Sequence, Tuple

import numpy as np
import scipy.sparse as sps
from dolfinx import fem
from dolfinx.fem import petsc as fem_petsc
from petsc4py import PETSc

from fem_dual.compat import destroy_petsc, quiet_jit_logging
from fem_dual.compat import compile_form as compat_compile_form
from fem_dual.continua.dofs import (dirichlet_dofs, dof_layout, gather_csr, gather_rows,
                                    global_offset, index_set, leaf_spaces, owned_free)
from fem_dual.continua.initial import interpolate_fields
from fem_dual.errors import InputError

__all__ = ["SpatialSystem", "DENSE_LIMIT", "compile_form"]

#: the largest number of free dofs :meth:`SpatialSystem.dense` returns dense matrices for
DENSE_LIMIT = 2000


def compile_form(a) -> fem.FormMetaClass:
    """A UFL form compiled (quietly, fem_dual.compat.compile_form); a compiled form is returned
    as it is."""
    if isinstance(a, fem.FormMetaClass):
        return a
    with quiet_jit_logging():
        return compat_compile_form(a)


class SpatialSystem:
    """M, K, D on the free dofs of V, and the maps between free vectors and fields.

    Attributes:
        V: the function space.
        M, K, D: free-dof PETSc AIJ matrices (distributed over V's mesh communicator).
        forms: the compiled forms ``{"m", "k"[, "d"]}``; after changing a ``fem.Constant`` in
            them, :meth:`refresh` assembles M, K, D again.
        free: this rank's owned free dofs (local unrolled indices, increasing).
        n: global number of free dofs; n_local: this rank's share; offset: its first global
            free index.
        field, coordinates: field index and (n_local, gdim) coordinates of the owned free dofs.
    """

    def __init__(self, V: fem.FunctionSpace, bcs: Iterable, m, k, d=None):
        self.V, self.comm = V, V.mesh.comm
        self.layout = dof_layout(V)
        self.free = owned_free(self.layout, dirichlet_dofs(bcs))
        self.n_local = int(self.free.size)
        self.offset = global_offset(self.comm, self.n_local)
        self.n = int(self.comm.allreduce(self.n_local))
        self.field = self.layout.field[self.free]
        self.coordinates = self.layout.coordinates[self.free]
        self.free_is = index_set(self.comm, self.layout.offset + self.free)
        self.forms = {name: compile_form(a) for name, a in (("m", m), ("k", k), ("d", d))
                      if a is not None}
        self.M = self.K = self.D = None
        self.refresh()

    @property
    def components(self) -> int:
        """The number of scalar field components (sub-spaces of :func:`leaf_spaces`)."""
        return len(leaf_spaces(self.V))

    @property
    def has_damping(self) -> bool:
        return "d" in self.forms

    def assemble(self, a) -> PETSc.Mat:
        """The free-dof matrix ``A_ij = a(phi_j, phi_i)`` of a bilinear form on V x V (UFL or
        compiled), distributed like M. The caller owns (destroys) it."""
        form = compile_form(a)
        full = fem_petsc.assemble_matrix(form)
        full.assemble()
        try:
            return full.createSubMatrix(self.free_is, self.free_is)
        finally:
            full.destroy()

    def refresh(self) -> None:
        """Assemble M, K and D (again) from their compiled forms; the previous matrices are
        destroyed."""
        destroy_petsc(self.M, self.K, self.D)
        self.M = self.assemble(self.forms["m"])
        self.K = self.assemble(self.forms["k"])
        self.D = self.assemble(self.forms["d"]) if self.has_damping else self._zero()

    def _zero(self) -> PETSc.Mat:
        size = ((self.n_local, self.n), (self.n_local, self.n))
        Z = PETSc.Mat().createAIJ(size, nnz=(0, 0), comm=self.comm)
        Z.assemble()
        return Z

    def destroy(self) -> None:
        """Free the PETSc objects (collective)."""
        destroy_petsc(self.M, self.K, self.D, self.free_is)
        self.M = self.K = self.D = None

    # --- free vectors and fields ----------------------------------------------------------

    def zeros(self) -> np.ndarray:
        return np.zeros(self.n_local)

    def _check(self, q: np.ndarray) -> np.ndarray:
        q = np.asarray(q, dtype=np.float64)
        if q.shape != (self.n_local,):
            raise ValueError(f"free vector of shape {q.shape}, expected ({self.n_local},)")
        return q

    def to_function(self, q: np.ndarray, u: Optional[fem.Function] = None) -> fem.Function:
        """The field of the free vector q (constrained dofs 0), ghosts updated from their
        owners; written into `u` if given."""
        q = self._check(q)
        u = u if u is not None else fem.Function(self.V)
        u.x.array[:] = 0.0
        u.x.array[self.free] = q
        u.x.scatter_forward()
        return u

    def from_function(self, u: fem.Function) -> np.ndarray:
        """The free vector of a field of V (its owned free values)."""
        return u.x.array[self.free].copy()

    def vector(self, q: Optional[np.ndarray] = None) -> PETSc.Vec:
        """A PETSc vector laid out like the columns of M (holding q if given)."""
        vec = self.M.createVecRight()
        if q is not None:
            vec.array[:] = q
        return vec

    def gather(self, q: np.ndarray) -> Optional[np.ndarray]:
        """The global free vector on rank 0 (None elsewhere)."""
        return gather_rows(self.comm, self._check(q))

    def scatter(self, q: Optional[np.ndarray]) -> np.ndarray:
        """This rank's part of a global free vector given on rank 0."""
        if self.comm.size == 1:
            return np.array(q, dtype=np.float64, copy=True)
        counts = self.comm.gather(self.n_local, root=0)
        parts = None
        if self.comm.rank == 0:
            parts = np.split(np.asarray(q, dtype=np.float64), np.cumsum(counts)[:-1])
        return self.comm.scatter(parts, root=0)

    def interpolate(self, exprs: Sequence[str],
                    parameters: Optional[Mapping[str, float]] = None) -> np.ndarray:
        """The free vector of the field given by one expression per scalar component in the
        spatial coordinates (see :mod:`fem_dual.continua.initial`)."""
        return interpolate_fields(self.V, exprs, parameters)[self.free]

    # --- gathered copies ------------------------------------------------------------------

    def to_scipy(self) -> Optional[Dict[str, sps.csr_matrix]]:
        """``{"M", "K", "D"}`` as scipy CSR matrices on rank 0 (None elsewhere), rows and
        columns in the free-dof order. For small problems and export."""
        mats = {name: gather_csr(A) for name, A in (("M", self.M), ("K", self.K),
                                                      ("D", self.D))}
        return mats if self.comm.rank == 0 else None

    def dense(self, limit: int = DENSE_LIMIT) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """M, K, D as dense arrays on every rank, for at most `limit` free dofs."""
        if self.n > limit:
            raise ValueError(f"dense: {self.n} free dofs, more than the limit {limit}; use the "
                             "PETSc matrices (or to_scipy for export)")
        mats = self.to_scipy()
        arrays = None if mats is None else tuple(mats[k].toarray() for k in ("M", "K", "D"))
        return arrays if self.comm.size == 1 else self.comm.bcast(arrays, root=0)

    def free_layout(self) -> Optional[Tuple[np.ndarray, np.ndarray]]:
        """(coordinates (n, gdim), field index (n,)) of all free dofs on rank 0, in the
        free-dof order (None elsewhere)."""
        coordinates = gather_rows(self.comm, self.coordinates)
        field = gather_rows(self.comm, self.field)
        return None if coordinates is None else (coordinates, field)

    def export_npz(self, path: "str | os.PathLike", u0: np.ndarray, v0: np.ndarray) -> None:
        """Write M, K, D (``<X>_data, <X>_indices, <X>_indptr, <X>_shape``, CSR), the initial
        free vectors u0, v0 (global), the free dofs' ``coordinates`` (n, gdim) and ``field``
        index, all in the free-dof order, to one ``.npz`` file on rank 0 (collective)."""
        mats, layout = self.to_scipy(), self.free_layout()
        u, v = self.gather(u0), self.gather(v0)
        problem = None
        if self.comm.rank == 0:
            arrays = {"u0": u, "v0": v, "coordinates": layout[0], "field": layout[1]}
            for name, A in mats.items():
                arrays.update({f"{name}_data": A.data, f"{name}_indices": A.indices,
                               f"{name}_indptr": A.indptr, f"{name}_shape": np.array(A.shape)})
            try:
                np.savez(path, **arrays)
            except OSError as exc:
                problem = f"export_npz: cannot write {os.fspath(path)!r}: {exc.strerror or exc}"
        problem = problem if self.comm.size == 1 else self.comm.bcast(problem, root=0)
        if problem is not None:
            raise InputError(problem)

