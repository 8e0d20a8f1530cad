"""The slab loop: step, judge, accept or reject, give the accepted slab to the sinks.

Each slab starts from the primal state recovered at the end of the previous one. One step is one
slab of the simulation (fem_dual.integrate.simulation: the answer, its companion and the tangent
that carries the start state's error); rank 0 judges it (fem_dual.integrate.judge) and every
rank learns the verdict; the controller (fem_dual.integrate.controller) accepts the slab and
chooses the next length, or retries it shorter; the sinks (fem_dual.integrate.sinks) take the
accepted slab. Linear scenes take chunks of equal slabs at once (fem_dual.integrate.chunks).
Results live on rank 0 and are broadcast at the end, so every rank returns the same RunResult.
"""
from __future__ import annotations

import signal
import time
from typing import TYPE_CHECKING, Any, Dict, List, Optional, Tuple

import numpy as np
from mpi4py import MPI

from fem_dual import faults, native
from fem_dual.config import STAGING_LIMIT, RunConfig
from fem_dual.errors import SolveError, one_line
from fem_dual.integrate.budget import SlabBudget
from fem_dual.integrate.chunks import batch_step
from fem_dual.integrate.conditioning import data_floor
from fem_dual.integrate.controller import SlabSchedule, schedule_for, step_factor
from fem_dual.integrate.estimate import ErrorWeights, carried_floor, carry, output_request
from fem_dual.integrate.judge import (GrowthBound, Verdict, check_resolution, judge, judged,
                                      volume_kept)
from fem_dual.integrate.kinks import PREDICTION_STEPS, kink_time, predicted_kink_time
from fem_dual.integrate.restart import Restart
from fem_dual.integrate.result import RunResult, t_eval_output, unvouched_output
from fem_dual.integrate.sinks import AcceptedSlab, Accumulator, ProgressSink, XdmfSink
from fem_dual.integrate.state import LoopState
from fem_dual.mpi import allreduce, bcast, input_on_root, on_root
from fem_dual.slab.base_state import FlowPredictor, motion_rate
from fem_dual.slab.values import VertexValues

if TYPE_CHECKING:
    from fem_dual.integrate.simulation import Simulation

__all__ = ["run_slabs"]

MAX_SUGGESTED_RTOL = 1e-2  # a data floor needing a looser --rtol than this: only a shorter --T


def run_slabs(sim: "Simulation", config: RunConfig, progress: bool = False,
              resume: bool = False, setup_s: float = 0.0) -> RunResult:
    """Run `config` on the simulation `sim` (begun for it): the slab loop. Collective.

    Raises:
        SolveError: a slab failed, or writing the output did; `partial` holds the result of the
            slabs completed before.
        fem_dual.faults.Interrupted: a signal stopped the run after a slab.
    """
    run = _Run(sim, config, progress, resume, setup_s)
    schedule, state = run.schedule, run.state
    failure: Optional[SolveError] = run.below_data_floor()
    while failure is None and not schedule.done():
        # --rtol: the cost predicted from the slabs so far (fem_dual.integrate.budget)
        failure = run.budget.check(state, *schedule.current(), run.rate, run.acc)
        if failure is not None:
            break
        taken, failure = run.chunk()  # linear scenes: a chunk of equal slabs at once
        if taken or failure is not None:
            continue
        t0, dt = schedule.current()
        values, verdict = run.step(t0, dt)  # answer, companion, tangent; judged
        if run.solver_failed(verdict):
            failure = run.refusal(verdict._replace(
                action="error", reason=f"{verdict.reason}; it failed alike on "
                f"{LINEAR_SOLVE_RETRIES} slabs, each half as long"), t0, dt)
            break
        if verdict.action == "cut" or (verdict.action == "retry" and
                                       schedule.halve(step_factor(verdict.err, run.order))):
            run.rejected.append({"t0": t0, "dt": dt, "reason": verdict.reason})
            continue
        if verdict.action != "accept":
            failure = run.refusal(verdict, t0, dt)
            break
        length = schedule.length
        schedule.accept(step_factor(verdict.err, run.order))
        state.settled = schedule.length == length
        failure = run.record(values, verdict, t0, dt)  # the sinks; the next start state
    return run.finish(failure)


