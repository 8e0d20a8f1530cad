"""The eigenvalue side of ``fem-dual flutter beck``: frequencies, the flutter load and the
buckling load of a loaded continuum, from dense eigenvalues (small n).

For M q'' + K(P) q = 0 the modes q = x exp(i omega t) solve K(P) x = lambda M x with
lambda = omega^2. While all lambda are real and positive the motion is bounded. As P grows, two
eigenvalues may meet and leave the real axis as a complex pair (flutter: one of the pair gives a
growing oscillation); one may also pass through 0 (divergence, static buckling). The flutter
load is the smallest P at which the spectrum is no longer real.

:func:`flutter_load` scans P = 0, step, 2 step, ... for the first load with a complex pair among
the lowest `count` eigenvalues, then narrows the bracket to `tol` by regula falsi (Illinois) on the
discriminant of the two modes about to coalesce, which is linear in P there (a handful of
eigen-solves where bisection takes about 25); it reports the bracket and Omega^2 = Re lambda of the
pair at its upper end (the flutter frequency squared). A negative real eigenvalue met first is
reported as divergence (bisected). Near the load the classification itself is round-off: at 200
elements the lowest eigenvalues read as complex or real within about 5e-8 of it, whatever the
search.

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

    kind, lam = state(start)
    if kind is not None:
        raise ValueError(f"flutter_load: the spectrum is not real and positive at P = {start}")
    lo, hi, lo_lam = start, start + step, lam
    kind, lam = state(hi)
    while kind is None:
        if hi >= P_max:
            raise ValueError(f"flutter_load: the spectrum stays real up to P = {P_max}")
        lo, hi, lo_lam = hi, min(hi + step, P_max), lam
        kind, lam = state(hi)
    centre = _pair_centre(lam)
    d_lo, d_hi, kept = _discriminant(lo_lam, centre), _discriminant(lam, centre), 0
    widths = [hi - lo]
    while hi - lo > tol:
        # a bisection step whenever two trials have not halved the bracket (the closest pair
        # need not be the one that coalesces): never much slower than bisection
        stalled = len(widths) > 2 and widths[-1] > 0.5 * widths[-3]
        mid = 0.5 * (lo + hi) if stalled else _next_load(lo, hi, d_lo, d_hi, tol)
        if not lo < mid < hi:  # tol below the spacing of floats at P: as narrow as it gets
            break
        mid_kind, mid_lam = state(mid)
        d_mid = _discriminant(mid_lam, centre)
        if mid_kind is None:
            lo, d_lo, kept = mid, d_mid, (kept + 1 if kept > 0 else 1)
            if kept > 1 and d_hi is not None:  # the same end kept twice (Illinois): the
                d_hi *= 0.5  # other end's value halves
        else:
            hi, kind, lam, d_hi, kept = mid, mid_kind, mid_lam, d_mid, (
                kept - 1 if kept < 0 else -1)
            if kept < -1 and d_lo is not None:
                d_lo *= 0.5
        widths.append(hi - lo)
    if kind == "flutter":
        pair = lam[np.abs(lam.imag) > COMPLEX_RTOL * np.abs(lam)]
        omega2 = float(pair[0].real)
    else:
        omega2 = float(lam.real[np.argmin(lam.real)])
    return FlutterResult(kind, 0.5 * (lo + hi), (lo, hi), omega2, lam, calls)


def _pair_centre(lam: np.ndarray) -> Optional[float]:
    """Re lambda of the widest complex pair past a flutter load (where the two modes met)."""
    if _state(lam) != "flutter":
        return None
    return float(lam.real[np.argmax(np.abs(lam.imag))])


def _discriminant(lam: np.ndarray, centre: Optional[float]) -> Optional[float]:
    """(lambda_a - lambda_b)^2 of the two modes about to coalesce, relative to their size:
    positive while the spectrum is real (the two neighbours whose mean is closest to `centre`,
    where the pair met, else the closest two), negative past a flutter load (the widest complex
    pair), linear in P through the coalescence (lambda has a square-root branch point there);
    None where an eigenvalue has crossed 0 (divergence)."""
    if len(lam) < 2 or _state(lam) == "divergence":
        return None
    size = float(np.abs(lam).max())
    if _state(lam) == "flutter":
        return -float((2 * np.abs(lam.imag)).max() / size) ** 2
    real = np.sort(lam.real)
    gaps = np.diff(real)
    k = (int(np.argmin(np.abs(0.5 * (real[1:] + real[:-1]) - centre))) if centre is not None
         else int(np.argmin(gaps)))
    return float(gaps[k] / size) ** 2


def _next_load(lo: float, hi: float, d_lo, d_hi, tol: float) -> float:
    """The next trial load in (lo, hi): where the discriminant, linear between the ends,
    vanishes (regula falsi, whose end values the caller halves when one end is kept twice:
    Illinois), else the middle; at least tol / 4 inside the bracket, so that a trial next to
    the load found closes the bracket on it."""
    if d_lo is None or d_hi is None or not d_lo > 0 > d_hi:
        return 0.5 * (lo + hi)
    trial = lo + (hi - lo) * d_lo / (d_lo - d_hi)
    return min(max(trial, lo + 0.25 * tol), hi - 0.25 * tol)


def buckling_load(beck: CondensedBeck) -> float:
    """The smallest P > 0 with K_c - P K_g singular (Euler buckling under the dead load): with
    K_g = L L^T (positive definite on the clamped column), 1/P is the largest eigenvalue of
    L^T F L."""
    L = np.linalg.cholesky(beck.K_g)
    mu = np.linalg.eigvalsh(L.T @ beck.F_el @ L)
    return float(1.0 / mu[-1])
