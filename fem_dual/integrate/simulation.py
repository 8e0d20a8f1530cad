"""The simulation: a slab backend with its error companion, stepped slab by slab.

One step is one slab: the answer (degree p), its companion (degree p + 1, the error estimate's
embedded partner), the tangent that carries the start state's error through the slab, and, for
linear scenes, slab maps from superposition. Everything here goes through the slab-backend
protocol (fem_dual.slab.backend); the loop over slabs is fem_dual.integrate.loop.
"""
from __future__ import annotations

import time
from typing import TYPE_CHECKING, Dict, Optional, Tuple

import numpy as np
from mpi4py import MPI

from fem_dual.compat import quiet_jit_logging
from fem_dual.config import RunConfig, auto_pointwise
from fem_dual.integrate.estimate import ESTIMATE_SAFETY
from fem_dual.integrate.loop import run_slabs
from fem_dual.mpi import root_first
from fem_dual.petsc_check import solver_prefix
from fem_dual.quiet import quiet_numpy
from fem_dual.slab.backends import make_backend
from fem_dual.slab.base_state import FlowPredictor
from fem_dual.slab.modal import RESOLVED_TURN, ModalBasis
from fem_dual.slab.values import VertexValues

if TYPE_CHECKING:
    from fem_dual.integrate.flow_check import FlowCheck

__all__ = ["Simulation"]