LINEAR_SOLVE_RETRIES = 6  # a linear slab whose solve failed this often in a row, each time on a
# slab half as long, stops the run: a solve that fails on conditioning fails at every length (a
# follower load of 1e9 on a beam halved 23 times, minutes of CG at its iteration limit each)


class _Run:
    """One run of the slab loop: its sinks, error weights, guards, controller and where it
    stands (`state`), and what the loop asks of them."""

    def __init__(self, sim: "Simulation", config: RunConfig, progress: bool, resume: bool,
                 setup_s: float = 0.0):
        # (built before the run's clock starts: its set-up is compile time; the companion whose
        # base it reads is built on every rank already: Simulation.run)
        self.flow_check = sim.flow_check if sim.comm.rank == 0 else None
        self.tic = time.perf_counter()
        self.sim, self.config, self.comm = sim, config, sim.comm
        scene, root = sim.scene, sim.comm.rank == 0
        self.floor = data_floor(scene, config.x0, config.v0, config.T) if root else None
        self.acc = Accumulator(config, self.floor) if root else None
        # bad or mismatched files to resume, an output directory that cannot take our files:
        # bad input, on every rank
        restart = input_on_root(self.comm, lambda: Restart(config, scene.name)) if resume \
            else None
        self.xdmf = None if config.out is None else input_on_root(
            self.comm, lambda: XdmfSink(config, scene.name, restart, self.floor))
        self.bar = ProgressSink(config.T) if (progress and root) else None
        self.sinks = [s for s in (self.acc, self.xdmf, self.bar) if s is not None]
        self.timings = {"compile_s": sim.charged_setup(), "setup_s": setup_s, "solve_s": 0.0,
                        "estimate_s": 0.0, "recovery_s": 0.0, "output_s": 0.0}
        start_rate = _start_rate(scene, config.x0, config.v0)
        # a motion slower than the horizon (a particle at rest) relates |v| to |x| / T: else the
        # round-off of its velocity would be the scale its velocity errors are measured against
        self.weights = (ErrorWeights(config.tolerance, config.x0, config.v0,
                                     max(start_rate, 1 / config.T)) if root else None)
        # the zero base damps what the slabs do not resolve: no resolution guard, no growth bound
        self.guarded = scene.linear and config.base_state != "zero"
        self.rate = None
        if self.guarded:
            self.rate = scene.fastest_rate(config.x0, config.v0)
        elif scene.linear and config.rtol is not None:
            # the zero base drops a mode once: the first slab need follow only the modes left
            # when the fastest, together within half the tolerance, are dropped
            self.rate = scene.fastest_rate(config.x0, config.v0, relative=0.5 * config.rtol,
                                           scales=(self.weights.scale_x, self.weights.scale_v)
                                           ) if root else None
            if self.comm.size > 1:
                self.rate = self.comm.bcast(self.rate, root=0)
        # (a sparse scene has no spectrum to bound its motion by)
        self.bound = GrowthBound(scene, config.x0, config.v0) if (
            self.guarded and root and not scene.sparse) else None
        self.schedule = schedule_for(config, sim.cells,
                                     start_rate if self.rate is None else self.rate)
        self.order = 2 * config.degree  # the local error per unit of time goes like dt^(2p)
        # a force with kinks (abs): slabs end at them, predicted by classical Runge-Kutta
        self.kinked = not scene.linear and scene.kinks(config.x0[None]) is not None
        self.kink_flow = FlowPredictor(scene, PREDICTION_STEPS) if self.kinked and root \
            else None
        self.state = LoopState(config)
        if resume:
            self.state.resume(self.comm, restart, self.acc, self.weights, self.schedule)
        self.rejected: List[Dict[str, Any]] = []
        self.lost: Optional[np.ndarray] = None  # what the zero base drops on the slab solved
        self.failed_solves = 0  # linear slabs in a row whose solve failed
        self.budget = SlabBudget(config, scene, sim.superposition is not None
                                 and sim.companion.superposition is not None, self.comm)

    def _resolved(self, dt: float) -> None:
        """SolveError when a linear slab of length dt is under-resolved (`check_resolution`)."""
        if self.guarded:
            check_resolution(self.rate, dt, self.sim.cells, self.config.degree)

    def chunk(self) -> Tuple[int, Optional[SolveError]]:
        """Linear scenes: a chunk of equal slabs from the slab maps (fem_dual.integrate.chunks);
        (slabs taken, the failure that ends the run or None). Collective."""
        tic = time.perf_counter()
        state, schedule = self.state, self.schedule
        taken, failure = batch_step(self.sim, self.config, state, schedule, self.weights,
                                    self.bound, self.sinks,
                                    lambda: self._resolved(schedule.current()[1]))
        self.timings["solve_s"] += time.perf_counter() - tic
        if taken:
            self.budget.chunk_ran(tic, taken)
        if taken and failure is None:
            state.batched += taken
            failure = _interruption(self.comm, schedule, state.k - 1, self.config.T)
        return taken, failure

    def solver_failed(self, verdict: Verdict) -> bool:
        """Count a linear slab's failed solve (reset by any other verdict); True once
        LINEAR_SOLVE_RETRIES of them came in a row."""
        failed = self.sim.scene.linear and verdict.action == "retry" and verdict.solver
        self.failed_solves = self.failed_solves + 1 if failed else 0
        return self.failed_solves >= LINEAR_SOLVE_RETRIES

    def step(self, t0: float, dt: float) -> Tuple[Optional[VertexValues], Verdict]:
        """Solve the slab [t0, t0 + dt] from the current start state with its error estimate,
        and judge it: (its vertex values on rank 0, the verdict on every rank). Collective."""
        sim, z, d = self.sim, self.state.z, self.state.d
        tic = time.perf_counter()
        estimate_before = self.timings["estimate_s"]  # (solve_s holds the rest of the step)
        vals = None
        try:
            self._resolved(dt)
            cut = self._cut_at_kink(None, t0, dt)  # (the kink ahead, predicted)
            if cut is not None:
                return vals, cut
            vals = sim.solve_slab(z, t0, dt)
            suspicious = sim.verify()
            if suspicious:
                raise SolveError(suspicious)
            cut = self._cut_at_kink(vals, t0, dt)
            if cut is not None:
                self.timings["solve_s"] += time.perf_counter() - tic
                return vals, cut
            t2 = time.perf_counter()
            algebraic = sim.algebraic_error(z, vals)
            # the companion starts from the answer's solved slab: before the tangent solves
            # another slab on the answer's backend
            companion = sim.companion.solve_slab(z, t0, dt, start=sim)
            # (no error carried in: none to propagate, the estimate is the local one)
            psi = sim.tangent(z, d, t0, dt, vals) if d.any() else None
            lost = self.lost = sim.unresolved(z, dt)
            self.timings["estimate_s"] += time.perf_counter() - t2
            config = self.config
            verdict = judged(self.comm, lambda: judge(
                vals, companion, algebraic, psi, lost, self.weights, self.bound, t0, dt,
                config.T, output_request(config), None if lost is None else self.state.dropped))
            if verdict.action == "accept" and not sim.scene.linear:
                verdict = volume_kept(sim, z, t0, dt, vals, verdict)
                if verdict.action == "accept":
                    verdict = self._follows_flow(z, dt, vals, verdict)
        except SolveError as exc:
            verdict = Verdict("retry", None, str(exc), solver=True)
        self.timings["solve_s"] += (time.perf_counter() - tic
                                    - (self.timings["estimate_s"] - estimate_before))
        return vals, verdict

    def _follows_flow(self, z: np.ndarray, dt: float, vals: Optional[VertexValues],
                      verdict: Verdict) -> Verdict:
        """The verdict on an accepted nonlinear slab: still that where its answer is as near
        classical Runge-Kutta from the same start as its estimate says, or where RK4 cannot
        tell (fem_dual.integrate.flow_check); else "retry". Collective."""
        why = problem = None
        if self.flow_check is not None and verdict.estimate is not None:  # (rank 0)
            tic = time.perf_counter()
            why, problem = on_root(self.comm, lambda: self.flow_check.excess(
                z, dt, vals, verdict.estimate))
            self.timings["estimate_s"] += time.perf_counter() - tic
        why, problem = bcast(self.comm, (why, problem))  # (a failure on rank 0 ends every rank)
        if problem is not None:
            return Verdict("error", None, problem)
        return verdict if why is None else Verdict("retry", None, why)

    def _cut_at_kink(self, vals: Optional[VertexValues], t0: float,
                     dt: float) -> Optional[Verdict]:
        """A "cut" verdict where the force has a kink inside the slab and the schedule ends the
        slab there (fem_dual.integrate.kinks: on the solved slab's values `vals`, or predicted
        from the start state where they are None), else None. Collective."""
        if not self.kinked:  # (a smooth force: no kink to look for)
            return None
        at = None
        if self.comm.rank == 0:
            scene = self.sim.scene
            at = (predicted_kink_time(scene, self.kink_flow, self.state.z, t0, dt)
                  if vals is None else kink_time(scene, t0, dt, vals))
        at = bcast(self.comm, at)
        if at is None or not self.schedule.cut(at):
            return None
        return Verdict("cut", None, f"the force has a kink (abs) at t = {at:.12g} inside the "
                       "slab: it ends there")

    def below_data_floor(self) -> Optional[SolveError]:
        """The failure that refuses a tolerance the run cannot vouch for before any slab: the
        data floor (fem_dual.integrate.conditioning) at T beyond what the tolerance allows
        (as the estimate's, ACCEPT_GLOBAL with --rtol); None otherwise. The same on every
        rank."""
        message = None
        if self.floor is not None:
            tol, w = self.config.tolerance, self.weights
            # (relative to the motion's scale as it grows, at least the start's, as the
            # error weights measure it)
            scales = np.maximum(self.floor.scale, [w.scale_x, w.scale_v])
            floor = self.floor.floor
            allowed = tol.refuse_factor * (tol.atol + tol.rtol * scales)
            if (floor > allowed).any():
                needed = float((floor / scales).max()) / tol.refuse_factor
                x, v = self.floor.final()
                advice = ("shorten --T" if needed > MAX_SUGGESTED_RTOL else
                          f"use --rtol {_rounded_up(needed):g} or looser, or a shorter --T")
                message = (f"the round-off of M and K alone moves this motion by {x:.3g} in x "
                           f"and {v:.3g} in v by T = {self.config.T:g} (it grows with the "
                           f"horizon, and with modes close to coalescing), more than the "
                           f"tolerance ({tol.label}) allows; no float64 answer can be vouched "
                           f"for: {advice}")
        message = bcast(self.comm, message)
        return None if message is None else SolveError(message, slab=0)

    def refusal(self, verdict: Verdict, t0: float, dt: float) -> SolveError:
        """The failure that ends the run at a slab that is neither accepted nor retried."""
        what = {"refuse": "; cannot vouch for the answer", "retry": "; no shorter slab left",
                "error": ""}[verdict.action]
        advice = "" if verdict.action == "error" else f"; {_advice(self.config)}"
        k = self.state.k
        return SolveError(f"slab {k} (t = {t0:g} .. {t0 + dt:g}): {verdict.reason}{what}"
                          + advice, slab=k)

    def record(self, vals: Optional[VertexValues], verdict: Verdict, t0: float,
               dt: float) -> Optional[SolveError]:
        """Give the accepted slab to the sinks (rank 0) and move the start state and its error
        to its end: the failure that ends the run (output, a signal) or None. Collective."""
        state, schedule, weights = self.state, self.schedule, self.weights
        state.lengths.append(dt)
        k = state.k
        state.k += 1

        def add() -> Tuple[np.ndarray, np.ndarray]:
            """The sinks take the slab; the next slab's start state and its error."""
            weights.record(vals.x, vals.v)
            if not self.sim.scene.linear:  # (linear scenes: the data floor)
                state.roundoff = carry(state.roundoff, verdict.estimate, verdict.tangent)
                verdict.estimate.carried = carried_floor(state.roundoff)
            slab = AcceptedSlab(k, t0, dt, vals, verdict.estimate, schedule.state,
                                (weights.scale_x, weights.scale_v))
            for sink in self.sinks:
                sink.add(slab)
            carried = verdict.estimate.glob[-1].copy()
            if self.lost is not None:  # (carried beside d: state.dropped)
                carried -= state.dropped + self.lost
            return np.concatenate([vals.x[-1], vals.v[-1]]), carried
        nxt, problem = on_root(self.comm, add)
        failure = _interruption(self.comm, schedule, k, self.config.T)
        shared = None
        if self.comm.rank == 0:
            shared = (state.z, state.d, problem) if problem else (*nxt, None)
        state.z, state.d, problem = bcast(self.comm, shared)
        if self.lost is not None and not problem:
            state.dropped = state.dropped + self.lost
        if problem:
            where = f" ({self.config.out})" if self.config.out is not None else ""
            return SolveError(f"slab {k} (t = {t0:g} .. {t0 + dt:g}): writing the output "
                              f"failed{where}: {problem}", slab=k)
        return failure

    def finish(self, failure: Optional[SolveError]) -> RunResult:
        """Close the sinks and make the result (the same on every rank); raises the failure
        with the result of the slabs completed before it as `partial`."""
        if self.bar is not None:
            self.bar.close()
        result = None
        if self.comm.rank == 0:
            arrays = self.acc.arrays(self.sim.scene.n)  # t, x, v
            files, failure = self._close_output(failure, arrays)
            result = self._result(files, arrays)
            if failure is not None:
                interrupted = isinstance(failure, faults.Interrupted)
                result.status = "interrupted" if interrupted else "failed"
                result.message = str(failure)
        failure = _shared_failure(self.comm, failure)
        result = bcast(self.comm, result)
        config = self.config
        result.scene_object = config.scene
        if config.t_eval is not None:
            result.t_eval = t_eval_output(result, config)
            if failure is None:
                failure = unvouched_output(result, config)
        if failure is not None:
            failure.partial = result
            raise failure
        return result

    def _close_output(self, failure: Optional[SolveError], arrays: tuple
                      ) -> Tuple[List[str], Optional[SolveError]]:
        """Rank 0: close the XDMF sink (the trajectory `arrays` t, x, v); (its files, the run's
        failure with its own added)."""
        if self.xdmf is None:
            return [], failure
        try:
            files = self.xdmf.close(*arrays)
        except Exception as exc:  # noqa: BLE001 -- a failure of its own, reported as one
            closing = f"writing the output failed ({self.config.out}): {one_line(exc)}"
            if failure is None:
                failure = SolveError(closing, slab=self.state.k)
            else:
                failure.args = (f"{failure}; {closing}",)
            files = self.xdmf.files_on_disk()
        self.timings["output_s"] = self.xdmf.seconds
        return files, failure

    def _result(self, files: List[str], arrays: tuple) -> RunResult:
        """Rank 0: the RunResult of the slabs accepted (`arrays`: their t, x, v)."""
        sim, config, acc, state, weights = self.sim, self.config, self.acc, self.state, \
            self.weights
        timings = self.timings
        timings["reference_s"] = acc.reference_s
        timings["total_s"] = (time.perf_counter() - self.tic + timings["compile_s"]
                              + timings["setup_s"])
        t, x, v = arrays
        tol, lengths = config.tolerance, state.lengths
        result = RunResult(
            scene=sim.scene.name, parameters=sim.scene.parameters(), T=config.T,
            cells=config.cells, degree=config.degree,
            slabs=config.slabs if config.rtol is None else len(lengths),
            x0=config.x0.tolist(), v0=config.v0.tolist(), dofs_per_slab=sim.backend.num_dofs,
            t=t, x=x, v=v, error=acc.error(), hamiltonian=acc.hamiltonian(), timings=timings,
            solver=self._solver_record(), slab_lengths=lengths, output_files=files,
            staging={"mode": config.staging, "stages_per_slab": config.stages,
                     "solved_slabs": len(lengths), "cells_per_solved_slab": config.slab_cells,
                     "limit_cells_times_degree_squared": STAGING_LIMIT},
            recovery=config.recovery, error_estimate=acc.estimate_max(),
            estimate=acc.estimate(),
            tolerance={"rtol": tol.rtol, "atol": tol.atol, "adaptive": tol.adaptive,
                       "given": config.rtol_given,
                       "scale_x": weights.scale_x, "scale_v": weights.scale_v})
        result.output_slabs = None if self.xdmf is None else self.xdmf.slabs_written
        if acc.est_rows:
            result.estimate_at_t = np.concatenate(acc.est_rows)
        if acc.err_rows:
            result.error_at_t = np.concatenate(acc.err_rows)
        return result

    def _solver_record(self) -> Dict[str, Any]:
        """The JSON `solver` record: the backend's, and what the loop did."""
        sim, scene, config = self.sim, self.sim.scene, self.config
        record = sim.backend.record(sim.prefix)
        record["halved_slabs"] = self.rejected
        record["rejected_slabs"] = len(self.rejected)
        record["superposition"] = sim.superposition is not None
        record["batched_slabs"] = self.state.batched
        record["budget"] = self.budget.record()
        record["estimates"] = self.acc.estimates
        record["companion_degree"] = sim.companion.degree
        companion = sim.companion.backend.record(sim.companion.prefix)
        if "ksp_iterations" in companion:
            record["companion_ksp_iterations"] = companion["ksp_iterations"]
        if scene.linear:
            record["weighting"] = scene.weighting()
        record["assembly"] = sim.backend.assembly
        record["base"], record["base_reason"] = config.base_choice
        record["compiled_loops"] = sim.backend.compiled_loops()
        record["compiled_loops_unavailable"] = native.reason()  # why none ran, or None
        if scene.linear:
            record["coordinates"] = "modal" if sim.modal is not None else "physical"
        record["slab_solves"] = sim.solves()
        record["companion_solves"] = sim.companion.solves()
        record["tangent_solves"] = sim.tangent_solves
        record["resumed_from"] = self.state.resumed_from
        return record


def _start_rate(scene, x0: np.ndarray, v0: np.ndarray) -> float:
    """|z'| / |z| at the start (motion_rate), from the scene's acceleration there."""
    if scene.linear:
        a0 = scene.acceleration(x0, v0)
    else:
        F, d = np.asarray(scene.force_numpy(x0), dtype=float), scene.mass_diagonal()
        a0 = F / d if d is not None else np.linalg.solve(scene.mass_matrix(), F)
    return motion_rate(x0, v0, a0)


def _advice(config: RunConfig) -> str:
    if config.rtol is None:
        return ("use more slabs or cells per slab, a higher degree, or --rtol to choose the "
                "slab lengths")
    return "loosen --rtol, or raise --cells or --degree"


def _rounded_up(value: float) -> float:
    """value rounded up to one significant digit (a tolerance to suggest)."""
    if not value > 0:
        return value
    power = 10.0 ** np.floor(np.log10(value))
    return float(np.ceil(value / power) * power)


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
