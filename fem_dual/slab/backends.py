"""The slab backends (fem_dual.slab.backend's protocol) and `make_backend`, which builds one.

Pointwise and forms backends hold a `SlabProblem` (UFL of the slab's action), its solver and a
`VertexSampler`; the pointwise ones hold the problem on one process and assemble it from the
density's pointwise derivatives (fem_dual.slab.local_action), the forms ones distribute it over
the communicator and solve it with PETSc. The Kronecker backend holds a linear scene's slab as
sums of Kronecker products (fem_dual.slab.kronecker).
"""
from __future__ import annotations

from typing import Any, Dict, List, Mapping, Optional, Tuple

import numpy as np
from mpi4py import MPI

from fem_dual.errors import SolveError
from fem_dual.slab.backend import LinearSlabBackend, NonlinearSlabBackend, SlabBackend
from fem_dual.slab.values import VertexValues

__all__ = ["make_backend", "ASSEMBLIES"]

ASSEMBLIES = ("pointwise", "forms", "kronecker", "spacetime")

# A partner's solution (the answer's, for its error companion) is a start only when its residual
# in the companion's space is below WARM_TRUST of the zero dual state's; otherwise the companion
# is solved again from zero, independently, as every answer is. At WARM_REFUSE or more it is no
# nearer than zero at all: the answer has converged to another solution of its slab's
# equations, and the slab fails (it is retried shorter). A companion started there lands on that
# solution's neighbour in its own space, and solved from zero it may creep there too, so that
# their difference cannot show the answer's error: curl3d T = 9.3, 45 slabs, 8 cells, p = 4,
# slab at t = 8.27 (ratio 5.0): error 9.5 against an estimate of 2.1e-2; 15 slabs of 10 cells,
# p = 4 (ratio 3.5): 2.3 against 1.6e-2; T = 9.096, 14 x 9, p = 4 (ratio 7.8): 0.61 against
# 1.4e-3. Slabs that follow the motion start their companions at 1e-5 to 1e-4 of the zero
# state's residual, coarse ones up to 0.32 (curl3d T = 8, 16 slabs of 8 cells, p = 2, honest).
# Below WARM_REFUSE the ratio does not tell a wrong answer (docs/limits.md). Nor above it
# alone: with badly balanced weights (curl3d alpha = 1e3, beta = 1e-3) a correct answer's
# solution starts its companion at 3.3 times the zero state's residual, so the slab fails only
# where the answer's Newton also started damped (`damped_start`: the three wrong answers above
# began 0.92, 0.96 and 0.72 of their first residual after one step; that one 2.7e-4).
WARM_TRUST = 0.1
WARM_REFUSE = 1.0


class _ProblemParts:
    """What the pointwise and forms backends share: a SlabProblem, its solver, its sampler."""

    def _hold(self, problem, solver, sampler, assembly: str) -> None:
        self.problem, self.solver, self.sampler = problem, solver, sampler
        self.scene, self.degree, self.cells = problem.scene, problem.degree, problem.mesh.cells
        self.comm, self.assembly = problem.comm, assembly
        self.mesh, self.predictor = problem.mesh, problem.predictor

    @property
    def num_dofs(self) -> int:
        return self.problem.num_dofs

    @property
    def solves(self) -> int:
        return len(self.solver.iterations)

    def set_scene(self, scene) -> None:
        self.problem.set_scene_constants(scene)
        self.scene = scene

    def _reset(self) -> None:
        self.solver.reset()
        if self.predictor is not None:  # (a timed repeat must step its base afresh)
            self.predictor.forget()

    def _set_slab(self, z0: np.ndarray, t0: float, dt: float) -> None:
        n = self.scene.n
        self.problem.set_slab(z0[:n], z0[n:], dt, t0)

    def sample(self) -> Optional[VertexValues]:
        return self.sampler()

    def close(self) -> None:
        self.solver.close()
        self.sampler.close()
        self.problem.close()

    def _rk4_loops(self) -> List[str]:
        return ["rk4"] if self.predictor is not None and self.predictor.compiled else []


