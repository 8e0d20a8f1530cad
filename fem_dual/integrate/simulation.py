"""The time-staging slab driver, used by every scene.

Each slab starts from the primal state recovered at the end of the previous one; that state is also
the slab's constant base state (xbar, vbar) of H. Forms are compiled once; only fem.Constants change
between slabs. Results live on rank 0 and are broadcast at the end, so every rank returns the same
RunResult.
"""
from __future__ import annotations

import copy
import json
import math
import os
import signal
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import numpy as np
from mpi4py import MPI

from fem_dual.slab.base_state import FlowPredictor
from fem_dual.compat import quiet_jit_logging
from fem_dual.config import STAGING_LIMIT, RunConfig
from fem_dual.integrate.dense import GAP_ORDER, hermite_at, hermite_estimate, slab_interpolation_gaps
from fem_dual.errors import InputError, SolveError
from fem_dual.slab.modal import ModalBasis
from fem_dual.slab.kronecker import (KroneckerProblem, KroneckerSampler, KroneckerSolver,
                                KroneckerSuperposition)
from fem_dual.mpi import allreduce, bcast, input_on_root, root_first
from fem_dual.output import check_output_dir_on_root
from fem_dual.integrate.sinks import (AcceptedSlab, Accumulator, PartialBatch, ProgressSink, Restart,
                            SlabBatch, XdmfSink)
from fem_dual import faults, native
from fem_dual.quiet import quiet_numpy
from fem_dual.slab.snes import NO_PROGRESS_ITS, NewtonSlabSolver
from fem_dual.slab.pointwise_newton import PointwiseLinearSolver, PointwiseNewtonSolver
from fem_dual.slab.problem import SlabProblem
from fem_dual.slab.recovery import VertexSampler, VertexValues
from fem_dual.slab.petsc_solvers import LinearSlabSolver, solver_prefix
from fem_dual.slab.superposition import Superposition
from fem_dual.integrate.estimate import (ESTIMATE_SAFETY, ROUNDOFF_REL, VOLUME_TOL, ErrorWeights,
                              SlabEstimate, initial_fraction, motion_rate, step_factor,
                              step_factors, volume_defect)
from fem_dual.meshes import SlabSchedule

__all__ = ["RunResult", "Simulation", "AcceptedSlab", "run"]

ADAPTIVE_LEVELS = 40  # --rtol: the shortest slab is T / 2^40


@dataclass
class RunResult:
    """What a run computed (the JSON object of `fem-dual run --json`)."""

    scene: str
    parameters: Dict[str, Any]
    T: float
    cells: int
    degree: int
    slabs: int
    x0: List[float]
    v0: List[float]
    dofs_per_slab: int
    t: np.ndarray
    x: np.ndarray
    v: np.ndarray
    error: Dict[str, float]
    hamiltonian: Dict[str, Any]
    timings: Dict[str, float]
    solver: Dict[str, Any]
    slab_lengths: List[float]
    status: str = "ok"
    message: str = ""
    output_files: List[str] = field(default_factory=list)
    staging: Dict[str, Any] = field(default_factory=dict)
    recovery: str = "momentum"
    error_estimate: Optional[float] = None
    estimate: Dict[str, Any] = field(default_factory=dict)
    tolerance: Dict[str, Any] = field(default_factory=dict)
    t_eval: Optional[Dict[str, Any]] = None
    output_slabs: Optional[int] = None  # slabs the --out files hold (None: no --out)
    scene_object: Any = field(default=None, repr=False, compare=False)
    estimate_at_t: Optional[np.ndarray] = field(default=None, repr=False, compare=False)
    error_at_t: Optional[np.ndarray] = field(default=None, repr=False, compare=False)

    def at(self, times) -> Tuple[np.ndarray, np.ndarray]:
        """(x, v) at any times within the computed part of [0, T], by quintic Hermite
        interpolation with the equation of motion at the vertices (fem_dual.integrate.dense)."""
        times = np.atleast_1d(np.asarray(times, dtype=float))
        if len(times) == 0:
            n = self.x.shape[1]
            return np.zeros((0, n)), np.zeros((0, n))
        if not np.isfinite(times).all():
            raise InputError("times must be finite numbers")
        if len(self.t) < 2 or times.min() < self.t[0] or times.max() > self.t[-1]:
            span = f"[{self.t[0]:g}, {self.t[-1]:g}]" if len(self.t) else "nothing"
            raise InputError(f"times outside the computed part of the motion ({span})")
        return hermite_at(self.scene_object, self.t, self.x, self.v, times)

    def write_csv(self, path) -> None:
        """Columns t, x1..xn, v1..vn at the output times."""
        n = self.x.shape[1] if self.x.ndim == 2 else 0
        head = ",".join(["t"] + [f"x{i + 1}" for i in range(n)] + [f"v{i + 1}" for i in range(n)])
        rows = np.column_stack([self.t, self.x, self.v])
        path = Path(path)
        if path.exists() and not path.is_file():  # a device or a pipe: write into it
            np.savetxt(path, rows, delimiter=",", header=head, comments="", fmt="%.17g")
            return
        tmp = path.with_name(f".{path.name}.tmp")  # complete or absent: a full disk left a
        try:  # file cut mid-number that parsed as a row
            np.savetxt(tmp, rows, delimiter=",", header=head, comments="", fmt="%.17g")
            os.replace(tmp, path)
        finally:
            if tmp.exists():
                tmp.unlink()

    @property
    def final(self) -> Dict[str, List[float]]:
        if len(self.t) == 0:
            return {"t": None, "x": None, "v": None}
        return {"t": float(self.t[-1]), "x": self.x[-1].tolist(), "v": self.v[-1].tolist()}

    def write_json(self, stream, chunk: int = 4096) -> None:
        """Write `to_dict()` as one JSON object, streaming the vertex arrays in chunks of rows so
        that long runs never hold their JSON text in memory."""
        with faults.signals_deferred():
            self._write_json(stream, chunk)
            stream.flush()

    def _write_json(self, stream, chunk: int) -> None:
        head = _null_where_not_finite(self.to_dict(arrays=False))
        stream.write(json.dumps(head, allow_nan=False)[:-1])
        for name in ("t", "x", "v"):
            values = getattr(self, name)
            stream.write(f', "{name}": [')
            for start in range(0, len(values), chunk):
                if start:
                    stream.write(", ")
                stream.write(json.dumps(values[start:start + chunk].tolist(),
                                        allow_nan=False)[1:-1])
            stream.write("]")
        stream.write("}\n")

    def to_dict(self, arrays: bool = True) -> Dict[str, Any]:
        out = {
            "scene": self.scene, "parameters": self.parameters, "T": self.T, "cells": self.cells,
            "degree": self.degree, "slabs": self.slabs, "x0": self.x0, "v0": self.v0,
            "status": self.status, "message": self.message,
            "dofs_per_slab": self.dofs_per_slab, "slab_lengths": self.slab_lengths,
            "final": self.final, "error": self.error, "hamiltonian": self.hamiltonian,
            "solver": self.solver, "timings": self.timings, "output_files": self.output_files,
            "staging": self.staging, "recovery": self.recovery,
            "error_estimate": self.error_estimate, "estimate": self.estimate,
            "tolerance": self.tolerance, "t_eval": self.t_eval,
            "output_slabs": self.output_slabs,
        }
        if arrays:
            out.update(t=self.t.tolist(), x=self.x.tolist(), v=self.v.tolist())
        return out


