"""Bindings of tangents.c: the exact tangents of a solved slab after their banded solve
(fem_dual.slab.local_action.LocalAction._tangent_matrix's compiled twin)."""
from __future__ import annotations

import numpy as np

from fem_dual.native import pointer, require

__all__ = ["Tangents"]


class Tangents:
    """fem_dual_tangents for one slab: from the solved unknowns dw (`dw`: the right-hand sides,
    solved in place by the caller, (N + 1, 2n + 1), the last row zero for the fixed unknowns)
    through the density's Hessian in `out` to the change of the momenta at the cell ends,
    dm (cells, 2, 2n, 2n + 1), the velocity rows times M^-1.

    Args:
        T: (cells, nq, 2, nd) the basis values and derivatives at the points.
        Tg: (cells, nd, nq 2) the weighted basis table of the residual.
        cols, pk, pl: the Hessian pairs' columns of an evaluation and their (row, column).
        rows: (cells, nd, bs) the row of each cell unknown (N for a fixed one).
        N: the free unknowns.
        sign: (cells, 2) the cell ends' orientation.
        out: (cells, nq, columns) the evaluation every call reads.
        n: the dimension of x.
    """

    def __init__(self, T: np.ndarray, Tg: np.ndarray, cols: np.ndarray, pk: np.ndarray,
                 pl: np.ndarray, rows: np.ndarray, N: int, sign: np.ndarray, out: np.ndarray,
                 n: int):
        ffi, self._lib = require()
        self._ffi = ffi
        self.cells, self.nq, _, self.nd = T.shape
        self.bs, self.n, self.ncols = rows.shape[2], n, out.shape[2]
        arrays = [np.ascontiguousarray(a, dtype=dtype) for a, dtype in (
            (T, float), (Tg, float), (cols, np.int64), (pk, np.int64), (pl, np.int64),
            (rows, np.int64), (sign, float))]
        self.pairs = len(arrays[2])
        self._fixed = [pointer(ffi, a) for a in arrays]  # (each keeps its array alive)
        # its right-hand sides (solved in place), its output and work, reused by every call
        K1 = 2 * n + 1
        self.dw = np.empty((N + 1, K1))
        self.dm = np.empty((self.cells, 2, 2 * n, K1))
        self._buffers = tuple(pointer(ffi, a) for a in (out, self.dw, self.dm,
                                                        np.empty(4 * self.bs * K1)))
        self._minv = None

    def use_mass_inverse(self, Minv: np.ndarray) -> None:
        """M^-1 (n, n), C-contiguous, for the next calls (kept while it is in use)."""
        self._minv = (Minv, self._ffi.from_buffer("double[]", Minv))

    def __call__(self) -> np.ndarray:
        """dm from the solved `dw` and the evaluation (see the class); returns dm, the
        binding's own array (the next call overwrites it)."""
        T, Tg, cols, pk, pl, rows, sign = self._fixed
        out, dw, dm, work = self._buffers
        self._lib.fem_dual_tangents(self.cells, self.nq, self.nd, self.bs, self.n,
                                    self.dw.shape[1], T, Tg, out, self.ncols, self.pairs, cols,
                                    pk, pl, dw, rows, sign, self._minv[1], dm, work)
        return self.dm
