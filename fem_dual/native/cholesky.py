"""Bindings of cholesky.c: the banded Cholesky factorisation in LAPACK's upper band storage
(dpbtrf's, uplo = 'U') and its solves (fem_dual.slab.banded.BandedLU)."""
from __future__ import annotations

import numpy as np

from fem_dual.native import require

__all__ = ["factor", "solve"]


def factor(upper: np.ndarray) -> int:
    """The Cholesky factor U (A = U^T U) in place of `upper`, A's upper band in LAPACK's storage
    (kd + 1, N), Fortran order; returns 0, or j + 1 where column j's pivot is not positive (A
    is not positive definite), as dpbtrf's info."""
    ffi, lib = require()
    if not upper.flags.f_contiguous:
        raise ValueError("the band must be in Fortran order")
    kd = upper.shape[0] - 1
    return lib.fem_dual_band_cholesky(upper.shape[1], kd, ffi.from_buffer("double[]", upper.T),
                                      kd + 1, ffi.from_buffer("double[]", np.empty(kd + 1)))


def solve(cholesky: np.ndarray, x: np.ndarray) -> np.ndarray:
    """x = A^-1 x in place, A = U^T U with U from `factor` ((kd + 1, N), Fortran order), for x
    C-contiguous (N,) or (N, columns); returns x."""
    ffi, lib = require()
    kd, N = cholesky.shape[0] - 1, cholesky.shape[1]
    lib.fem_dual_band_solve(N, kd, ffi.from_buffer("double[]", cholesky.T), kd + 1,
                            x.size // N if N else 0, ffi.from_buffer("double[]", x))
    return x