def _solver_record(solver, prefix: str) -> Dict[str, Any]:
    if isinstance(solver, (NewtonSlabSolver, PointwiseNewtonSolver)):
        kind = "newton" if isinstance(solver, PointwiseNewtonSolver) else "snes"
        return {"kind": kind, "prefix": prefix, "newton_iterations": list(solver.iterations),
                "residual_norms": list(solver.residual_norms),
                "residual_histories": [list(h) for h in solver.histories]}
    if isinstance(solver, PointwiseLinearSolver):
        return {"kind": "direct", "prefix": prefix, "solves": len(solver.iterations)}
    return {"kind": "ksp", "prefix": prefix, "ksp_iterations": list(solver.iterations)}


class Simulation:
    """A compiled slab problem with its solver and vertex sampler: everything a run builds before
    its first slab. Build it once and `run` it for many horizons, start states or slab
    settings of the same scene, degree and cells per slab (`fem-dual bench` does).

    Args:
        scene: the validated scene.
        degree, cells: the dual fields' degree and the time cells per solved slab.
        comm: the communicator.
        petsc: PETSc options for the slab solver.
        recovery: how the primal state is read from the dual solution ("momentum" or "dtp").
        kronecker: linear scenes: solve in Kronecker form (matrix-free CG).
        with_dual: also sample the dual fields (output); the error companion does without.
        base: the base state of H on a slab (fem_dual.slab.problem.BASES).
        modal: linear scenes: solve in modal coordinates (fem_dual.slab.modal); a ModalBasis is
            shared (the error companion uses its partner's).
        mesh: the slab mesh to share (the companion uses its partner's).
        shared_predictor: the base state's predictor to use (the companion's: a linearised
            predictor is its partner's, an rk4 one its own with twice the steps).
        pointwise: assemble pointwise and solve by the banded LU or dense Newton of
            fem_dual.slab.pointwise_newton (every rank solves the whole slab), not by PETSc KSP or
            SNES on forms distributed over `comm`; None: unless PETSc options are given.
    """

    def __init__(self, scene, degree: int, cells: int, comm: MPI.Comm = MPI.COMM_WORLD,
                 petsc: Optional[Dict[str, str]] = None, recovery: str = "momentum",
                 kronecker: bool = False, with_dual: bool = True, base: str = "start",
                 modal: "bool | ModalBasis" = False, mesh=None,
                 pointwise: Optional[bool] = None, shared_predictor=None):
        if pointwise is None:  # as RunConfig's auto
            from fem_dual.config import auto_pointwise

            pointwise = auto_pointwise(scene, cells, degree, petsc, kronecker)
        pointwise = pointwise and not kronecker

        def build():
            with quiet_jit_logging():
                self._build(scene, degree, cells, comm, petsc, recovery, kronecker, with_dual,
                            base, modal, mesh, pointwise, shared_predictor)
        # The pointwise path's forms and expressions live on COMM_SELF meshes, so every rank
        # would compile the same code at the same time: FFCx lets one write it and the others
        # wait 10 s for it, then fail, alone, leaving the rest in a collective. Rank 0
        # compiles first; the others load its cache.
        root_first(comm, build) if pointwise else build()

    def _build(self, scene, degree: int, cells: int, comm: MPI.Comm,
               petsc: Optional[Dict[str, str]], recovery: str, kronecker: bool,
               with_dual: bool, base: str, modal: "bool | ModalBasis", mesh=None,
               pointwise: Optional[bool] = None, shared_predictor=None) -> None:
        tic = time.perf_counter()
        self.scene, self.degree, self.cells, self.comm = scene, degree, cells, comm
        self.prefix = solver_prefix(scene.name)
        self.recovery, self.kronecker, self.petsc, self.base = recovery, kronecker, petsc, base
        self.pointwise = pointwise
        self.modal = modal if isinstance(modal, ModalBasis) else (ModalBasis(scene) if modal
                                                                  else None)
        solved = self.modal.scene if modal else scene  # the scene whose slabs are solved
        if kronecker:
            self.problem = KroneckerProblem(solved, degree, cells, comm, base)
            self.solver = KroneckerSolver(self.problem, self.prefix, petsc)
            self.sampler = KroneckerSampler(self.problem, with_dual=with_dual)
        elif pointwise:  # the slab is small: every rank holds and solves it whole
            self.problem = SlabProblem(solved, degree, cells, MPI.COMM_SELF, base, mesh,
                                       shared_predictor)
            self.solver = (PointwiseLinearSolver if scene.linear
                           else PointwiseNewtonSolver)(self.problem)
            self.sampler = VertexSampler(self.problem, with_dual=with_dual, recovery=recovery,
                                         momenta=self.solver.local.momenta)
            self.solver.local.factor_solution = with_dual  # (the companion takes no tangents)
        else:
            self.problem = SlabProblem(solved, degree, cells, comm, base, mesh, shared_predictor)
            solver_class = LinearSlabSolver if scene.linear else NewtonSlabSolver
            self.solver = solver_class(self.problem, self.prefix, petsc)
            self.sampler = VertexSampler(self.problem, with_dual=with_dual, recovery=recovery)
        self.setup_s = time.perf_counter() - tic
        self._fresh = True
        self._companion: Optional["Simulation"] = None
        # whether a partner's solved dual state is a start for ours (solve_slab): not where our
        # base state is a run of our own (the companion's rk4, with twice the steps)
        self._warm = not isinstance(shared_predictor, FlowPredictor)
        self.superposition = None
        self.tangent_solves = 0
        self._maps: Dict[float, Tuple[np.ndarray, np.ndarray]] = {}
        self._pairs: Dict[float, np.ndarray] = {}

    def close(self) -> None:
        """Destroy the PETSc objects of the solver, the sampler, the problem and the companion;
        the simulation cannot solve after it. Collective: call it on every rank at the same
        point (MUMPS ends its factorisation collectively). petsc4py 3.18 does not destroy what
        Python drops (fem_dual.compat.destroy_petsc): a run that did not close its Simulation
        kept 160 KB (ziegler, 2 dofs) to 290 KB (curl3d) allocated for good."""
        if self._companion is not None:
            self._companion.close()
        self.solver.close()
        for part in (self.sampler, self.problem):
            close = getattr(part, "close", None)  # the Kronecker ones hold no PETSc object
            if close is not None:
                close()

    def uses_superposition(self, config: RunConfig) -> bool:
        if config.superpose != "auto":
            return config.superpose == "yes"
        if config.rtol is not None:  # adaptive lengths recur (powers of two): bases pay off
            return self.scene.linear
        return self.scene.linear and config.slab_count > self.basis_solves()

    def basis_solves(self) -> int:
        """Slab solves that a basis of one slab length costs (2n, or fewer probes when the
        solved problem decouples into modes: fem_dual.slab.kronecker.probes)."""
        if self.kronecker:
            return KroneckerSuperposition.solves_per_basis(self.problem)
        return 2 * self.scene.n

    @classmethod
    def for_config(cls, config: RunConfig, comm: MPI.Comm = MPI.COMM_WORLD) -> "Simulation":
        """The simulation that runs `config` (its staged cells per slab)."""
        return cls(config.scene, config.degree, config.slab_cells, comm, config.petsc,
                   config.recovery, config.kronecker, base=config.base_state,
                   modal=config.modal, pointwise=config.pointwise)

    @property
    def companion(self) -> "Simulation":
        """The same slabs with degree p + 1: the error estimate's embedded partner (built on
        first use, then kept)."""
        if self._companion is None:
            base_state = getattr(self.problem, "predictor", None)
            if isinstance(base_state, FlowPredictor):
                # its own rk4 run with twice the steps: a base error the two shared would
                # be missed by their difference (curl3d T = 8 --rtol 1e-10 at p = 6, one cell:
                # ok 6.2e-11 off with an estimate of 3.8e-12, the companion as far off)
                base_state = base_state.with_steps(2 * base_state.steps)
            self._companion = Simulation(self.scene, self.degree + 1, self.cells, self.comm,
                                         self.petsc, self.recovery, self.kronecker,
                                         with_dual=False, base=self.base,
                                         modal=self.modal is not None and self.modal,
                                         mesh=getattr(self.problem, "mesh", None)
                                         if not self.kronecker else None,
                                         pointwise=self.pointwise,
                                         shared_predictor=base_state)
            self.setup_s += self._companion.setup_s
        return self._companion

    def begin(self, config: RunConfig) -> None:
        """Set up a run: the scene's parameter values, fresh counts, superposition bases."""
        if config.scene is not self.scene and config.scene != self.scene:
            if self.modal is not None and self.modal.physical != config.scene:
                self.modal = ModalBasis(config.scene)
                if self._companion is not None:  # shares the modes
                    self._companion.modal = self.modal
            self.problem.set_scene_constants(config.scene if self.modal is None
                                             else self.modal.scene)
            self.scene = config.scene
        self.solver.reset()
        forget = getattr(getattr(self.problem, "predictor", None), "forget", None)
        if forget is not None:
            forget()
        if hasattr(self.solver, "patience"):  # Newton: guessed slab lengths give up early
            self.solver.patience = NO_PROGRESS_ITS if config.rtol is not None else None
        self.superposition = None
        self.tangent_solves = 0
        self._maps = {}
        self._pairs = {}
        if self.uses_superposition(config):
            if self.kronecker:  # H_d from the fields
                self.superposition = KroneckerSuperposition(self.problem, self.solver,
                                                            self.sampler, config.T)
            else:  # H_d by polarisation, which the companion (x, v only) does without
                self.superposition = Superposition(self.problem, self.solver, self.sampler,
                                                   config.T, self.sampler.with_dual)

    def solve_slab(self, z0: np.ndarray, t0: float, dt: float,
                   start: Optional["Simulation"] = None) -> Optional[VertexValues]:
        """The vertex values of the slab [t0, t0 + dt] from z0 = (x0, v0), on rank 0 (None
        elsewhere). `start`: a nonlinear slab's Newton starts from that simulation's solved dual
        state of the same slab (the error companion starts from the answer's: exact in its
        richer space, two Newton steps from its own solution instead of four from zero; not
        with its own rk4 base, which the answer's dual state, the correction of another base,
        fits worse than zero: curl3d T = 8, p = 6, 8 cells, first residual 2.5e-4 against
        8.1e-6 from zero, three Newton steps against two).
        Collective; raises SolveError when the slab cannot be solved."""
        n = self.scene.n
        if self.modal is not None:
            z0 = self.modal.forward(z0)
        if self.superposition is not None:
            values = self.superposition(z0[:n], z0[n:], dt)
        else:
            self.problem.set_slab(z0[:n], z0[n:], dt, t0)
            first = (start.solver.histories[-1][:1] if start is not None and self._warm
                     and not self.scene.linear and not self.kronecker else [])
            if first and first[0] > 0:  # (no history: SNES options without a residual norm)
                self.problem.take_dual_state(start.problem)
                self.solver.solve(warm=first[0])
            else:
                self.solver.solve()
            values = self.sampler()
        return values if self.modal is None else self.modal.back(values)

    def solve_batch(self, Z: np.ndarray, dt: float, fields: bool = True, duals: bool = True,
                    last: bool = False) -> Optional[VertexValues]:
        """The vertex values of slabs of length dt from the start states Z (slabs, 2n), with a
        leading slab axis, by superposition, on rank 0 (None elsewhere); without `fields` only
        x and v, without `duals` no dual fields, with `last` the slab's end only. Collective
        the first time dt is seen."""
        if self.modal is None:
            values = self.superposition.batch(Z, dt, fields, last)
        else:
            values = self.superposition.batch(self.modal.forward(Z), dt, fields, last)
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
            mine = np.eye(n2)[cuts[comm.rank]:cuts[comm.rank + 1]]
            ends = []
            for sim in (self, self.companion):
                local = np.zeros((0, n2))
                if len(mine):
                    values = sim.solve_batch(mine, dt, fields=False, last=True)
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
        its own tangent; a nonlinear one is linearised around the converged solution (a
        forward difference in the start state of relative size 1e-6, error O(1e-6); `central`:
        the mean of those in dz and -dz, of size `relative`, error O(relative^2)). The size is
        relative to `scale` (the size of the motion, e.g. an orbit's extent), by default to
        that of z0. Collective; call it right after the slab was solved."""
        if getattr(self.solver, "exact_tangents", False):  # the pointwise Newton's: exact
            if not np.any(dz):
                return np.zeros((len(values.s), 2 * self.scene.n))
            return self.solver.exact_tangent(dz)
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
            if self.superposition is None:
                self.tangent_solves += 1
            moved = self.solve_slab(dz, t0, dt)
            return None if moved is None else np.hstack([moved.x, moved.v])
        eps = self.solver.tangent(z0, dz, relative, scale)
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
        if self.recovery == "momentum" and getattr(self.solver, "exact_tangents", False):
            return self.solver.newton_change()  # (every rank holds the slab whole)
        self.solver.newton_step()
        moved = self._sample_and_restore(z0)
        if moved is None:
            return None
        return np.hstack([moved.x - values.x, moved.v - values.v])

    def _sample_and_restore(self, z0: np.ndarray) -> Optional[VertexValues]:
        """The vertex values of the perturbed dual state, then the converged slab from z0 back
        (whatever the sampling raises)."""
        try:
            return self.sampler()
        finally:
            self.solver.restore(z0)

    def unresolved(self, z0: np.ndarray, dt: float) -> Optional[np.ndarray]:
        """(2n,): the part of z0 in modes the slab does not resolve, which the zero base damps
        (modal coordinates only: elsewhere the modes are not at hand; None); of many start
        states (slabs, 2n) at once."""
        if self.modal is None or self.base != "zero":
            return None
        return self.modal.unresolved(z0, dt, self.cells, self.degree)

    def verify(self) -> Optional[str]:
        """Why the last slab solve cannot be trusted although it converged, or None."""
        stalled = getattr(self.solver, "stalled", None)
        if stalled is not None and stalled():
            its = self.solver.iterations[-1]
            return (f"Newton stalled before it converged ({its} iterations): it may have found "
                    "another solution branch")
        return None

    def run(self, config: RunConfig, progress: bool = False, resume: bool = False) -> RunResult:
        """Solve the dual problem slab by slab, recover the primal motion, estimate its error,
        compare with the reference (see `run`)."""
        if ((config.scene.name, config.degree, config.slab_cells, config.recovery,
             config.kronecker, config.base_state, config.modal, config.pointwise)
                != (self.scene.name, self.degree, self.cells, self.recovery, self.kronecker,
                    self.base, self.modal is not None, self.pointwise)):
            raise ValueError("the configuration does not match the compiled simulation")
        self.begin(config)
        self.companion.begin(config)
        with quiet_numpy():  # (overflows are judged: the run says what failed, once)
            return _run_slabs(self, config, progress, resume)


def check_resolution(rate: Optional[float], dt: float, cells: int, degree: int) -> None:
    """SolveError when a time cell spans more radians of the fastest mode (`rate`, known for
    linear scenes, else None) than the degree can follow (rate * h > p): the answer would be
    noise, however well solved."""
    h = dt / cells
    if rate is not None and rate * h > degree:
        factor = math.ceil(rate * h / degree)
        raise SolveError(f"under-resolved: the fastest mode (|lambda| = {rate:.4g}) turns "
                         f"{rate * h:.3g} radians per time cell, more than degree {degree} can "
                         f"follow; use {factor}x more slabs or cells per slab, or a higher "
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


def _finite(values: VertexValues) -> np.ndarray:
    """Per slab (values with a leading slab axis): whether every value is finite."""
    arrays = [values.x, values.v, values.hamiltonian[..., None]] + [
        a for a in (values.xi, values.eta) if a is not None]
    return np.logical_and.reduce([np.isfinite(a).reshape(len(a), -1).all(axis=1)
                                  for a in arrays])


@dataclass
class _Estimates:
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


def _estimates(vals: VertexValues, companion: VertexValues, algebraic: Optional[np.ndarray],
               psi: Optional[np.ndarray], lost: Optional[np.ndarray], weights: ErrorWeights,
               dt, T: float, output: Optional[Tuple[Any, int]] = None,
               compiled: bool = True) -> _Estimates:
    """The estimates of consecutive slabs (values with a leading slab axis; lost (slabs, 2n)),
    each slab's motion recorded in the weights before the next. With `output` (the scene and
    the order 2p of the vertex values), times between the vertices are asked for: the
    interpolation error there (`slab_interpolation_gaps`) must be within the tolerance too, and
    enters the controller's error at the vertices' order (a slab whose gap exceeds it is
    retried shorter, as one whose local error does). In compiled code where it is available
    (fem_dual.native's `estimate`, `compiled`), for finite values and positive weights; the
    numpy below judges the rest."""
    done = _compiled_estimates(vals, companion, algebraic, psi, lost, weights, dt,
                               T) if compiled else None
    if done is not None:
        local, glob, scales, floor, err_local, err_global = done
        finite = np.ones(len(scales), dtype=bool)
        if output is None:
            return _Estimates(local, glob, scales, floor, err_local, err_global, finite)
        with quiet_numpy():
            return _with_output(vals, weights, dt, output,
                                _Estimates(local, glob, scales, floor, err_local, err_global,
                                           finite))
    local = companion.state() - vals.state()
    if algebraic is not None:  # the answer's own Newton error (the companion's cancels it)
        local += algebraic
    local *= ESTIMATE_SAFETY
    if lost is not None:  # damped by the zero base: gone from the answer after the start
        local[:, 1:] += lost[:, None, :]
    glob = local if psi is None else local + psi
    scales = weights.running(vals.x, vals.v)
    # local errors at the round-off floor are not resolved: counted as such they would grow per
    # unit of time as slabs shrink and drive the lengths down to the minimum
    floor = ROUNDOFF_REL * scales
    with quiet_numpy():
        # the largest |error| of x's and of v's (slabs, 2), NaN where one is NaN; less the
        # floor, one number per part, that is the largest of max(|l| - floor, 0)
        peak_local = weights.peaks(local)
        peak_glob = peak_local if psi is None else weights.peaks(glob)
        count = len(scales)
        both = weights.weigh(np.concatenate([np.maximum(peak_local - floor, 0.0), peak_glob]),
                             np.concatenate([scales, scales]))  # (weighted in one pass)
        err_local, err_global = both[:count] / (np.asarray(dt) / T), both[count:]
        finite = np.isfinite(peak_local).all(axis=1) & np.isfinite(peak_glob).all(axis=1)
        est = _Estimates(local, glob, scales, floor, err_local, err_global, finite)
        return est if output is None else _with_output(vals, weights, dt, output, est)


def _with_output(vals: VertexValues, weights: ErrorWeights, dt, output: Tuple[Any, int],
                 est: _Estimates) -> _Estimates:
    """`est` with the weighted interpolation error between the vertices (`_estimates`)."""
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
    """(local, glob, scales, floor, err_local, err_global) of `_estimates` from fem_dual.native's
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


def _batched(values: VertexValues) -> VertexValues:
    """One slab's values with a leading slab axis of length 1 (what `_estimates` reads: s, x, v
    and the state; H_d too)."""
    z = values.z
    return VertexValues(values.s, values.x[None], values.v[None], values.hamiltonian[None],
                        z=None if z is None else z[None])


def _output(config: RunConfig) -> Optional[Tuple[Any, int]]:
    """What `_estimates` needs to judge the times between vertices, when they are asked for."""
    return None if config.t_eval is None else (config.scene, 2 * config.degree)


def _judge(vals: VertexValues, companion: VertexValues, algebraic: Optional[np.ndarray],
           psi: Optional[np.ndarray], lost: Optional[np.ndarray], weights: ErrorWeights,
           bound: Optional[GrowthBound],
           t0: float, dt: float, T: float,
           output: Optional[Tuple[Any, int]] = None
           ) -> Tuple[str, Optional[float], str, Optional[SlabEstimate]]:
    """(action, weighted local error, reason, estimate) for a solved slab on rank 0: "accept",
    "retry" (shorter) or "refuse" (the run cannot vouch for its answer any more)."""
    if not vals.finite():
        if np.isfinite(vals.x).all() and np.isfinite(vals.v).all():  # H_d, quadratic, overflows
            size = max(np.abs(vals.x).max(), np.abs(vals.v).max())
            return "error", None, (f"the motion grew to {size:.3g}, where H_d (quadratic in the "
                                   "state) overflows float64; a shorter T ends before it"), None
        return "retry", None, "the recovered state is not finite; try more slabs or cells", None
    if bound is not None and not bound.allows(t0 + dt, vals):
        return "retry", None, ("the motion outgrows the exact flow's bound (noise amplified in "
                               "modes the slabs do not resolve); use more slabs or cells per "
                               "slab"), None
    one = (lambda a: None if a is None else a[None])
    est = _estimates(_batched(vals), _batched(companion), one(algebraic), one(psi), one(lost),
                     weights, dt, T, output)
    local, glob = est.local[0], est.glob[0]
    if not est.finite[0]:
        return "retry", None, "the error estimate is not finite", None
    err_local = float(est.err_local[0])
    slab = est.slab(0, t0, dt)
    tol = weights.tol
    if est.err_output is not None and est.err_output[0] > 1.0:
        return "retry", err_local, (f"the state between output vertices is estimated to be "
                                    f"{est.err_output[0]:.3g} times the tolerance "
                                    f"({tol.label}) off: the vertices are too far apart for "
                                    "--t-eval"), slab
    if err_local > 1.0:
        return "retry", err_local, (f"estimated local error {np.abs(local).max():.3g} exceeds "
                                    f"its share of the tolerance ({tol.label})"), slab
    if est.err_global[0] > tol.refuse_factor:
        return "refuse", err_local, (f"estimated error {np.abs(glob).max():.3g} exceeds the "
                                     f"tolerance ({tol.label}) by a factor "
                                     f"{est.err_global[0]:.3g}"), slab
    return "accept", err_local, "", slab


def _volume_kept(comm: MPI.Comm, sim: Simulation, z: np.ndarray, t0: float, dt: float,
                 vals: Optional[VertexValues], err: Optional[float]
                 ) -> Tuple[str, Optional[float], str]:
    """(action, err, reason) of a nonlinear slab (start state z, vertex values `vals` on rank
    0) the estimate accepts: still "accept" if its slab map's tangent preserves phase-space
    volume within stepper.VOLUME_TOL, else "retry" (the slab does not follow the motion, and
    the companion may miss it too). The tangent is exact on the pointwise path; PETSc's SNES
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
            return "accept", err, ""
    jacobian = getattr(sim.solver, "slab_jacobian", None)
    if jacobian is not None:  # (each rank holds the slab whole)
        J = jacobian()
    else:
        columns = [sim.tangent(z, unit, t0, dt, vals) for unit in np.eye(len(z))]
        J = None if comm.rank != 0 else np.column_stack([c[-1] for c in columns])
    c = sim.problem.c  # (the scene's values, as the slab used them)
    M, D = c["M"].value, c["D"].value if "D" in c else None
    defect = bcast(comm, volume_defect(J, M, D, dt) if J is not None else None)
    if defect <= VOLUME_TOL:
        return "accept", err, ""
    return "retry", None, (f"the slab map does not keep phase-space volume as the motion does "
                           f"(det of its tangent off by {defect:.2g}): the cells do not follow "
                           "a fast or unstable part of the motion, which the estimate cannot see")


def _null_where_not_finite(value):
    """`value` (JSON-like) with every float that is not finite replaced by None: the residual
    history of a failed Newton can hold inf, which JSON has no number for (the vertex arrays
    are finite: a run keeps only the slabs it accepted)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _null_where_not_finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_null_where_not_finite(v) for v in value]
    return value


