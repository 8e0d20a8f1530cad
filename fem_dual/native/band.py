"""Bindings of band.c: a slab Jacobian's band from the density's Hessian at the quadrature points
(fem_dual.slab.local_action.LocalAction._band's compiled twin)."""
from __future__ import annotations

from typing import Sequence

import numpy as np

from fem_dual.native import pointer, require

__all__ = ["Band", "MAX_BASIS_PAIRS"]

MAX_BASIS_PAIRS = 1024  # nd^2 at most: the loop's sums for one Hessian pair are on its stack


class Band:
    """fem_dual_band for one slab's pattern: B[group start + (ab cells + e) members + m - lo] =
    sum_q P_g[ab, q] out[e, q, cols[m]] scale[e, m] for the Hessian pairs m of each group g
    (lo[g] .. hi[g] - 1), then band[flat[k]] += B[source[k]].

    Args:
        cols: (pairs,) the Hessian pairs' columns of an evaluation.
        scale: (cells, pairs) each cell's factor of its group's table.
        lo, hi, start: (groups,) each group's pairs and where its products start in B.
        PT: (groups, nq, nd^2) each group's basis table, transposed.
        flat, source: the band's entries and the products they sum.
        total: the size of B.
    """

    def __init__(self, cols: np.ndarray, scale: np.ndarray, lo: Sequence[int],
                 hi: Sequence[int], start: Sequence[int], PT: np.ndarray, flat: np.ndarray,
                 source: np.ndarray, total: int):
        ffi, self._lib = require()
        self._ffi = ffi
        ints = [np.ascontiguousarray(a, dtype=np.int64) for a in (cols, lo, hi, start, flat,
                                                                  source)]
        cols, lo, hi, start, flat, source = ints
        PT = np.ascontiguousarray(PT, dtype=float)
        if PT.shape[2] > MAX_BASIS_PAIRS:
            raise ValueError(f"at most {MAX_BASIS_PAIRS} products of basis functions a cell")
        self.pairs, self.groups, self.nd2, self.entries = len(cols), len(lo), PT.shape[2], \
            len(flat)
        self.B = np.empty(total)  # the products, one buffer for every call
        # C pointers of what every call reads (each keeps its array alive); the compiled
        # Newton (fem_dual.native.newton) reads them too
        self._pointers = {name: pointer(ffi, a) for name, a in (
            ("cols", cols), ("lo", lo), ("hi", hi), ("start", start), ("flat", flat),
            ("source", source))}
        self._pointers.update(scale=pointer(ffi, np.ascontiguousarray(scale, dtype=float)),
                              PT=pointer(ffi, PT), B=pointer(ffi, self.B))

    def __call__(self, out: np.ndarray, band: np.ndarray) -> np.ndarray:
        """The band (C-contiguous, filled) from an evaluation `out` (cells, nq, columns),
        C-contiguous; returns band."""
        d = self._pointers
        self._lib.fem_dual_band(out.shape[0], out.shape[1], out.shape[2],
                                self._ffi.from_buffer("double[]", out), self.pairs, d["cols"],
                                d["scale"], self.groups, d["lo"], d["hi"], d["start"], d["PT"],
                                self.nd2, self.entries, d["flat"], d["source"], d["B"],
                                self._ffi.from_buffer("double[]", band), band.size)
        return band
