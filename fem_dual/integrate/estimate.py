"""The error estimate of a slab, computed from the dual solutions alone (no reference).

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

Errors are weighted by w = atol + rtol * scale, with scale the running maximum of |x| (for
position errors) and of |v| (for velocity errors), as in Hairer-Norsett-Wanner and SUNDIALS. A
slab is accepted when its local error per unit of time, max |l| / w / (dt / T), is at most 1, so
that the local errors of the whole run add up to at most the tolerance
(`fem_dual.integrate.controller` chooses the next length from it).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Optional, Tuple

import numpy as np

from fem_dual import native
from fem_dual.config import ROUNDOFF_REL, RunConfig, Tolerance
from fem_dual.integrate.dense import GAP_ORDER, slab_interpolation_gaps
from fem_dual.quiet import quiet_numpy
from fem_dual.slab.values import VertexValues

__all__ = ["ErrorWeights", "SlabEstimate", "Estimates", "estimate_slabs", "accumulated_floor",
           "carry", "carried_floor",
           "batched", "all_finite", "output_request", "ESTIMATE_SAFETY", "ROUNDOFF_REL"]

# The companion's difference times this: the companion's own error (a factor O(h^2) smaller)
# and its alignment with the answer's make the bare difference 0.9-1.1 times the true error;
# doubled, the estimate sits above it (measured ratios in the README).
ESTIMATE_SAFETY = 2.0


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


def accumulated_floor(floor: np.ndarray, first: int) -> np.ndarray:
    """The round-off floors (slabs, 2) of consecutive slabs, the first being the run's slab
    `first`, as the reported estimate counts them: each slab's state may carry its own floor
    (ROUNDOFF_REL of the scale), which the companion's difference does not see, so after
    k + 1 slabs sqrt(k + 1) of it (independent errors). A linear 3-dof run of 2049 slabs at
    --rtol 1.6e-11 ended 9.2e-12 of its scale off (a mpmath matrix exponential) where one slab's
    floor, reported alone, said 1e-12."""
    return floor * np.sqrt(first + 1.0 + np.arange(len(floor)))[:, None]


def _peaks(part: np.ndarray) -> np.ndarray:
    """max |part| of each slab (part: (slabs, vertices, n))."""
    return np.abs(part).reshape(len(part), -1).max(axis=1, initial=0.0)


@dataclass
class SlabEstimate:
    """The error estimate of one accepted slab (rank 0)."""

    t0: float
    dt: float
    local: np.ndarray  # (vertices, 2n) companion minus answer
    glob: np.ndarray  # (vertices, 2n) propagated global error of the answer
    local_weighted: float  # per unit of time, for the controller
    global_weighted: float
    floor: Tuple[float, float] = (0.0, 0.0)  # round-off floor of x and v errors (one slab's)
    carried: Tuple[float, float] = (0.0, 0.0)  # the floors of the slabs so far, grown (`carry`)


# the share of a slab's floor (ROUNDOFF_REL of the scale) that `carry` grows: a slab's own
# round-off is some 1e-14 of the scale (curl3d from its default start: 7.6e-16 off at t = 1,
# |v| 0.057, in 39 slabs), so a tenth of the floor keeps a tenfold margin, and the carried
# floor overtakes sqrt(k) floors only where perturbations outgrow the motion tenfold
CARRIED_SHARE = 0.1


def carry(covariance: np.ndarray, estimate: SlabEstimate,
          J: Optional[np.ndarray] = None) -> np.ndarray:
    """(2n, 2n): the covariance of the round-off the slabs so far left in the state at this
    slab's end: the previous one carried by the slab map's tangent J (2n, 2n: d z_end / d z0;
    J C J^T, the identity where J was not computed), plus this slab's floor in every component,
    independently. The companion's difference does not see round-off, and sqrt(k) floors
    (`accumulated_floor`) do not follow a motion whose perturbations grow faster than it does:
    curl3d T = 9.3 grows its tangent 9e6-fold, |v| to 2.7e3, and answers of every degree ended
    5e-8 to 1.4e-7 off (DOP853 at 1e-13 and at 2.3e-14 agree to 1.1e-9), 2.8e-11 of the scale
    against sqrt(k) floors of 7.5e-12."""
    n = len(covariance) // 2
    carried = covariance if J is None else J @ covariance @ J.T
    floor = np.repeat(np.asarray(estimate.floor, dtype=float), n) * CARRIED_SHARE
    return carried + np.diag(floor ** 2)


def carried_floor(covariance: np.ndarray) -> Tuple[float, float]:
    """The floors of x's and of v's errors a covariance of round-off gives: the largest
    standard deviation of a component of each."""
    n = len(covariance) // 2
    std = np.sqrt(np.maximum(np.diag(covariance), 0.0))
    return float(std[:n].max(initial=0.0)), float(std[n:].max(initial=0.0))


@dataclass
class Estimates:
    """The error estimates of consecutive slabs (arrays with a leading slab axis)."""

    local: np.ndarray
    glob: np.ndarray
    scales: np.ndarray  # (slabs, 2): the error weights' scales with each slab's motion
    floor: np.ndarray  # (slabs, 2): round-off floor of x and v errors
    err_local: np.ndarray  # weighted local error per unit of time (the controller's)
    err_global: np.ndarray
    finite: np.ndarray  # (slabs,): whether every local and global error is finite
    err_output: Optional[np.ndarray] = None  # weighted interpolation error between vertices

    def slab(self, j: int, t0: float, dt: float) -> SlabEstimate:
        return SlabEstimate(t0, dt, self.local[j], self.glob[j], float(self.err_local[j]),
                            float(self.err_global[j]), tuple(self.floor[j]))


def estimate_slabs(vals: VertexValues, companion: VertexValues, algebraic: Optional[np.ndarray],
               psi: Optional[np.ndarray], lost: Optional[np.ndarray], weights: ErrorWeights,
               dt, T: float, output: Optional[Tuple[Any, int]] = None,
               compiled: bool = True, dropped: Optional[np.ndarray] = None) -> Estimates:
    """The estimates of consecutive slabs (values with a leading slab axis; lost (slabs, 2n)),
    each slab's motion recorded in the weights before the next. `dropped` (slabs, 2n): what the
    zero base dropped before each slab, added to its global error as it is (a dropped mode is
    gone from the answer for good, and no slab map carries it: they drop it again). With
    `output` (the scene and the order 2p of the vertex values), times between the vertices are
    asked for: the interpolation error there (`slab_interpolation_gaps`) must be within the
    tolerance too, and enters the controller's error at the vertices' order (a slab whose gap
    exceeds it is retried shorter, as one whose local error does). In compiled code where it is available
    (fem_dual.native's `estimate`, `compiled`), for finite values and positive weights; the
    numpy below judges the rest."""
    # (the compiled loop judges a damped part per unit of time: runs with one take numpy)
    done = _compiled_estimates(vals, companion, algebraic, psi, lost, weights, dt,
                               T) if compiled and lost is None and dropped is None else None
    if done is not None:
        local, glob, scales, floor, err_local, err_global = done
        finite = np.ones(len(scales), dtype=bool)
        if output is None:
            return Estimates(local, glob, scales, floor, err_local, err_global, finite)
        with quiet_numpy():
            return _with_output(vals, weights, dt, output,
                                Estimates(local, glob, scales, floor, err_local, err_global,
                                           finite))
    local = companion.state() - vals.state()
    if algebraic is not None:  # the answer's own Newton error (the companion's cancels it)
        local += algebraic
    local *= ESTIMATE_SAFETY
    damped = None
    if lost is not None:  # dropped by the zero base: gone from the answer
        damped = np.zeros_like(local)
        damped[:] = lost[:, None, :]  # (dropped at the start: vertex 0 lacks it too)
    scales = weights.running(vals.x, vals.v)
    # local errors at the round-off floor are not resolved: counted as such they would grow per
    # unit of time as slabs shrink and drive the lengths down to the minimum
    floor = ROUNDOFF_REL * scales
    with quiet_numpy():
        # the largest |error| of x's and of v's (slabs, 2), NaN where one is NaN; less the
        # floor, one number per part, that is the largest of max(|l| - floor, 0)
        peak_local = weights.peaks(local)
        err_local = weights.weigh(np.maximum(peak_local - floor, 0.0), scales) / (
            np.asarray(dt) / T)
        if damped is not None:
            # a damped mode is lost once, whatever the slab's length: judged against the
            # tolerance itself, not per unit of time (which would shorten the slabs towards
            # resolving every mode the start state touches)
            peak_damped = weights.peaks(damped)
            err_local = np.maximum(err_local, weights.weigh(np.maximum(peak_damped - floor, 0.0),
                                                            scales))
            local = local + damped
        glob = local if psi is None else local + psi
        if dropped is not None:
            glob = glob + dropped[:, None, :]
        peak_glob = weights.peaks(glob)
        err_global = weights.weigh(peak_glob, scales)
        finite = np.isfinite(peak_local).all(axis=1) & np.isfinite(peak_glob).all(axis=1)
        est = Estimates(local, glob, scales, floor, err_local, err_global, finite)
        return est if output is None else _with_output(vals, weights, dt, output, est)


def _with_output(vals: VertexValues, weights: ErrorWeights, dt, output: Tuple[Any, int],
                 est: Estimates) -> Estimates:
    """`est` with the weighted interpolation error between the vertices (`estimate_slabs`)."""
    scene, order = output
    n = vals.x.shape[-1]
    gaps = np.maximum(slab_interpolation_gaps(scene, vals.s, dt, vals.x, vals.v) - est.floor,
                      0.0)
    est.err_output = weights.norms(np.repeat(gaps, n, axis=1)[:, None, :], est.scales)
    est.err_local = np.maximum(est.err_local, est.err_output ** (order / GAP_ORDER))
    return est


def _compiled_estimates(vals: VertexValues, companion: VertexValues,
                        algebraic: Optional[np.ndarray], psi: Optional[np.ndarray],
                        lost: Optional[np.ndarray], weights: ErrorWeights, dt, T: float):
    """(local, glob, scales, floor, err_local, err_global) of `estimate_slabs` from fem_dual.native's
    `estimate`; None where it is not compiled, or a value is not finite or a weight is not
    positive (the numpy code judges those)."""
    from fem_dual.native.estimate import estimates

    if native.library() is None:
        return None
    z = vals.state()
    if companion.state().shape != z.shape:
        return None
    per_slab = None if np.ndim(dt) == 0 else np.asarray(dt, dtype=float) / T
    tol = weights.tol
    return estimates(z, companion.state(), algebraic, psi, lost, ESTIMATE_SAFETY, ROUNDOFF_REL,
                     tol.atol, tol.rtol, weights.scale_x, weights.scale_v,
                     float(dt) / T if per_slab is None else None, per_slab)


def batched(values: VertexValues) -> VertexValues:
    """One slab's values with a leading slab axis of length 1 (what `estimate_slabs` reads: s, x, v
    and the state; H_d too)."""
    z = values.z
    return VertexValues(values.s, values.x[None], values.v[None], values.hamiltonian[None],
                        z=None if z is None else z[None])


def all_finite(values: VertexValues) -> np.ndarray:
    """Per slab (values with a leading slab axis): whether every value is finite."""
    arrays = [values.x, values.v, values.hamiltonian[..., None]] + [
        a for a in (values.xi, values.eta) if a is not None]
    return np.logical_and.reduce([np.isfinite(a).reshape(len(a), -1).all(axis=1)
                                  for a in arrays])


def output_request(config: RunConfig) -> Optional[Tuple[Any, int]]:
    """What `estimate_slabs` needs to judge the times between vertices, when they are asked for."""
    return None if config.t_eval is None else (config.scene, 2 * config.degree)
