"""The slab-backend protocol: what the integrator asks of one slab's dual problem.

A backend holds one slab's compiled problem, its solver and its primal recovery, and solves the
slab [t0, t0 + dt] from a start state z0 = (x0, v0) into the primal state at the slab's
vertices. For the error estimate (fem_dual.integrate) it also linearises the solved slab: the
change of the vertex values with the start state (tangent), and how far one more Newton step
would move them (algebraic error). Linear scenes add a superposition of solved unit start
states. The integrator calls only what this protocol names (as scipy's `OdeSolver` lists what
a subclass provides). The implementations (fem_dual.slab.backends, `make_backend` chooses):

- pointwise: derivatives of L_d at the quadrature points, banded LU (linear) or dense Newton
  (nonlinear); every rank solves the whole slab.
- forms: UFL forms assembled by DOLFINx, PETSc KSP or SNES, distributed over the communicator.
- kronecker: linear scenes in Kronecker form, sums of (time matrix) x (n x n coefficient),
  matrix-free CG.
"""
from __future__ import annotations

import abc
from typing import Any, Dict, List, Optional, Tuple

import numpy as np
from mpi4py import MPI

from fem_dual.slab.values import VertexValues

__all__ = ["SlabBackend", "LinearSlabBackend", "NonlinearSlabBackend"]


class SlabBackend(abc.ABC):
    """One slab's dual problem, solved one way.

    Attributes every backend sets:
        scene: the scene whose slabs it solves (in modal coordinates: the modal scene).
        degree, cells: the dual fields' degree and the time cells per slab.
        comm: the communicator it solves over.
        assembly: its name in the JSON (`solver.assembly`): "pointwise", "forms", "kronecker".
        num_dofs: dual unknowns per slab.
        mesh: the slab mesh an error companion shares (None: nothing to share).
        predictor: the flow predictor of a base state that is a function of time, or None.
        linear: whether the scene is linear: a `LinearSlabBackend` (one linear solve per
            slab, superposition) or a `NonlinearSlabBackend` (Newton, linearisation).
    """

    scene: Any
    degree: int
    cells: int
    comm: MPI.Comm
    assembly: str
    mesh: Any = None
    predictor: Any = None

    @property
    def linear(self) -> bool:
        return bool(self.scene.linear)

    @property
    @abc.abstractmethod
    def num_dofs(self) -> int:
        """Dual unknowns per slab."""

    # -- a run ----------------------------------------------------------------------------------

    @abc.abstractmethod
    def set_scene(self, scene) -> None:
        """Use the parameter values of `scene`, a scene of the same kind and size (nothing is
        compiled again)."""

    @abc.abstractmethod
    def reset(self, adaptive: bool) -> None:
        """Forget the counts of earlier runs; `adaptive`: slab lengths are the controller's
        guesses (a Newton that makes no progress gives up early)."""

    @abc.abstractmethod
    def close(self) -> None:
        """Destroy the PETSc objects (collective); the backend cannot solve after it."""

    # -- one slab -------------------------------------------------------------------------------

    @abc.abstractmethod
    def solve(self, z0: np.ndarray, t0: float, dt: float,
              start: Optional["SlabBackend"] = None) -> Optional[VertexValues]:
        """The vertex values of the slab [t0, t0 + dt] from z0 on rank 0 (None elsewhere).
        `start`: a nonlinear slab's Newton starts from that backend's solved dual state of the
        same slab (the error companion from its answer's). Collective; raises SolveError."""

    @property
    @abc.abstractmethod
    def solves(self) -> int:
        """Slab solves so far in this run (tangent solves of linear slabs included)."""

    # -- what the JSON reports --------------------------------------------------------------------

    @abc.abstractmethod
    def record(self, prefix: str) -> Dict[str, Any]:
        """The solver's part of the JSON `solver` record: kind, prefix, iteration counts."""

    def compiled_loops(self) -> List[str]:
        """Which inner loops ran in compiled code (fem_dual.native): "rk4", "band", "newton",
        "dtp", "tangents"."""
        return []


class LinearSlabBackend(SlabBackend):
    """A backend of a linear scene: the slab's action is quadratic, one linear solve a slab, and
    the vertex values are linear in the start state (superposition)."""

    superposes: bool = True  # whether `superposition` is available

    @abc.abstractmethod
    def superposition(self, T: float, hamiltonian: bool):
        """Slabs of any start state from this backend's solved unit start states, one basis per
        slab length (fem_dual.slab.superposition); `hamiltonian`: H_d of the fields too. `T`:
        the horizon the basis's slab map is checked against."""

    def basis_solves(self) -> int:
        """Slab solves a superposition basis of one slab length costs."""
        return 2 * self.scene.n

    def condition_estimate(self) -> Optional[float]:
        """lambda_max / lambda_min of the last slab length's matrix (SPD), by power iteration;
        None where the backend holds no matrix (matrix-free)."""
        return None


class NonlinearSlabBackend(SlabBackend):
    """A backend of a nonlinear scene: Newton on the slab's action, and the linearisation of a
    solved slab that the error estimate needs.

    Attributes:
        exact_tangents: whether `exact_tangent` and `newton_change` apply (the exact
            linearisation of the solved slab); else tangents are difference quotients of
            `perturb_start`.
    """

    exact_tangents: bool = False

    @abc.abstractmethod
    def verify(self) -> Optional[str]:
        """Why the last solve cannot be trusted although it converged (a Newton that stalled:
        it may have found another branch), or None."""

    @abc.abstractmethod
    def perturb_start(self, z0: np.ndarray, dz: np.ndarray, relative: float,
                      scale: Optional[float]) -> float:
        """Leave the problem at start state z0 + eps dz with its dual state moved to first
        order (a residual and a solve with the last Newton step's factors); returns eps.
        `sample` reads it, `restore(z0)` goes back. Collective."""

    @abc.abstractmethod
    def newton_step(self) -> None:
        """Leave the problem one more Newton step past its solution (`restore` goes back)."""

    @abc.abstractmethod
    def restore(self, z0: np.ndarray) -> None:
        """Back to the solved slab from start state z0 after `perturb_start`/`newton_step`."""

    @abc.abstractmethod
    def sample(self) -> Optional[VertexValues]:
        """The vertex values of the problem's current dual state on rank 0. Collective."""

    @abc.abstractmethod
    def mass_and_damping(self) -> Tuple[np.ndarray, Optional[np.ndarray]]:
        """(M, D) as the slab uses them (D None without damping): the flow's volume change."""

    def slab_jacobian(self) -> Optional[np.ndarray]:
        """d z_end / d z0 (2n, 2n) of the solved slab, exactly; None where the backend has
        none (the integrator then takes difference tangents)."""
        return None

    def exact_tangent(self, dz: np.ndarray) -> np.ndarray:
        """d(x, v)/dz0 . dz at the vertices (vertices, 2n) of the solved slab, exactly (where
        `exact_tangents`)."""
        raise TypeError(f"{type(self).__name__} has no exact tangents")

    def newton_change(self) -> Optional[np.ndarray]:
        """How far the vertex values (vertices, 2n) would move with one more Newton step, from
        the exact linearisation; None where there is none (the integrator then takes
        `newton_step` and samples)."""
        return None
