"""PETSc solvers of one slab. A linear scene gets one KSP (matrix assembled and factored once while
the slab length stays the same); a nonlinear scene gets PETSc SNES (see fem_dual.slab.snes).

Options are a dict applied under a per-solver prefix (`dual_<scene>_`) while the solver is set up
and while it solves, and removed in between, so solvers never leak settings into each other.
Options the user set already (PETSC_OPTIONS, or `--petsc-option` on the command line) win over
the defaults. The user's options are input (see fem_dual.petsc_check): their values are checked
before anything is compiled, and an option the solver's set-up did not query is refused.
"""
from __future__ import annotations

import contextlib
import math
import time
from contextlib import contextmanager
from typing import Dict, Iterator, Mapping, Optional

from dolfinx.fem import petsc as fem_petsc
from mpi4py import MPI
from petsc4py import PETSc

from fem_dual.compat import compile_form, destroy_petsc
from fem_dual.errors import InputError, SolveError
from fem_dual.petsc_check import (check_user_options, last_line, require_used, solver_prefix,
                                  user_options)
from fem_dual.slab.problem import SlabProblem

__all__ = ["LINEAR_DEFAULTS", "direct_solver", "solver_prefix", "petsc_options", "SolverOptions",
           "CompiledSlab", "LinearSlabSolver", "check_true_residual", "TRUE_RESIDUAL_TOL"]

LINEAR_DEFAULTS: Dict[str, str] = {
    "ksp_type": "preonly",
    "pc_type": "lu",
    "ksp_error_if_not_converged": "true",
}
# Where the user sets no KSP or PC option: LU with one step of iterative refinement (Richardson,
# two iterations, no norm computed). The answer and its companion then carry the round-off of
# the matrix, not that of the factors, and the error estimate at the round-off floor is the same
# on one rank (PETSc's LU) and on two (MUMPS): ziegler --assembly forms --cells 80 --degree 3
# --slabs 10 estimated 9.5e-12 serial and 4.1e-11 under mpirun -n 2 with a bare LU, 1.83e-11
# and 1.82e-11 refined.
REFINED_LU: Dict[str, str] = {"ksp_type": "richardson", "ksp_max_it": "2",
                              "ksp_norm_type": "none"}


def direct_solver(comm) -> str:
    """LU package: PETSc's own in serial (the slab matrices are banded; it beats MUMPS from a few
    hundred to a few hundred thousand dofs, measured in the README), MUMPS in parallel."""
    return "petsc" if comm.size == 1 else "mumps"


@contextmanager
def _pushed(prefix: str, defaults: Mapping[str, str],
            overrides: Optional[Mapping[str, str]] = None) -> Iterator[None]:
    """Push `defaults` (unless already set) and `overrides` under `prefix`, then remove them.
    Whether an option is set is read from the whole database (getAll), which, unlike hasName,
    does not mark the user's options used."""
    opts = PETSc.Options()
    present = {name.lower() for name in opts.getAll()}
    pushed = []
    for key, value in {**defaults, **(overrides or {})}.items():
        full = prefix + key
        if key in (overrides or {}) or full.lower() not in present:
            opts[full] = value
            pushed.append(full)
    try:
        yield
    finally:
        for full in pushed:
            opts.delValue(full)


@contextmanager
def petsc_options(prefix: str, defaults: Mapping[str, str],
                  overrides: Optional[Mapping[str, str]] = None) -> Iterator[None]:
    """Push `defaults` (unless already set) and `overrides` under `prefix`, then remove them.

    Raises:
        InputError: PETSc rejected the options while they were set (an unknown solver or
            preconditioner type, a value of the wrong kind), naming the options given.
    """
    with _pushed(prefix, defaults, overrides):
        try:
            yield
        except PETSc.Error as exc:
            given = ", ".join(f"{k}={v}" for k, v in (overrides or {}).items()) or "none given"
            raise InputError(f"PETSc rejected the solver options under {prefix} (options: "
                             f"{given}): {last_line(exc)} (PETSc error {exc.ierr})") from None


