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
    # where the sampler made them so (fem_dual.slab.recovery), x and v are views of z (..., vertices,
    # 2n), and every sampled array a view of block (..., vertices, columns: s, x, v, H_d, then
    # xi and eta): one array operation instead of one per part
    z: Optional[np.ndarray] = None
    block: Optional[np.ndarray] = None

    def apply(self, f) -> "VertexValues":
        """The values with f applied to each array of vertex values (x, v, H_d and the dual
        fields when present; s kept): f(a) = a[j] picks slab j of batched values, a[None] makes
        one slab a batch."""
        g = (lambda a: None if a is None else f(a))
        return VertexValues(self.s, f(self.x), f(self.v), f(self.hamiltonian), g(self.xi),
                            g(self.eta), g(self.z), g(self.block))

    def state(self) -> np.ndarray:
        """(..., vertices, 2n): x then v."""
        if self.z is not None:
            return self.z
        return np.concatenate([self.x, self.v], axis=-1)

    def finite(self) -> bool:
        n = self.x.shape[-1]
        if self.block is not None and (self.xi is not None or self.block.shape[-1] == 2 * n + 2):
            return bool(np.isfinite(self.block).all())  # (s is finite)
        arrays = [self.x, self.v, self.hamiltonian] + [a for a in (self.xi, self.eta)
                                                       if a is not None]
        return bool(np.isfinite(np.concatenate([a.ravel() for a in arrays])).all())


def times_last(a: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """a @ matrix over the last axis of a stack a (..., k), as one BLAS product: numpy's
    matmul of a strided stack loops without BLAS (30x slower for 200 links)."""
    flat = np.ascontiguousarray(a).reshape(-1, a.shape[-1])
    return (flat @ matrix).reshape(*a.shape[:-1], matrix.shape[1])
