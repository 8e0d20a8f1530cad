"""Judging a solved slab: accept it, retry it shorter, or refuse the run.

Rank 0 judges (its estimate, the guards below); every rank learns the verdict in one broadcast
(`judged`), so a failure on rank 0 ends the run on every rank instead of leaving them waiting
in the next collective. The guards catch what an error estimate cannot see: a linear slab that
turns more radians per cell than its degree follows (`check_resolution`), a linear motion that
outgrows the exact flow's bound (`GrowthBound`), a nonlinear slab map that does not keep
phase-space volume (`volume_kept`).
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any, Callable, NamedTuple, Optional, Tuple

import numpy as np
from mpi4py import MPI

from fem_dual.errors import SolveError
from fem_dual.integrate.estimate import ErrorWeights, SlabEstimate, batched, estimate_slabs
from fem_dual.mpi import bcast, on_root
from fem_dual.quiet import quiet_numpy
from fem_dual.slab.values import VertexValues

if TYPE_CHECKING:
    from fem_dual.integrate.simulation import Simulation

__all__ = ["Verdict", "judge", "judged", "volume_kept", "check_resolution", "GrowthBound",
           "volume_defect", "VOLUME_TOL"]

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


def volume_defect(jacobian: np.ndarray, M: np.ndarray, D: Optional[np.ndarray],
                  dt: float) -> float:
    """|det(jacobian) - exp(-tr(M^-1 D) dt)|: how far a slab map's tangent (2n, 2n) is from
    preserving phase-space volume as the flow of M v' + D v = F(x) does (VOLUME_TOL)."""
    exact = 1.0 if D is None else math.exp(-float(np.trace(np.linalg.solve(M, D))) * dt)
    with quiet_numpy():
        defect = abs(float(np.linalg.det(jacobian)) - exact)
    return defect if math.isfinite(defect) else math.inf


class Verdict(NamedTuple):
    """What becomes of a solved slab: `action` "accept", "retry" (shorter), "refuse" (the run
    cannot vouch for its answer) or "error" (the run ends); `err` the weighted local error per
    unit of time (the controller's, None where the slab was not estimated), `reason` why not
    accepted, `estimate` the slab's error estimate (rank 0 only), `solver` whether the slab's
    solve itself failed, `tangent` the slab map's tangent where the volume check computed it
    (rank 0 only: the round-off it carries on, fem_dual.integrate.estimate.carry)."""

    action: str
    err: Optional[float]
    reason: str
    estimate: Optional[SlabEstimate] = None
    solver: bool = False
    tangent: Optional[np.ndarray] = None


def check_resolution(rate: Optional[float], dt: float, cells: int, degree: int) -> None:
    """SolveError when a time cell spans more radians of the fastest mode (`rate`, known for
    linear scenes, else None) than the degree can follow (rate * h > p): the answer would be
    noise, however well solved."""
    h = dt / cells
    if rate is not None and rate * h > degree:
        factor = rate * h / degree
        times = f"{math.ceil(factor)}" if factor < 1e6 else f"{factor:.3g}"
        raise SolveError(f"under-resolved: the fastest mode (|lambda| = {rate:.4g}) turns "
                         f"{rate * h:.3g} radians per time cell, more than degree {degree} can "
                         f"follow; use {times}x more slabs or cells per slab, or a higher "
                         "degree")


class GrowthBound:
    """|z(t)| <= kappa(U) exp(sigma t) |z0| for z' = A z with A = U diag(lambda) U^-1: a linear
    motion that outgrows this (by a factor 10) is noise amplified by the slab map in modes the
    slabs do not resolve."""

    def __init__(self, scene, x0: np.ndarray, v0: np.ndarray):
        lam, U = scene.spectrum
        self.sigma = float(lam.real.max())
        self.kappa = float(np.linalg.cond(U))
        z0 = np.concatenate([x0, v0])
        scale = float(np.abs(z0).max(initial=0.0))  # scaled: |z0| = 1e-200 does not underflow
        self.z0 = scale * float(np.linalg.norm(z0 / scale)) if scale > 0 else 0.0

    def allows(self, t, values: VertexValues):
        """Whether the slab ending at t stays within the bound; of many slabs (t: (slabs,),
        values with a leading slab axis) at once."""
        # max norm <= 2-norm: the bound holds for it, and it does not underflow at 1e-160
        z = np.maximum(np.abs(values.x).max(axis=-1), np.abs(values.v).max(axis=-1))
        if not np.isfinite(self.kappa):  # defective A: no bound to check against
            return np.ones(np.shape(t), dtype=bool) if np.ndim(t) else True
        with np.errstate(divide="ignore"):  # in logarithms: e^(sigma t) may overflow first
            log_bound = np.log(10 * self.kappa * self.z0) + self.sigma * np.asarray(t)
            return np.log(z.max(axis=-1)) <= log_bound


