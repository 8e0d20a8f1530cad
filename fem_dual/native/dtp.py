"""Bindings of dtp.c: the pointwise Newton of an implicit DtP map
(fem_dual.slab.pointwise_dtp.PointwiseDtP)."""
from __future__ import annotations

from typing import Tuple

import numpy as np

from fem_dual.native import pointer, require

__all__ = ["dtp_newton"]


def dtp_newton(kernel: int, packed: np.ndarray, xslot: np.ndarray, constants: np.ndarray,
               coords: np.ndarray, max_it: int, last_step: float, out: np.ndarray,
               step: np.ndarray, X: np.ndarray, xdofs: np.ndarray) -> Tuple[int, int]:
    """fem_dual_dtp_newton: Newton on every point from X, stopping after the step at which
    max |step| <= last_step (1 + max |X|); returns (status: 0 converged, 1 a step not finite,
    2 not converged after max_it + 1 evaluations; the last iteration).

    Args:
        kernel: the expression's tabulate_tensor_float64 (G, G_x, t at the points).
        packed: (cells, wsize) its packed rows; X's columns follow every step.
        xslot: (points n,) X's columns in a row.
        constants: the kernel's constants.
        coords: (cells, 6) the cells' coordinate dofs.
        max_it: the last iteration.
        last_step: the relative step after which the iteration stops.
        out: (cells, points (n + n^2 + 1)) the last evaluation (written).
        step: (cells, points, n) the last step (written).
        X: the point function's values (updated in place).
        xdofs: (cells, points) X's block of each point.
    """
    ffi, lib = require()
    cells, points, n = step.shape
    it = ffi.new("int *")
    status = lib.fem_dual_dtp_newton(
        kernel, cells, points, n, packed.shape[1], pointer(ffi, packed),
        pointer(ffi, np.ascontiguousarray(xslot, dtype=np.int64), "int64_t *"),
        pointer(ffi, constants), pointer(ffi, coords), max_it, last_step, pointer(ffi, out),
        pointer(ffi, step), pointer(ffi, X),
        pointer(ffi, np.ascontiguousarray(xdofs, dtype=np.int64), "int64_t *"),
        pointer(ffi, np.empty(n * n)), it)
    return status, it[0]