class _LinearParts(_ProblemParts, LinearSlabBackend):
    """A linear scene's slab on a SlabProblem: one linear solve a slab."""

    def reset(self, adaptive: bool) -> None:
        self._reset()

    def solve(self, z0, t0, dt, start=None) -> Optional[VertexValues]:
        self._set_slab(z0, t0, dt)
        self.solver.solve()
        return self.sampler()

    def superposition(self, T: float, hamiltonian: bool):
        from fem_dual.slab.superposition import Superposition

        return Superposition(self.problem, self.solver, self.sampler, T, hamiltonian)

    def condition_estimate(self) -> Optional[float]:
        return self.solver.condition_estimate()


class _NewtonParts(_ProblemParts, NonlinearSlabBackend):
    """A nonlinear scene's slab on a SlabProblem: Newton, and the linearisation of its
    solution."""

    def reset(self, adaptive: bool) -> None:
        from fem_dual.slab.snes import NO_PROGRESS_ITS

        self._reset()
        # guessed slab lengths (--rtol) give up early on a Newton that makes no progress
        self.solver.patience = NO_PROGRESS_ITS if adaptive else None

    def damped_start(self) -> bool:
        """Whether the last solve's first Newton step lowered the residual by less than half
        (its line search cut it: the iterate went far from the base's correction, where another
        solution of the slab's equations can be reached; a Newton that converges quadratically
        from the start stays near it)."""
        history = self.solver.histories[-1] if self.solver.histories else []
        return len(history) > 1 and history[1] > 0.5 * history[0]

    def _no_start(self, warm: float, first: float) -> bool:
        """Whether a warm start's residual `warm` is no nearer than the zero state's `first`
        (WARM_REFUSE), above the residual's round-off (where residuals tell nothing: an
        equilibrium's zero state is its solution)."""
        if warm < WARM_REFUSE * first:
            return False
        from fem_dual.slab.snes import RESIDUAL_ROUNDOFF, residual_size  # (the Newton's own)

        return not warm < RESIDUAL_ROUNDOFF * residual_size(self.problem)

    def first_residual(self) -> Optional[float]:
        """The residual norm of the zero dual state in the last solve (None: none recorded)."""
        first = self.solver.histories[-1][:1]
        return first[0] if first else None

    def solve(self, z0, t0, dt, start=None) -> Optional[VertexValues]:
        self._set_slab(z0, t0, dt)
        first = start.first_residual() if start is not None else None
        if first is not None and first > 0:  # (no history: options without a residual norm)
            self.problem.take_dual_state(start.problem)
            self.solver.solve(warm=first)
            warm = self.first_residual()  # (the warm start's: the first of this solve)
            if warm is not None and self._no_start(warm, first) and start.damped_start():
                raise SolveError(f"the answer's solution is no start for its degree p + 1 "
                                 f"companion (residual {warm:.3g} there, {first:.3g} from "
                                 "zero): it converged to another solution of the slab's "
                                 "equations")
            if warm is not None and not warm <= WARM_TRUST * first:
                self.solver.solve()
        else:
            self.solver.solve()
        return self.sampler()

    def verify(self) -> Optional[str]:
        if self.solver.stalled():
            its = self.solver.iterations[-1]
            return (f"Newton stalled before it converged ({its} iterations): it may have found "
                    "another solution branch")
        return None

    def perturb_start(self, z0, dz, relative, scale) -> float:
        return self.solver.tangent(z0, dz, relative, scale)

    def newton_step(self) -> None:
        self.solver.newton_step()

    def restore(self, z0) -> None:
        self.solver.restore(z0)

    def mass_and_damping(self) -> Tuple[np.ndarray, Optional[np.ndarray]]:
        c = self.problem.c  # (the scene's values, as the slab used them)
        return c["M"].value, c["D"].value if "D" in c else None

    def record(self, prefix: str) -> Dict[str, Any]:
        s = self.solver
        return {"kind": self.kind, "prefix": prefix, "newton_iterations": list(s.iterations),
                "residual_norms": list(s.residual_norms),
                "residual_histories": [list(h) for h in s.histories]}

    def _dtp_loops(self, newton: bool) -> List[str]:
        dtp = self.problem.pointwise  # (an implicit DtP map solved at the quadrature points)
        return ["dtp"] if dtp is not None and (newton or dtp.compiled) else []


