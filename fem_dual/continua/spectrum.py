"""Is the spectrum of a spatial system real? The eigenvalues lambda of K x = lambda M x
(lambda = omega^2 of M q'' + K q = 0) of a :class:`~fem_dual.continua.system.SpatialSystem`.

What :func:`spectrum_check` checks depends on the size:

* n <= ``dense_limit`` ("dense"): *all* n eigenvalues, by dense QZ on the gathered M, K. The
  answer is exact up to round-off: an eigenvalue counts as complex when
  |Im lambda| > rtol max|lambda| (QZ's backward error is of order eps max|lambda|; a double
  eigenvalue of a symmetric problem may split into a pair that far off the axis). A defective
  eigenvalue (a Jordan block: Cauchy elasticity at delta = lam + mu exactly) moves by the
  square root of that and may be reported as a complex pair of |Im| ~ 1e-9 max|lambda|.
* n > ``dense_limit`` ("slepc"): only the `nev` eigenvalues nearest 0, by SLEPc's Krylov-Schur
  with shift-and-invert at target 0 (LU: PETSc's own in serial, MUMPS in parallel), and the same
  test on them. This is a check of the low spectrum only; it does not prove the rest real. For
  the clamped Cauchy square a proof covers all of it:
  :func:`fem_dual.continua.cauchy.real_spectrum_guaranteed` (|delta| <= lam + mu).

SLEPc options are set under the prefix ``continua_spectrum_`` while the solver is set up, and
may be overridden there (``-continua_spectrum_eps_nev 40``).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Optional

import numpy as np
import scipy.linalg as sla
from slepc4py import SLEPc

from fem_dual.compat import destroy_petsc
from fem_dual.continua.system import DENSE_LIMIT, SpatialSystem
from fem_dual.errors import SolveError
from fem_dual.slab.petsc_solvers import petsc_options

__all__ = ["SpectrumCheck", "spectrum_check", "REAL_RTOL", "PREFIX"]

REAL_RTOL = 1e-9
PREFIX = "continua_spectrum_"


@dataclass(frozen=True)
class SpectrumCheck:
    """The verdict of :func:`spectrum_check`.

    method: "dense" (all eigenvalues) or "slepc" (those nearest 0); n: free dofs; checked: how
    many eigenvalues were examined; real: none of them complex; positive: all Re lambda > 0;
    complex_count: how many are complex; max_imag: max |Im lambda| / max |lambda|;
    lowest: up to 20 examined eigenvalues of smallest modulus.
    """

    method: str
    n: int
    checked: int
    real: bool
    positive: bool
    complex_count: int
    max_imag: float
    lowest: np.ndarray

    @property
    def stable(self) -> bool:
        """Real and positive: neither flutter nor divergence among the examined eigenvalues."""
        return self.real and self.positive


def _verdict(method: str, n: int, lam: np.ndarray, rtol: float) -> SpectrumCheck:
    scale = np.abs(lam).max()
    complex_ = np.abs(lam.imag) > rtol * scale
    order = np.argsort(np.abs(lam), kind="stable")
    return SpectrumCheck(method, n, lam.size, not np.any(complex_), bool(np.all(lam.real > 0)),
                         int(np.count_nonzero(complex_)), float(np.abs(lam.imag).max() / scale),
                         lam[order][:20])


def _slepc_lowest(system: SpatialSystem, nev: int,
                  options: Optional[Mapping[str, str]]) -> np.ndarray:
    """The eigenvalues nearest 0 of K x = lambda M x, by shift-and-invert Krylov-Schur."""
    defaults = {"eps_nev": str(nev), "eps_target": "0", "eps_target_magnitude": "",
                "eps_type": "krylovschur", "st_type": "sinvert", "st_ksp_type": "preonly",
                "st_pc_type": "lu",
                "st_pc_factor_mat_solver_type": "petsc" if system.comm.size == 1 else "mumps"}
    eps = SLEPc.EPS().create(system.comm)
    try:
        eps.setOperators(system.K, system.M)
        eps.setProblemType(SLEPc.EPS.ProblemType.GNHEP)
        eps.setOptionsPrefix(PREFIX)
        with petsc_options(PREFIX, defaults, options):
            eps.setFromOptions()
            eps.solve()
        count = eps.getConverged()
        if count < 1:
            raise SolveError("spectrum_check: SLEPc converged no eigenvalue near 0")
        return np.array([eps.getEigenvalue(i) for i in range(count)], dtype=complex)
    finally:
        destroy_petsc(eps)


def spectrum_check(system: SpatialSystem, dense_limit: int = DENSE_LIMIT, nev: int = 20,
                   rtol: float = REAL_RTOL,
                   options: Optional[Mapping[str, str]] = None) -> SpectrumCheck:
    """Whether the eigenvalues of K x = lambda M x are real and positive (see the module
    docstring for what is examined at which size). Collective; the verdict on every rank.

    Args:
        system: M and K (D is ignored: the check is of the undamped pencil).
        dense_limit: up to this many free dofs every eigenvalue is computed densely.
        nev: beyond it, how many eigenvalues nearest 0 SLEPc computes.
        rtol: |Im lambda| > rtol max|lambda| counts as complex.
        options: SLEPc/PETSc options (without the prefix) over the defaults.
    """
    if system.n <= dense_limit:
        M, K, _ = system.dense(limit=dense_limit)
        lam = sla.eigvals(K, M)
        return _verdict("dense", system.n, lam[np.isfinite(lam)], rtol)
    return _verdict("slepc", system.n, _slepc_lowest(system, nev, options), rtol)