def _compiled_loops(sim: "Simulation") -> List[str]:
    """Which inner loops of the run ran in compiled code (fem_dual.native): "rk4" (the rk4
    base), "band" (the pointwise Jacobian's band), "newton" (the slab's Newton iterations),
    "dtp" (the implicit DtP map's Newton, within those or alone), "tangents" (a solved slab's
    exact tangents after their solve; not with the base state "start")."""
    loops = []
    if getattr(getattr(sim.problem, "predictor", None), "compiled", False):
        loops.append("rk4")
    local = getattr(sim.solver, "local", None)
    if getattr(local, "compiled_band", False):
        loops.append("band")
    newton = getattr(local, "compiled_newton", False) and sim.scene.linear is False
    if newton:
        loops.append("newton")
    pointwise = getattr(sim.problem, "pointwise", None)
    if pointwise is not None and (newton or pointwise.compiled):  # (within the C Newton)
        loops.append("dtp")
    if (getattr(local, "_native_tangents", None) is not None and sim.scene.linear is False
            and sim.base != "start"):
        loops.append("tangents")
    return loops


def _solves(sim: Simulation) -> int:
    """Slab solves of the answer (tangents not counted) or of the companion."""
    if sim.superposition is not None:
        return sim.superposition.basis_solves
    return len(sim.solver.iterations) - sim.tangent_solves