class Simulation:
    """A compiled slab problem with its solver and vertex recovery (a slab backend): everything
    a run builds before its first slab. Build it once and `run` it for many horizons, start
    states or slab settings of the same scene, degree and cells per slab (`fem-dual bench`
    does).

    Args:
        scene: the validated scene.
        degree, cells: the dual fields' degree and the time cells per solved slab.
        comm: the communicator.
        petsc: PETSc options for the slab solver.
        recovery: how the primal state is read from the dual solution ("momentum" or "dtp").
        kronecker: linear scenes: solve in Kronecker form (matrix-free CG).
        with_dual: also sample the dual fields (output); the error companion does without.
        base: the base state of H on a slab (fem_dual.choices.BASES).
        modal: linear scenes: solve in modal coordinates (fem_dual.slab.modal); a ModalBasis
            is shared (the error companion uses its partner's).
        mesh: the slab mesh to share (the companion uses its partner's).
        shared_predictor: the base state's predictor to use (the companion's: a linearised
            predictor is its partner's, an rk4 one its own with twice the steps).
        pointwise: assemble pointwise and solve by the banded LU or dense Newton of
            fem_dual.slab.pointwise_newton (every rank solves the whole slab), not by PETSc KSP
            or SNES on forms distributed over `comm`; None: unless PETSc options are given.
    """

    def __init__(self, scene, degree: int, cells: int, comm: MPI.Comm = MPI.COMM_WORLD,
                 petsc: Optional[Dict[str, str]] = None, recovery: str = "momentum",
                 kronecker: bool = False, with_dual: bool = True, base: str = "start",
                 modal: "bool | ModalBasis" = False, mesh=None,
                 pointwise: Optional[bool] = None, shared_predictor=None,
                 spacetime: bool = False):
        if pointwise is None:  # as RunConfig's auto
            pointwise = auto_pointwise(scene, cells, degree, petsc, kronecker) and not spacetime
        pointwise = pointwise and not kronecker
        tic = time.perf_counter()
        self.scene, self.degree, self.cells, self.comm = scene, degree, cells, comm
        self.prefix = solver_prefix(scene.name)
        self.recovery, self.kronecker, self.petsc, self.base = recovery, kronecker, petsc, base
        self.pointwise, self.spacetime = pointwise, spacetime
        self.modal = modal if isinstance(modal, ModalBasis) else (ModalBasis(scene) if modal
                                                                  else None)
        solved = self.modal.scene if modal else scene  # the scene whose slabs are solved
        assembly = ("spacetime" if spacetime else "kronecker" if kronecker
                    else "pointwise" if pointwise else "forms")

        def build():
            with quiet_jit_logging():
                self.backend = make_backend(solved, degree, cells, comm, assembly, self.prefix,
                                            petsc, recovery, with_dual, base, mesh,
                                            shared_predictor)
        # A pointwise backend's forms and expressions live on COMM_SELF meshes, so every rank
        # would compile the same code at the same time: FFCx lets one write it and the others
        # wait 10 s for it, then fail, alone, leaving the rest in a collective. Rank 0
        # compiles first; the others load its cache.
        root_first(comm, build) if pointwise else build()
        self.with_dual = with_dual
        self.setup_s = time.perf_counter() - tic
        self._fresh = True
        self._companion: Optional["Simulation"] = None
        self._flow_check: Optional["FlowCheck"] = None
        # whether a partner's solved dual state is a start for ours (solve_slab): not where our
        # base state is a run of our own (the companion's rk4, with twice the steps)
        self._warm = not isinstance(shared_predictor, FlowPredictor)
        self.superposition = None
        self.tangent_solves = 0
        self.direct_solves = 0  # slabs of a superposed run solved directly (`_superposed`)
        self._first_t0: Dict[float, float] = {}
        self._eager_bases = True
        self._maps: Dict[float, Tuple[np.ndarray, np.ndarray]] = {}
        self._pairs: Dict[float, np.ndarray] = {}
        self.resolution = (cells, degree)  # which modes the zero base drops (the companion's:
        self.adaptive = False  # its partner's), under a tolerance

    def close(self) -> None:
        """Destroy the PETSc objects of the backend and the companion; the simulation cannot
        solve after it. Collective: call it on every rank at the same point (MUMPS ends its
        factorisation collectively). petsc4py 3.18 does not destroy what Python drops
        (fem_dual.compat.destroy_petsc): a run that did not close its Simulation kept 160 KB
        (ziegler, 2 dofs) to 290 KB (curl3d) allocated for good."""
        if self._companion is not None:
            self._companion.close()
        self.backend.close()

    def charged_setup(self) -> float:
        """The set-up seconds a run reports as its compile time: all of them for the first run
        of this simulation, none after."""
        seconds = self.setup_s if self._fresh else 0.0
        self._fresh = False
        return seconds

    def uses_superposition(self, config: RunConfig) -> bool:
        if not getattr(self.backend, "superposes", False):
            return False
        if config.superpose != "auto":
            return config.superpose == "yes"
        if config.rtol is not None:  # adaptive lengths recur (powers of two): bases pay off
            return self.scene.linear
        return self.scene.linear and config.slab_count > self.backend.basis_solves()

    @classmethod
    def for_config(cls, config: RunConfig, comm: MPI.Comm = MPI.COMM_WORLD) -> "Simulation":
        """The simulation that runs `config` (its staged cells per slab)."""
        return cls(config.scene, config.degree, config.slab_cells, comm, config.petsc,
                   config.recovery, config.kronecker, base=config.base_state,
                   modal=config.modal, pointwise=config.pointwise,
                   spacetime=config.spacetime)

    def matches(self, config: RunConfig) -> bool:
        """Whether `config` runs on this simulation's compiled slab problem."""
        return ((config.scene.name, config.degree, config.slab_cells, config.recovery,
                 config.kronecker, config.base_state, config.modal, config.pointwise,
                 config.spacetime)
                == (self.scene.name, self.degree, self.cells, self.recovery, self.kronecker,
                    self.base, self.modal is not None, self.pointwise, self.spacetime))

    @property
    def companion(self) -> "Simulation":
        """The same slabs with degree p + 1: the error estimate's embedded partner (built on
        first use, then kept)."""
        if self._companion is None:
            base_state = self.backend.predictor
            if isinstance(base_state, FlowPredictor):
                # its own rk4 run with twice the steps: a base error the two shared would
                # be missed by their difference (curl3d T = 8 --rtol 1e-10 at p = 6, one cell:
                # ok 6.2e-11 off with an estimate of 3.8e-12, the companion as far off)
                base_state = base_state.with_steps(2 * base_state.steps)
            self._companion = Simulation(self.scene, self.degree + 1, self.cells, self.comm,
                                         self.petsc, self.recovery, self.kronecker,
                                         with_dual=False, base=self.base,
                                         modal=self.modal is not None and self.modal,
                                         mesh=self.backend.mesh, pointwise=self.pointwise,
                                         shared_predictor=base_state, spacetime=self.spacetime)
            self._companion.resolution = self.resolution
            self._companion.adaptive = self.adaptive
            self.setup_s += self._companion.setup_s
        return self._companion

    @property
    def flow_check(self) -> Optional["FlowCheck"]:
        """The RK4 runs a nonlinear slab's answer is compared with (fem_dual.integrate.
        flow_check; built on first use, sharing the base's compiled force, then kept), None for
        a linear scene or the predictor base. Rank 0 only."""
        if self.scene.linear or self.base == "predictor":
            return None
        if self._flow_check is None:
            from fem_dual.integrate.flow_check import FlowCheck

            companion = self.companion.backend.predictor  # (the companion's set-up is its own)
            tic = time.perf_counter()
            self._flow_check = FlowCheck.of(self.scene, self.cells, self.backend.predictor,
                                            companion)
            self.setup_s += time.perf_counter() - tic
        return self._flow_check

    def begin(self, config: RunConfig) -> None:
        """Set up a run: the scene's parameter values, fresh counts, superposition bases."""
        if config.scene is not self.scene and config.scene != self.scene:
            if self._flow_check is not None:
                self._flow_check.use_scene(config.scene)
            if self.modal is not None and self.modal.physical != config.scene:
                self.modal = ModalBasis(config.scene)
                if self._companion is not None:  # shares the modes
                    self._companion.modal = self.modal
            self.backend.set_scene(config.scene if self.modal is None else self.modal.scene)
            self.scene = config.scene
        self.backend.reset(adaptive=config.rtol is not None)
        self.adaptive = config.rtol is not None
        if self._companion is not None:
            self._companion.adaptive = self.adaptive
        self.superposition = None
        self.tangent_solves = self.direct_solves = 0
        self._first_t0 = {}
        self._maps = {}
        self._pairs = {}
        if self.uses_superposition(config):
            # H_d by polarisation where the fields are sampled (the companion does without)
            self.superposition = self.backend.superposition(config.T, self.with_dual)
            self._eager_bases = (config.superpose == "yes"
                                 or self.backend.basis_solves() <= 2)

    def _superposed(self, t0: float, dt: float) -> bool:
        """Whether the slab [t0, t0 + dt] comes from a superposition basis. Under a tolerance a
        length's basis (2n solves, or 2 x the largest modal block) is built when a second slab
        of that length is solved: a length tried once (rejected, or the short last slab) costs
        one solve (column links=6 --rtol 1e-10 on a fine grid of lengths: 3.8 s with a basis for
        every length tried). A basis of two solves (decoupled modes) is built at once, and so
        is every basis with --superpose yes."""
        if self.superposition is None:
            return False
        if not self.adaptive or self._eager_bases or self.superposition.has(dt):
            return True
        return self._first_t0.setdefault(dt, t0) != t0

    def solve_slab(self, z0: np.ndarray, t0: float, dt: float,
                   start: Optional["Simulation"] = None,
                   counted: bool = True) -> Optional[VertexValues]:
        """The vertex values of the slab [t0, t0 + dt] from z0 = (x0, v0), on rank 0 (None
        elsewhere). `start`: a nonlinear slab's Newton starts from that simulation's solved dual
        state of the same slab (the error companion starts from the answer's: exact in its
        richer space, two Newton steps from its own solution instead of four from zero; not
        with its own rk4 base, which the answer's dual state, the correction of another base,
        fits worse than zero: curl3d T = 8, p = 6, 8 cells, first residual 2.5e-4 against
        8.1e-6 from zero, three Newton steps against two).
        `counted`: a slab of the motion (not a tangent's) in the solve counts.
        Collective; raises SolveError when the slab cannot be solved."""
        n = self.scene.n
        if self.modal is not None:
            z0 = self._dropped(self.modal.forward(z0), dt)
        if self._superposed(t0, dt):
            values = self.superposition(z0[:n], z0[n:], dt)
        else:
            self.direct_solves += self.superposition is not None and counted
            partner = start.backend if start is not None and self._warm else None
            values = self.backend.solve(z0, t0, dt, partner)
        return values if self.modal is None else self.modal.back(values)

    def solve_batch(self, Z: np.ndarray, dt: float, fields: bool = True, duals: bool = True,
                    last: bool = False) -> Optional[VertexValues]:
        """The vertex values of slabs of length dt from the start states Z (slabs, 2n), with a
        leading slab axis, by superposition, on rank 0 (None elsewhere); without `fields` only
        x and v, without `duals` no dual fields, with `last` the slab's end only. Collective
        the first time dt is seen."""
        return self._modal_batch(Z if self.modal is None else self.modal.forward(Z), dt,
                                 fields, duals, last)

    def _modal_batch(self, R: np.ndarray, dt: float, fields: bool, duals: bool,
                     last: bool) -> Optional[VertexValues]:
        """solve_batch from the start states R in the coordinates the slabs are solved in."""
        if self.modal is None:
            values = self.superposition.batch(R, dt, fields, last)
        else:
            values = self.superposition.batch(self._dropped(R, dt), dt, fields, last)
        if values is not None and not duals:
            values.xi = values.eta = None
        return values if self.modal is None else self.modal.back(values)

    def share_bases(self, dt: float) -> None:
        """Give every rank the superposition bases of slabs of length dt (of the answer and
        its companion), which rank 0 holds, so that each can compute a share of the slabs.
        Collective."""
        for sim in (self, self.companion):
            sim.superposition.share(dt)

    def slab_maps(self, dt: float) -> Tuple[Optional[np.ndarray], Optional[np.ndarray]]:
        """(Phi, L) of slabs of length dt (rank 0; None elsewhere): the slab map, z_end =
        Phi z0, and the estimated local error at the slab's end, L z0 = ESTIMATE_SAFETY x
        (companion - answer) (without the modes the zero base damps). Every rank computes the
        columns of its share of the unit start states from the shared bases, rank 0 gathers
        them (the 200-link column's maps took rank 0 alone 0.24 s). Collective the first time
        dt is seen."""
        if dt not in self._maps:
            comm, n2 = self.comm, 2 * self.scene.n
            for sim in (self, self.companion):
                sim.solve_batch(np.zeros((1, n2)), dt, fields=False, last=True)  # the bases
            self.share_bases(dt)
            cuts = np.linspace(0, n2, comm.size + 1).round().astype(int)
            rows = slice(cuts[comm.rank], cuts[comm.rank + 1])
            # this rank's unit start states, in the slabs' coordinates
            mine = np.eye(n2)[rows] if self.modal is None else self.modal.forward_units(rows)
            ends = []
            for sim in (self, self.companion):
                local = np.zeros((0, n2))
                if len(mine):
                    values = sim._modal_batch(mine, dt, fields=False, duals=True, last=True)
                    local = np.hstack([values.x[:, -1], values.v[:, -1]])
                parts = comm.gather(local, root=0) if comm.size > 1 else [local]
                ends.append(np.vstack(parts).T if comm.rank == 0 else None)
            phi, phi_c = ends
            self._maps[dt] = (phi, None if phi is None else ESTIMATE_SAFETY * (phi_c - phi))
        return self._maps[dt]

    def pair_map(self, dt: float) -> np.ndarray:
        """[[Phi, 0], [L, Phi]]: the start state z and its estimated error d of a slab of length
        dt to the next slab's (rank 0; see slab_maps)."""
        if dt not in self._pairs:
            phi, lend = self.slab_maps(dt)
            m = len(phi)
            step = np.zeros((2 * m, 2 * m))
            step[:m, :m] = step[m:, m:] = phi
            step[m:, :m] = lend
            self._pairs[dt] = step
        return self._pairs[dt]

    def tangent(self, z0: np.ndarray, dz: np.ndarray, t0: float, dt: float,
                values: Optional[VertexValues], central: bool = False,
                scale: Optional[float] = None, relative: float = 1e-5) -> Optional[np.ndarray]:
        """Psi dz: the first-order change (vertices, 2n) of the slab's vertex values `values`
        (solved from z0) when its start state changes by dz, on rank 0. A linear slab map is
        its own tangent; a nonlinear one is linearised around the converged solution (exactly
        where the backend can, else a forward difference in the start state of relative size
        1e-6, error O(1e-6); `central`: the mean of those in dz and -dz, of size `relative`,
        error O(relative^2)). The size is relative to `scale` (the size of the motion, e.g. an
        orbit's extent), by default to that of z0. Collective; call it right after the slab
        was solved."""
        if not self.scene.linear and self.backend.exact_tangents:
            if not np.any(dz):
                return np.zeros((len(values.s), 2 * self.scene.n))
            return self.backend.exact_tangent(dz)
        if central and not self.scene.linear:
            ahead = self._tangent(z0, dz, t0, dt, values, relative, scale)
            behind = self._tangent(z0, -dz, t0, dt, values, relative, scale)
            return None if ahead is None else 0.5 * (ahead - behind)
        return self._tangent(z0, dz, t0, dt, values, 1e-6, scale)

    def _tangent(self, z0, dz, t0, dt, values, relative: float,
                 scale: Optional[float] = None) -> Optional[np.ndarray]:
        if not np.any(dz):
            return None if values is None else np.zeros((len(values.s), 2 * self.scene.n))
        if self.scene.linear:
            if not self._superposed(t0, dt):
                self.tangent_solves += 1
            moved = self.solve_slab(dz, t0, dt, counted=False)
            return None if moved is None else np.hstack([moved.x, moved.v])
        eps = self.backend.perturb_start(z0, dz, relative, scale)
        moved = self._sample_and_restore(z0)
        if moved is None:
            return None
        return (np.hstack([moved.x, moved.v]) - np.hstack([values.x, values.v])) / eps

    def algebraic_error(self, z0: np.ndarray,
                        values: Optional[VertexValues]) -> Optional[np.ndarray]:
        """How far the vertex values (vertices, 2n) would still move with one more Newton step
        (rank 0; None for linear slabs, whose solves are checked by their true residual). It
        joins the discretisation error in the estimate, so a Newton stopped early (by loosened
        solver options) cannot pass as converged: the companion, stopped by the same test,
        would not show it. Collective; call it right after the slab was solved."""
        if self.scene.linear:
            return None
        change = self.backend.newton_change()  # (exact: every rank holds the slab whole)
        if change is not None:
            return change
        self.backend.newton_step()
        moved = self._sample_and_restore(z0)
        if moved is None:
            return None
        return np.hstack([moved.x - values.x, moved.v - values.v])

    def _sample_and_restore(self, z0: np.ndarray) -> Optional[VertexValues]:
        """The vertex values of the perturbed dual state, then the converged slab from z0 back
        (whatever the sampling raises)."""
        try:
            return self.backend.sample()
        finally:
            self.backend.restore(z0)

    def slab_jacobian(self, z: np.ndarray, t0: float, dt: float,
                      values: Optional[VertexValues]) -> Optional[np.ndarray]:
        """d z_end / d z0 (2n, 2n) of the solved nonlinear slab on rank 0: exact where the
        backend has it (each rank holds the slab whole), else its 2n difference tangents (a
        residual and a solve each). Collective."""
        jacobian = self.backend.slab_jacobian()
        if jacobian is not None:
            return jacobian
        columns = [self.tangent(z, unit, t0, dt, values) for unit in np.eye(len(z))]
        return None if self.comm.rank != 0 else np.column_stack([c[-1] for c in columns])

    def _dropped(self, r: np.ndarray, dt: float) -> np.ndarray:
        """Modal start state(s) r without the modes the answer's slabs do not resolve on the
        zero base (the companion drops the same ones): those turning more than RESOLVED_TURN x
        p radians per cell under a tolerance, more than p on fixed slabs (which the zero base
        damps anyway, not exactly: the companion then told their loss 5 % short)."""
        if self.base != "zero":
            return r
        return self.modal.drop(r, dt, *self._drop_rule())

    def unresolved(self, z0: np.ndarray, dt: float) -> Optional[np.ndarray]:
        """(2n,): the part of z0 in modes the slab does not resolve, which the zero base damps
        (modal coordinates only: elsewhere the modes are not at hand; None); of many start
        states (slabs, 2n) at once."""
        if self.modal is None or self.base != "zero":
            return None
        return self.modal.unresolved(z0, dt, *self._drop_rule())

    def _drop_rule(self) -> Tuple[int, int, float]:
        """(cells, degree, turn) of the modes the zero base drops: those turning more than
        turn x degree radians per cell of the answer's slabs."""
        return (*self.resolution, RESOLVED_TURN if self.adaptive else 1.0)

    def verify(self) -> Optional[str]:
        """Why the last slab solve cannot be trusted although it converged, or None."""
        return None if self.scene.linear else self.backend.verify()

    def solves(self) -> int:
        """Slab solves of the answer (tangents not counted) or of the companion."""
        if self.superposition is not None:
            return self.superposition.basis_solves + self.direct_solves
        return self.backend.solves - self.tangent_solves

    def run(self, config: RunConfig, progress: bool = False, resume: bool = False,
            setup_s: float = 0.0):
        """Solve the dual problem slab by slab, recover the primal motion, estimate its error,
        compare with the reference (fem_dual.integrate.loop.run); returns the RunResult.
        `setup_s`: the caller's set-up seconds before it, reported in timings (and total_s)."""
        if not self.matches(config):
            raise ValueError("the configuration does not match the compiled simulation")
        self.begin(config)
        self.companion.begin(config)
        with quiet_numpy():  # (overflows are judged: the run says what failed, once)
            return run_slabs(self, config, progress, resume, setup_s)
