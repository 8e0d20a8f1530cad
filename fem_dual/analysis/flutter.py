"""Critical follower load of a linear scene, found two independent ways.

(a) eigen: the smallest load P at which an eigenvalue of the first-order system matrix crosses
    into the right half-plane (flutter or divergence);
(b) dual: from dual simulations alone. For each trial P, fem-dual solves the motion over a
    horizon; the growth rate of the recovered motion is read off the motion itself (the
    one-step map z_{k+1} = Phi z_k fitted by least squares to the vertex states a fixed time
    step H apart, sigma = max log|eig Phi| / H), and P is bisected on the sign of sigma.

Both scan P = 0, P0, 2 P0, 4 P0, ... for the first unstable value, then bisect.

Both thresholds are scale-aware. The eigenvalue threshold is relative to the largest |eigenvalue|
at P = 0. The fit of (b) carries its own uncertainty (`GrowthFit.noise`: the least-squares
residual and the run's error estimate, carried to the eigenvalues of Phi through their condition
numbers), and P counts as unstable only when the fitted rate exceeds the threshold (by default
relative to the motion's fastest fitted frequency at P = 0) by more than that uncertainty.

Only the eigenvalues decide that a system is unstable without load (InputError, exit 2). A dual
simulation that cannot resolve growth (a window too short for the motion's time scale, an
under-resolved run whose numerical growth the eigenvalues contradict) or that fails is a
SolveError (exit 3), with what to change.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from typing import Callable, Dict, Optional, Tuple

import numpy as np
import scipy.linalg as sla
from mpi4py import MPI

from fem_dual.config import RunConfig
from fem_dual.integrate.api import run
from fem_dual.errors import InputError, SolveError
from fem_dual.scenes.linear import LinearScene

__all__ = ["GrowthFit", "fit_growth", "growth_rate", "critical_load", "bisect", "eigen_rate",
           "eigen_tolerance", "dual_fit", "dual_rate", "flutter", "DUAL_REL_TOL",
           "EIGEN_REL_TOL", "RESOLVED_GROWTH"]

EIGEN_REL_TOL = 1e-9  # eigen: unstable when max Re(lambda) > this * max |lambda(P = 0)|
DUAL_REL_TOL = 1e-7  # dual (default): growth when sigma - noise > this * fastest frequency
RESOLVED_GROWTH = 0.1  # a fit resolves growth when its uncertainty over the window is below this
_EPS = np.finfo(float).eps


@dataclass(frozen=True)
class GrowthFit:
    """The growth rate of a sampled linear motion and how well the samples determine it.

    rate: max log|eig Phi| / step; noise: its uncertainty (the fitted rate may be this much too
    high or too low); frequency: max |log eig Phi| / step, the fastest rate of the fitted motion
    (aliased if the step exceeds half its period); step: the time between the paired samples;
    window: the time the pairs span; pairs: how many (state, state one step later) pairs."""

    rate: float
    noise: float
    frequency: float
    step: float
    window: float
    pairs: int

    @property
    def resolved(self) -> bool:
        """Whether the uncertainty of the rate, over the window, is below RESOLVED_GROWTH
        (beyond it, growth by 10 % over the window could go unnoticed)."""
        return bool(math.isfinite(self.rate) and math.isfinite(self.noise)
                    and self.noise * self.window <= RESOLVED_GROWTH)

    @property
    def lower(self) -> float:
        """The smallest rate the samples allow (what must exceed a threshold to call it
        growth)."""
        return self.rate - self.noise


def _pairs(t: np.ndarray, candidates: int = 16):
    """(i, j, H): sample pairs t[j] - t[i] = H for the step H that the most pairs share (ties:
    the longer step), among the `candidates` most frequent consecutive steps. The run's vertices
    are not uniform when its slabs differ in length (halved, or shortened at the start)."""
    steps = np.diff(t)
    steps = np.sort(steps[steps > 0])
    if len(steps) == 0:
        return np.zeros(0, int), np.zeros(0, int), 0.0
    # distinct steps, merging those equal to 1e-6 relative (times are sums of slab lengths)
    starts = np.flatnonzero(np.concatenate([[True], np.diff(steps) > 1e-6 * steps[1:]]))
    counts = np.diff(np.concatenate([starts, [len(steps)]]))
    best = (np.zeros(0, int), np.zeros(0, int), 0.0)
    for H in sorted(steps[starts[np.argsort(-counts, kind="stable")[:candidates]]]):
        tol = 1e-6 * H
        i = np.arange(len(t))
        j = np.searchsorted(t, t + H - tol)
        ok = j < len(t)
        i, j = i[ok], j[ok]
        ok = np.abs(t[j] - t[i] - H) <= tol
        if ok.sum() >= len(best[0]):
            best = (i[ok], j[ok], float(H))
    return best


def fit_growth(t: np.ndarray, x: np.ndarray, v: np.ndarray,
               error: Optional[float] = None) -> GrowthFit:
    """Growth rate of a sampled linear motion by a least-squares fit of the map over one step H
    (the step most sample pairs share), with its uncertainty.

    The uncertainty carries the fit's residual (at least round-off) and, given `error` (the
    run's estimated max-norm error of the state), the accumulated discretisation error, to the
    eigenvalues of Phi through their condition numbers; samples that do not span the state space
    (a window too short for the motion, unexcited modes) give an infinite one."""
    t = np.asarray(t, dtype=float)
    z = np.hstack([np.asarray(x, float).reshape(len(t), -1),
                   np.asarray(v, float).reshape(len(t), -1)])
    dim = z.shape[1]
    i, j, H = _pairs(t)
    if len(i) == 0 or not np.isfinite(z).all():
        return GrowthFit(math.nan, math.inf, math.nan, H, 0.0, len(i))
    # Each pair is scaled to a unit start state (z_j = Phi z_i holds for any multiple of a
    # pair: a growing or decaying motion weighs every part of the window alike, and round-off
    # is relative to each pair), then each component to its largest value (a similarity, which
    # leaves the eigenvalues of Phi alone).
    norms = np.linalg.norm(z[i], axis=1)
    use = norms > 0
    i, j, norms = i[use], j[use], norms[use]
    if len(i) == 0:  # at rest
        return GrowthFit(math.nan, math.inf, math.nan, H, 0.0, 0)
    Z0, Z1 = (z[i] / norms[:, None]).T, (z[j] / norms[:, None]).T
    scale = np.abs(Z0).max(axis=1)
    scale[scale == 0] = 1.0
    Z0, Z1 = Z0 / scale[:, None], Z1 / scale[:, None]
    U, S, Vt = np.linalg.svd(Z0, full_matrices=False)
    keep = S > _EPS * S[0] * max(Z0.shape) if S[0] > 0 else S > 0
    Phi = (Z1 @ Vt[keep].T / S[keep]) @ U[:, keep].T
    window = float(t[j].max() - t[i].min())
    mu, left, right = sla.eig(Phi, left=True, right=True)
    modulus = np.abs(mu)
    with np.errstate(divide="ignore"):
        rates = np.log(modulus) / H
        frequencies = np.abs(np.log(mu.astype(complex))) / H
    rate = float(rates.max())
    frequency = float(frequencies[np.isfinite(frequencies)].max(initial=0.0))
    if keep.sum() < dim or len(i) < dim:  # the samples do not determine Phi
        return GrowthFit(rate, math.inf, frequency, H, window, len(i))
    residual = max(np.linalg.norm(Z1 - Phi @ Z0), 16 * _EPS * np.linalg.norm(Z1))
    dPhi = residual / S[-1]
    if error is not None and np.isfinite(error) and window > 0:
        # a relative error e accumulated over the window: each step's map is off by e H / window
        dPhi += float(error / np.abs(z).max()) * H / window
    with np.errstate(divide="ignore"):
        condition = 1.0 / np.abs(np.einsum("ij,ij->j", left.conj(), right))  # unit vectors
    with np.errstate(divide="ignore", invalid="ignore"):
        upper = np.log(modulus + condition * dPhi) / H
    noise = float(np.nanmax(upper) - rate) if np.isfinite(upper).all() else math.inf
    return GrowthFit(rate, max(noise, 0.0), frequency, H, window, len(i))


def growth_rate(t: np.ndarray, x: np.ndarray, v: np.ndarray) -> float:
    """Largest exponential rate of a sampled linear motion, by a least-squares fit of the
    one-step map (fit_growth)."""
    return fit_growth(t, x, v).rate


def critical_load(rate: Callable[[float], float], tol: float, first: float = 0.25,
                  rel_width: float = 1e-5, max_load: float = 1e6) -> float:
    """Smallest P with rate(P) > tol: doubling scan from `first`, then bisection."""
    if rate(0.0) > tol:
        raise InputError("the system is already unstable without load (P = 0)")
    lo, hi = 0.0, first
    while rate(hi) <= tol:
        lo, hi = hi, 2 * hi
        if hi > max_load:
            raise InputError(f"no instability found for P up to {max_load:g}")
    lo, hi = bisect(lambda P: rate(P) > tol, lo, hi, rel_width)
    return 0.5 * (lo + hi)


def bisect(unstable: Callable[[float], bool], lo: float, hi: float,
           rel_width: float) -> Tuple[float, float]:
    """(lo, hi) with lo stable and hi unstable, narrowed from a bracket to rel_width * hi."""
    while hi - lo > rel_width * hi:
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if unstable(mid) else (mid, hi)
    return lo, hi


def _with_load(scene: LinearScene, P: float) -> LinearScene:
    return replace(scene, P=P).checked()


def _eigenvalues(scene: LinearScene, P: float) -> np.ndarray:
    return np.linalg.eigvals(_with_load(scene, P).first_order_matrix())


def eigen_rate(scene: LinearScene) -> Callable[[float], float]:
    return lambda P: float(_eigenvalues(scene, P).real.max())


def eigen_tolerance(scene: LinearScene) -> float:
    """EIGEN_REL_TOL of the largest |eigenvalue| at P = 0, plus the round-off of the eigenvalues
    (1000 eps of the first-order matrix, whose identity block keeps its norm at least 1 however
    slow the motion). An absolute threshold would call a fast system unstable, and find a slow
    one's load too high."""
    A = _with_load(scene, 0.0).first_order_matrix()
    scale = float(np.abs(np.linalg.eigvals(A)).max())
    return EIGEN_REL_TOL * scale + 1000 * _EPS * float(np.linalg.norm(A, 1))