def _start_rate(scene, x0: np.ndarray, v0: np.ndarray) -> float:
    """|z'| / |z| at the start (motion_rate), from the scene's acceleration there."""
    if scene.linear:
        a0 = (scene.first_order_matrix() @ np.concatenate([x0, v0]))[scene.n:]
    else:
        F, d = np.asarray(scene.force_numpy(x0), dtype=float), scene.mass_diagonal()
        a0 = F / d if d is not None else np.linalg.solve(scene.mass_matrix(), F)
    return motion_rate(x0, v0, a0)


def _schedule(config: RunConfig, cells: int, rate: float) -> SlabSchedule:
    """Fixed slabs (cut at most max_halvings times), or adaptive lengths from a first guess of
    about one radian per cell (`rate`: the fastest mode of a linear scene, the start's rate of
    a nonlinear one)."""
    if config.rtol is None:
        return SlabSchedule(config.T, config.slab_count, config.max_halvings, shrinks=False)
    return SlabSchedule(config.T, 1, ADAPTIVE_LEVELS,
                        first=initial_fraction(rate, config.T, cells))


def _advice(config: RunConfig) -> str:
    if config.rtol is None:
        return ("use more slabs or cells per slab, a higher degree, or --rtol to choose the "
                "slab lengths")
    return "loosen --rtol, or raise --cells or --degree"


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return f"{type(exc).__name__}: {text}" if not isinstance(exc, OSError) else text


