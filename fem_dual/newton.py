"""Newton (PETSc SNES) on the dual action of one slab, for nonlinear scenes.

DOLFINx 0.5.2 has no SNES wrapper: this is the small problem class of its
`python/test/unit/nls/test_newton.py`, with residual = dS/dw and Jacobian = its UFL derivative.
Each slab starts from the zero dual state. For an implicit DtP map, every residual and Jacobian
evaluation first solves the pointwise DtP equations at the quadrature points.
"""
from __future__ import annotations

from typing import Dict, List, Mapping, Optional

from dolfinx.fem import petsc as fem_petsc
from petsc4py import PETSc

from fem_dual.errors import SolveError
from fem_dual.problem import SlabProblem
from fem_dual.solvers import CompiledSlab, direct_solver, petsc_options

__all__ = ["NEWTON_DEFAULTS", "NewtonSlabSolver"]

_REASONS = {getattr(PETSc.SNES.ConvergedReason, name): name
            for name in dir(PETSc.SNES.ConvergedReason) if name.isupper()}

NEWTON_DEFAULTS: Dict[str, str] = {
    "snes_type": "newtonls",
    # Backtracking: full steps are taken when they reduce the residual (quadratic rate near the
    # solution); a trial state where the implicit DtP map has no solution gives a NaN residual,
    # and the step is cut.
    "snes_linesearch_type": "bt",
    "snes_rtol": "1e-11",
    "snes_atol": "1e-10",  # above the round-off floor of the residual (~1e-12)
    "snes_stol": "0",
    "snes_max_it": "30",
    "ksp_type": "preonly",
    "pc_type": "lu",
}


class NewtonSlabSolver(CompiledSlab):
    """SNES on the residual of one slab; per-slab iteration counts and residual histories."""

    def __init__(self, problem: SlabProblem, prefix: str,
                 overrides: Optional[Mapping[str, str]] = None):
        super().__init__(problem)
        self.x = problem.w.vector.copy()
        self.snes = PETSc.SNES().create(problem.comm)
        self.snes.setFunction(self._residual, self.b)
        self.snes.setJacobian(self._jacobian, self.A)
        self.snes.setOptionsPrefix(prefix)
        defaults = {**NEWTON_DEFAULTS, "pc_factor_mat_solver_type": direct_solver(problem.comm),
                    **problem.scene.solver_defaults}
        with petsc_options(prefix, defaults, overrides):
            self.snes.setFromOptions()
        self.snes.setConvergenceHistory(length=1000, reset=True)
        self.iterations: List[int] = []
        self.residual_norms: List[float] = []
        self.histories: List[List[float]] = []
        self._error: Optional[str] = None

    def reset(self) -> None:
        """Forget the counts of earlier runs."""
        self.iterations, self.residual_norms, self.histories = [], [], []

    def _update(self, x: PETSc.Vec) -> None:
        x.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
        x.copy(self.problem.w.vector)
        self.problem.w.x.scatter_forward()
        if self.problem.pointwise is not None:
            self._error = self.problem.pointwise.solve(self.problem.comm)

    def _residual(self, snes, x, b) -> None:
        self._update(x)
        with b.localForm() as loc:
            loc.set(0.0)
        if self._error:  # NaN residual: the line search cuts the step, or SNES stops
            b.set(float("nan"))
            return
        fem_petsc.assemble_vector(b, self.L)
        fem_petsc.apply_lifting(b, [self.a], bcs=[self.problem.bcs], x0=[x], scale=-1.0)
        b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        fem_petsc.set_bc(b, self.problem.bcs, x, -1.0)

    def _jacobian(self, snes, x, A, P) -> None:
        self._update(x)
        A.zeroEntries()
        fem_petsc.assemble_matrix(A, self.a, bcs=self.problem.bcs)
        A.assemble()

    def solve(self) -> None:
        """Newton from the zero dual state into problem.w; raises SolveError on failure."""
        self._error = None
        self.x.set(0.0)
        self.snes.setConvergenceHistory(length=1000, reset=True)
        try:
            self.snes.solve(None, self.x)
        except PETSc.Error as exc:
            raise SolveError(f"Newton failed (PETSc error {exc.ierr})") from None
        reason = self.snes.getConvergedReason()
        history = [float(r) for r in self.snes.getConvergenceHistory()[0]]
        if reason < 0 and self._error:
            raise SolveError(self._error)
        if reason < 0:
            raise SolveError(f"Newton did not converge ({_REASONS.get(reason, reason)}, residual "
                             f"{history[-1] if history else float('nan'):.3g} after "
                             f"{self.snes.getIterationNumber()} iterations); use smaller slabs "
                             "(more --slabs)")
        self._update(self.x)
        self.iterations.append(self.snes.getIterationNumber())
        self.residual_norms.append(history[-1] if history else 0.0)
        self.histories.append(history)
