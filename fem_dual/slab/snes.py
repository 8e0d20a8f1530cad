"""Newton (PETSc SNES) on the dual action of one slab, for nonlinear scenes.

DOLFINx 0.5.2 has no SNES wrapper: this is the small problem class of its
`python/test/unit/nls/test_newton.py`, with residual = dS/dw and Jacobian = its UFL derivative.
Each slab starts from the zero dual state. For an implicit DtP map, every residual and Jacobian
evaluation first solves the pointwise DtP equations at the quadrature points.
"""
from __future__ import annotations

import math
from typing import Dict, List, Mapping, Optional, Tuple

import numpy as np

from dolfinx.fem import petsc as fem_petsc
from mpi4py import MPI
from petsc4py import PETSc

from fem_dual.compat import destroy_petsc
from fem_dual.errors import SolveError
from fem_dual.quiet import quiet_numpy
from fem_dual.slab.problem import SlabProblem
from fem_dual.slab.petsc_solvers import CompiledSlab, SolverOptions, direct_solver

__all__ = ["NEWTON_DEFAULTS", "NewtonSlabSolver", "NO_PROGRESS_ITS", "RESIDUAL_ROUNDOFF",
           "difference_step", "residual_size", "stalled"]

_REASONS = {getattr(PETSc.SNES.ConvergedReason, name): name
            for name in dir(PETSc.SNES.ConvergedReason) if name.isupper()}

NEWTON_DEFAULTS: Dict[str, str] = {
    "snes_type": "newtonls",
    # Backtracking: full steps are taken when they reduce the residual (quadratic rate near the
    # solution); a trial state where the implicit DtP map has no solution gives a NaN residual,
    # and the step is cut.
    "snes_linesearch_type": "bt",
    # Relative tests only: a short slab's residual starts small, and an absolute test stopped
    # its Newton before the discretisation's own accuracy. The step test ends Newton at the
    # round-off floor: after a relative step of 1e-12 a quadratically converging iterate is
    # exact to round-off.
    "snes_rtol": "1e-13",
    "snes_atol": "0",
    "snes_stol": "1e-12",
    "snes_max_it": "30",
    "ksp_type": "preonly",
    "pc_type": "lu",
}


# SNES stopped on its line search or iteration limit is still taken when its residual fell by
# ROUND_OFF_REDUCTION, or below ROUND_OFF_ABSOLUTE times the size of the start state (the initial
# conditions enter the residual as they are; a short slab's first residual can be tiny): the
# residual cannot fall further than round-off. Whether Newton stopped early (loosened snes
# options) is measured by the error estimate itself (Simulation.algebraic_error).
ROUND_OFF_REDUCTION = 1e-9
ROUND_OFF_ABSOLUTE = 1e-12
BACKWARD_ROUNDOFF = 8.0  # units in the last place of the dual state (backward_floor)

# Under --rtol a slab's length is the controller's guess: a Newton still above NO_PROGRESS_RATIO
# of its first residual after NO_PROGRESS_ITS iterations is taking damped steps far from the
# solution, and the driver halves the slab now rather than after snes_max_it (curl3d T = 8
# --rtol 1e-8: four guesses failed after 30 iterations each, a third of the run, 46 -> 29 ms).
# Measured there: every Newton that converged was below 3e-4 of its first residual after three
# iterations; every one that failed was above 0.5, its full steps raising the residual tenfold
# and the line search cutting them to a tenth (its five failures took 10 iterations each, half
# of the run's evaluations). Slabs the user fixed keep every iteration (curl2d-lifted, 4 slabs:
# one converges after 19, at 0.38 of its start after 10).
NO_PROGRESS_ITS = 3
NO_PROGRESS_RATIO = 0.1
# A residual below this times the size of the start state is round-off of its assembly (the
# initial terms enter it as they are): Newton stops there, where its steps would be noise (a
# start at rest in an equilibrium took ten steps of 1e-15 and moved the state by 1e-14; with the
# rk4 base, whose first residual is 1e-8, SNES took ten steps at 1e-16 and ended on noise).
RESIDUAL_ROUNDOFF = 64 * np.finfo(float).eps
_R = PETSc.SNES.ConvergedReason


