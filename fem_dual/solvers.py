"""PETSc solvers of one slab. A linear scene gets one KSP (matrix assembled and factored once while
the slab length stays the same); a nonlinear scene gets PETSc SNES (see fem_dual.newton).

Options are a dict applied under a per-solver prefix (`dual_<scene>_`) and removed again after
`setFromOptions()`, so solvers never leak settings into each other. Options the user set already
(PETSC_OPTIONS, or `--petsc-option` on the command line) win over the defaults.
"""
from __future__ import annotations

import os
import time
from contextlib import contextmanager
from typing import Dict, Iterator, Mapping, Optional

from dolfinx import fem
from dolfinx.fem import petsc as fem_petsc
from petsc4py import PETSc

from fem_dual.errors import InputError, SolveError
from fem_dual.problem import SlabProblem

__all__ = ["LINEAR_DEFAULTS", "direct_solver", "solver_prefix", "petsc_options", "CompiledSlab",
           "LinearSlabSolver", "check_true_residual", "TRUE_RESIDUAL_TOL"]

LINEAR_DEFAULTS: Dict[str, str] = {
    "ksp_type": "preonly",
    "pc_type": "lu",
    "ksp_error_if_not_converged": "true",
}


def direct_solver(comm) -> str:
    """LU package: PETSc's own in serial (the slab matrices are banded; it beats MUMPS from a few
    hundred to a few hundred thousand dofs, measured in the README), MUMPS in parallel."""
    return "petsc" if comm.size == 1 else "mumps"


def solver_prefix(scene_name: str) -> str:
    return "dual_" + scene_name.replace("-", "_") + "_"


@contextmanager
def petsc_options(prefix: str, defaults: Mapping[str, str],
                  overrides: Optional[Mapping[str, str]] = None) -> Iterator[None]:
    """Push `defaults` (unless already set) and `overrides` under `prefix`, then remove them.

    Raises:
        InputError: PETSc rejected the options while they were set (an unknown solver or
            preconditioner type, a value of the wrong kind), naming the options given.
    """
    opts = PETSc.Options()
    pushed = []
    for key, value in {**defaults, **(overrides or {})}.items():
        full = prefix + key
        if key in (overrides or {}) or not opts.hasName(full):
            opts[full] = value
            pushed.append(full)
    try:
        yield
    except PETSc.Error as exc:
        given = ", ".join(f"{k}={v}" for k, v in (overrides or {}).items()) or "none given"
        raise InputError(f"PETSc rejected the solver options under {prefix} (PETSc error "
                         f"{exc.ierr}; options: {given}; PETSC_OPTIONS="
                         f"{os.environ.get('PETSC_OPTIONS', '')!r})") from None
    finally:
        for full in pushed:
            opts.delValue(full)


class CompiledSlab:
    """The compiled residual and Jacobian of a slab problem, with the matrix and vector they fill;
    the part every slab solver shares."""

    def __init__(self, problem: SlabProblem):
        self.problem = problem
        tic = time.perf_counter()
        self.a = fem.form(problem.jacobian)
        self.L = fem.form(problem.residual)
        self.compile_s = time.perf_counter() - tic
        self.A = fem_petsc.create_matrix(self.a)
        self.b = fem_petsc.create_vector(self.L)


