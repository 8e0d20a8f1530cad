"""The time-staging slab driver, used by every scene.

Each slab starts from the primal state recovered at the end of the previous one; that state is also
the slab's constant base state (xbar, vbar) of H. Forms are compiled once; only fem.Constants change
between slabs. Results live on rank 0 and are broadcast at the end, so every rank returns the same
RunResult.
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional

import numpy as np
from mpi4py import MPI

from fem_dual.compat import quiet_jit_logging
from fem_dual.config import STAGING_LIMIT, RunConfig
from fem_dual.errors import SolveError
from fem_dual.kronecker import (KroneckerProblem, KroneckerSampler, KroneckerSolver,
                                KroneckerSuperposition)
from fem_dual.mpi import bcast
from fem_dual.output import OutputDir, check_output_dir_on_root, XdmfSeries, write_polyline
from fem_dual.newton import NewtonSlabSolver
from fem_dual.problem import SlabProblem
from fem_dual.recovery import VertexSampler, VertexValues
from fem_dual.solvers import LinearSlabSolver, solver_prefix
from fem_dual.superposition import Superposition
from meshes import SlabSchedule

__all__ = ["RunResult", "Simulation", "run"]


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

    @property
    def final(self) -> Dict[str, List[float]]:
        if len(self.t) == 0:
            return {"t": None, "x": None, "v": None}
        return {"t": float(self.t[-1]), "x": self.x[-1].tolist(), "v": self.v[-1].tolist()}

    def write_json(self, stream, chunk: int = 4096) -> None:
        """Write `to_dict()` as one JSON object, streaming the vertex arrays in chunks of rows so
        that long runs never hold their JSON text in memory."""
        head = self.to_dict(arrays=False)
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
        }
        if arrays:
            out.update(t=self.t.tolist(), x=self.x.tolist(), v=self.v.tolist())
        return out


class _Accumulator:
    """Vertex arrays of the whole run and their errors against the reference (rank 0 only)."""

    def __init__(self, config: RunConfig):
        self.flow = config.scene.reference(config.x0, config.v0)
        self.t: List[np.ndarray] = []
        self.x: List[np.ndarray] = []
        self.v: List[np.ndarray] = []
        self.err_x = 0.0
        self.err_v = 0.0
        self.final_err = (float("nan"), float("nan"))
        self.ham: List[Dict[str, float]] = []
        self.reference_s = 0.0

    def add(self, t0: float, dt: float, vals: VertexValues, first: bool) -> None:
        keep = slice(0 if first else 1, None)  # each slab junction once: the end of the slab before
        t = t0 + dt * vals.s[keep]
        x, v = vals.x[keep], vals.v[keep]
        tic = time.perf_counter()
        x_ref, v_ref = self.flow(t)
        self.reference_s += time.perf_counter() - tic
        ex, ev = np.abs(x - x_ref).max(axis=1), np.abs(v - v_ref).max(axis=1)
        self.err_x, self.err_v = max(self.err_x, ex.max()), max(self.err_v, ev.max())
        self.final_err = (float(ex[-1]), float(ev[-1]))
        self.t.append(t), self.x.append(x), self.v.append(v)
        h = vals.hamiltonian
        scale = max(np.abs(h).max(), np.finfo(float).tiny)
        self.ham.append({"min": float(h.min()), "max": float(h.max()),
                         "drift": float((h.max() - h.min()) / scale)})

    def arrays(self, n: int):
        if not self.t:
            return np.zeros(0), np.zeros((0, n)), np.zeros((0, n))
        return np.concatenate(self.t), np.concatenate(self.x), np.concatenate(self.v)

    def hamiltonian(self) -> Dict[str, Any]:
        if not self.ham:
            return {"min": None, "max": None, "drift": None, "per_slab": []}
        return {"min": min(h["min"] for h in self.ham), "max": max(h["max"] for h in self.ham),
                "drift": max(h["drift"] for h in self.ham), "per_slab": self.ham}

    def error(self) -> Dict[str, Optional[float]]:
        if not self.t:
            return {"x_max": None, "v_max": None, "final": None, "final_x": None, "final_v": None}
        return {"x_max": float(self.err_x), "v_max": float(self.err_v),
                "final": max(self.final_err), "final_x": self.final_err[0],
                "final_v": self.final_err[1]}


def _solver_record(solver, prefix: str) -> Dict[str, Any]:
    if isinstance(solver, NewtonSlabSolver):
        return {"kind": "snes", "prefix": prefix, "newton_iterations": list(solver.iterations),
                "residual_norms": list(solver.residual_norms),
                "residual_histories": [list(h) for h in solver.histories]}
    return {"kind": "ksp", "prefix": prefix, "ksp_iterations": list(solver.iterations)}


def _progress_bar(T: float):
    from tqdm import tqdm

    return tqdm(total=T, unit="t", desc="slabs", leave=False,
                bar_format="{l_bar}{bar}| t={n:.4g}/{total:.4g} [{elapsed}<{remaining}, {rate_fmt}]")


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
    """

    def __init__(self, scene, degree: int, cells: int, comm: MPI.Comm = MPI.COMM_WORLD,
                 petsc: Optional[Dict[str, str]] = None, recovery: str = "momentum",
                 kronecker: bool = False):
        quiet_jit_logging()
        tic = time.perf_counter()
        self.scene, self.degree, self.cells, self.comm = scene, degree, cells, comm
        self.prefix = solver_prefix(scene.name)
        self.recovery, self.kronecker = recovery, kronecker
        if kronecker:
            self.problem = KroneckerProblem(scene, degree, cells, comm)
            self.solver = KroneckerSolver(self.problem, self.prefix, petsc)
            self.sampler = KroneckerSampler(self.problem)
        else:
            self.problem = SlabProblem(scene, degree, cells, comm)
            solver_class = LinearSlabSolver if scene.linear else NewtonSlabSolver
            self.solver = solver_class(self.problem, self.prefix, petsc)
            self.sampler = VertexSampler(self.problem, with_dual=True, recovery=recovery)
        self.setup_s = time.perf_counter() - tic
        self._fresh = True

    def uses_superposition(self, config: RunConfig) -> bool:
        if config.superpose != "auto":
            return config.superpose == "yes"
        return self.scene.linear and config.slab_count > 2 * self.scene.n

    @classmethod
    def for_config(cls, config: RunConfig, comm: MPI.Comm = MPI.COMM_WORLD) -> "Simulation":
        """The simulation that runs `config` (its staged cells per slab)."""
        return cls(config.scene, config.degree, config.slab_cells, comm, config.petsc,
                   config.recovery, config.kronecker)

    def run(self, config: RunConfig, progress: bool = False) -> RunResult:
        """Solve the dual problem slab by slab, recover the primal motion, compare with the
        reference (see `run`). The matrix is assembled and factored again in every run."""
        if ((config.scene.name, config.degree, config.slab_cells, config.recovery,
             config.kronecker)
                != (self.scene.name, self.degree, self.cells, self.recovery, self.kronecker)):
            raise ValueError("the configuration does not match the compiled simulation")
        if config.scene != self.scene:
            self.problem.set_scene_constants(config.scene)
            self.scene = config.scene
        self.solver.reset()
        return _run_slabs(self, config, progress)


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
        self.z0 = float(np.linalg.norm(np.concatenate([x0, v0])))

    def allows(self, t: float, values: VertexValues) -> bool:
        z = np.hypot(np.linalg.norm(values.x, axis=1), np.linalg.norm(values.v, axis=1)).max()
        if not np.isfinite(self.kappa):  # defective A: no bound to check against
            return True
        return z <= 10 * self.kappa * np.exp(min(self.sigma * t, 700.0)) * self.z0