def residual_size(problem) -> float:
    """The size of the terms a slab's residual sums, which its round-off scales with: the
    initial terms x0 and M v0, and for a force the slab's impulse dt |F(x0)|. A start at rest
    at x = 0 under F(0) != 0 has only the last (force --F "1 - x" --x0 0 --base rk4: the rk4
    base left a first residual at round-off, which Newton could reduce neither by its relative
    test nor to an absolute floor of size 0, and every halving failed). The last one is kept:
    a slab's error companion starts from the same state of the same scene."""
    p = problem
    x0, v0, dt = p.x0.value, p.v0.value, float(p.dt.value)
    key = (dt, x0.tobytes(), v0.tobytes())
    if _LAST_SIZE[0] is p.scene and _LAST_SIZE[1] == key:
        return _LAST_SIZE[2]
    size = max(float(np.abs(x0).max()), float(np.abs(p.c["M"].value @ v0).max()))
    if not p.scene.linear:
        with quiet_numpy():
            impulse = dt * float(np.abs(p.scene.force_numpy(x0)).max())
        if math.isfinite(impulse):
            size = max(size, impulse)
    _LAST_SIZE[:] = [p.scene, key, size]
    return size


_LAST_SIZE: list = [None, None, 0.0]  # (scene, (dt, x0, v0), residual_size): the last one


def backward_floor(jacobian_norm: float, state_norm: float) -> float:
    """The residual that a change of the dual state by BACKWARD_ROUNDOFF units in its last
    place makes: |J| eps |w| (max norms). The residual cannot be computed closer to zero: with
    unbalanced weights (alpha = 1e3, beta = 1e-3: |J| = 3e5) Newton stalled at 1.6e-11, where
    this is 8.8e-11, and was called diverged; at alpha = beta = 1 it is 6e-16."""
    value = BACKWARD_ROUNDOFF * np.finfo(float).eps * jacobian_norm * state_norm
    return value if math.isfinite(value) else 0.0


def round_off_floor(history: List[float], size: float, backward: float = 0.0,
                    first: Optional[float] = None) -> float:
    """The residual below which Newton is at the round-off of the assembled residual: a part
    of the first residual (`first`: the zero dual state's, for a start from a partner's
    solution), of the size of the start state, and `backward_floor`."""
    if not history:
        return 0.0
    reference = history[0] if first is None else max(first, history[0])
    return max(ROUND_OFF_REDUCTION * reference, ROUND_OFF_ABSOLUTE * size, backward)


def at_round_off(history: List[float], size: float, backward: float = 0.0,
                 first: Optional[float] = None) -> bool:
    """Whether the last residual of a Newton history that SNES called diverged is at or below
    round_off_floor: taken as converged (a start already at the solution, an equilibrium,
    included)."""
    if not history or not math.isfinite(history[-1]):
        return False
    return history[-1] <= round_off_floor(history, size, backward, first)


def difference_step(z0: np.ndarray, dz: np.ndarray, relative: float,
                    scale: Optional[float]) -> Tuple[np.ndarray, float]:
    """(z0 + eps dz, eps) of a difference quotient in the start state: eps is `relative` times
    `scale` (by default the size of z0 and dz) over the size of dz; along one component, the
    step z0 + eps dz - z0 as rounded."""
    size = float(np.abs(dz).max(initial=0.0))
    if scale is None or not scale > 0:
        scale = max(float(np.abs(z0).max(initial=0.0)), size)
    eps = relative * scale / size
    z1 = z0 + eps * dz
    if np.count_nonzero(dz) == 1:  # the step that was taken, not the one asked for
        j = int(np.flatnonzero(dz)[0])
        eps = float(z1[j] - z0[j]) / float(dz[j])
    return z1, eps


def stalled(history: List[float], floor: float = 0.0) -> bool:
    """Whether a Newton residual history stalled (three or more steps that reduced the residual
    by less than a factor 0.9, counted while it is above the round-off `floor`) before it
    converged: the solution it found may be another branch, and the slab is retried shorter."""
    steps = [b / a for a, b in zip(history[:-1], history[1:]) if a > floor and a > 0]
    return sum(r > 0.9 for r in steps) >= 3