class SolverOptions:
    """The options of one solver: `defaults` under `prefix`, the user's (`overrides`, and
    PETSC_OPTIONS under the prefix) on top. Checked at construction (InputError, collective);
    set while the solver is set up (`setup`, which refuses options left unused) and while it
    solves (`solving`: options PETSc reads only then, such as ksp_converged_reason or MUMPS's
    mat_mumps_* at the first factorisation, take effect).

    Args:
        path: "forms", "snes" or "kronecker" (fem_dual.petsc_check).
    """

    def __init__(self, prefix: str, defaults: Mapping[str, str],
                 overrides: Optional[Mapping[str, str]], path: str,
                 comm: MPI.Comm = MPI.COMM_WORLD):
        self.prefix, self.defaults, self.path, self.comm = prefix, dict(defaults), path, comm
        self.overrides = dict(overrides or {})
        self.given = user_options(prefix, self.overrides)
        _collective(comm, lambda: check_user_options(prefix, self.overrides, path))

    def value(self, key: str) -> Optional[str]:
        """The value in force for `key` (the user's, else the default)."""
        if key in self.given:
            return self.given[key][0]
        return self.defaults.get(key)

    @contextmanager
    def setup(self) -> Iterator[None]:
        """The options set for the solver's set-up (setFromOptions and what follows). A PETSc
        error in it is an InputError naming the options given; afterwards every user option the
        set-up did not query is one. Collective."""
        with _pushed(self.prefix, self.defaults, self.overrides):
            failure = None
            try:
                yield
            except PETSc.Error as exc:
                given = ", ".join(f"{k}={v}" for k, (v, _) in self.given.items())
                failure = (f"PETSc cannot set up the {self.path} solver with the options "
                           f"{given or '(defaults only)'}: "
                           f"{last_line(exc)} (PETSc error {exc.ierr})")
            failures = [f for f in self.comm.allgather(failure) if f]
            if failures:
                raise InputError(failures[0])
            _collective(self.comm, lambda: require_used(
                self.given, self.prefix, self.path, self.comm,
                values={k: self.value(k) or "" for k in ("ksp_type", "pc_type")}))

    def solving(self):
        """The options set while the solver solves (nothing to do without --petsc-option)."""
        if not self.overrides:
            return contextlib.nullcontext()
        return _pushed(self.prefix, self.defaults, self.overrides)

    def probe(self) -> None:
        """Set up (PCSetUp: factorisation packages, sub-solvers) a KSP under the solver's prefix
        on a small identity matrix of the slab matrix's type and communicator, so that the
        options PETSc reads only at set-up are checked (and queried) now, before any work. Only
        with user options (a default run factors nothing extra). Collective."""
        if not self.given:
            return
        comm = self.comm
        A = PETSc.Mat().createAIJ(((1, None), (1, None)), nnz=(1, 0), comm=comm)
        row = A.getOwnershipRange()[0]
        A.setValue(row, row, 1.0)
        A.assemble()
        ksp = PETSc.KSP().create(comm)
        try:
            ksp.setOptionsPrefix(self.prefix)
            ksp.setOperators(A)
            ksp.setFromOptions()
            ksp.setUp()
        finally:
            ksp.destroy()
            A.destroy()


def _collective(comm: MPI.Comm, check) -> None:
    """Run `check` on every rank; if it raised InputError on any, raise the first rank's message
    on all."""
    error = None
    try:
        check()
    except InputError as exc:
        error = str(exc)
    errors = [e for e in comm.allgather(error) if e]
    if errors:
        raise InputError(errors[0])


class CompiledSlab:
    """The compiled residual and Jacobian of a slab problem, with the matrix and vector they fill;
    the part every slab solver shares."""

    def __init__(self, problem: SlabProblem):
        self.problem = problem
        tic = time.perf_counter()
        self.a = compile_form(problem.jacobian)
        self.L = compile_form(problem.residual)
        self.compile_s = time.perf_counter() - tic
        self.A = fem_petsc.create_matrix(self.a)
        self.b = fem_petsc.create_vector(self.L)

    def close(self) -> None:
        """Destroy the PETSc objects (collective); the solver cannot solve any more."""
        destroy_petsc(self.A, self.b)