def _on_root(comm: MPI.Comm, action) -> Tuple[Any, Optional[str]]:
    """action() on rank 0: (its value, why it failed in one line or None); (None, None)
    elsewhere. Not collective: the caller shares the outcome with its next broadcast, so an
    error on rank 0 (a full disk, a bug) ends the run on every rank instead of leaving them
    waiting in the next collective."""
    if comm.rank != 0:
        return None, None
    try:
        return action(), None
    except Exception as exc:  # noqa: BLE001 -- shared, then raised on every rank
        return None, _one_line(exc)


class _LoopState:
    """Where the slab loop stands: slab index, start state and its estimated error, lengths."""

    def __init__(self, config: RunConfig):
        self.k = 0
        self.z = np.concatenate([config.x0, config.v0])
        self.d = np.zeros_like(self.z)  # estimated global error of the state at the slab start
        self.lengths: List[float] = []
        self.batched = 0  # slabs taken in chunks from their slab maps (_batch_step)
        # slabs of the next chunk (before the limits of _batch_step): fixed slabs have their
        # length from the start, a controller finds its length first
        self.chunk = CHUNK_SLABS if config.rtol is None else FIRST_CHUNK
        # whether the slab length has settled (the last slab kept it): while the controller
        # still shortens, grows and retries, chunks that stop after one slab would cost more
        # than the slab loop
        self.settled = config.rtol is None
        self.resumed_from: Optional[Dict[str, float]] = None

    def resume(self, comm: MPI.Comm, restart: Optional[Restart], acc: Optional[Accumulator],
               weights: Optional[ErrorWeights], schedule: SlabSchedule) -> None:
        """Go on after the slabs of `restart` (rank 0's; shared with every rank)."""
        state = None
        if comm.rank == 0 and restart.slabs:
            for slab in restart.slabs:
                acc.add(slab)
            last = restart.slabs[-1]
            weights.scale_x, weights.scale_v = last.scales
            state = (len(restart.slabs), np.concatenate([last.values.x[-1], last.values.v[-1]]),
                     last.estimate.glob[-1].copy(), [s.dt for s in restart.slabs],
                     last.schedule, last.t0 + last.dt)
        state = bcast(comm, state)
        if state is None:
            return
        self.k, self.z, self.d, self.lengths, schedule.state, t = state
        self.resumed_from = {"slab": self.k, "t": t}


CHUNK_BYTES = 8 * 2**20  # working arrays of one chunk of slabs solved at once
CHUNK_SLABS = 1024  # at most this many (a signal is answered after a chunk)
FIRST_CHUNK = 8


def _recurrence(sim: Simulation, state: _LoopState, dt: float,
                count: int) -> Tuple[np.ndarray, np.ndarray, Optional[np.ndarray]]:
    """Rank 0: the start states Z and propagated errors D (count + 1, 2n) of the next `count`
    slabs of length dt, slab by slab (as a resumed run repeats them), and the part of each
    start state the zero base damps (`Simulation.unresolved`)."""
    phi, lend = sim.slab_maps(dt)
    m = len(state.z)
    if sim.unresolved(state.z[None], dt) is None:  # (z, d) together: one product a slab
        step = sim.pair_map(dt)
        Y = np.empty((count + 1, 2 * m))
        Y[0, :m], Y[0, m:] = state.z, state.d
        for j in range(count):  # (the ufunc into the rows: no temporaries, no dispatch)
            np.matmul(step, Y[j], out=Y[j + 1])
        return Y[:, :m], Y[:, m:], None
    Z = np.empty((count + 1, m))
    Z[0] = state.z
    for j in range(count):
        np.matmul(phi, Z[j], out=Z[j + 1])
    lost = sim.unresolved(Z[:-1], dt)
    carried = Z[:-1] @ lend.T + lost
    D = np.empty_like(Z)
    D[0] = state.d
    for j in range(count):
        np.matmul(phi, D[j], out=D[j + 1])
        D[j + 1] += carried[j]
    return Z, D, lost


