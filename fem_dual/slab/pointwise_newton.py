"""Newton on one slab's dual action, assembled pointwise (fem_dual.slab.local_action): the default
solver of nonlinear slabs.

The same iteration as the PETSc SNES of fem_dual.slab.snes with its defaults (newtonls with a
backtracking line search, relative residual and step tests, the same give-up rule under
--rtol, the same round-off acceptance), without PETSc: the residual and the banded Jacobian come
from one expression evaluation each and the Newton step from LAPACK's banded LU. That solver
remains (`--assembly forms`, and whenever PETSc options are given) for PETSc's own options and
for slabs distributed over many processes.
"""
from __future__ import annotations

import math
from typing import List, Mapping, Optional

import numpy as np

from fem_dual.errors import SolveError
from fem_dual.slab.banded import BandedLU
from fem_dual.slab.local_action import LocalAction, _quiet
from fem_dual.slab.snes import (NEWTON_DEFAULTS, NO_PROGRESS_RATIO, RESIDUAL_ROUNDOFF,
                             backward_floor, difference_step, residual_size,
                             round_off_floor, stalled)
from fem_dual.slab.problem import SlabProblem

__all__ = ["PointwiseNewtonSolver"]

RTOL = float(NEWTON_DEFAULTS["snes_rtol"])
STOL = float(NEWTON_DEFAULTS["snes_stol"])
MAX_IT = int(NEWTON_DEFAULTS["snes_max_it"])
DECREASE = 1e-4  # sufficient decrease of the line search (PETSc's bt: alpha)
MIN_LAMBDA = 1e-12  # the shortest step the line search tries
GUESSED_MIN_LAMBDA = 0.05  # ... on a slab whose length the controller guessed (--rtol)


def _band_norm(band: np.ndarray) -> float:
    """The max norm of a symmetric matrix in band storage (its largest column sum)."""
    return float(np.abs(band).sum(axis=0).max(initial=0.0))


def _norm(a: np.ndarray) -> float:
    """The 2-norm (np.linalg.norm costs microseconds of checks on these small vectors)."""
    return math.sqrt(float(a @ a))


class _PointwiseSolver:
    """What both pointwise slab solvers hold: the problem and its pointwise assembly (compiled
    here: `compile_s`). `prefix` and `overrides` are accepted for the driver's uniform call;
    PETSc options select the PETSc solvers instead (fem_dual.config.RunConfig.pointwise)."""

    def __init__(self, problem: SlabProblem, prefix: str = "",
                 overrides: Optional[Mapping[str, str]] = None):
        import time

        if overrides:
            raise ValueError("the pointwise solvers take no PETSc options")
        tic = time.perf_counter()
        self.problem = problem
        self.local = LocalAction(problem)
        self.compile_s = time.perf_counter() - tic
        self._lu: Optional[BandedLU] = None
        self.iterations: List[int] = []

    def close(self) -> None:
        """Nothing to destroy (no PETSc objects)."""


