"""The guess of an orbit: a run's motion from (x0, v0) over T0, or an orbit found before."""
from __future__ import annotations

from typing import Tuple

import numpy as np
from mpi4py import MPI

from fem_dual import faults
from fem_dual.errors import SolveError
from fem_dual.analysis.floquet import stop_if_asked

__all__ = ["OrbitGuess", "GuessMotion", "GUESS_RTOLS"]

GUESS_RTOLS = (1e-9, 1e-6)  # the guess's run: this tolerance, or the next where it fails


class OrbitGuess:
    """An orbit found as the guess of another (its vertex values, Hermite-interpolated at the
    base nodes: fem_dual.integrate.dense, order 8), in place of a run's motion."""

    def __init__(self, scene, t: np.ndarray, x: np.ndarray, v: np.ndarray):
        self.scene, self.t, self.x, self.v = scene, t, x, v

    def at(self, times: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        from fem_dual.integrate.dense import hermite_at

        return hermite_at(self.scene, self.t, self.x, self.v, times)


class GuessMotion:
    """The guess of an orbit: the motion from (x0, v0) over T0, by fem-dual (p = 4, 4 cells per
    slab, --rtol GUESS_RTOLS[0], or the next where a run cannot vouch for that: a guess need not
    be accurate, a motion near a separatrix over a long T0 is not to 1e-9), on one compiled
    simulation reused for every guess of a family."""

    def __init__(self):
        self.sim = None

    def __call__(self, scene, x0: np.ndarray, v0: np.ndarray, T0: float):
        """The run's result (its `at(times)` gives the motion anywhere in [0, T0])."""
        from fem_dual.config import RunConfig
        from fem_dual.integrate.simulation import Simulation

        for rtol in GUESS_RTOLS:
            config = RunConfig.create(scene, T=T0, x0=x0, v0=v0, cells=4, degree=4, rtol=rtol,
                                      reference="none")
            if self.sim is None:
                self.sim = Simulation.for_config(config, MPI.COMM_SELF)
            try:
                result = self.sim.run(config)
            except faults.Interrupted:
                raise
            except SolveError as exc:
                result = getattr(exc, "partial", None)
                message = str(exc)
            else:
                message = result.message
            if result is not None and result.status == "interrupted":
                stop_if_asked("the guess")
            if result is not None and result.status == "ok":
                return result
        reason = message.split("; ")[0]  # without a run's advice (--rtol, slabs)
        raise SolveError(f"the guess (the motion from x0, v0 over {T0:g}) could not be "
                         f"computed: {reason}; give another guess (--x0, --v0, --period)")

    def close(self) -> None:
        if self.sim is not None:
            self.sim.close()
