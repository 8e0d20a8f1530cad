"""The slab backend of a large continuum: the sparse, distributed space-time slab
(fem_dual.continua.spacetime) behind the slab-backend protocol (fem_dual.slab.backend).

The scene's spatial system is assembled over the run's communicator (DOLFINx partitions the
mesh); every slab is one preconditioned CG solve on it, with the start state as base state. The
run's state vectors (x, v of the free dofs, on every rank) keep the order of the scene's serial
system, whatever the partition: `FreeOrder` maps between them and each rank's owned free dofs.
No superposition basis (2n solves) and no modal coordinates: both need what only a dense path
holds.
"""
from __future__ import annotations

from typing import Any, Dict, Optional

import numpy as np
from mpi4py import MPI

from fem_dual.continua.dofs import dof_keys
from fem_dual.slab.backend import LinearSlabBackend
from fem_dual.slab.values import VertexValues

__all__ = ["SpaceTimeBackend", "FreeOrder"]


class FreeOrder:
    """The owned free dofs of a distributed SpatialSystem as positions in the serial system's
    free order (matched by coordinates and field component).

    Attributes:
        mine: (n_local,) this rank's owned free dofs' positions in the serial order.
        n: free dofs in all.
    """

    def __init__(self, distributed, serial_coordinates: np.ndarray, serial_field: np.ndarray):
        comm = distributed.comm
        coords = np.asarray(distributed.coordinates, float)
        field = np.asarray(distributed.field)
        self.n = comm.allreduce(len(field), op=MPI.SUM)
        scale = float(np.abs(serial_coordinates).max(initial=1.0))
        lookup = {key: i for i, key in enumerate(dof_keys(serial_coordinates, serial_field,
                                                          scale))}
        try:
            self.mine = np.array([lookup[key] for key in dof_keys(coords, field, scale)],
                                 dtype=np.int64)
        except KeyError:
            raise RuntimeError("the distributed free dofs do not match the serial ones") from None
        if len(lookup) != self.n:
            raise RuntimeError("the serial and distributed systems differ in their free dofs")
        self.comm = comm

    def gather(self, local: np.ndarray) -> Optional[np.ndarray]:
        """(rows, n) in the serial order on rank 0 from every rank's (rows, n_local); None
        elsewhere. Collective."""
        parts = self.comm.gather((self.mine, np.asarray(local)), root=0)
        if parts is None:
            return None
        out = np.empty((np.asarray(local).shape[0], self.n))
        for index, values in parts:
            out[:, index] = values
        return out


class SpaceTimeBackend(LinearSlabBackend):
    """Linear slabs of a large continuum, sparse and distributed (module docstring)."""

    assembly = "spacetime"
    superposes = False

    def __init__(self, scene, degree: int, cells: int, comm: MPI.Comm, prefix: str, petsc,
                 with_dual: bool, mesh: Optional["SpaceTimeBackend"] = None):
        """mesh: the partner whose distributed system and FreeOrder to share, for the same
        scene (the error companion shares the answer's: one assembly, one partition, the same
        order of the rows)."""
        self.degree, self.cells, self.comm = degree, cells, comm
        self.with_dual, self.prefix, self.petsc = with_dual, prefix, dict(petsc or {})
        self.s = np.linspace(0.0, 1.0, cells + 1)
        self.partner = mesh
        self.mesh = self  # (what a companion shares)
        self._build(scene)

    def _build(self, scene) -> None:
        """The distributed system of `scene` (the partner's, if it holds that scene), its
        order and its slab (collective)."""
        from fem_dual.continua.spacetime import SpaceTimeSlab

        self.scene = scene
        partner = self.partner
        self.owns_system = partner is None or partner.scene != scene
        if self.owns_system:
            self.system = scene.distributed_system(self.comm)
            serial = scene.serial_system()
            self.order = FreeOrder(self.system, serial.coordinates, serial.field)
        else:
            self.system, self.order = partner.system, partner.order
        self.slab = SpaceTimeSlab.from_system(self.system, self.degree, self.cells,
                                              self.prefix, options=self.petsc)

    @property
    def num_dofs(self) -> int:
        return self.slab.num_dofs

    @property
    def solves(self) -> int:
        return len(self.slab.iterations)

    def set_scene(self, scene) -> None:
        """Other parameter values: the spatial matrices change, so the slab is built again (a
        companion shares its partner's new system: the partner is set first)."""
        self.close()
        self._build(scene)

    def reset(self, adaptive: bool) -> None:
        self.slab.iterations = []

    def close(self) -> None:
        self.slab.close()
        if self.owns_system:
            self.system.destroy()

    def solve(self, z0, t0, dt, start=None) -> Optional[VertexValues]:
        n, mine = self.scene.n, self.order.mine
        z0 = np.asarray(z0, float)
        self.slab.set_slab(z0[:n][mine], z0[n:][mine], dt)
        # the companion starts from the answer's dual fields (same slab, same base state, the
        # same rows when the spatial system is shared)
        warm = isinstance(start, SpaceTimeBackend) and start.order is self.order
        self.slab.solve(start.slab if warm else None)
        x, v = self.slab.vertex_values()
        xi, eta = self.slab.dual_vertex_values()
        ham = self.comm.allreduce(self._hamiltonian(x, v, xi, eta), op=MPI.SUM)
        parts = [self.order.gather(a) for a in ((x, v, xi, eta) if self.with_dual else (x, v))]
        if self.comm.rank != 0:
            return None
        values = VertexValues(s=self.s, x=parts[0], v=parts[1], hamiltonian=ham)
        if self.with_dual:
            values.xi, values.eta = parts[2], parts[3]
        return values

    def _hamiltonian(self, x, v, xi, eta) -> np.ndarray:
        """This rank's part of H_d = xi.v - eta.(K x + D v) + H(x - xbar, v - vbar) at the
        vertices (H with the energy weights Ke, M)."""
        slab = self.slab
        rows = slab.rows
        force = rows.mult(slab.K, x)
        if slab.D is not None:
            force = force + rows.mult(slab.D, v)
        dx, dv = x - slab.xbar, v - slab.vbar
        return (np.einsum("tj,tj->t", xi, v) - np.einsum("tj,tj->t", eta, force)
                + 0.5 * np.einsum("tj,tj->t", dx, rows.mult(slab.Ke, dx))
                + 0.5 * np.einsum("tj,tj->t", dv, rows.mult(slab.M, dv)))

    def superposition(self, T: float, hamiltonian: bool):
        raise TypeError("the space-time backend solves every slab (no superposition)")

    def record(self, prefix: str) -> Dict[str, Any]:
        return {"kind": "ksp", "prefix": prefix, "ksp_iterations": list(self.slab.iterations),
                "preconditioner": "time modes, spatial AMG (fem_dual.continua.spacetime_pc)"}