class PointwiseNewtonSolver(_PointwiseSolver):
    """Newton on the residual of one slab; per-slab iteration counts and residual histories,
    like fem_dual.slab.snes.NewtonSlabSolver (the driver uses either).

    Args:
        problem: the slab problem (on a mesh of one process).
    """

    kind = "newton"

    def __init__(self, problem: SlabProblem, prefix: str = "",
                 overrides: Optional[Mapping[str, str]] = None):
        super().__init__(problem, prefix, overrides)  # _lu: the last Newton step's factors
        self.x = np.zeros(self.local.size)  # the converged (or last) iterate
        self._solved_residual: Optional[np.ndarray] = None
        self.patience: Optional[int] = None  # NO_PROGRESS_ITS for guessed slab lengths
        self.residual_norms: List[float] = []
        self.histories: List[List[float]] = []
        self._floor = 0.0

    def reset(self) -> None:
        """Forget the counts of earlier runs."""
        self.iterations, self.residual_norms, self.histories = [], [], []

    # -- Newton -----------------------------------------------------------------------------

    def _give_up(self, it: int, fnorm: float, first: float) -> bool:
        return (self.patience is not None and it >= min(MAX_IT, self.patience)
                and fnorm > NO_PROGRESS_RATIO * first)

    @_quiet
    def solve(self, warm: Optional[float] = None) -> None:
        """Newton from the zero dual state into problem.w; raises SolveError on failure.

        warm: start from the dual state problem.w holds (a partner's solution of the same
        slab), with at least one step; the value is the residual norm of the zero dual state
        (the partner's first), which the absolute test refers to, as it would from zero."""
        local, p = self.local, self.problem
        self._solved_residual, self._lu = None, None
        x = local.state() if warm is not None else np.zeros(local.size)
        size = residual_size(p)
        atol = max(RESIDUAL_ROUNDOFF * size, 0.0 if warm is None else RTOL * warm)
        fast = local.native_newton(x, atol=atol, check_start=warm is None, rtol=RTOL,
                                   stol=STOL, max_it=MAX_IT, patience=self.patience,
                                   no_progress=NO_PROGRESS_RATIO, decrease=DECREASE)
        if fast is not None:  # every step taken whole (else the numpy iteration decides)
            self._lu = fast.lu
            self._finish(fast.x, fast.reason, fast.history, len(fast.history) - 1, size,
                         fast.backward, warm, None, placed=True)
            return
        local.set_state(x)
        F, band = local.residual_and_jacobian()
        fnorm = _norm(F)
        first, history, it, reason = fnorm, [fnorm], 0, None
        if not math.isfinite(fnorm):
            reason = "DIVERGED_FNORM_NAN"
        elif warm is None and fnorm < atol:  # at round-off from the start (an equilibrium)
            reason = "CONVERGED_FNORM_ABS"
        failure: Optional[str] = None  # why the implicit DtP map failed at the last trial
        backward = 0.0  # backward_floor at the current iterate
        while reason is None:
            if band is None:  # (a state whose residual was finite has a Jacobian)
                reason = "DIVERGED_FNORM_NAN"
                break
            backward = backward_floor(_band_norm(band), float(np.abs(x).max(initial=0.0)))
            lu = local.factor(band)
            if lu.singular:
                reason = "DIVERGED_LINEAR_SOLVE"
                break
            self._lu = lu
            step = lu.solve(F)
            if not np.isfinite(step).all():
                reason = "DIVERGED_LINEAR_SOLVE"
                break
            floor = round_off_floor(history, size, backward, warm)
            lam, trial, F_new, band_new, gnorm, failure = self._line_search(x, step, fnorm,
                                                                            floor, it)
            if lam == -1.0:
                # a guessed length (--rtol) whose first full step did not lower the residual:
                # every such Newton failed on curl3d T = 8 (the damped steps then gain a tenth
                # each), every converging one took its first step whole; the driver halves the
                # slab now (the five failures took a fifth of the run's evaluations). So for a
                # later step cut below GUESSED_MIN_LAMBDA (with the rk4 base, the whole horizon
                # of curl3d T = 8 took 8 damped steps and some 50 evaluations before its line
                # search failed)
                local.set_state(x)
                reason = "DIVERGED_DAMPED_START"
                break
            if not lam >= MIN_LAMBDA:
                local.set_state(x)
                reason = "DIVERGED_LINE_SEARCH"
                break
            it += 1
            ynorm = lam * _norm(step)
            x, F, band, fnorm = trial, F_new, band_new, gnorm
            history.append(fnorm)
            xnorm = _norm(x)
            if fnorm < atol:
                reason = "CONVERGED_FNORM_ABS"
            elif fnorm <= RTOL * first:
                reason = "CONVERGED_FNORM_RELATIVE"
            elif ynorm < STOL * xnorm:
                reason = "CONVERGED_SNORM_RELATIVE"
            elif self._give_up(it, fnorm, first) or it >= MAX_IT:
                reason = "DIVERGED_MAX_IT"
        self._finish(x, reason, history, it, size, backward, warm, failure)

    def _line_search(self, x: np.ndarray, step: np.ndarray, fnorm: float, floor: float,
                     it: int) -> tuple:
        """PETSc's bt line search along -step from x, whose residual norm is fnorm: (lam, the
        last trial state, its residual, band and residual norm, why the implicit DtP map
        failed there). lam is the accepted fraction of the step; 0 where x is at the round-off
        floor already, -1 for a guessed slab length whose Newton is damped hard (`solve` says
        why), below MIN_LAMBDA where the search failed."""
        local, lam = self.local, 1.0
        while lam >= MIN_LAMBDA:
            trial = x - lam * step
            local.set_state(trial)
            F_new, band_new = local.residual_and_jacobian()
            failure = local.error
            gnorm = _norm(F_new)
            if math.isfinite(gnorm) and gnorm <= (1.0 - DECREASE * lam) * fnorm:
                break
            if fnorm <= floor:  # at round-off already: shorter steps are noise too (a
                lam, failure = 0.0, None  # companion cut 40 to 1e-12, then was accepted)
                break
            if self.patience is not None and (it == 0 or lam < GUESSED_MIN_LAMBDA):
                lam = -1.0  # a guessed length whose Newton is damped hard: see solve
                break
            # PETSc's bt: halve past NaN, else the minimum of the quadratic model of
            # |F|^2 / 2 along the step, kept within [0.1, 0.5] of the step
            if math.isfinite(gnorm):
                model = lam ** 2 * fnorm ** 2 / (gnorm ** 2 + (2 * lam - 1) * fnorm ** 2)
                lam = min(max(model, 0.1 * lam), 0.5 * lam)
            else:
                lam *= 0.5
        return lam, trial, F_new, band_new, gnorm, failure

    def _finish(self, x: np.ndarray, reason: str, history: List[float], it: int, size: float,
                backward: float, warm: Optional[float], failure: Optional[str],
                placed: bool = False) -> None:
        """Record how Newton ended at x (`placed`: the problem holds it already, as the compiled
        Newton leaves it); raises SolveError where it failed short of the round-off floor."""
        local = self.local
        self.x = x
        floor = round_off_floor(history, size, backward, warm)
        if reason.startswith("DIVERGED"):
            error = failure if reason == "DIVERGED_LINE_SEARCH" else local.error
            local.set_state(x)
            if error:
                raise SolveError(error)
            if not history[-1] <= floor:
                raise SolveError(f"Newton did not converge ({reason}, residual "
                                 f"{history[-1]:.3g} after {it} iterations); use smaller "
                                 "slabs (more --slabs)")
        if not placed:
            local.set_state(x)
        self._floor = floor
        self.iterations.append(it)
        self.residual_norms.append(history[-1])
        self.histories.append(history)

    # -- linearisation around the converged slab ------------------------------------------------

    def _factors(self) -> BandedLU:
        """The factors of the last Newton step's Jacobian (of the converged state's, when Newton
        took no step)."""
        if self._lu is None:
            self.local.set_state(self.x)
            _, band = self.local.residual_and_jacobian()
            if band is None:
                raise SolveError(self.local.error or "the slab's Jacobian is not finite")
            self._lu = self.local.factor(band)
        return self._lu

    def _converged_residual(self) -> np.ndarray:
        """R at the converged slab from its start state (the tangents in every direction and
        the extra Newton step share it)."""
        if self._solved_residual is None:
            self.local.set_state(self.x)
            self._solved_residual = self.local.residual()
        return self._solved_residual

    def tangent(self, z0: np.ndarray, dz: np.ndarray, relative: float = 1e-6,
                scale: Optional[float] = None) -> float:
        """As fem_dual.slab.snes.NewtonSlabSolver.tangent: leaves the problem at start state
        z0 + eps dz with the dual state w + eps dw, J dw = -dR/dz dz, and returns eps."""
        p, n = self.problem, self.problem.n
        z1, eps = difference_step(z0, dz, relative, scale)
        r0 = self._converged_residual()
        p.set_start(z1[:n], z1[n:])
        self.local.set_state(self.x)
        self._displace(self.local.residual() - r0)
        return eps

    @property
    def exact_tangents(self) -> bool:
        """Whether `exact_tangent` applies: a base state that is a constant, or the flow
        predictor's, held (fem_dual.slab.local_action.LocalAction.vertex_tangent)."""
        return self.problem.Zbar is not None or self.problem.base == "rk4"

    def _linearised(self, what, *args):
        """`what` (a LocalAction linearisation) at the converged slab; its failure to solve the
        implicit DtP map there as a SolveError."""
        self.local.set_state(self.x)
        try:
            return what(*args)
        except ValueError as exc:
            raise SolveError(str(exc)) from None

    def exact_tangent(self, dz: np.ndarray) -> np.ndarray:
        """d(x, v)/dz0 . dz at the vertices (vertices, 2n) of the converged slab, exactly
        (fem_dual.slab.local_action.LocalAction.vertex_tangent): no difference step, no error of
        its own."""
        return self._linearised(self.local.vertex_tangent, dz)[0]

    def slab_jacobian(self) -> np.ndarray:
        """d z_end / d z0 (2n, 2n) of the converged slab, exactly (see exact_tangent)."""
        return self._linearised(self.local.tangent_matrix)[-1]

    def newton_change(self) -> np.ndarray:
        """How far the vertex values (vertices, 2n) of the converged slab would move with one
        more Newton step, to first order in the step, from the exact tangents' solve (no
        displaced state to sample and restore)."""
        return self._linearised(self.local.newton_change)

    def newton_step(self) -> None:
        """Leave the problem at the converged state plus one more Newton step, w - J^-1 R(w):
        how far the answer would still move is its algebraic error. `restore(z0)` goes back."""
        self._displace(self._converged_residual())

    @_quiet
    def _displace(self, r: np.ndarray) -> None:
        """w = x - J^-1 r, with the implicit DtP map solved there."""
        if not np.isfinite(r).all():
            raise SolveError(self.local.error or "the slab's residual is not finite")
        error = self.local.set_state(self.x - self._factors().solve(r))
        if error:
            raise SolveError(error)

    def restore(self, z0: np.ndarray) -> None:
        """Back to the converged slab from start state z0 after `tangent` or `newton_step`."""
        n = self.problem.n
        self.problem.set_start(z0[:n], z0[n:])
        self.local.set_state(self.x)

    def stalled(self) -> bool:
        """Whether the last solve's residual history stalled before it converged."""
        return bool(self.histories) and stalled(self.histories[-1], self._floor)


