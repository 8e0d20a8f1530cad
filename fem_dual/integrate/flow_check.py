"""A nonlinear slab's answer against classical Runge-Kutta from the same start.

The slab's equations may have more than one solution. Newton can converge to another one, and
the degree p + 1 companion, warm-started from the answer or solved from zero, can land next to
it too: their difference (the error estimate) is then small although the answer is not the
motion. On curl3d T = 9.3 with 12 slabs of 6 cells at p = 3, the slab at t = 8.9125 had a
velocity jump of 1.5e-2 in one cell while its estimate was 1.3e-5; the run ended ok 0.24 off
with an estimate of 6.2e-4.

So each accepted nonlinear slab is compared, at its vertices, with two RK4 runs from its start
state, the finer with twice the steps: on the rk4 base the base runs of the answer and of its
companion, else runs of FLOW_STEPS and twice as many steps per cell. Their difference bounds the
finer run's own error (some fifteen times over: RK4 is of order 4). Where the answer is farther
from the finer run than FLOW_FACTOR times its estimated error (the largest vertex value of the
companion's difference, plus the slab's round-off floor), beyond what the two runs can tell,
the estimate does not vouch for the slab, and it is retried shorter. Answers that follow the
motion were at most 1.2 times their estimate from DOP853's flow (48 runs of curl3d, curl2d,
Hénon-Heiles and a Duffing force, p = 1..6, fixed slabs and --rtol); that wrong slab 1.1e3.

Where RK4 cannot follow the cells (a stiff motion overflows, or its two runs disagree by more
than the answer's distance) the check tells nothing and the slab keeps its verdict; the
predictor base, which damps the fast oscillations its cells do not resolve by design, is not
checked.
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from fem_dual.errors import SolveError
from fem_dual.integrate.estimate import SlabEstimate
from fem_dual.quiet import quiet_numpy
from fem_dual.slab.base_state import FlowPredictor
from fem_dual.slab.values import VertexValues

__all__ = ["FlowCheck", "FLOW_STEPS", "FLOW_FACTOR"]

FLOW_STEPS = 4  # RK4 steps per cell of the coarser run
FLOW_FACTOR = 10.0  # how far beyond its estimate an answer may be from the RK4 flow


class FlowCheck:
    """Two RK4 runs over a slab of `cells` equal cells, each with a whole number of steps per
    cell, and the answer's distance from them (`excess`).

    Args:
        coarse, fine: the runs (fem_dual.slab.base_state.FlowPredictor), fine with more steps.
        cells: the slab's cells.
        owned: whether the runs are this check's own (`use_scene` moves them to new parameter
            values; shared ones are their backends').
    """

    def __init__(self, coarse: FlowPredictor, fine: FlowPredictor, cells: int,
                 owned: bool = True):
        self.cells, self.coarse, self.fine, self.owned = cells, coarse, fine, owned
        self.strides = (coarse.steps // cells, fine.steps // cells)

    @classmethod
    def of(cls, scene, cells: int, answer_base=None,
           companion_base=None) -> "FlowCheck":
        """The check of a slab of `cells` cells of `scene`. On the rk4 base, the base runs of
        the answer and of its companion (`answer_base`, `companion_base`: the same start, the
        slab's whole length, (p + 1) 8 and twice as many steps per cell; kept, so that the check
        costs no step); else runs of its own, FLOW_STEPS and twice as many steps per cell, on
        the base's compiled force where there is one, else on one compiled here (a JIT cache
        lookup of some 30 ms on a cached run) where the compiled loops are available: a slab of
        curl3d with 4 cells takes 34 microseconds to check."""
        if (isinstance(answer_base, FlowPredictor) and isinstance(companion_base, FlowPredictor)
                and answer_base.steps % cells == 0 and companion_base.steps % cells == 0):
            return cls(answer_base, companion_base, cells, owned=False)
        force = answer_base.force if isinstance(answer_base, FlowPredictor) else None
        coarse = FlowPredictor(scene, FLOW_STEPS * cells, force)
        return cls(coarse, coarse.with_steps(2 * FLOW_STEPS * cells), cells)

    def use_scene(self, scene) -> None:
        """Check the motion of `scene` (new parameter values of the same kind of scene)."""
        if self.owned:
            self.coarse.use_scene(scene)
            self.fine.use_scene(scene)

    def excess(self, z: np.ndarray, dt: float, vals: VertexValues,
               estimate: SlabEstimate) -> Optional[str]:
        """Why the answer `vals` of the slab of length dt from the start state z is not what its
        `estimate` says, or None (it is, or RK4 cannot tell)."""
        answer = vals.state()
        if len(answer) != self.cells + 1:
            return None  # (vertex values of part of the slab: nothing to compare)
        try:
            coarse = self.coarse.ends(z, dt)[::self.strides[0]]
            fine = self.fine.ends(z, dt)[::self.strides[1]]
        except SolveError:
            return None  # (RK4 overflows: a stiff or blowing-up motion it cannot follow)
        with quiet_numpy():  # (a difference of states near 1e308 overflows)
            doubt = np.abs(fine - coarse).max(axis=1)
            distance = np.abs(answer - fine).max(axis=1)
        bound = FLOW_FACTOR * (float(np.abs(estimate.local).max()) + max(estimate.floor))
        beyond = distance > bound + doubt
        if not beyond.any():
            return None
        k = int(np.argmax(beyond))
        return (f"the slab's answer is {distance[k]:.3g} from classical Runge-Kutta from the "
                f"same start at its vertex {k} (which RK4 tells to {doubt[k]:.2g}), more than "
                f"{FLOW_FACTOR:g} times its error estimate: it may have converged to another "
                "solution of the slab's equations, which the estimate cannot see")