def dual_fit(base: RunConfig, comm: MPI.Comm) -> Callable[[float], GrowthFit]:
    """P -> the growth fit of the dual simulation under load P (each P solved once; rank 0
    fits). A failed simulation is a SolveError naming the load."""
    cache: Dict[float, GrowthFit] = {}

    def fit(P: float) -> GrowthFit:
        if P not in cache:
            try:
                result = run(replace(base, scene=_with_load(base.scene, P)), comm)
            except SolveError as exc:
                raise SolveError(f"the dual simulation at P = {P:.6g} failed: {exc}",
                                 slab=exc.slab) from exc
            # rank 0's fit on every rank: the decisions (and a SolveError) must not differ
            cache[P] = comm.bcast(fit_growth(result.t, result.x, result.v, result.error_estimate)
                                  if comm.rank == 0 else None, root=0)
        return cache[P]
    return fit


def dual_rate(base: RunConfig, comm: MPI.Comm) -> Callable[[float], float]:
    fit = dual_fit(base, comm)
    return lambda P: fit(P).rate


def _advice(base: RunConfig, lam0: np.ndarray) -> str:
    oscillating = np.abs(lam0.imag)[np.abs(lam0.imag) > 0]
    period = (f"the slowest period at P = 0 is {2 * np.pi / oscillating.min():.3g}; "
              if len(oscillating) else "")
    return (f"{period}the window is T = {base.T:.3g}: use a longer --T, or more --cells or "
            "--slabs, or a higher --degree")