class PointwiseLinearSolver(_PointwiseSolver):
    """One banded LU solve per slab of a linear scene's quadratic dual action, J w = -R(0),
    assembled pointwise (fem_dual.slab.local_action): the default for linear scenes on their UFL
    forms (fem_dual.slab.petsc_solvers.LinearSlabSolver is the PETSc KSP of `--assembly forms`). J does
    not depend on the start or base state: it is assembled and factored again only when the
    slab length changes (or `reset`)."""

    kind = "direct"

    def __init__(self, problem: SlabProblem, prefix: str = "",
                 overrides: Optional[Mapping[str, str]] = None):
        super().__init__(problem, prefix, overrides)
        self._band: Optional[np.ndarray] = None
        self._assembled_dt: Optional[float] = None
        self.assemblies = 0

    def reset(self) -> None:
        """Forget the factorisation and the counts: the next solve assembles and factors."""
        self._assembled_dt = None
        self.iterations, self.assemblies = [], 0

    @_quiet
    def solve(self) -> None:
        """Solve the current slab into problem.w; raises SolveError if the slab matrix is
        singular or the solution is not finite."""
        p, local = self.problem, self.local
        local.set_state(np.zeros(local.size))
        dt = float(p.dt.value)
        if self._assembled_dt != dt:
            R, band = local.residual_and_jacobian()
            self._band = band.copy()
            self._lu = local.factor(band)
            self._assembled_dt = dt
            self.assemblies += 1
        else:
            R = local.residual()
        if self._lu.singular:
            raise SolveError("the slab matrix is numerically singular; the scene's scales are "
                             "too far apart (rescale time or masses, or give H weights A and B "
                             "that balance them)")
        w = -self._lu.solve(R)
        if not np.isfinite(w).all():
            raise SolveError("the slab's solution is not finite")
        local.set_state(w)
        self.iterations.append(0)

    def condition_estimate(self, iterations: int = 60) -> float:
        """lambda_max / lambda_min of the slab matrix (SPD) on the free unknowns, by power
        iteration on it and on its inverse (the factors of the last solve), as
        fem_dual.slab.petsc_solvers.LinearSlabSolver's."""
        from scipy import sparse

        if self._assembled_dt != float(self.problem.dt.value):
            self.solve()
        kd, N = self.local.kd, self.local.size
        # band[2 kd + i - j, j] = J[i, j]: row kd + k holds the diagonal j - i = kd - k
        J = sparse.dia_matrix((self._band[kd:], kd - np.arange(2 * kd + 1)), shape=(N, N))
        rng = np.random.default_rng(0)

        def largest(apply) -> float:
            x, value = rng.standard_normal(N), 0.0
            for _ in range(iterations):
                x /= np.linalg.norm(x)
                y = apply(x)
                value, x = float(x @ y), y
            return value
        return largest(lambda x: J @ x) * largest(self._lu.solve)