class PointwiseLinear(_LinearParts):
    """Linear slabs assembled pointwise, one banded LU a slab length (every rank the whole
    slab)."""

    def __init__(self, problem, recovery: str, with_dual: bool):
        from fem_dual.slab.pointwise_newton import PointwiseLinearSolver
        from fem_dual.slab.recovery import VertexSampler

        solver = PointwiseLinearSolver(problem)
        sampler = VertexSampler(problem, with_dual=with_dual, recovery=recovery,
                                momenta=solver.local.momenta)
        solver.local.factor_solution = with_dual  # (the companion takes no tangents)
        self._hold(problem, solver, sampler, "pointwise")

    def record(self, prefix: str) -> Dict[str, Any]:
        return {"kind": "direct", "prefix": prefix, "solves": len(self.solver.iterations)}

    def compiled_loops(self) -> List[str]:
        return self._rk4_loops() + (["band"] if self.solver.local.compiled_band else [])


class PointwiseNewton(_NewtonParts):
    """Nonlinear slabs assembled pointwise, the dense Newton of fem_dual.slab.pointwise_newton,
    with the exact linearisation of the solved slab where its base state allows."""

    kind = "newton"

    def __init__(self, problem, recovery: str, with_dual: bool):
        from fem_dual.slab.pointwise_newton import PointwiseNewtonSolver
        from fem_dual.slab.recovery import VertexSampler

        solver = PointwiseNewtonSolver(problem)
        sampler = VertexSampler(problem, with_dual=with_dual, recovery=recovery,
                                momenta=solver.local.momenta)
        solver.local.factor_solution = with_dual  # (the companion takes no tangents)
        self._hold(problem, solver, sampler, "pointwise")
        self.exact_tangents = solver.exact_tangents
        self._momentum = recovery == "momentum"

    def exact_tangent(self, dz: np.ndarray) -> np.ndarray:
        return self.solver.exact_tangent(dz)

    def newton_change(self) -> Optional[np.ndarray]:
        """The exact one where the vertex values are the momenta's (else None: the integrator
        takes a Newton step and samples)."""
        return self.solver.newton_change() if self._momentum and self.exact_tangents else None

    def slab_jacobian(self) -> Optional[np.ndarray]:
        return self.solver.slab_jacobian()

    def compiled_loops(self) -> List[str]:
        local = self.solver.local
        newton = bool(local.compiled_newton)
        loops = self._rk4_loops() + (["band"] if local.compiled_band else [])
        loops += ["newton"] if newton else []
        loops += self._dtp_loops(newton)
        if local.compiled_tangents and self.problem.base != "start":
            loops.append("tangents")
        return loops


class FormsLinear(_LinearParts):
    """Linear slabs on the UFL forms: PETSc KSP (LU by default), distributed over comm."""

    def __init__(self, problem, prefix: str, petsc, recovery: str, with_dual: bool):
        from fem_dual.slab.petsc_solvers import LinearSlabSolver
        from fem_dual.slab.recovery import VertexSampler

        solver = LinearSlabSolver(problem, prefix, petsc)
        self._hold(problem, solver, VertexSampler(problem, with_dual=with_dual,
                                                  recovery=recovery), "forms")

    def record(self, prefix: str) -> Dict[str, Any]:
        return {"kind": "ksp", "prefix": prefix, "ksp_iterations": list(self.solver.iterations)}

    def compiled_loops(self) -> List[str]:
        return self._rk4_loops()


class FormsNewton(_NewtonParts):
    """Nonlinear slabs on the UFL forms: PETSc SNES, distributed over comm."""

    kind = "snes"

    def __init__(self, problem, prefix: str, petsc, recovery: str, with_dual: bool):
        from fem_dual.slab.recovery import VertexSampler
        from fem_dual.slab.snes import NewtonSlabSolver

        solver = NewtonSlabSolver(problem, prefix, petsc)
        self._hold(problem, solver, VertexSampler(problem, with_dual=with_dual,
                                                  recovery=recovery), "forms")

    def compiled_loops(self) -> List[str]:
        return self._rk4_loops() + self._dtp_loops(False)


