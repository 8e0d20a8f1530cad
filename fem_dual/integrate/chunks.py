"""Linear slabs in chunks: many equal slabs solved, judged and recorded at once.

A linear scene's slabs of one length are linear maps of their start states (superposition): the
start states and carried errors of the next slabs follow from the slab maps by a recurrence
(rank 0), every rank computes the vertex values of its share of the slabs from the shared
bases, and rank 0 judges them as the slab loop would, slab by slab, stopping before a slab that
would not be accepted (the loop then takes it) or after one whose step factor changes the
length. Chunks grow while their slabs are all taken.
"""
from __future__ import annotations

import copy
from typing import TYPE_CHECKING, Any, List, Optional, Tuple

import numpy as np

from fem_dual.config import RunConfig
from fem_dual.errors import SolveError, one_line
from fem_dual.integrate.controller import SlabSchedule, step_factors
from fem_dual.integrate.estimate import ErrorWeights, all_finite, estimate_slabs, output_request
from fem_dual.integrate.judge import GrowthBound
from fem_dual.integrate.sinks import PartialBatch, SlabBatch, XdmfSink
from fem_dual.integrate.state import CHUNK_SLABS, FIRST_CHUNK, LoopState
from fem_dual.mpi import bcast, on_root
from fem_dual.slab.values import VertexValues

if TYPE_CHECKING:
    from fem_dual.integrate.simulation import Simulation

__all__ = ["batch_step"]

CHUNK_BYTES = 8 * 2**20  # working arrays of one chunk of slabs solved at once


def _recurrence(sim: Simulation, state: LoopState, dt: float,
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
    carried = Z[:-1] @ lend.T  # (what is dropped is carried beside: state.dropped)
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


def _judge_chunk(config: RunConfig, state: LoopState, schedule: SlabSchedule,
                 weights: ErrorWeights, bound: Optional[GrowthBound], Z: np.ndarray,
                 D: np.ndarray, lost: Optional[np.ndarray], vals: VertexValues,
                 companion: VertexValues, psi: np.ndarray
                 ) -> Tuple[Tuple[int, tuple], np.ndarray, np.ndarray, Optional[SlabBatch]]:
    """Rank 0: the chunk's slabs judged as `judge` does. Returns (the number of accepted slabs,
    the schedule's state after them), the state (z, d) after them and the accepted slabs
    (None: none)."""
    count = len(Z) - 1
    t0, dt = schedule.current()
    dropped = None if lost is None else state.dropped + np.cumsum(lost, axis=0) - lost
    est = estimate_slabs(vals, companion, None, psi, lost, weights, dt, config.T,
                         output_request(config), dropped=dropped)
    est.glob[:, -1] = D[1:] if lost is None else D[1:] + dropped + lost
    t0s = (schedule.pos + schedule.length * np.arange(count)) * schedule.T / schedule.total
    ok = (all_finite(vals) & est.finite & np.isfinite(D[1:]).all(axis=1)
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
    after = state.dropped if lost is None or not done else dropped[done - 1] + lost[done - 1]
    return (done, trial.state), Z[done], D[done], batch, after


def _chunk(sim: Simulation, config: RunConfig, state: LoopState, schedule: SlabSchedule,
           weights: Optional[ErrorWeights], bound: Optional[GrowthBound],
           count: int) -> Tuple[Optional[tuple], Optional[str]]:
    """The next `count` slabs of the current length (see `batch_step`): rank 0 propagates the
    start states, every rank computes the vertex values of its share of the slabs (the array
    products, split by slabs), rank 0 gathers and judges them. (outcome of `_judge_chunk` on
    rank 0, None elsewhere; why it failed on any rank, the same on every rank). Collective."""
    comm, dt = sim.comm, schedule.current()[1]
    with np.errstate(all="ignore"):  # a blow-up is judged (not finite), not warned about
        states, problem = on_root(comm, lambda: _recurrence(sim, state, dt, count))
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
            part, mine = None, one_line(exc)
        parts = comm.gather((part, mine), root=0) if comm.size > 1 else [(part, mine)]
        outcome, problem = None, None
        if comm.rank == 0:
            problem = next((p for _, p in parts if p), None)
            if problem is None:
                outcome, problem = on_root(comm, lambda: _judge_chunk(
                    config, state, schedule, weights, bound, Z, D, lost,
                    *_join([q for q, _ in parts])))
        return outcome, bcast(comm, problem)


def _slice(values: VertexValues, count: int) -> VertexValues:
    return values.apply(lambda a: a[:count])


def batch_step(sim: "Simulation", config: RunConfig, state: LoopState, schedule: SlabSchedule,
               weights: Optional[ErrorWeights], bound: Optional[GrowthBound],
               sinks: List[Any], check) -> Tuple[int, Optional[SolveError]]:
    """Solve, judge and record a chunk of equal slabs of a linear scene at once from its slab
    maps (superposition), instead of slab by slab: (slabs accepted, the failure that ends the
    run or None). Fixed slabs and --rtol alike; it stops before a slab that `judge` would not
    accept (the slab loop then takes it) or after one whose step factor changes the length.
    Collective."""
    comm = sim.comm
    if (sim.superposition is None or sim.companion.superposition is None
            or not state.settled):
        return 0, None
    # (on the fine grid the last slab, whose dt reaches T exactly, is the slab loop's)
    remaining = (schedule.total - schedule.pos - schedule.fine) // schedule.length
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
    dropped = bcast(comm, outcome[4] if root else None)
    # chunks grow while their slabs are all taken (the length settled), and start small again
    # after one stopped early (a controller still finding its length wastes little). Fixed
    # slabs refused at a chunk's first slab keep their chunk size: the slab loop halves that
    # slab, and the halved length is the one the rest keeps (small chunks would cost a run
    # asked in slabs too long for the tolerance three times what the halved slabs need)
    if done == count:
        state.chunk *= 4
    elif done or config.rtol is not None:
        state.chunk = FIRST_CHUNK
    state.settled = done == count
    if not done:
        return 0, None
    batch = outcome[3] if root else None
    fed, problem = on_root(comm, lambda: _feed(sinks, batch))
    taken, problem = bcast(comm, (fed if fed is not None else (done, problem)) if root else None)
    k = state.k + taken - 1
    state.lengths += [dt] * taken
    state.k += taken
    if problem:
        where = f" ({config.out})" if config.out is not None else ""
        return taken, SolveError(f"slab {k} (t = {t0 + (taken - 1) * dt:g} .. "
                                 f"{t0 + taken * dt:g}): writing the output failed{where}: "
                                 f"{problem}", slab=k)
    state.z, state.d, state.dropped = z, d, dropped
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
            taken, problem = exc.taken + 1, one_line(exc.cause)
    return taken, problem