class NewtonSlabSolver(CompiledSlab):
    """SNES on the residual of one slab; per-slab iteration counts and residual histories."""

    def __init__(self, problem: SlabProblem, prefix: str,
                 overrides: Optional[Mapping[str, str]] = None):
        defaults = {**NEWTON_DEFAULTS, "pc_factor_mat_solver_type": direct_solver(problem.comm),
                    **problem.scene.solver_defaults}
        self.options = SolverOptions(prefix, defaults, overrides, "snes", problem.comm)
        super().__init__(problem)  # compiles: after the options are checked
        self.x = problem.w.vector.copy()
        self.snes = PETSc.SNES().create(problem.comm)
        self.snes.setFunction(self._residual, self.b)
        self.snes.setJacobian(self._jacobian, self.A)
        self.snes.setOptionsPrefix(prefix)
        with self.options.setup():
            self.snes.setFromOptions()
            self.options.probe()  # the Newton steps' KSP has the SNES's prefix
        self.snes.setConvergenceHistory(length=1000, reset=True)
        self.snes.setConvergenceTest(self._converged)
        self._first = 0.0
        self.patience: Optional[int] = None  # NO_PROGRESS_ITS for slab lengths that are guesses
        self.iterations: List[int] = []
        self.residual_norms: List[float] = []
        self.histories: List[List[float]] = []
        self._error: Optional[str] = None
        self._floor = 0.0
        self._solved_residual: Optional[PETSc.Vec] = None  # of the last solve (tangent)
        self._held = None  # (problem version, dual state) the DtP map was last solved at

    def close(self) -> None:
        self._forget_residual()
        destroy_petsc(self.snes, self.x)
        super().close()

    def _converged_residual(self) -> PETSc.Vec:
        """R at the converged slab from its start state, assembled once per solve (the tangents
        in every direction and the extra Newton step share it). Collective."""
        if self._solved_residual is None:
            self._solved_residual = self.b.duplicate()
            self._residual(self.snes, self.x, self._solved_residual)
        return self._solved_residual

    def _forget_residual(self) -> None:
        if self._solved_residual is not None:
            self._solved_residual.destroy()
            self._solved_residual = None

    def reset(self) -> None:
        """Forget the counts of earlier runs."""
        self.iterations, self.residual_norms, self.histories = [], [], []

    def _update(self, x: PETSc.Vec) -> None:
        """The problem's dual state from x, and the implicit DtP map solved there; skipped
        when it already holds x at the same constants (SNES evaluates the Jacobian where it
        evaluated the last residual: a third of an implicit scene's pointwise solves)."""
        p = self.problem
        x.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
        if p.pointwise is not None:
            local = x.array_r
            same = (self._held is not None and self._held[0] == p.version
                    and np.array_equal(self._held[1], local))
            if p.comm.size > 1:
                same = p.comm.allreduce(same, op=MPI.LAND)
            if same:
                return
        x.copy(p.w.vector)
        p.w.x.scatter_forward()
        if p.pointwise is not None:
            self._error = p.pointwise.solve(p.comm)
            self._held = (p.version, local.copy())

    def _converged(self, snes, it: int, norms) -> int:
        """PETSc's default tests (atol, rtol, stol, max_it, NaN), and no progress (above)."""
        xnorm, ynorm, fnorm = norms
        rtol, atol, stol, max_it = snes.getTolerances()
        if it == 0:
            self._first = fnorm
        if not math.isfinite(fnorm):
            return _R.DIVERGED_FNORM_NAN
        if fnorm < atol:
            return _R.CONVERGED_FNORM_ABS
        if it > 0 and fnorm <= rtol * self._first:
            return _R.CONVERGED_FNORM_RELATIVE
        if it > 0 and ynorm < stol * xnorm:
            return _R.CONVERGED_SNORM_RELATIVE
        if (self.patience is not None and it >= min(max_it, self.patience)
                and fnorm > NO_PROGRESS_RATIO * self._first):
            return _R.DIVERGED_MAX_IT
        if it >= max_it:
            return _R.DIVERGED_MAX_IT
        return _R.CONVERGED_ITERATING

    def _residual(self, snes, x, b) -> None:
        self._update(x)
        with b.localForm() as loc:
            loc.set(0.0)
        if self._error:  # NaN residual: the line search cuts the step, or SNES stops
            b.set(float("nan"))
            return
        fem_petsc.assemble_vector(b, self.L)
        # No lifting: the Dirichlet values (xi = eta = 0 at s = 1) and the iterate's values there
        # are zero (every start, Newton step and tangent keeps them so), and lifting adds
        # A (g - x) on those columns, zero; it was a fifth of a curl3d run.
        b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        fem_petsc.set_bc(b, self.problem.bcs, x, -1.0)

    def _jacobian(self, snes, x, A, P) -> None:
        self._update(x)
        A.zeroEntries()
        fem_petsc.assemble_matrix(A, self.a, bcs=self.problem.bcs)
        A.assemble()

    def solve(self, warm: Optional[float] = None) -> None:
        """Newton from the zero dual state into problem.w; raises SolveError on failure.

        warm: start from the dual state problem.w holds (a partner's solution of the same
        slab); the value is the residual norm of the zero dual state (the partner's first),
        which the relative tolerance refers to, as it would from zero."""
        self._error = None
        self._forget_residual()
        if warm is not None:
            self.problem.w.vector.copy(self.x)
            fem_petsc.set_bc(self.x, self.problem.bcs)  # exactly zero, as the residual assumes
        else:
            self.x.set(0.0)
        self.snes.setConvergenceHistory(length=1000, reset=True)
        tolerances = self.snes.getTolerances()  # (rtol, atol, stol, max_it)
        p = self.problem
        size = residual_size(p)
        # the round-off of the residual ends Newton, as on the pointwise path, unless the user
        # set snes_atol
        floor = 0.0 if "snes_atol" in self.options.given else RESIDUAL_ROUNDOFF * size
        self.snes.setTolerances(atol=max(tolerances[1], floor,
                                         0.0 if warm is None else tolerances[0] * warm))
        if warm is not None:
            # at least one step, whatever the options: a companion left at its partner's
            # solution would estimate no discretisation error at all
            self.snes.setForceIteration(True)
        try:
            with self.options.solving():
                self.snes.solve(None, self.x)
        except PETSc.Error as exc:
            raise SolveError(f"Newton failed (PETSc error {exc.ierr})") from None
        finally:
            self.snes.setTolerances(atol=tolerances[1])
            self.snes.setForceIteration(False)
        reason = self.snes.getConvergedReason()
        history = [float(r) for r in self.snes.getConvergenceHistory()[0]]
        if reason < 0 and self._error:
            raise SolveError(self._error)
        if self.snes.getIterationNumber() == 0 or not self.A.assembled:
            # no Newton step (a start at the residual's round-off: an equilibrium, a base state
            # that is the motion), or a method that never forms the Jacobian (anderson: its
            # norm crashed PETSc, exit 1): the Jacobian that the round-off test, the tangents
            # and the extra Newton step use is assembled here, at the state SNES stopped at (it
            # was never assembled, or held an earlier slab's)
            self._jacobian(self.snes, self.x, self.A, self.A)
            self.snes.getKSP().setOperators(self.A)  # new values: refactor at the next solve
        backward = 0.0
        if reason < 0:  # (collective norms: every rank has the same reason)
            J = self.snes.getJacobian()[0]
            backward = backward_floor(J.norm(PETSc.NormType.NORM_INFINITY),
                                      self.x.norm(PETSc.NormType.NORM_INFINITY))
        if reason < 0 and not at_round_off(history, size, backward, warm):
            raise SolveError(f"Newton did not converge ({_REASONS.get(reason, reason)}, residual "
                             f"{history[-1] if history else float('nan'):.3g} after "
                             f"{self.snes.getIterationNumber()} iterations); use smaller slabs "
                             "(more --slabs)")
        self._update(self.x)
        self._floor = round_off_floor(history, size, backward, warm)
        self.iterations.append(self.snes.getIterationNumber())
        self.residual_norms.append(history[-1] if history else 0.0)
        self.histories.append(history)

    def tangent(self, z0: np.ndarray, dz: np.ndarray, relative: float = 1e-6,
                scale: Optional[float] = None) -> float:
        """Linearise the converged slab around its start state z0 in the direction dz: leaves
        the problem at start state z0 + eps dz with the dual state w + eps dw, where
        J dw = -dR/dz dz (J: the Jacobian factored in the last Newton step), and returns eps
        (`relative` times `scale`, by default the size of z0 and dz, over the size of dz; along
        one component, the step z0 + eps dz - z0 as rounded). `restore(z0)` goes back.
        Collective."""
        p, n = self.problem, self.problem.n
        z1, eps = difference_step(z0, dz, relative, scale)
        r0 = self._converged_residual()
        r1 = self.b.duplicate()
        p.set_start(z1[:n], z1[n:])
        self._residual(self.snes, self.x, r1)
        r1.axpy(-1.0, r0)
        self._displace(r1)
        return eps

    def newton_step(self) -> None:
        """Leave the problem at the converged state plus one more Newton step, w - J^-1 R(w) (J:
        the Jacobian factored in the last Newton step): how far the answer would still move is
        its algebraic error. `restore(z0)` goes back. Collective."""
        self._displace(self._converged_residual().copy())

    def _displace(self, r: PETSc.Vec) -> None:
        """w = x - J^-1 r, with the implicit DtP map solved there; destroys r."""
        dw = self.x.duplicate()
        with self.options.solving():
            self.snes.getKSP().solve(r, dw)
        dw.aypx(-1.0, self.x)
        self._update(dw)
        for vec in (r, dw):
            vec.destroy()
        if self._error:
            raise SolveError(self._error)

    def restore(self, z0: np.ndarray) -> None:
        """Back to the converged slab from start state z0 after `tangent` or `newton_step`."""
        n = self.problem.n
        self.problem.set_start(z0[:n], z0[n:])
        self._update(self.x)

    def stalled(self) -> bool:
        """Whether the last solve's residual history stalled before it converged."""
        return bool(self.histories) and stalled(self.histories[-1], self._floor)
