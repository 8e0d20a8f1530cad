"""Bindings of dtp.c: the pointwise Newton of an implicit DtP map
(fem_dual.slab.pointwise_dtp.PointwiseDtP), alone (`dtp_newton`) or inside a slab's compiled
Newton (`DtpMap`, its fem_dual_dtp struct)."""
from __future__ import annotations

from typing import Tuple

import numpy as np

from fem_dual.native import pointer, require

__all__ = ["dtp_newton", "DtpMap"]


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
        pointer(ffi, np.ascontiguousarray(xslot, dtype=np.int64)),
        pointer(ffi, constants), pointer(ffi, coords), max_it, last_step, pointer(ffi, out),
        pointer(ffi, step), pointer(ffi, X),
        pointer(ffi, np.ascontiguousarray(xdofs, dtype=np.int64)),
        pointer(ffi, np.empty(n * n)), it)
    return status, it[0]


class DtpMap:
    """The fem_dual_dtp struct of an implicit DtP map solved inside each evaluation of a slab's
    compiled Newton (fem_dual.native.newton): the map's packed rows, where the dual state, X
    and G_x^-1 sit in them and in the density's rows, and its Newton's settings.

    Args:
        kernel: the map's expression's tabulate_tensor_float64.
        n: the dimension of X at a point.
        packed: (cells, wsize) the map's packed rows.
        coords: (cells, 6) the cells' coordinate dofs.
        X, Ginv: the values of the point functions X and G_x^-1 (updated in place).
        index: int arrays: wfree, wslot ((cells, nw): each dual state column's free unknown,
            -1 for none, and its column in the map's row), xslot (X's columns there), xdofs
            ((cells, points): X's blocks), both_xslot, both_xindex, both_gslot, both_gindex
            (X's and G_x^-1's columns in the density's row and where their values come from).
        max_it, last_step, branch_tol: the pointwise Newton's and the branch test's settings.
    """

    def __init__(self, kernel: int, n: int, packed: np.ndarray, coords: np.ndarray,
                 X: np.ndarray, Ginv: np.ndarray, index: dict, max_it: int, last_step: float,
                 branch_tol: float):
        ffi, _ = require()
        self._ffi = ffi
        kept = {k: np.ascontiguousarray(a, dtype=np.int64) for k, a in index.items()}
        cells, points = kept["xdofs"].shape
        kept.update(out=np.zeros(cells * points * (n + n * n + 1)),
                    step=np.zeros(cells * points * n), work=np.zeros(2 * n * n))
        D = self.struct = ffi.new("fem_dual_dtp *")
        D.kernel, D.points, D.n, D.wsize = kernel, points, n, packed.shape[1]
        D.nw, D.max_it, D.last_step, D.branch_tol = kept["wfree"].shape[1], max_it, last_step, \
            branch_tol
        D.nx, D.ng = len(kept["both_xslot"]), len(kept["both_gslot"])
        self._pointers = {}  # (each keeps its array alive while the struct points to it)
        for name, array in list(kept.items()) + [("packed", packed), ("coords", coords),
                                                 ("X", X), ("Ginv", Ginv)]:
            self._pointers[name] = p = pointer(ffi, array)
            setattr(D, name, p)
        self._constants = None

    def use_constants(self, constants: np.ndarray) -> None:
        """The map's kernel constants for the next solves (kept while they are in use)."""
        self._constants = constants
        self.struct.c = self._ffi.from_buffer("double[]", constants)

    @property
    def iterations(self) -> int:
        """The last pointwise Newton's last iteration."""
        return self.struct.iterations
