"""Vertex values of slabs and the products that map them (numpy only: modal coordinates and
input checks use them without loading DOLFINx)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

__all__ = ["VertexValues", "times_last"]


@dataclass
class VertexValues:
    """Values at the vertices of one slab, sorted by the reference coordinate s in [0, 1]."""

    s: np.ndarray
    x: np.ndarray  # (vertices, n)
    v: np.ndarray
    hamiltonian: np.ndarray
    xi: Optional[np.ndarray] = None
    eta: Optional[np.ndarray] = None

    def apply(self, f) -> "VertexValues":
        """The values with f applied to each array of vertex values (x, v, H_d and the dual
        fields when present; s kept): f(a) = a[j] picks slab j of batched values, a[None] makes
        one slab a batch."""
        return VertexValues(self.s, f(self.x), f(self.v), f(self.hamiltonian),
                            None if self.xi is None else f(self.xi),
                            None if self.eta is None else f(self.eta))

    def finite(self) -> bool:
        arrays = [self.x, self.v, self.hamiltonian] + [a for a in (self.xi, self.eta)
                                                       if a is not None]
        return bool(np.isfinite(np.concatenate([a.ravel() for a in arrays])).all())


def times_last(a: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """a @ matrix over the last axis of a stack a (..., k), as one BLAS product: numpy's
    matmul of a strided stack loops without BLAS (30x slower for 200 links)."""
    flat = np.ascontiguousarray(a).reshape(-1, a.shape[-1])
    return (flat @ matrix).reshape(*a.shape[:-1], matrix.shape[1])