def judge(vals: VertexValues, companion: VertexValues, algebraic: Optional[np.ndarray],
          psi: Optional[np.ndarray], lost: Optional[np.ndarray], weights: ErrorWeights,
          bound: Optional[GrowthBound], t0: float, dt: float, T: float,
          output: Optional[Tuple[Any, int]] = None,
          dropped: Optional[np.ndarray] = None) -> Verdict:
    """The verdict on a solved slab on rank 0 from its values, its companion's, its algebraic
    error, the tangent of the carried error `psi` and the part `lost` that the zero base damps
    (fem_dual.integrate.estimate.estimate_slabs)."""
    if not vals.finite():
        if np.isfinite(vals.x).all() and np.isfinite(vals.v).all():  # H_d, quadratic, overflows
            size = max(np.abs(vals.x).max(), np.abs(vals.v).max())
            return Verdict("error", None, f"the motion grew to {size:.3g}, where H_d (quadratic "
                           "in the state) overflows float64; a shorter T ends before it")
        return Verdict("retry", None, "the recovered state is not finite; try more slabs or "
                       "cells")
    if bound is not None and not bound.allows(t0 + dt, vals):
        return Verdict("retry", None, "the motion outgrows the exact flow's bound (noise "
                       "amplified in modes the slabs do not resolve); use more slabs or cells "
                       "per slab")
    one = (lambda a: None if a is None else a[None])
    est = estimate_slabs(batched(vals), batched(companion), one(algebraic), one(psi), one(lost),
                         weights, dt, T, output, dropped=one(dropped))
    local, glob = est.local[0], est.glob[0]
    if not est.finite[0]:
        return Verdict("retry", None, "the error estimate is not finite")
    err_local = float(est.err_local[0])
    slab = est.slab(0, t0, dt)
    tol = weights.tol
    if est.err_output is not None and est.err_output[0] > 1.0:
        return Verdict("retry", err_local, f"the state between output vertices is estimated "
                       f"to be {est.err_output[0]:.3g} times the tolerance ({tol.label}) off: "
                       "the vertices are too far apart for --t-eval", slab)
    if err_local > 1.0:
        return Verdict("retry", err_local, f"estimated local error {np.abs(local).max():.3g} "
                       f"exceeds its share of the tolerance ({tol.label})", slab)
    if est.err_global[0] > tol.refuse_factor:
        return Verdict("refuse", err_local, f"estimated error {np.abs(glob).max():.3g} exceeds "
                       f"the tolerance ({tol.label}) by a factor {est.err_global[0]:.3g}", slab)
    return Verdict("accept", err_local, "", slab)


def volume_kept(sim: "Simulation", z: np.ndarray, t0: float, dt: float,
                vals: Optional[VertexValues], verdict: Verdict) -> Verdict:
    """The verdict on a nonlinear slab (start state z, vertex values `vals` on rank 0) that the
    estimate accepts (`verdict`): still that if its slab map's tangent preserves phase-space
    volume within VOLUME_TOL, else "retry" (the slab does not follow the motion, and the
    companion may miss it too). The tangent is exact on the pointwise path; PETSc's SNES
    (forms) has none, so there its 2n columns are difference tangents of the solved slab (a
    residual and a solve each: `curl3d --x0 1e3,0,0 --v0 0,1e-9,0 --cells 8 --assembly forms`
    ended ok 444 off with an estimate of 1.6e-8 without them). On the predictor base, which
    damps the fast oscillations the cells do not resolve by design (fem_dual.slab.base_state),
    only slabs over which a mode of the linearised motion grows by more than e are judged (it
    damped a saddle's growth too: `force --F 1e4*x --x0 1 --v0 -100 --T 0.15 --base
    predictor` ended ok 13 off with an estimate of 2e-3). On the rk4 base the exact tangent
    holds the base (its own change moves the answer by the discretisation error only).
    Collective."""
    if sim.base == "predictor":
        from fem_dual.slab.base_state import grows_within

        if not grows_within(sim.scene, z[:sim.scene.n], dt):
            return verdict
    J = sim.slab_jacobian(z, t0, dt, vals)
    M, D = sim.backend.mass_and_damping()
    defect = bcast(sim.comm, volume_defect(J, M, D, dt) if J is not None else None)
    if defect <= VOLUME_TOL:
        return verdict._replace(tangent=J)
    return Verdict("retry", None, f"the slab map does not keep phase-space volume as the motion "
                   f"does (det of its tangent off by {defect:.2g}): the cells do not follow a "
                   "fast or unstable part of the motion, which the estimate cannot see")


def judged(comm: MPI.Comm, verdict: Callable[[], Verdict]) -> Verdict:
    """`verdict()` on rank 0, its action, error and reason on every rank (its estimate stays on
    rank 0): rank 0 judges, every rank learns the verdict. A judge that fails on rank 0 ends
    the run on every rank ("error")."""
    decided, problem = on_root(comm, verdict)
    shared = None
    if comm.rank == 0:
        shared = ("error", None, problem) if problem else tuple(decided[:3])
    action, err, reason = bcast(comm, shared)
    return Verdict(action, err, reason, decided.estimate if decided is not None else None)