def _vertex_part(sim: Simulation, Z: np.ndarray, D: np.ndarray, dt: float,
                 duals: bool) -> Tuple[VertexValues, VertexValues, np.ndarray]:
    """Any rank: the vertex values of the slabs from Z[:-1] (the answer, its companion) and the
    change psi of the answer's from the errors D[:-1], the slabs' ends set to Z[1:]."""
    n = Z.shape[1] // 2
    vals = sim.solve_batch(Z[:-1], dt, duals=duals)
    vals.x[:, -1], vals.v[:, -1] = Z[1:, :n], Z[1:, n:]  # each slab ends where the next starts
    companion = sim.companion.solve_batch(Z[:-1], dt, fields=False)
    moved = sim.solve_batch(D[:-1], dt, fields=False)
    return vals, companion, np.concatenate([moved.x, moved.v], axis=-1)


def _join(parts: List[Tuple[VertexValues, VertexValues, np.ndarray]]):
    """The ranks' parts of `_vertex_part` as one, in rank order."""
    def values(items: List[VertexValues]) -> VertexValues:
        cat = (lambda name: None if getattr(items[0], name) is None else
               np.concatenate([getattr(i, name) for i in items]))
        return VertexValues(items[0].s, cat("x"), cat("v"), cat("hamiltonian"), cat("xi"),
                            cat("eta"))
    parts = [p for p in parts if len(p[2])]
    return (values([p[0] for p in parts]), values([p[1] for p in parts]),
            np.concatenate([p[2] for p in parts]))


def _judge_chunk(config: RunConfig, state: _LoopState, schedule: SlabSchedule,
                 weights: ErrorWeights, bound: Optional[GrowthBound], Z: np.ndarray,
                 D: np.ndarray, lost: Optional[np.ndarray], vals: VertexValues,
                 companion: VertexValues,
                 psi: np.ndarray) -> Tuple[List[float], np.ndarray, np.ndarray, Optional[SlabBatch]]:
    """Rank 0: the chunk's slabs judged as `_judge` does. Returns the step factors of the
    accepted slabs, the state (z, d) after them and the accepted slabs (None: none)."""
    count = len(Z) - 1
    t0, dt = schedule.current()
    est = _estimates(vals, companion, None, psi, lost, weights, dt, config.T,
                     _output(config))
    est.glob[:, -1] = D[1:]
    t0s = (schedule.pos + schedule.length * np.arange(count)) * schedule.T / schedule.total
    ok = (_finite(vals) & est.finite & np.isfinite(D[1:]).all(axis=1)
          & (est.err_local <= 1.0) & (est.err_global <= weights.tol.refuse_factor))
    if bound is not None:
        ok &= bound.allows(t0s + dt, vals)
    # the accepted run ends before a slab that fails, or after one whose step factor changes
    # the length (SlabSchedule.accept: below 1 it shortens, from 2 on it may grow)
    order = 2 * config.degree
    done = int(np.argmin(ok)) if not ok.all() else count
    trial = copy.copy(schedule)
    states = trial.accept_run(step_factors(est.err_local[:done], order))
    done, batch = len(states), None
    if done:
        batch = SlabBatch(state.k, t0s[:done], np.full(done, dt), _slice(vals, done),
                          est.local[:done], est.glob[:done], est.err_local[:done],
                          est.err_global[:done], est.floor[:done], states,
                          est.scales[:done])
        weights.scale_x, weights.scale_v = est.scales[done - 1]
    return (done, trial.state), Z[done], D[done], batch


def _chunk(sim: Simulation, config: RunConfig, state: _LoopState, schedule: SlabSchedule,
           weights: Optional[ErrorWeights], bound: Optional[GrowthBound],
           count: int) -> Tuple[Optional[tuple], Optional[str]]:
    """The next `count` slabs of the current length (see `_batch_step`): rank 0 propagates the
    start states, every rank computes the vertex values of its share of the slabs (the array
    products, split by slabs), rank 0 gathers and judges them. (outcome of `_judge_chunk` on
    rank 0, None elsewhere; why it failed on any rank, the same on every rank). Collective."""
    comm, dt = sim.comm, schedule.current()[1]
    with np.errstate(all="ignore"):  # a blow-up is judged (not finite), not warned about
        states, problem = _on_root(comm, lambda: _recurrence(sim, state, dt, count))
        problem = bcast(comm, problem)
        if problem:
            return None, problem
        Z, D, lost = bcast(comm, states)
        cuts = np.linspace(0, count, comm.size + 1).round().astype(int)
        lo, hi = cuts[comm.rank], cuts[comm.rank + 1]
        try:
            part, mine = _vertex_part(sim, Z[lo:hi + 1], D[lo:hi + 1], dt,
                                      config.out is not None), None
        except Exception as exc:  # noqa: BLE001 -- shared, then raised on every rank
            part, mine = None, _one_line(exc)
        parts = comm.gather((part, mine), root=0) if comm.size > 1 else [(part, mine)]
        outcome, problem = None, None
        if comm.rank == 0:
            problem = next((p for _, p in parts if p), None)
            if problem is None:
                outcome, problem = _on_root(comm, lambda: _judge_chunk(
                    config, state, schedule, weights, bound, Z, D, lost,
                    *_join([q for q, _ in parts])))
        return outcome, bcast(comm, problem)


def _slice(values: VertexValues, count: int) -> VertexValues:
    return values.apply(lambda a: a[:count])