def flutter(base: RunConfig, comm: MPI.Comm = MPI.COMM_WORLD,
            tol: Optional[float] = None) -> Dict[str, float]:
    """{eigen, dual, eigen_s, dual_s, dual_tol}: the critical loads, the seconds each search
    took, and the growth-rate threshold of the dual search (`tol` if given, else DUAL_REL_TOL of
    the fastest frequency fitted at P = 0). A continuum (Beck's column) has its own search,
    fem_dual.analysis.continuum_flutter, which reads the motion in its slow modes.

    InputError when the eigenvalues are unstable at P = 0; SolveError when a dual simulation
    fails or cannot resolve the growth (its fit's uncertainty, or growth at P = 0 that the
    eigenvalues contradict)."""
    if not isinstance(base, RunConfig):
        raise InputError(f"base must be a RunConfig (RunConfig.create(...)), not "
                         f"{type(base).__name__}")
    if not isinstance(base.scene, LinearScene) or not hasattr(base.scene, "P"):
        raise InputError(f"flutter needs a linear scene with a load P, not {base.scene.name}")
    if base.scene.continuum:
        raise InputError(f"flutter {base.scene.name}: a continuum's search is "
                         "fem_dual.analysis.continuum_flutter.continuum_flutter")
    tic = time.perf_counter()
    lam0 = _eigenvalues(base.scene, 0.0)
    eig_tol = eigen_tolerance(base.scene)
    if lam0.real.max() > eig_tol:
        raise InputError("the system is already unstable without load (P = 0): an eigenvalue "
                         f"of the first-order system has real part {lam0.real.max():.6g}")
    eigen = critical_load(eigen_rate(base.scene), tol=eig_tol)
    eigen_s = time.perf_counter() - tic
    if not (np.any(base.x0) or np.any(base.v0)):
        raise InputError("flutter needs a start state that moves: with x0 = v0 = 0 the dual "
                         "simulations stay at rest under every load")

    tic = time.perf_counter()
    fit = dual_fit(base, comm)
    zero = fit(0.0)
    if not zero.resolved:
        raise SolveError(
            "the dual simulation cannot resolve growth in this window or at this resolution: at "
            f"P = 0 its fitted growth rate is {zero.rate:.3g} +- {zero.noise:.3g} (the "
            f"eigenvalues are stable, max real part {lam0.real.max():.3g}); " + _advice(base, lam0))
    dual_tol = DUAL_REL_TOL * zero.frequency if tol is None else float(tol)
    if zero.lower > dual_tol:
        raise SolveError(
            "the dual simulation grows without load where the eigenvalues do not (fitted growth "
            f"rate {zero.rate:.3g} +- {zero.noise:.3g} at P = 0, eigenvalues' max real part "
            f"{lam0.real.max():.3g}): numerical growth of an under-resolved run; "
            + _advice(base, lam0))

    bracketed = False  # critical_load scans up from P = 0 until growth, then bisects

    def margin(P: float) -> float:
        """The rate the fit is sure of (its lower bound): above dual_tol means growth. In the
        scan a fit that can decide nothing stops the search (it would walk on to max_load and
        blame the input); in the bisection an undecided fit counts as stable, so the load found
        is the smallest at which the dual simulation is sure of growth."""
        nonlocal bracketed
        found = fit(P)
        if found.lower > dual_tol:
            bracketed = True
        elif not bracketed and not found.resolved:
            raise SolveError(
                f"the dual simulation at P = {P:.6g} cannot resolve growth: fitted rate "
                f"{found.rate:.3g} +- {found.noise:.3g} over the window T = {base.T:.3g}; use a "
                "longer --T, or more --cells or --slabs, or a higher --degree")
        return found.lower

    try:
        dual = critical_load(margin, tol=dual_tol)
    except InputError as exc:  # the eigenvalues found the load: the dual search missed it
        raise SolveError(f"the dual simulations found no growth where the eigenvalues do "
                         f"(P = {eigen:.6g}): {exc}; the start state may not excite the "
                         "unstable mode") from exc
    dual_s = time.perf_counter() - tic
    return {"eigen": eigen, "dual": dual, "eigen_s": eigen_s, "dual_s": dual_s,
            "dual_tol": dual_tol}
