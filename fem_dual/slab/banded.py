"""The factors of a slab's banded Jacobian: Cholesky where it is positive definite (near the
solution), else LU with pivoting, for later solves."""
from __future__ import annotations

import numpy as np
from scipy.linalg import lapack

from fem_dual import native
from fem_dual.native import cholesky as compiled_cholesky

__all__ = ["BandedLU"]


class BandedLU:
    """The factors of a symmetric banded matrix for later solves: Cholesky, which the slab
    Jacobians admit near their solution (positive definite there), else LU with pivoting
    (LAPACK's dgbtrf). The Cholesky factor is in LAPACK's upper band storage (dpbtrf's): the
    compiled one of fem_dual.native (twice the reference LAPACK's speed here) where it is
    available, else dpbtrf.

    Args:
        band: the matrix in dgbtrf's storage with kl = ku = `kd` (band[2 kd + i - j, j]); rows
            kd .. 2 kd of it are dpbtrf's upper storage.
    """

    def __init__(self, band: np.ndarray, kd: int):
        self.kd = kd
        self.piv = None
        self._compiled = native.library() is not None
        if self._compiled:
            upper = np.array(band[kd:2 * kd + 1], dtype=float, order="F")
            info = compiled_cholesky.factor(upper)
            self.cholesky = upper
        else:
            self.cholesky, info = lapack.dpbtrf(band[kd:2 * kd + 1])
        if info != 0:  # not positive definite
            self.cholesky = None
            self.lu, self.piv, info = lapack.dgbtrf(band, kd, kd, overwrite_ab=1)
        self.singular = info != 0

    @classmethod
    def of_cholesky(cls, cholesky: np.ndarray, kd: int) -> "BandedLU":
        """The Cholesky factor computed by fem_dual.native's Newton: upper storage, (kd + 1, N),
        Fortran order."""
        lu = cls.__new__(cls)
        lu.kd, lu.cholesky, lu.piv, lu.singular = kd, cholesky, None, False
        lu._compiled = True
        return lu

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """The solution of A x = rhs, rhs (N,) or (N, columns)."""
        if self.cholesky is not None and self._compiled:
            return self.solve_in_place(np.array(rhs, dtype=float, order="C"))
        if self.cholesky is not None:
            x, info = lapack.dpbtrs(self.cholesky, rhs)
        else:
            x, info = lapack.dgbtrs(self.lu, self.kd, self.kd, rhs, self.piv)
        if info != 0:
            raise ValueError(f"banded solve: illegal argument {-info}")
        return x

    def solve_in_place(self, x: np.ndarray) -> np.ndarray:
        """The solution in x, a C-contiguous float array (N,) or (N, columns) of right-hand
        sides (no copy where the compiled solve runs); returns x."""
        if self.cholesky is None or not self._compiled:
            x[...] = self.solve(x)
            return x
        return compiled_cholesky.solve(self.cholesky, x)
