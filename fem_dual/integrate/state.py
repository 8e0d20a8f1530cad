"""Where the slab loop stands: the slab index, the start state and its estimated error, the
lengths taken, and how the chunks of linear slabs grow (fem_dual.integrate.chunks)."""
from __future__ import annotations

from typing import Dict, List, Optional

import numpy as np
from mpi4py import MPI

from fem_dual.config import RunConfig
from fem_dual.integrate.controller import SlabSchedule
from fem_dual.integrate.estimate import ErrorWeights
from fem_dual.integrate.restart import Restart
from fem_dual.integrate.sinks import Accumulator
from fem_dual.mpi import bcast

__all__ = ["LoopState", "CHUNK_SLABS", "FIRST_CHUNK"]

CHUNK_SLABS = 1024  # chunks of linear slabs: at most this many (a signal is answered after one)
FIRST_CHUNK = 8


class LoopState:
    """Where the slab loop stands: slab index, start state and its estimated error, lengths."""

    def __init__(self, config: RunConfig):
        self.k = 0
        self.z = np.concatenate([config.x0, config.v0])
        self.d = np.zeros_like(self.z)  # estimated global error of the state at the slab start
        # what the zero base dropped so far (amplitudes per component): part of the global
        # error for good, carried beside d (no slab map carries it)
        self.dropped = np.zeros_like(self.z)
        # the covariance of the round-off the slabs left in the state (estimate.carry; rank 0,
        # nonlinear scenes: a resumed run starts it again from zero)
        self.roundoff = np.zeros((len(self.z), len(self.z)))
        self.lengths: List[float] = []
        self.batched = 0  # slabs taken in chunks from their slab maps (fem_dual.integrate.chunks)
        # slabs of the next chunk (before the limits of fem_dual.integrate.chunks): fixed slabs have their
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


