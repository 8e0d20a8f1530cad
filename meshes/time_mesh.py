"""The time mesh of one slab and the partition of [0, T] into slabs.

Every slab is solved on the same reference mesh of s in [0, 1], with physical time
t = t0 + dt * s; the slab length dt is a `fem.Constant` in the forms, so slabs of any length reuse
one compiled form (and, for linear scenes with equal slabs, one factored matrix).
"""
from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Tuple

import numpy as np
from dolfinx import mesh
from mpi4py import MPI

__all__ = ["START", "END", "SlabMesh", "SlabSchedule", "slab_mesh"]

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
    msh.topology.create_connectivity(0, 1)
    start = mesh.locate_entities_boundary(msh, 0, lambda x: np.isclose(x[0], 0.0))
    end = mesh.locate_entities_boundary(msh, 0, lambda x: np.isclose(x[0], 1.0))
    entities = np.concatenate([start, end]).astype(np.int32)
    values = np.concatenate([np.full(len(start), START), np.full(len(end), END)]).astype(np.int32)
    order = np.argsort(entities)
    tags = mesh.meshtags(msh, 0, entities[order], values[order])
    return SlabMesh(msh, tags, start, end, cells)


FIRST_PATIENCE = 4  # slabs a rejected length is not tried again, after its first rejection
MAX_PATIENCE = 256  # ... doubled after each repeated rejection up to this


class SlabSchedule:
    """Slabs of [0, T]: nominally `slabs` equal ones, each cut at most `max_halvings` times
    (minimum length T / (slabs 2^max_halvings)). Lengths are powers of two of that minimum, so
    equal lengths recur (linear scenes reuse their slab maps); a slab grows back after a success
    by the factor its caller allows, never beyond the nominal length, and only to a length its
    start position is a multiple of (so the end of [0, T] is met without an odd last slab).

    A rejected length is remembered (`ceiling`): the slabs grow back to it only after `wait`
    accepted slabs, a wait that doubles each time the same length is rejected again (up to
    MAX_PATIENCE) and halves when it passes. Without it an error just above the tolerance at
    one length and well below it at half that length made every other attempt a rejection.

    Positions are kept as integers in units of the minimum length, so start times carry no
    accumulated round-off and equal slabs start exactly at k T / slabs.

    Args:
        T: horizon.
        slabs: number of nominal slabs.
        max_halvings: how often a nominal slab may be halved.
        first: the first slab's length as a fraction of the nominal one (rounded down to a
            power of two).
        shrinks: whether an accepted slab's factor below 1 shortens the next one (lengths
            chosen by a tolerance); fixed slabs keep their length until one is rejected (a slab
            accepted close to the tolerance made two half slabs every few dozen slabs).
    """

    STATE_SIZE = 5  # len(state)

    def __init__(self, T: float, slabs: int, max_halvings: int = 0, first: float = 1.0,
                 shrinks: bool = True):
        self.T, self.shrinks = T, shrinks
        self.nominal = 2**max_halvings
        self.total = slabs * self.nominal
        self.pos = 0
        self.length = self._power_of_two_at_most(self.nominal * min(max(first, 0.0), 1.0))
        self.ceiling = 0  # units; 0: no rejected length to keep below
        self.wait = 0  # accepted slabs before the ceiling may be tried again
        self.patience = 0  # the wait after the next rejection at the ceiling (halved)

    @property
    def state(self) -> Tuple[int, int, int, int, int]:
        """Everything `accept` and `halve` depend on (a resumed run restores it)."""
        return (self.pos, self.length, self.ceiling, self.wait, self.patience)

    @state.setter
    def state(self, value) -> None:
        self.pos, self.length, self.ceiling, self.wait, self.patience = (int(a) for a in value)

    def _power_of_two_at_most(self, units: float) -> int:
        units = min(max(units, 1.0), float(self.nominal))
        return 1 << int(math.floor(math.log2(units)))

    def done(self) -> bool:
        return self.pos >= self.total

    def current(self) -> Tuple[float, float]:
        """(t0, dt) of the slab to solve next."""
        length = min(self.length, self.total - self.pos)
        return self.pos * self.T / self.total, length * self.T / self.total

    def accept(self, factor: float = 2.0) -> None:
        """Advance past the current slab; the next one is at most `factor` times as long."""
        self.pos += min(self.length, self.total - self.pos)
        length = self._power_of_two_at_most(self.length * (factor if self.shrinks
                                                          else max(factor, 1.0)))
        if self.ceiling and self.length >= self.ceiling:  # the rejected length passed now
            self.ceiling, self.patience = 0, self.patience // 2
        elif self.ceiling:
            self.wait = max(self.wait - 1, 0)
            if self.wait:
                length = min(length, self.ceiling // 2)
        while length > 1 and self.pos % length:
            length //= 2
        self.length = length

    def accept_each(self, factors) -> np.ndarray:
        """`accept_run` slab by slab (its states; what the vectorised path must equal)."""
        states = []
        for factor in factors:
            length = self.length
            self.accept(float(factor))
            states.append(self.state)
            if self.length != length:
                break
        return np.array(states, dtype=np.int64).reshape(-1, self.STATE_SIZE)

    def accept_run(self, factors) -> np.ndarray:
        """`accept` slab after slab with the step factors `factors`, stopping after the first
        slab whose factor changes the length; returns the state after each accepted slab
        ((slabs, STATE_SIZE) integers).
        Vectorised where no rejected length is remembered (a chunk of hundreds of equal slabs
        of a linear scene took a millisecond slab by slab); the same states as `accept`."""
        factors = np.asarray(factors, dtype=float)
        if self.ceiling or not len(factors):
            return self.accept_each(factors)
        k = np.arange(1, len(factors) + 1)
        length = self.length
        pos = np.minimum(self.pos + k * length, self.total)  # (the last slab may be short)
        scaled = length * (factors if self.shrinks else np.maximum(factors, 1.0))
        with np.errstate(divide="ignore", invalid="ignore"):
            units = np.clip(np.nan_to_num(scaled, nan=1.0), 1.0, float(self.nominal))
            candidate = np.left_shift(1, np.floor(np.log2(units)).astype(np.int64))
        lowest = pos & -pos  # the largest power of two dividing pos (pos > 0)
        candidate = np.maximum(np.minimum(candidate, np.where(pos > 0, lowest, candidate)), 1)
        changed = np.flatnonzero(candidate != length)
        count = int(changed[0]) + 1 if len(changed) else len(factors)
        self.pos, self.length = int(pos[count - 1]), int(candidate[count - 1])
        states = np.empty((count, self.STATE_SIZE), dtype=np.int64)
        states[:, 0], states[:, 1] = pos[:count], candidate[:count]
        states[:, 2:] = (0, self.wait, self.patience)
        return states

    def halve(self, factor: float = 0.5) -> bool:
        """Shorten the current slab to at most `factor` (at most 1/2) of its length; False when
        it is already at the minimum length."""
        if self.length == 1:
            return False
        if self.length == self.ceiling:  # rejected again after the wait: wait longer
            self.patience = min(2 * self.patience, MAX_PATIENCE)
        else:
            self.patience = max(self.patience, FIRST_PATIENCE)
        self.ceiling, self.wait = self.length, self.patience
        self.length = self._power_of_two_at_most(self.length * min(factor, 0.5))
        return True
