"""The time mesh of one slab: the reference interval s in [0, 1] and its boundary tags.

Every slab is solved on the same reference mesh of s in [0, 1], with physical time
t = t0 + dt * s; the slab length dt is a `fem.Constant` in the forms, so slabs of any length reuse
one compiled form (and, for linear scenes with equal slabs, one factored matrix).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from dolfinx import mesh
from mpi4py import MPI

from fem_dual.compat import equispaced_coordinates

__all__ = ["START", "END", "SlabMesh", "slab_mesh"]

START = 1  # tag of the vertex s = 0, where the initial conditions enter the action
END = 2  # tag of the vertex s = 1, where xi = eta = 0 (Dirichlet)


@dataclass
class SlabMesh:
    """The reference interval mesh of one slab with its boundary-vertex tags."""

    msh: mesh.Mesh
    tags: mesh.MeshTagsMetaClass
    start_vertices: np.ndarray
    end_vertices: np.ndarray
    cells: int


def slab_mesh(comm: MPI.Comm, cells: int) -> SlabMesh:
    """A uniform mesh of [0, 1] with `cells` cells, distributed over `comm`.

    Args:
        comm: the communicator the time mesh is distributed over.
        cells: number of time cells per slab.

    Returns:
        The mesh and the tags START (s = 0) and END (s = 1) on its boundary vertices.
    """
    msh = mesh.create_unit_interval(comm, cells, ghost_mode=mesh.GhostMode.shared_facet)
    equispaced_coordinates(msh)  # (stable signatures of the forms on it)
    msh.topology.create_connectivity(0, 1)
    start = mesh.locate_entities_boundary(msh, 0, lambda x: np.isclose(x[0], 0.0))
    end = mesh.locate_entities_boundary(msh, 0, lambda x: np.isclose(x[0], 1.0))
    entities = np.concatenate([start, end]).astype(np.int32)
    values = np.concatenate([np.full(len(start), START), np.full(len(end), END)]).astype(np.int32)
    order = np.argsort(entities)
    tags = mesh.meshtags(msh, 0, entities[order], values[order])
    return SlabMesh(msh, tags, start, end, cells)
