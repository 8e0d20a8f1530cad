"""The slab loop's parts: an error estimate for every slab, a step-size controller, and sinks.

Error estimate (computed from the dual solutions alone, no reference):

- The *companion*: the same slab (same start state, cells and length) solved with degree p + 1.
  Its vertex values are far more accurate (order 2p + 2 against 2p), so the difference
  l(s) = z_{p+1}(s) - z_p(s) at the slab's vertices estimates the slab's local error (an embedded
  pair, as in Runge-Kutta-Fehlberg; the answer stays the degree-p one the user asked for).
- The *global* error d(s) of the reported motion is propagated from slab to slab by the tangent
  of the slab map: d(s) = Psi(s) d_start + l(s), where Psi(s) dz is the change of the vertex values
  for a change dz of the start state. A linear slab map is its own tangent (Psi dz is the slab
  solved from dz); a nonlinear one is linearised around the converged Newton solution (one
  residual assembly and one solve with the factored Jacobian). So the estimate follows the
  errors through growth, damping and rotation of the motion, as the true error does.

Step-size control (Hairer-Norsett-Wanner, SUNDIALS): errors are weighted by
w = atol + rtol * scale, with scale the running maximum of |x| (for position errors) and of |v|
(for velocity errors). A slab is accepted when its local error per unit of time,
max |l| / w / (dt / T), is at most 1, so that the local errors of the whole run add up to at most
the tolerance. The next length is the slab's times step_factor(err) (about err^(-1/(2p))),
rounded by meshes.SlabSchedule to a power of two of its unit.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Dict, List, Optional, Tuple

import numpy as np

from fem_dual.quiet import quiet_numpy

__all__ = ["ErrorWeights", "step_factor", "step_factors", "SlabEstimate", "Tolerance", "REFUSE_RELATIVE",
           "VOLUME_TOL", "volume_defect",
           "ACCEPT_GLOBAL", "ESTIMATE_SAFETY", "ROUNDOFF_REL", "initial_fraction",
           "motion_rate", "stalled"]

# Fixed slabs (no --rtol): the acceptance rule. A run whose estimated error exceeds this fraction
# of the motion's scale is refused (exit 3), and a slab whose local error would make it so is
# retried shorter.
REFUSE_RELATIVE = 1e-3
# --rtol: the estimated global error may exceed the tolerance by at most this factor before the
# run is refused (the local errors are controlled; growth of the motion can still amplify them).
ACCEPT_GLOBAL = 10.0
# The companion's difference times this: the companion's own error (a factor O(h^2) smaller)
# and its alignment with the answer's make the bare difference 0.9-1.1 times the true error;
# doubled, the estimate sits above it (measured ratios in the README).
ESTIMATE_SAFETY = 2.0
# The estimate does not resolve errors below this fraction of the motion's scale (round-off of
# the assembled slab systems and of the recovery): it reports at least this much.
ROUNDOFF_REL = 1e-12
# Nonlinear slabs: the flow of x' = v, M v' = F(x) preserves phase-space volume whatever F
# (Liouville: det dz(t)/dz0 = 1; exp(-tr(M^-1 D) t) with damping D), and so does an accurate
# slab map. Where det of the answer's exact slab tangent is off by more than this, the cells do
# not follow the motion, although the companion of degree p + 1 may miss it the same way, so
# that the estimate cannot show it (curl3d near its unstable equilibrium x = (1e3, 0, 0),
# v0 = 1e-9: det - 1 = -1.0 and -0.98 with 8 and 32 cells, estimate 5e-8 against a true error
# of 1e9; slabs that follow the motion measured 1e-13 .. 3e-2, a coarse p = 1 slab of curl2d
# 0.45, a slab of 4 cells through a bump of F narrower than a cell 0.62, its answer still
# within its estimate). A gross failure, not an accuracy test: that is the estimate's.
VOLUME_TOL = 0.5
SAFETY = 0.9
MAX_GROWTH = 4.0
MIN_SHRINK = 0.125


@dataclass(frozen=True)
class Tolerance:
    """What the run must reach: relative and absolute tolerances, and whether the user set them
    (adaptive slab lengths) or they are the acceptance rule of fixed slabs."""

    rtol: float
    atol: float
    adaptive: bool

    @classmethod
    def fixed(cls) -> "Tolerance":
        return cls(REFUSE_RELATIVE, 0.0, False)

    @property
    def label(self) -> str:
        """The tolerance as messages name it."""
        return (f"rtol={self.rtol:g}, atol={self.atol:g}" if self.adaptive
                else f"{self.rtol:g} of the motion's scale")

    @property
    def refuse_factor(self) -> float:
        """How far the weighted global estimate may exceed 1 before the run is refused."""
        return ACCEPT_GLOBAL if self.adaptive else 1.0


class ErrorWeights:
    """w_i = atol + rtol * scale_i; scale = running max of |x| (position components) and |v|
    (velocity components) over the motion so far, starting from the start state and its rate
    (`motion_rate`)."""

    def __init__(self, tol: Tolerance, x0: np.ndarray, v0: np.ndarray, rate: float = 0.0):
        self.tol = tol
        self.n = len(x0)
        nx, nv = float(np.abs(x0).max(initial=0.0)), float(np.abs(v0).max(initial=0.0))
        # the motion's own rate relates the parts from the start: a particle released at rest
        # has |v| ~ rate |x| to come, not the |v| ~ 0 of its first short slab
        self.scale_x = max(nx, nv / rate) if rate > 0 else nx
        self.scale_v = max(nv, rate * nx)

    def _seen(self, x: np.ndarray, v: np.ndarray) -> Tuple[float, float]:
        return (max(self.scale_x, float(np.abs(x).max(initial=0.0))),
                max(self.scale_v, float(np.abs(v).max(initial=0.0))))

    def with_motion(self, x: np.ndarray, v: np.ndarray) -> Tuple[float, float]:
        """The scales including the values (vertices, n) of a slab (not yet recorded). A part
        that has not moved at all (v of an equilibrium) takes the other part's scale: its
        round-off is measured against the size of the state."""
        sx, sv = self._seen(x, v)
        return (sx or sv, sv or sx)

    def record(self, x: np.ndarray, v: np.ndarray) -> None:
        self.scale_x, self.scale_v = self._seen(x, v)

    def running(self, x: np.ndarray, v: np.ndarray) -> np.ndarray:
        """(slabs, 2): `with_motion` of each of consecutive slabs (x, v: (slabs, vertices, n)),
        each recorded before the next."""
        if len(x) == 1:  # one slab (the slab loop's): in floats, where they are finite
            px, pv = float(np.abs(x).max(initial=0.0)), float(np.abs(v).max(initial=0.0))
            if math.isfinite(px) and math.isfinite(pv):
                sx, sv = max(self.scale_x, px), max(self.scale_v, pv)
                return np.array([[sx if sx > 0 else sv, sv if sv > 0 else sx]])
        peaks = np.column_stack([_peaks(x), _peaks(v)])
        peaks[0] = np.maximum(peaks[0], (self.scale_x, self.scale_v))
        seen = np.maximum.accumulate(peaks, axis=0)
        # a part that has not moved at all takes the other part's scale
        return np.where(seen > 0, seen, seen[:, ::-1])

    def norm(self, e: np.ndarray, scales: Tuple[float, float]) -> float:
        """max_i |e_i| / w_i over the rows of e (vertices, 2n); 0 for a zero error."""
        return float(self.norms(e[None], np.array([scales], dtype=float))[0])

    def norms(self, e: np.ndarray, scales: np.ndarray) -> np.ndarray:
        """`norm` of many slabs: e (slabs, vertices, 2n), scales (slabs, 2)."""
        return self.weigh(self.peaks(e), scales)

    def peaks(self, e: np.ndarray) -> np.ndarray:
        """(slabs, 2): max |e| of the x components and of the v components of each slab's
        errors e (slabs, vertices, 2n); NaN where one is NaN."""
        return np.abs(e.reshape(len(e), -1, 2, self.n)).max(axis=(1, 3), initial=0.0)

    def weigh(self, size: np.ndarray, scales: np.ndarray) -> np.ndarray:
        """`norms` from the peaks (slabs, 2) of the errors of x and of v."""
        weight = self.tol.atol + self.tol.rtol * scales
        if weight.min(initial=1.0) > 0:  # (the usual case: a few array calls fewer)
            return (size / weight).max(axis=1)
        ratio = np.divide(size, weight, out=np.zeros_like(size), where=weight > 0)
        ratio[(weight <= 0) & (size > 0)] = np.inf  # an error where nothing may err
        return ratio.max(axis=1)


def _peaks(part: np.ndarray) -> np.ndarray:
    """max |part| of each slab (part: (slabs, vertices, n))."""
    return np.abs(part).reshape(len(part), -1).max(axis=1, initial=0.0)


def step_factor(err: Optional[float], order: int) -> float:
    """Hairer's factor for the next slab length from the weighted error per unit of time
    (err ~ dt^order); a solve that failed (err None) or a non-finite error halves."""
    if err is None or not math.isfinite(err):
        return 0.5 if err is None else MIN_SHRINK
    if not err > 0.0:
        return MAX_GROWTH
    return min(max(SAFETY * err ** (-1.0 / order), MIN_SHRINK), MAX_GROWTH)


def step_factors(err: np.ndarray, order: int) -> np.ndarray:
    """`step_factor` of finite errors, at once."""
    with np.errstate(divide="ignore"):
        grown = SAFETY * np.where(err > 0.0, err, 1.0) ** (-1.0 / order)
    return np.where(err > 0.0, np.clip(grown, MIN_SHRINK, MAX_GROWTH), MAX_GROWTH)


@dataclass
class SlabEstimate:
    """The error estimate of one accepted slab (rank 0)."""

    t0: float
    dt: float
    local: np.ndarray  # (vertices, 2n) companion minus answer
    glob: np.ndarray  # (vertices, 2n) propagated global error of the answer
    local_weighted: float  # per unit of time, for the controller
    global_weighted: float
    floor: Tuple[float, float] = (0.0, 0.0)  # round-off floor of x and v errors

    def reported(self, rows: slice = slice(None)) -> Tuple[np.ndarray, np.ndarray]:
        """Estimated |error| of x and of v per vertex (max over components), at least the
        round-off floor."""
        n = self.glob.shape[1] // 2
        g = np.abs(self.glob[rows])
        return (np.maximum(g[:, :n].max(axis=1), self.floor[0]),
                np.maximum(g[:, n:].max(axis=1), self.floor[1]))

    def record(self) -> Dict[str, Any]:
        ex, ev = self.reported()
        return {"t0": self.t0, "dt": self.dt,
                "local": float(np.abs(self.local).max(initial=0.0)),
                "global": float(max(ex.max(), ev.max())),
                "local_weighted": self.local_weighted, "global_weighted": self.global_weighted}


def initial_fraction(rate: float, T: float, cells: int) -> float:
    """The first adaptive slab's length as a fraction of T: about one radian of the motion per
    cell, from the rate |z'| / |z| at the start (the controller corrects it within a few
    slabs)."""
    if not (rate > 0 and math.isfinite(rate)):
        return 1.0
    return min(1.0, cells / (rate * T))


def motion_rate(x0: np.ndarray, v0: np.ndarray, a0: np.ndarray) -> float:
    """|z'| / |z| of the start state z = (x0, v0), z' = (v0, a0), taken per part so that units
    do not mix: max(|v0| / |x0|, |a0| / |v0|, sqrt(|a0| / |x0|))."""
    nx, nv, na = (float(np.abs(a).max(initial=0.0)) for a in (x0, v0, a0))
    rates = []
    if nx > 0:
        rates += [nv / nx, math.sqrt(na / nx)]
    if nv > 0:
        rates.append(na / nv)
    finite = [r for r in rates if math.isfinite(r)]
    return max(finite) if finite else 0.0


def stalled(history: List[float], floor: float = 0.0) -> bool:
    """Whether a Newton residual history stalled (three or more steps that reduced the residual
    by less than a factor 0.9, counted while it is above the round-off `floor`) before it
    converged: the solution it found may be another branch, and the slab is retried shorter."""
    steps = [b / a for a, b in zip(history[:-1], history[1:]) if a > floor and a > 0]
    return sum(r > 0.9 for r in steps) >= 3


def volume_defect(jacobian: np.ndarray, M: np.ndarray, D: Optional[np.ndarray],
                  dt: float) -> float:
    """|det(jacobian) - exp(-tr(M^-1 D) dt)|: how far a slab map's tangent (2n, 2n) is from
    preserving phase-space volume as the flow of M v' + D v = F(x) does (VOLUME_TOL)."""
    exact = 1.0 if D is None else math.exp(-float(np.trace(np.linalg.solve(M, D))) * dt)
    with quiet_numpy():
        defect = abs(float(np.linalg.det(jacobian)) - exact)
    return defect if math.isfinite(defect) else math.inf