def _batch_step(sim: Simulation, config: RunConfig, state: _LoopState, schedule: SlabSchedule,
                weights: Optional[ErrorWeights], bound: Optional[GrowthBound],
                sinks: List[Any], check) -> Tuple[int, Optional[SolveError]]:
    """Solve, judge and record a chunk of equal slabs of a linear scene at once from its slab
    maps (superposition), instead of slab by slab: (slabs accepted, the failure that ends the
    run or None). Fixed slabs and --rtol alike; it stops before a slab that `_judge` would not
    accept (the slab loop then takes it) or after one whose step factor changes the length.
    Collective."""
    comm = sim.comm
    if (sim.superposition is None or sim.companion.superposition is None
            or not state.settled):
        return 0, None
    remaining = (schedule.total - schedule.pos) // schedule.length
    if remaining < 2:
        return 0, None
    try:
        check()
    except SolveError:  # the slab loop says why
        return 0, None
    t0, dt = schedule.current()
    per_slab = 8 * (sim.cells + 1) * 14 * sim.scene.n
    count = int(max(1, min(remaining, state.chunk, CHUNK_SLABS, CHUNK_BYTES // per_slab)))
    try:
        sim.slab_maps(dt)  # collective: the bases and the check of their slab map
    except SolveError:  # the slab loop retries shorter
        return 0, None
    sim.share_bases(dt)  # collective: every rank computes its share of the slabs
    outcome, problem = _chunk(sim, config, state, schedule, weights, bound, count)
    root = comm.rank == 0
    if problem:
        return 0, SolveError(f"slab {state.k} (t = {t0:g}): {problem}", slab=state.k)
    (done, schedule.state), z, d = bcast(comm, outcome[:3] if root else None)
    # chunks grow while their slabs are all taken (the length settled), and start small again
    # after one stopped early (a controller still finding its length wastes little)
    state.chunk = state.chunk * 4 if done == count else FIRST_CHUNK
    state.settled = done == count
    if not done:
        return 0, None
    batch = outcome[3] if root else None
    fed, problem = _on_root(comm, lambda: _feed(sinks, batch))
    taken, problem = bcast(comm, (fed if fed is not None else (done, problem)) if root else None)
    k = state.k + taken - 1
    state.lengths += [dt] * taken
    state.k += taken
    if problem:
        where = f" ({config.out})" if config.out is not None else ""
        return taken, SolveError(f"slab {k} (t = {t0 + (taken - 1) * dt:g} .. "
                                 f"{t0 + taken * dt:g}): writing the output failed{where}: "
                                 f"{problem}", slab=k)
    state.z, state.d = z, d
    return done, None


def _feed(sinks: List[Any], batch: SlabBatch) -> Tuple[int, Optional[str]]:
    """Give the accepted slabs to the sinks, the writer first: when it fails at a slab, the
    others take the slabs up to that one, as the slab loop's sinks would have (the slab whose
    write failed is in the results). (slabs taken, the failure in one line or None)."""
    taken, problem = len(batch), None
    for sink in sorted(sinks, key=lambda s: not isinstance(s, XdmfSink)):
        try:
            sink.add_batch(batch if taken == len(batch) else batch.head(taken))
        except PartialBatch as exc:
            taken, problem = exc.taken + 1, _one_line(exc.cause)
    return taken, problem


def _interruption(comm: MPI.Comm, schedule: SlabSchedule, k: int,
                  T: float) -> Optional[faults.Interrupted]:
    """The stop a signal asked for (on any rank) after slab k, unless the run is done.
    Collective."""
    signum = faults.requested()
    if comm.size > 1:
        signum = allreduce(comm, signum, "max")
    if not signum or schedule.done():
        return None
    t = schedule.current()[0]
    return faults.Interrupted(f"interrupted by {signal.Signals(signum).name} after slab {k} "
                              f"(t = {t:g} of T = {T:g})", signum, slab=k)


def _run_slabs(sim: Simulation, config: RunConfig, progress: bool,
               resume: bool = False) -> RunResult:
    tic = time.perf_counter()
    comm, scene = sim.comm, sim.scene
    root = comm.rank == 0
    n = scene.n
    acc = Accumulator(config) if root else None
    # bad or mismatched files to resume, an output directory that cannot take our files: bad
    # input, on every rank
    restart = input_on_root(comm, lambda: Restart(config, scene.name)) if resume else None
    xdmf = None if config.out is None else input_on_root(
        comm, lambda: XdmfSink(config, scene.name, restart))
    bar = ProgressSink(config.T) if (progress and root) else None
    sinks = [s for s in (acc, xdmf, bar) if s is not None]
    timings = {"compile_s": sim.setup_s if sim._fresh else 0.0, "solve_s": 0.0,
               "estimate_s": 0.0, "recovery_s": 0.0, "output_s": 0.0}
    sim._fresh = False
    start_rate = _start_rate(scene, config.x0, config.v0)
    # a motion slower than the horizon (a particle at rest) relates |v| to |x| / T: else the
    # round-off of its velocity would be the scale its velocity errors are measured against
    weights = (ErrorWeights(config.tolerance, config.x0, config.v0, max(start_rate, 1 / config.T))
               if root else None)
    # the zero base damps what the slabs do not resolve: no resolution guard, no growth bound
    guarded = scene.linear and config.base_state != "zero"
    rate = scene.fastest_rate(config.x0, config.v0) if (
        guarded or (scene.linear and config.rtol is not None)) else None
    bound = GrowthBound(scene, config.x0, config.v0) if (guarded and root) else None
    schedule = _schedule(config, sim.cells, start_rate if rate is None else rate)
    order = 2 * config.degree  # the local error per unit of time goes like dt^(2p)
    state = _LoopState(config)
    if resume:
        state.resume(comm, restart, acc, weights, schedule)
    rejected: List[Dict[str, Any]] = []
    failure: Optional[SolveError] = None
    while not schedule.done():
        t1 = time.perf_counter()
        batched, failure = _batch_step(
            sim, config, state, schedule, weights, bound, sinks,
            lambda: check_resolution(rate, schedule.current()[1], sim.cells, config.degree)
            if guarded else None)
        timings["solve_s"] += time.perf_counter() - t1
        if failure is not None:
            break
        if batched:
            state.batched += batched
            failure = _interruption(comm, schedule, state.k - 1, config.T)
            if failure is not None:
                break
            continue
        k, z, d = state.k, state.z, state.d
        t0, dt = schedule.current()
        t1 = time.perf_counter()
        try:
            if guarded:
                check_resolution(rate, dt, sim.cells, config.degree)
            vals = sim.solve_slab(z, t0, dt)
            suspicious = sim.verify()
            if suspicious:
                raise SolveError(suspicious)
            t2 = time.perf_counter()
            algebraic = sim.algebraic_error(z, vals)
            # (no error carried in: none to propagate, the estimate is the local one)
            psi = sim.tangent(z, d, t0, dt, vals) if d.any() else None
            lost = sim.unresolved(z, dt)
            companion = sim.companion.solve_slab(z, t0, dt, start=sim)
            timings["estimate_s"] += time.perf_counter() - t2
            verdict, problem = _on_root(comm, lambda: _judge(
                vals, companion, algebraic, psi, lost, weights, bound, t0, dt, config.T,
                _output(config)))
            shared = (("error", None, problem) if problem else verdict[:3]) if root else None
            action, err, reason = bcast(comm, shared)
            if action == "accept" and not sim.scene.linear:
                action, err, reason = _volume_kept(comm, sim, z, t0, dt, vals, err)
        except SolveError as exc:
            action, err, reason = "retry", None, str(exc)
        timings["solve_s"] += time.perf_counter() - t1
        if action == "retry" and schedule.halve(step_factor(err, order)):
            rejected.append({"t0": t0, "dt": dt, "reason": reason})
            continue
        if action != "accept":
            what = {"refuse": "; cannot vouch for the answer", "retry": "; no shorter slab left",
                    "error": ""}[action]
            failure = SolveError(f"slab {k} (t = {t0:g} .. {t0 + dt:g}): {reason}{what}"
                                 + ("" if action == "error" else f"; {_advice(config)}"), slab=k)
            break
        length = schedule.length
        schedule.accept(step_factor(err, order))
        state.settled = schedule.length == length
        state.lengths.append(dt)
        state.k += 1

        def record() -> Tuple[np.ndarray, np.ndarray]:
            """The sinks take the slab; the next slab's start state and its error."""
            weights.record(vals.x, vals.v)
            slab = AcceptedSlab(k, t0, dt, vals, verdict[3], schedule.state,
                                (weights.scale_x, weights.scale_v))
            for sink in sinks:
                sink.add(slab)
            return np.concatenate([vals.x[-1], vals.v[-1]]), verdict[3].glob[-1].copy()
        nxt, problem = _on_root(comm, record)
        failure = _interruption(comm, schedule, k, config.T)
        shared = ((z, d, problem) if problem else (*nxt, None)) if root else None
        state.z, state.d, problem = bcast(comm, shared)
        if problem:
            where = f" ({config.out})" if config.out is not None else ""
            failure = SolveError(f"slab {k} (t = {t0:g} .. {t0 + dt:g}): writing the output "
                                 f"failed{where}: {problem}", slab=k)
            break
        if failure is not None:
            break
    if bar is not None:
        bar.close()

    result = None
    if root:
        t, x, v = acc.arrays(n)
        files: List[str] = []
        output_slabs = None
        if xdmf is not None:
            try:
                files = xdmf.close(t, x, v)
            except Exception as exc:  # noqa: BLE001 -- a failure of its own, reported as one
                closing = f"writing the output failed ({config.out}): {_one_line(exc)}"
                if failure is None:
                    failure = SolveError(closing, slab=state.k)
                else:
                    failure.args = (f"{failure}; {closing}",)
                files = xdmf.files_on_disk()
            timings["output_s"] = xdmf.seconds
            output_slabs = xdmf.slabs_written
        timings["reference_s"] = acc.reference_s
        timings["total_s"] = time.perf_counter() - tic + timings["compile_s"]
        record = _solver_record(sim.solver, sim.prefix)
        record["halved_slabs"] = rejected
        record["rejected_slabs"] = len(rejected)
        record["superposition"] = sim.superposition is not None
        record["batched_slabs"] = state.batched
        record["estimates"] = acc.estimates
        record["companion_degree"] = sim.companion.degree
        if scene.linear:
            record["weighting"] = scene.weighting()
        record["assembly"] = ("pointwise" if sim.pointwise  # (never with kronecker)
                              else "kronecker" if sim.kronecker else "forms")
        record["base"] = config.base_state
        record["compiled_loops"] = _compiled_loops(sim)
        record["compiled_loops_unavailable"] = native.reason()  # why none ran, or None
        if scene.linear:
            record["coordinates"] = "modal" if sim.modal is not None else "physical"
        record["slab_solves"] = _solves(sim)
        record["companion_solves"] = _solves(sim.companion)
        record["tangent_solves"] = sim.tangent_solves
        record["resumed_from"] = state.resumed_from
        tol = config.tolerance
        lengths = state.lengths
        result = RunResult(
            scene=scene.name, parameters=scene.parameters(), T=config.T, cells=config.cells,
            degree=config.degree, slabs=config.slabs if config.rtol is None else len(lengths),
            x0=config.x0.tolist(), v0=config.v0.tolist(), dofs_per_slab=sim.problem.num_dofs,
            t=t, x=x, v=v, error=acc.error(), hamiltonian=acc.hamiltonian(), timings=timings,
            solver=record, slab_lengths=lengths, output_files=files,
            staging={"mode": config.staging, "stages_per_slab": config.stages,
                     "solved_slabs": len(lengths), "cells_per_solved_slab": config.slab_cells,
                     "limit_cells_times_degree_squared": STAGING_LIMIT},
            recovery=config.recovery, error_estimate=acc.estimate_max(),
            estimate=acc.estimate(),
            tolerance={"rtol": tol.rtol, "atol": tol.atol, "adaptive": tol.adaptive,
                       "scale_x": weights.scale_x, "scale_v": weights.scale_v})
        result.output_slabs = output_slabs
        if acc.est_rows:
            result.estimate_at_t = np.concatenate(acc.est_rows)
        if acc.err_rows:
            result.error_at_t = np.concatenate(acc.err_rows)
        if failure is not None:
            interrupted = isinstance(failure, faults.Interrupted)
            result.status = "interrupted" if interrupted else "failed"
            result.message = str(failure)
    failure = _shared_failure(comm, failure)
    result = bcast(comm, result)
    result.scene_object = config.scene
    if config.t_eval is not None:
        result.t_eval = _dense_output(result, config)
        if failure is None:
            failure = _unvouched_output(result, config)
    if failure is not None:
        failure.partial = result
        raise failure
    return result


def _unvouched_output(result: RunResult, config: RunConfig) -> Optional[SolveError]:
    """A failure when the estimate at the --t-eval times exceeds what the run vouches for (the
    slab loop keeps the gaps between vertices within the tolerance; this catches what its
    sample points within each vertex interval missed). The same on every rank."""
    estimate = result.t_eval.get("error_estimate")
    tol = config.tolerance
    scale = max(result.tolerance.get("scale_x", 0.0), result.tolerance.get("scale_v", 0.0))
    allowed = tol.refuse_factor * (tol.atol + tol.rtol * scale)
    if estimate is None or estimate <= allowed:
        return None
    message = (f"the state at the --t-eval times is estimated to be {estimate:.3g} off, more "
               f"than the tolerance allows ({tol.label}): the output vertices are too far apart; "
               "use more --cells or a degree of at most 4")
    result.status, result.message = "failed", message
    return SolveError(message)


def _shared_failure(comm: MPI.Comm, failure: Optional[SolveError]) -> Optional[SolveError]:
    """Rank 0's failure (a failed close is known there only) on every rank."""
    if comm.size == 1:
        return failure
    what = None if failure is None else (
        str(failure), failure.slab, getattr(failure, "signum", None))
    what = comm.bcast(what if comm.rank == 0 else None, root=0)
    if what is None:
        return None
    message, slab, signum = what
    return faults.Interrupted(message, signum, slab) if signum else SolveError(message, slab)


def _dense_output(result: RunResult, config: RunConfig) -> Dict[str, Any]:
    """The state at config.t_eval (those within the computed part), and its error against the
    reference when there is one; the same on every rank."""
    times = config.t_eval
    done = times[times <= (result.t[-1] if len(result.t) else -1.0)]
    out: Dict[str, Any] = {"t": done.tolist(), "x": [], "v": [], "error": None,
                           "error_estimate": None, "omitted": int(len(times) - len(done))}
    if len(done) == 0 or len(result.t) < 2:
        return out
    x, v, interpolation = hermite_estimate(config.scene, result.t, result.x, result.v, done)
    if result.estimate_at_t is not None:  # the vertex estimate on both sides, plus the Hermite's
        k = np.clip(np.searchsorted(result.t, done, side="right") - 1, 0, len(result.t) - 2)
        vertex = np.maximum(result.estimate_at_t[k], result.estimate_at_t[k + 1])
        estimate = vertex + interpolation
        out["error_estimate"] = float(estimate.max())
        if result.error_estimate is not None:  # the run's estimate covers every output time
            result.error_estimate = max(result.error_estimate, out["error_estimate"])
    out.update(x=x.tolist(), v=v.tolist())
    if config.reference != "none":  # at the distinct times, in increasing order
        distinct, where = np.unique(done, return_inverse=True)
        x_ref, v_ref = config.scene.reference(config.x0, config.v0)(distinct)
        ex = np.abs(x - x_ref[where]).max(initial=0.0)
        ev = np.abs(v - v_ref[where]).max(initial=0.0)
        out["error"] = {"x_max": float(ex), "v_max": float(ev)}
    return out


def run(config: RunConfig, comm: MPI.Comm = MPI.COMM_WORLD, progress: bool = False,
        resume: bool = False) -> RunResult:
    """Solve the dual problem slab by slab, recover the primal motion, compare with the reference.

    With `resume`, go on from the last slab an earlier run of the same options wrote into
    `config.out` (the end state equals an uninterrupted run's).

    Nonlinear scenes retry a slab whose Newton (or DtP map) fails with half its length, up to
    `config.max_halvings` times; `progress` shows a bar over the slabs on stderr (rank 0).

    Raises:
        SolveError: a slab failed, or writing the output did; `partial` holds the result of the
            slabs completed before, whose output files (if any) are readable.
        fem_dual.faults.Interrupted: SIGINT/SIGTERM (with fem_dual.faults.graceful_signals)
            stopped the run after a slab; `partial` as for SolveError.
    """
    if not isinstance(config, RunConfig):
        raise InputError(f"config must be a RunConfig (RunConfig.create(...)), not "
                         f"{type(config).__name__}")
    config.scene.checked()  # a RunConfig built without create() is validated all the same
    if resume and config.out is None:
        raise InputError("resume needs the output directory of the run to go on with (--out)")
    if config.out is not None:  # before any work: a bad --out is bad input, on every rank
        check_output_dir_on_root(comm, config.out)
    sim = Simulation.for_config(config, comm)
    try:
        result = sim.run(config, progress, resume)
    except (SolveError, InputError):  # raised on every rank alike: close collectively
        sim.close()
        raise
    # any other exception may be one rank's own: a collective close could hang, so its
    # objects are left to petsc4py's garbage
    sim.close()
    return result