class LinearSlabSolver(CompiledSlab):
    """One KSP solve per slab of the quadratic dual action: J w = -R(0).

    The Jacobian does not depend on the initial or base state; it is assembled and factored once
    and again only when the slab length changes.
    """

    def __init__(self, problem: SlabProblem, prefix: str,
                 overrides: Optional[Mapping[str, str]] = None):
        defaults = {**LINEAR_DEFAULTS, "pc_factor_mat_solver_type": direct_solver(problem.comm)}
        self.options = SolverOptions(prefix, defaults, overrides, "forms", problem.comm)
        if not any(key.startswith(("ksp_", "pc_")) for key in self.options.given):
            self.options.defaults.update(REFINED_LU)
        super().__init__(problem)  # compiles: after the options are checked
        self.ksp = PETSc.KSP().create(problem.comm)
        self.ksp.setOperators(self.A)
        self.ksp.setOptionsPrefix(prefix)
        with self.options.setup():
            self.ksp.setFromOptions()
            self.options.probe()
        self._assembled_dt: Optional[float] = None
        self.iterations = []
        self.assemblies = 0

    def close(self) -> None:
        destroy_petsc(self.ksp)
        super().close()

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
            with self.options.solving():
                self.ksp.solve(self.b, p.w.vector)
        except PETSc.Error as exc:
            raise SolveError(f"linear solve failed (PETSc error {exc.ierr})") from None
        reason = self.ksp.getConvergedReason()
        if reason < 0:
            raise SolveError(f"linear solve did not converge (KSP reason {reason})")
        its = self.ksp.getIterationNumber()
        self.iterations.append(its + check_true_residual(self.ksp, self.A, p.w.vector, self.b))
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
REFINED_RESIDUAL = 1e-12  # |b - A x| / |b| that iterative refinement aims at
MAX_REFINEMENTS = 4


def check_true_residual(ksp: PETSc.KSP, A: PETSc.Mat, x: PETSc.Vec, b: PETSc.Vec) -> int:
    """Refine an iterative solve's x until it solves A x = b to REFINED_RESIDUAL (x += A^-1
    (b - A x), each correction by the same KSP, at most MAX_REFINEMENTS times, while the residual falls), and
    raise SolveError unless it reaches TRUE_RESIDUAL_TOL. A loosened ksp_rtol then costs
    iterations, not accuracy: its algebraic error is in no error estimate (the companion,
    stopped by the same test, does not show it). A KSP that "converged" on a preconditioned or
    unchecked residual (preonly with a preconditioner that is not a direct solver) does not pass
    its answer on. Returns the KSP iterations the refinement took. Collective."""
    r, dx = b.duplicate(), b.duplicate()
    iterations = 0
    # a direct solve is backward stable: its residual is round-off of |A| |x|, which the same
    # factors cannot reduce further than the KSP's own refinement step (REFINED_LU) did: they
    # are checked, not refined
    iterative = ksp.getPC().getType() not in ("lu", "cholesky")
    try:
        bnorm = max(b.norm(), 1e-300)
        previous = math.inf
        for step in range(MAX_REFINEMENTS + 1):
            A.mult(x, r)
            r.aypx(-1.0, b)
            rel = r.norm() / bnorm
            if (not rel > REFINED_RESIDUAL or step == MAX_REFINEMENTS or not iterative
                    or not rel < 0.5 * previous):
                break
            previous = rel
            ksp.solve(r, dx)
            if ksp.getConvergedReason() < 0:
                break
            iterations += ksp.getIterationNumber()
            x.axpy(1.0, dx)
    finally:
        r.destroy(), dx.destroy()
    if not rel <= TRUE_RESIDUAL_TOL:
        pc = ksp.getPC().getType()
        if pc in ("lu", "cholesky"):
            raise SolveError(f"the slab matrix is numerically singular: its LU solve leaves a "
                             f"true residual {rel:.3g} relative; the "
                             "scene's scales are too far apart (rescale time or masses, or "
                             "give H weights A and B that balance them)")
        raise SolveError(f"the slab's linear solve is inaccurate: true residual "
                         f"{rel:.3g} relative (at most "
                         f"{TRUE_RESIDUAL_TOL:g}) with ksp_type={ksp.getType()}, pc_type={pc}; "
                         "use a direct solver (pc_type=lu) or an iterative one with ksp_rtol "
                         "1e-12")
    return iterations


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
    destroy_petsc(x, y)
    return value