class KroneckerBackend(LinearSlabBackend):
    """Linear slabs in Kronecker form: matrix-free CG with the fast-diagonalisation
    preconditioner; each rank owns a share of the n components."""

    assembly = "kronecker"

    def __init__(self, scene, degree: int, cells: int, comm: MPI.Comm, prefix: str, petsc,
                 base: str, with_dual: bool):
        from fem_dual.slab.kronecker import KroneckerProblem, KroneckerSampler
        from fem_dual.slab.kronecker_solver import KroneckerSolver

        self.problem = KroneckerProblem(scene, degree, cells, comm, base)
        self.solver = KroneckerSolver(self.problem, prefix, petsc)
        self.sampler = KroneckerSampler(self.problem, with_dual=with_dual)
        self.scene, self.degree, self.cells, self.comm = scene, degree, cells, comm

    @property
    def num_dofs(self) -> int:
        return self.problem.num_dofs

    @property
    def solves(self) -> int:
        return len(self.solver.iterations)

    def set_scene(self, scene) -> None:
        self.problem.set_scene_constants(scene)
        self.scene = scene

    def reset(self, adaptive: bool) -> None:
        self.solver.reset()

    def solve(self, z0, t0, dt, start=None) -> Optional[VertexValues]:
        n = self.scene.n
        self.problem.set_slab(z0[:n], z0[n:], dt, t0)
        self.solver.solve()
        return self.sampler()

    def superposition(self, T: float, hamiltonian: bool):
        from fem_dual.slab.kronecker import KroneckerSuperposition

        # (H_d from the fields, whatever `hamiltonian`)
        return KroneckerSuperposition(self.problem, self.solver, self.sampler, T)

    def basis_solves(self) -> int:
        from fem_dual.slab.kronecker import KroneckerSuperposition

        return KroneckerSuperposition.solves_per_basis(self.problem)

    def record(self, prefix: str) -> Dict[str, Any]:
        return {"kind": "ksp", "prefix": prefix, "ksp_iterations": list(self.solver.iterations)}

    def close(self) -> None:
        self.solver.close()  # (the problem and the sampler hold no PETSc object)


def make_backend(scene, degree: int, cells: int, comm: MPI.Comm, assembly: str, prefix: str,
                 petsc: Optional[Mapping[str, str]], recovery: str, with_dual: bool, base: str,
                 mesh=None, shared_predictor=None) -> SlabBackend:
    """The backend that solves `scene`'s slabs with `assembly` (ASSEMBLIES).

    Args:
        scene: the scene whose slabs are solved (the modal scene in modal coordinates).
        degree, cells: the dual fields' degree and the time cells per slab.
        comm: the communicator (a pointwise slab is held whole by every rank).
        prefix, petsc: the PETSc options prefix and the user's options (forms, kronecker).
        recovery: how the primal state is read from the dual solution ("momentum", "dtp").
        with_dual: also sample the dual fields (output); the error companion does without.
        base: the base state of H on a slab (fem_dual.choices.BASES).
        mesh: a slab mesh to share (the companion uses its partner's; on the space-time
            path, the partner's distributed spatial system).
        shared_predictor: the base state's predictor to use instead of a new one.
    """
    if assembly == "kronecker":
        return KroneckerBackend(scene, degree, cells, comm, prefix, petsc, base, with_dual)
    if assembly == "spacetime":
        from fem_dual.continua.spacetime_backend import SpaceTimeBackend

        return SpaceTimeBackend(scene, degree, cells, comm, prefix, petsc, with_dual, mesh)
    from fem_dual.slab.problem import SlabProblem

    if assembly == "pointwise":  # the slab is small: every rank holds and solves it whole
        problem = SlabProblem(scene, degree, cells, MPI.COMM_SELF, base, mesh, shared_predictor)
        kind = PointwiseLinear if scene.linear else PointwiseNewton
        return kind(problem, recovery, with_dual)
    problem = SlabProblem(scene, degree, cells, comm, base, mesh, shared_predictor)
    kind = FormsLinear if scene.linear else FormsNewton
    return kind(problem, prefix, petsc, recovery, with_dual)