def _insane(vals: VertexValues, bound: Optional[GrowthBound], t: float) -> Optional[str]:
    """Why the slab's recovered state cannot be right, or None."""
    if not vals.finite():
        return "the recovered state is not finite; try more slabs or cells"
    if bound is not None and not bound.allows(t, vals):
        return ("the motion outgrows the exact flow's bound (noise amplified in modes the "
                "slabs do not resolve); use more slabs or cells per slab")
    return None


def _run_slabs(sim: Simulation, config: RunConfig, progress: bool) -> RunResult:
    tic = time.perf_counter()
    comm, scene, problem, solver, sampler = (sim.comm, sim.scene, sim.problem, sim.solver,
                                             sim.sampler)
    root = comm.rank == 0
    superposition = None
    if sim.uses_superposition(config):
        kind = KroneckerSuperposition if sim.kronecker else Superposition
        superposition = kind(problem, solver, sampler, config.T)
    acc = _Accumulator(config) if root else None
    outdir = OutputDir(config.out) if (root and config.out is not None) else None
    series: Optional[XdmfSeries] = None
    timings = {"compile_s": sim.setup_s if sim._fresh else 0.0, "solve_s": 0.0,
               "recovery_s": 0.0, "output_s": 0.0}
    sim._fresh = False
    lengths: List[float] = []
    retries: List[Dict[str, Any]] = []
    failure: Optional[SolveError] = None
    state = (config.x0, config.v0)

    halvings = 0 if scene.linear else config.max_halvings  # a linear solve does not diverge
    rate = scene.fastest_rate(config.x0, config.v0) if scene.linear else None
    bound = GrowthBound(scene, config.x0, config.v0) if (scene.linear and root) else None
    schedule = SlabSchedule(config.T, config.slab_count, halvings)
    bar = _progress_bar(config.T) if (progress and root) else None
    k = 0
    while not schedule.done():
        t0, dt = schedule.current()
        t1 = time.perf_counter()
        try:
            check_resolution(rate, dt, problem.mesh.cells, config.degree)
            if superposition is not None:
                vals = superposition(state[0], state[1], dt)
                t2 = time.perf_counter()
            else:
                problem.set_slab(state[0], state[1], dt, t0)
                solver.solve()
                t2 = time.perf_counter()
                vals = sampler()
            problem_text = bcast(comm, _insane(vals, bound, t0 + dt) if root else None)
            if problem_text:
                raise SolveError(problem_text)
        except SolveError as exc:
            if schedule.halve():
                retries.append({"t0": t0, "dt": dt, "reason": str(exc)})
                continue
            failure = SolveError(f"slab {k} (t = {t0:g} .. {t0 + dt:g}): {exc}", slab=k)
            break
        timings["solve_s"] += t2 - t1
        timings["recovery_s"] += time.perf_counter() - t2
        if root:
            acc.add(t0, dt, vals, first=(k == 0))
            if outdir is not None:
                t3 = time.perf_counter()
                if series is None:
                    series = XdmfSeries(outdir.file(f"{scene.name}.xdmf"),
                                        config.T / config.slab_count * vals.s)
                series.write(t0, {"t": t0 + dt * vals.s, "xi": vals.xi, "eta": vals.eta,
                                  "x_hat": vals.x, "v_hat": vals.v,
                                  "hamiltonian": vals.hamiltonian})
                timings["output_s"] += time.perf_counter() - t3
            if bar is not None:
                bar.update(dt)
        lengths.append(dt)
        if superposition is None:  # the next slab's constants are set on every rank
            state = bcast(comm, (vals.x[-1].copy(), vals.v[-1].copy()) if root else None)
        elif root:
            state = (vals.x[-1].copy(), vals.v[-1].copy())
        schedule.accept()
        k += 1
    if bar is not None:
        bar.close()

    result = None
    if root:
        t, x, v = acc.arrays(scene.n)
        files: List[str] = []
        if outdir is not None:
            t3 = time.perf_counter()
            if series is not None:
                series.close()
                write_polyline(outdir.file(f"{scene.name}_trajectory.xdmf"), x,
                               {"t": t, "v_hat": v})
            files = [str(p) for p in outdir.commit()]
            timings["output_s"] += time.perf_counter() - t3
        timings["reference_s"] = acc.reference_s
        timings["total_s"] = time.perf_counter() - tic + timings["compile_s"]
        record = _solver_record(solver, sim.prefix)
        record["halved_slabs"] = retries
        record["superposition"] = superposition is not None
        if scene.linear:
            record["weighting"] = scene.weighting()
            record["assembly"] = "kronecker" if sim.kronecker else "forms"
        record["slab_solves"] = (superposition.basis_solves if superposition is not None
                                 else len(solver.iterations))
        result = RunResult(
            scene=scene.name, parameters=scene.parameters(), T=config.T, cells=config.cells,
            degree=config.degree, slabs=config.slabs, x0=config.x0.tolist(),
            v0=config.v0.tolist(), dofs_per_slab=problem.num_dofs, t=t, x=x, v=v,
            error=acc.error(), hamiltonian=acc.hamiltonian(), timings=timings,
            solver=record, slab_lengths=lengths, output_files=files,
            staging={"mode": config.staging, "stages_per_slab": config.stages,
                     "solved_slabs": config.slab_count, "cells_per_solved_slab": config.slab_cells,
                     "limit_cells_times_degree_squared": STAGING_LIMIT},
            recovery=config.recovery)
        if failure is not None:
            result.status, result.message = "failed", str(failure)
    result = bcast(comm, result)
    if failure is not None:
        failure.partial = result
        raise failure
    return result


def run(config: RunConfig, comm: MPI.Comm = MPI.COMM_WORLD, progress: bool = False) -> RunResult:
    """Solve the dual problem slab by slab, recover the primal motion, compare with the reference.

    Nonlinear scenes retry a slab whose Newton (or DtP map) fails with half its length, up to
    `config.max_halvings` times; `progress` shows a bar over the slabs on stderr (rank 0).

    Raises:
        SolveError: a slab failed; `partial` holds the result of the slabs completed before it,
            whose output files (if any) are complete.
    """
    quiet_jit_logging()
    if config.out is not None:  # before any work: a bad --out is bad input, on every rank
        check_output_dir_on_root(comm, config.out)
    return Simulation.for_config(config, comm).run(config, progress)