class LinearSlabSolver(CompiledSlab):
    """One KSP solve per slab of the quadratic dual action: J w = -R(0).

    The Jacobian does not depend on the initial or base state; it is assembled and factored once
    and again only when the slab length changes.
    """

    def __init__(self, problem: SlabProblem, prefix: str,
                 overrides: Optional[Mapping[str, str]] = None):
        super().__init__(problem)
        self.ksp = PETSc.KSP().create(problem.comm)
        self.ksp.setOperators(self.A)
        self.ksp.setOptionsPrefix(prefix)
        defaults = {**LINEAR_DEFAULTS, "pc_factor_mat_solver_type": direct_solver(problem.comm)}
        with petsc_options(prefix, defaults, overrides):
            self.ksp.setFromOptions()
        self._assembled_dt: Optional[float] = None
        self.iterations = []
        self.assemblies = 0

    def reset(self) -> None:
        """Forget the factorisation and the counts: the next solve assembles and factors."""
        self._assembled_dt = None
        self.iterations = []
        self.assemblies = 0

    def assemble_matrix(self) -> None:
        self.A.zeroEntries()
        fem_petsc.assemble_matrix(self.A, self.a, bcs=self.problem.bcs)
        self.A.assemble()
        self.ksp.setOperators(self.A)  # new values: refactor at the next solve
        self._assembled_dt = float(self.problem.dt.value)
        self.assemblies += 1

    def solve(self) -> None:
        """Solve the current slab into problem.w; raises SolveError if KSP fails."""
        p = self.problem
        if self._assembled_dt != float(p.dt.value):
            self.assemble_matrix()
        p.w.x.array[:] = 0.0  # the residual is affine: R(0) is minus the right-hand side
        with self.b.localForm() as loc:
            loc.set(0.0)
        fem_petsc.assemble_vector(self.b, self.L)
        self.b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        self.b.scale(-1.0)
        fem_petsc.set_bc(self.b, p.bcs)
        try:
            self.ksp.solve(self.b, p.w.vector)
        except PETSc.Error as exc:
            raise SolveError(f"linear solve failed (PETSc error {exc.ierr})") from None
        reason = self.ksp.getConvergedReason()
        if reason < 0:
            raise SolveError(f"linear solve did not converge (KSP reason {reason})")
        check_true_residual(self.ksp, self.A, p.w.vector, self.b)
        self.iterations.append(self.ksp.getIterationNumber())
        p.w.x.scatter_forward()

    def condition_estimate(self, iterations: int = 60) -> float:
        """lambda_max / lambda_min of the slab matrix (SPD) by power iteration on it and on its
        inverse (the factorisation of the last solve), on the free dofs only (the Dirichlet rows
        are identity rows). An estimate from below, good to a few per cent. Collective."""
        if self._assembled_dt != float(self.problem.dt.value):
            self.solve()
        lam_max = _largest_eigenvalue(self.A.mult, self.A, self.problem.bcs, iterations)
        lam_min = 1.0 / _largest_eigenvalue(self.ksp.solve, self.A, self.problem.bcs, iterations)
        return lam_max / lam_min


TRUE_RESIDUAL_TOL = 1e-6  # |b - A x| / |b| a slab solve must reach (garbage solvers: ~1)


def check_true_residual(ksp: PETSc.KSP, A: PETSc.Mat, x: PETSc.Vec, b: PETSc.Vec) -> None:
    """SolveError unless x solves A x = b to TRUE_RESIDUAL_TOL: a KSP that "converged" on a
    preconditioned or unchecked residual (preonly with a preconditioner that is not a direct
    solver, a loose rtol) must not pass its answer on. Collective."""
    r = b.duplicate()
    A.mult(x, r)
    r.aypx(-1.0, b)
    bnorm, rnorm = b.norm(), r.norm()
    r.destroy()
    if not rnorm <= TRUE_RESIDUAL_TOL * max(bnorm, 1e-300):
        pc = ksp.getPC().getType()
        if pc in ("lu", "cholesky"):
            raise SolveError(f"the slab matrix is numerically singular: its LU solve leaves a "
                             f"true residual {rnorm / max(bnorm, 1e-300):.3g} relative; the "
                             "scene's scales are too far apart (rescale time or masses, or "
                             "give H weights A and B that balance them)")
        raise SolveError(f"the slab's linear solve is inaccurate: true residual "
                         f"{rnorm / max(bnorm, 1e-300):.3g} relative (at most "
                         f"{TRUE_RESIDUAL_TOL:g}) with ksp_type={ksp.getType()}, pc_type={pc}; "
                         "use a direct solver (pc_type=lu) or an iterative one with ksp_rtol "
                         "1e-12")


def _largest_eigenvalue(apply, A: PETSc.Mat, bcs, iterations: int) -> float:
    """Rayleigh quotient after power iteration with `apply(x, y)` (y = op x), x zero on bcs."""
    x, y = A.createVecs()
    x.setRandom()
    value = 0.0
    for _ in range(iterations):
        fem_petsc.set_bc(x, bcs)
        x.normalize()
        apply(x, y)
        fem_petsc.set_bc(y, bcs)
        value = x.dot(y)
        x, y = y, x
    return value
