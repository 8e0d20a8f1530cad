"""The degrees of freedom of a DOLFINx function space seen as one flat list: the field (scalar
component) and the coordinates of every local dof, the owned free dofs, their global numbering,
and the gathers of distributed rows and matrices onto rank 0.

Indices here are *unrolled*: for a blocked space (``ufl.VectorElement``, block size bs) local dof
``bs * node + c`` is component c at node ``node``; for a mixed space (bs = 1) the mixed dofmap's
own numbering. These are the indices of ``Function.x.array`` and of the rows of the PETSc
matrices that ``fem.petsc.assemble_matrix`` returns (global row ``bs * local_range[0] + i`` for
the owned local dof i).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, List, Optional, Sequence, Union

import numpy as np
import scipy.sparse as sps
from dolfinx import fem
from mpi4py import MPI
from petsc4py import PETSc

__all__ = ["DofLayout", "leaf_spaces", "dof_layout", "dirichlet_dofs", "owned_free",
           "global_offset", "index_set", "gather_rows", "gather_csr"]


def leaf_spaces(V: fem.FunctionSpace) -> List[fem.FunctionSpace]:
    """The scalar sub-spaces of V, depth first (V itself if V is scalar): for a mixed (w, theta)
    space [V.sub(0), V.sub(1)], for a 2D vector space [V.sub(0), V.sub(1)] (x and y)."""
    if V.num_sub_spaces == 0:
        return [V]
    return [leaf for i in range(V.num_sub_spaces) for leaf in leaf_spaces(V.sub(i))]


@dataclass(frozen=True)
class DofLayout:
    """Every local dof of a space, owned first, then ghosts (unrolled indices).

    Attributes:
        owned: number of owned local dofs (``size_local * bs``).
        offset: global index of the first owned dof (``local_range[0] * bs``).
        field: (owned + ghosts,) index of the scalar component (the position in
            :func:`leaf_spaces`) each dof belongs to.
        coordinates: (owned + ghosts, gdim) the point each dof sits at (Lagrange nodes).
    """

    owned: int
    offset: int
    field: np.ndarray
    coordinates: np.ndarray


def dof_layout(V: fem.FunctionSpace) -> DofLayout:
    """Field index and coordinates of every local dof, through the collapse maps of the scalar
    sub-spaces (a mixed space cannot tabulate its coordinates itself)."""
    imap, bs = V.dofmap.index_map, V.dofmap.index_map_bs
    total = (imap.size_local + imap.num_ghosts) * bs
    gdim = V.mesh.geometry.dim
    field = np.full(total, -1, dtype=np.int32)
    coordinates = np.zeros((total, gdim))
    for k, leaf in enumerate(leaf_spaces(V)):
        if leaf is V:
            collapsed, parent = V, np.arange(total)
        else:
            collapsed, parent = leaf.collapse()
        field[parent] = k
        coordinates[parent] = collapsed.tabulate_dof_coordinates()[:, :gdim]
    if np.any(field < 0):
        raise ValueError("dof_layout: the scalar sub-spaces do not cover every dof of V")
    return DofLayout(imap.size_local * bs, imap.local_range[0] * bs, field, coordinates)


def dirichlet_dofs(bcs: Iterable[Union[fem.DirichletBCMetaClass, Sequence[int]]]) -> np.ndarray:
    """The union of the local (unrolled) dofs of Dirichlet conditions: each item a
    ``fem.DirichletBC`` (its dofs are taken, its value is not: the conditions are homogeneous)
    or an array of local dof indices of V."""
    parts = [np.zeros(0, dtype=np.int64)]
    for bc in bcs:
        if isinstance(bc, fem.DirichletBCMetaClass):
            dofs, _ = bc.dof_indices()
        else:
            dofs = np.asarray(bc)
        parts.append(np.asarray(dofs, dtype=np.int64).ravel())
    return np.unique(np.concatenate(parts))


def owned_free(layout: DofLayout, constrained: np.ndarray) -> np.ndarray:
    """The owned local dofs that are not constrained, increasing (int32)."""
    free = np.ones(layout.owned, dtype=bool)
    constrained = constrained[constrained < layout.owned]
    free[constrained] = False
    return np.flatnonzero(free).astype(np.int32)


def global_offset(comm: MPI.Comm, count: int) -> int:
    """The number of items on the ranks before this one (exclusive prefix sum)."""
    offset = comm.exscan(count)
    return 0 if comm.rank == 0 or offset is None else int(offset)


def index_set(comm: MPI.Comm, indices: np.ndarray) -> PETSc.IS:
    """A PETSc index set of global indices (in PETSc's index type)."""
    return PETSc.IS().createGeneral(np.asarray(indices, dtype=PETSc.IntType), comm=comm)


def gather_rows(comm: MPI.Comm, values: np.ndarray) -> Optional[np.ndarray]:
    """The ranks' arrays concatenated in rank order on rank 0 (None elsewhere)."""
    if comm.size == 1:
        return np.array(values, copy=True)
    parts = comm.gather(np.ascontiguousarray(values), root=0)
    return np.concatenate(parts, axis=0) if comm.rank == 0 else None


def gather_csr(A: PETSc.Mat) -> Optional[sps.csr_matrix]:
    """A distributed PETSc AIJ matrix as one scipy CSR matrix on rank 0 (None elsewhere): each
    rank's rows with their global column indices, stacked in rank order."""
    comm = A.getComm().tompi4py()
    indptr, indices, data = A.getValuesCSR()
    parts = comm.gather((indptr, indices, data), root=0) if comm.size > 1 else [
        (indptr, indices, data)]
    if comm.rank != 0:
        return None
    counts = [p[0][-1] for p in parts]
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    rows = np.concatenate([p[0][:-1] + s for p, s in zip(parts, starts)] + [[sum(counts)]])
    return sps.csr_matrix((np.concatenate([p[2] for p in parts]),
                           np.concatenate([p[1] for p in parts]), rows), shape=A.getSize())


def dof_keys(coordinates: np.ndarray, field: Sequence[int], scale: float) -> List[tuple]:
    """Hashable keys of points or dofs: coordinates rounded to 1e-9 of `scale`, then the field
    component; equal keys find the same dof in two numberings (serial and distributed, dofs
    and mesh vertices)."""
    rounded = np.round(np.asarray(coordinates, float) / scale, 9)
    return [tuple(row) + (int(f),) for row, f in zip(rounded.tolist(), field)]
