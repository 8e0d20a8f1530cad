"""The cost of a tolerance-driven run, predicted before it is spent (--max-slabs).

Once BUDGET_WATCH slabs are accepted, the slabs left are predicted at the length of the last ones;
a run predicted beyond the budget stops at once (exit 3) with the figure, keeping what it
computed, instead of computing for minutes.

The budget is --max-slabs where the user gives it, and DEFAULT_MAX_SLABS slabs otherwise, except
for a linear scene whose slab maps take its slabs in chunks (fem_dual.integrate.chunks): there a
slab costs a few products with the maps once the lengths settle (Beck's column at 50 P2 elements,
0.32 ms a slab), so the budget is time and memory. Once a chunk of at least PACE_SLABS slabs has
run, its pace (small chunks carry the maps' set-up) prices the slabs left: the run's slabs,
those done and those predicted, must fit in BUDGET_SECONDS, and the memory of their output (held
until the run ends, then copied into its result) in BUDGET_BYTES. A run whose chunks have not
come after PACE_WAIT slabs is held to the count. `fem-dual run beck --rtol 1e-4` is predicted at
32,768 slabs (it takes 8,233, 3.7 s): over 5,000, it runs. The time is the machine's: near the
budget the same run may end on one machine and stop on another; --max-slabs makes the budget a
count again.
"""
from __future__ import annotations

import time
from typing import TYPE_CHECKING, Optional

import numpy as np

from fem_dual.config import RunConfig
from fem_dual.errors import SolveError
from fem_dual.mpi import bcast

if TYPE_CHECKING:
    from fem_dual.integrate.sinks import Accumulator
    from fem_dual.integrate.state import LoopState

__all__ = ["SlabBudget", "BUDGET_WATCH", "BUDGET_SECONDS", "BUDGET_BYTES", "PACE_SLABS"]

BUDGET_WATCH = 8  # accepted slabs before the cost of the rest is predicted
DEFAULT_MAX_SLABS = 5000  # the budget in slabs where --max-slabs is not given
BUDGET_SECONDS = 60.0  # chunked linear slabs: the time the slabs left may take at their pace
BUDGET_BYTES = 2**30  # chunked linear slabs: the memory their output may take at its peak
PEAK_COPIES = 2  # the output held to the end, and its copy in the run's result (measured: beck
# --rtol 1e-4 holds 7.7 KB a slab and grows 13.5 KB a slab resident; 65,536 slabs: 1.0 GB)
PACE_SLABS = 64  # slabs of the chunk whose pace is trusted (smaller: the set-up dominates)
PACE_WAIT = 512  # slabs a paced run may take waiting for such a chunk

FAST_MODES = 100.0  # modes this many times faster than the slowest: a start state's, not the
# motion's own (a continuum's start fields excite the fastest modes of its mesh)
ZERO_SPEED = 1e-7  # speeds below this part of the fastest are round-off (a free body's)
_ADVICE = ": loosen --rtol, shorten --T, or raise --max-slabs"


class SlabBudget:
    """The budget of one run: `check` before each step. Collective where it is paced."""

    def __init__(self, config: RunConfig, scene, chunked: bool, comm):
        self.config, self.scene, self.comm = config, scene, comm
        self.slabs = DEFAULT_MAX_SLABS if config.max_slabs is None else config.max_slabs
        # (the chunk path needs the slab maps of a linear scene: `chunked`)
        self.paced = config.max_slabs is None and chunked and config.rtol is not None
        self.first_chunk: Optional[float] = None  # the clock when the first chunk began
        self.pace: Optional[float] = None  # seconds a slab of the last chunk of PACE_SLABS

    def record(self) -> dict:
        """What the JSON's solver.budget says."""
        return {"max_slabs": self.slabs, "paced": self.paced, "seconds": BUDGET_SECONDS,
                "bytes": BUDGET_BYTES, "pace_s": self.pace}

    def chunk_ran(self, clock: float, slabs: int) -> None:
        """A chunk of `slabs` slabs ran from `clock` to now (rank 0's figures decide)."""
        now = time.perf_counter()
        if self.first_chunk is None:
            self.first_chunk = clock
        if slabs >= PACE_SLABS:
            self.pace = (now - clock) / slabs

    def check(self, state: "LoopState", t0: float, dt: float, rate: Optional[float],
              acc: Optional["Accumulator"]) -> Optional[SolveError]:
        """The failure that stops a run whose predicted slabs exceed the budget (from the
        accepted lengths, the same on every rank; where paced, from rank 0's clock, sent to
        every rank); None while it stays within. Collective where paced."""
        config, lengths = self.config, state.lengths
        if config.rtol is None or len(lengths) < BUDGET_WATCH:
            return None
        typical = max(max(lengths[-BUDGET_WATCH:]), dt)
        predicted = len(lengths) + int(np.ceil((config.T - t0) / typical))
        if predicted <= self.slabs:
            return None
        beyond = f"beyond the budget of {self.slabs:,} (--max-slabs)"
        if self.paced:
            paced = self.pace is not None  # (chunk sizes: the same on every rank)
            if not paced and len(lengths) <= PACE_WAIT:
                return None  # (a chunk first: its pace decides)
            if paced:  # (else no such chunk came: the count decides; rank 0's clock decides)
                over = bcast(self.comm, self._over_time(predicted - len(lengths),
                                                        len(lengths), acc)
                             if self.comm.rank == 0 else None)
                if over is None:
                    return None
                beyond += f", and {over}"
        why = _fast_modes(self.scene, rate) or _ADVICE
        return SolveError(
            f"rtol={config.rtol:g} would take {predicted:,} slabs at the length of the last "
            f"ones ({typical:.3g}) to reach T = {config.T:g}, {beyond}; stopped at "
            f"t = {t0:.6g} after {len(lengths)} slabs{why}", slab=len(lengths))

    def _over_time(self, left: int, accepted: int, acc: "Accumulator") -> Optional[str]:
        """How the run's slabs, `accepted` done and `left` predicted, exceed the time or the
        memory budget at the pace of the last large chunk (rank 0), None where they do not."""
        seconds = time.perf_counter() - self.first_chunk + left * self.pace
        held = PEAK_COPIES * acc.held * (1 + left / max(accepted, 1))
        if seconds <= BUDGET_SECONDS and held <= BUDGET_BYTES:
            return None
        return (f"at the pace of its last chunk ({1e3 * self.pace:.3g} ms a slab) its slabs "
                f"would take {seconds:,.0f} s and {held / 2**20:,.0f} MB for their output, beyond "
                f"{BUDGET_SECONDS:g} s or {BUDGET_BYTES / 2**20:g} MB")


def _fast_modes(scene, rate: Optional[float]) -> str:
    """Why a continuum's slabs are short, where it is the start state's fast modes: the slabs
    follow the modes the start excites (`rate`, the fastest of them), and those are FAST_MODES
    times the slowest mode or faster; "" otherwise (particles, the sparse path: no modes at
    hand)."""
    if rate is None or not scene.continuum or scene.sparse:
        return ""
    speeds = np.abs(scene.spectrum[0])
    speeds = speeds[speeds > ZERO_SPEED * speeds.max(initial=0.0)]
    slowest = float(speeds.min(initial=np.inf))
    if not rate >= FAST_MODES * slowest:
        return ""
    return (f", since the start state excites modes up to |lambda| = {rate:.3g} "
            f"({rate / slowest:.3g} times the slowest), which every slab must follow (a start "
            "field's mismatch with the mesh excites its fastest modes): use a coarser mesh or a "
            "start state with less in those modes, or raise --max-slabs")
