"""The eigenvalue side of ``fem-dual flutter beck``: frequencies, the flutter load and the
buckling load of a loaded continuum, from dense eigenvalues (small n).

For M q'' + K(P) q = 0 the modes q = x exp(i omega t) solve K(P) x = lambda M x with
lambda = omega^2. While all lambda are real and positive the motion is bounded. As P grows, two
eigenvalues may meet and leave the real axis as a complex pair (flutter: one of the pair gives a
growing oscillation); one may also pass through 0 (divergence, static buckling). The flutter
load is the smallest P at which the spectrum is no longer real.

:func:`flutter_load` scans P = 0, step, 2 step, ... for the first load with a complex pair among
the lowest `count` eigenvalues, then bisects to `tol`; it reports the bracket and
Omega^2 = Re lambda of the pair at its upper end (the flutter frequency squared). A negative
real eigenvalue met first is reported as divergence.

For Beck's column with theta condensed (:class:`fem_dual.continua.condense.CondensedBeck`) the
pencil is taken in flexibility form: with K_c(P) = K_c - P G_P and F = K_c^-1,

    K_c(P) x = lambda M x   <=>   (I - P F G_P) x = lambda F M x,

whose matrices are bounded whatever the mesh (K_c itself grows like h^-4); the eigenvalues are
those of A = (I - P F G_P)^-1 F M, lambda = 1 / mu(A).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np
import scipy.linalg as sla

from fem_dual.continua.condense import CondensedBeck

__all__ = ["FlutterResult", "lowest_eigenvalues", "pencil_eigenvalues", "beck_eigenvalues",
           "frequencies", "flutter_load", "buckling_load", "COMPLEX_RTOL"]

#: an eigenvalue is complex when |Im lambda| > COMPLEX_RTOL |lambda| (LAPACK returns exact zero
#: imaginary parts for the real eigenvalues of a real matrix)
COMPLEX_RTOL = 1e-10


@dataclass(frozen=True)
class FlutterResult:
    """The critical load of :func:`flutter_load`.

    kind: "flutter" (a complex pair) or "divergence" (an eigenvalue <= 0); load: the middle of
    the bracket; bracket: (last real load, first load past it), width <= tol; omega2: at the
    upper end, Re lambda of the complex pair (flutter) or the eigenvalue that crossed 0;
    eigenvalues: the lowest eigenvalues at the upper end; evaluations: eigen-solves done.
    """

    kind: str
    load: float
    bracket: tuple
    omega2: float
    eigenvalues: np.ndarray
    evaluations: int


def lowest_eigenvalues(lam: np.ndarray, count: int) -> np.ndarray:
    """The `count` finite eigenvalues of smallest modulus, in increasing modulus."""
    lam = lam[np.isfinite(lam)]
    return lam[np.argsort(np.abs(lam), kind="stable")][:count]


def pencil_eigenvalues(K: np.ndarray, M: np.ndarray) -> np.ndarray:
    """All eigenvalues of K x = lambda M x (dense QZ; infinite ones, from massless dofs,
    dropped)."""
    lam = sla.eigvals(K, M)
    return lam[np.isfinite(lam)]


def beck_eigenvalues(beck: CondensedBeck, P: float) -> np.ndarray:
    """All eigenvalues lambda = omega^2 of Beck's condensed column at load P, through the
    flexibility form of the module docstring."""
    FG, FM = beck.flexibility_pencil
    A = np.linalg.solve(np.eye(beck.n) - P * FG, FM)
    return 1.0 / np.linalg.eigvals(A)


def frequencies(beck: CondensedBeck, count: int = 2, P: float = 0.0) -> np.ndarray:
    """The lowest `count` circular frequencies omega = sqrt(lambda) at a load P below the
    critical one (at P = 0 the symmetric pencil (M F M, M): F M x = x / lambda)."""
    if P == 0.0:
        mu = sla.eigh(beck.M @ beck.F_el @ beck.M, beck.M, eigvals_only=True)
        lam = np.sort(1.0 / mu[::-1][:count])
    else:
        lam = lowest_eigenvalues(beck_eigenvalues(beck, P), count)
        if np.any(np.abs(lam.imag) > COMPLEX_RTOL * np.abs(lam)) or np.any(lam.real <= 0):
            raise ValueError(f"frequencies: the spectrum at P = {P} is not real and positive")
        lam = lam.real
    return np.sqrt(lam)


def _state(lam: np.ndarray) -> Optional[str]:
    """None while the spectrum is real and positive, else "flutter" or "divergence"."""
    if np.any(np.abs(lam.imag) > COMPLEX_RTOL * np.abs(lam)):
        return "flutter"
    if np.any(lam.real <= 0):
        return "divergence"
    return None


def flutter_load(eigenvalues: Callable[[float], np.ndarray], step: float, P_max: float,
                 tol: float = 1e-9, count: int = 8, start: float = 0.0) -> FlutterResult:
    """The smallest load at which the lowest `count` eigenvalues stop being real and positive.

    Args:
        eigenvalues: P -> the eigenvalues lambda of K(P) x = lambda M x (any order).
        step: the scan's step in P (smaller than the width of any stable window to be found).
        P_max: scan no further (ValueError if the spectrum is still real there).
        tol: the width of the final bracket.
        count: how many of the eigenvalues of smallest modulus are watched.
        start: the scan starts here (its spectrum must be real and positive: a load known to
            be below the critical one, such as a coarser mesh's just below its own).

    Returns:
        The :class:`FlutterResult`.
    """
    calls = 0

    def state(P):
        nonlocal calls
        calls += 1
        lam = lowest_eigenvalues(eigenvalues(P), count)
        return _state(lam), lam

    if state(start)[0] is not None:
        raise ValueError(f"flutter_load: the spectrum is not real and positive at P = {start}")
    lo, hi = start, start + step
    kind, lam = state(hi)
    while kind is None:
        if hi >= P_max:
            raise ValueError(f"flutter_load: the spectrum stays real up to P = {P_max}")
        lo, hi = hi, min(hi + step, P_max)
        kind, lam = state(hi)
    while hi - lo > tol:
        mid = 0.5 * (lo + hi)
        mid_kind, mid_lam = state(mid)
        if mid_kind is None:
            lo = mid
        else:
            hi, kind, lam = mid, mid_kind, mid_lam
    if kind == "flutter":
        pair = lam[np.abs(lam.imag) > COMPLEX_RTOL * np.abs(lam)]
        omega2 = float(pair[0].real)
    else:
        omega2 = float(lam.real[np.argmin(lam.real)])
    return FlutterResult(kind, 0.5 * (lo + hi), (lo, hi), omega2, lam, calls)


def buckling_load(beck: CondensedBeck) -> float:
    """The smallest P > 0 with K_c - P K_g singular (Euler buckling under the dead load): with
    K_g = L L^T (positive definite on the clamped column), 1/P is the largest eigenvalue of
    L^T F L."""
    L = np.linalg.cholesky(beck.K_g)
    mu = np.linalg.eigvalsh(L.T @ beck.F_el @ L)
    return float(1.0 / mu[-1])
