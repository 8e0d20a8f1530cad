"""A slab's Newton iteration in compiled code (fem_dual.native.newton), driven from the
pointwise assembly (fem_dual.slab.local_action.LocalAction): what the C loop reads of the slab,
an implicit DtP map solved inside each evaluation, and its answer as the numpy iteration's
(fem_dual.slab.pointwise_newton)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Optional

import numpy as np

from fem_dual.native.dtp import DtpMap
from fem_dual.native.force import PackedExpression
from fem_dual.native.newton import SlabNewton
from fem_dual.slab.banded import BandedLU

if TYPE_CHECKING:
    from fem_dual.slab.local_action import LocalAction

__all__ = ["FACTORS_KEPT_STEP", "NativeNewton", "NativeNewtonResult"]

# The factors of Newton's last Jacobian serve the tangents at its last iterate when that step
# moved the state by at most this much (relative): the Jacobians differ by as little, and the
# tangents feed estimates (a factorisation less per slab: 85 us of 3 ms on curl3d T = 8, p = 6,
# 8 cells); after a longer step the compiled Newton factors the Jacobian there itself, from
# the band it assembles anyway
FACTORS_KEPT_STEP = 1e-8


@dataclass
class NativeNewtonResult:
    """How a compiled Newton (NativeNewton.run) ended: SNES's reason name, the last iterate
    and its residual, the residual history, the last step's factors (None without a step),
    the backward floor (fem_dual.slab.snes.backward_floor) at the last factored iterate and the
    last step's size relative to the iterate."""

    reason: str
    x: np.ndarray
    F: np.ndarray
    history: list
    lu: Optional[BandedLU]
    backward: float
    last_step: float  # |the last step| / |x| (inf without a step)
    at_x: Optional[BandedLU] = None  # the factors of the Jacobian at x (to round-off)


class NativeNewton:
    """The Newton iteration of fem_dual.slab.pointwise_newton.PointwiseNewtonSolver in compiled
    code (fem_dual.native.newton), an implicit DtP map solved inside each evaluation
    (_ImplicitMap): the same evaluations, band, banded Cholesky and tests, while every full
    step is taken; where the line search would shorten a step, or a factorisation, a value or
    the DtP map fails, `run` returns None and the numpy iteration starts over (the failure
    paths stay in one place). One call per solve instead of some 30 Python calls per Newton
    step.

    Args:
        local: the slab's pointwise assembly (with its compiled band).
    """

    def __init__(self, local: "LocalAction"):
        self.local = local
        p = local.problem
        self.expr = PackedExpression(local._both.compiled, local.cells)
        index = self.expr.index(p.w)  # (cells, nd bs): the dual state's values in each row
        free = np.full(p.w.x.array.size, -1, dtype=np.int64)
        free[local.free_global] = np.arange(local.size)
        cells = len(local.cells)
        packed = self.expr.pack()  # (its rows stay where they are: packed again per solve)
        self.dtp = _ImplicitMap(local, self.expr, free) if p.pointwise is not None else None
        self._loop = SlabNewton(
            self.expr.kernel, packed, self.expr.coords,
            local._out_both.reshape(cells, local.nq, -1), np.broadcast_to(
                self.expr.slot(p.w), index.shape), free[index], local._Tg, local.bs,
            local._r_keep, local._r_rows, local.start_rows, local._native_band,
            local._layout.u_flat, local._layout.u_source, local.size, local.kd,
            None if self.dtp is None else self.dtp.binding, FACTORS_KEPT_STEP)

    def run(self, x0: np.ndarray, atol: float, check_start: bool, rtol: float, stol: float,
            max_it: int, patience: Optional[int], no_progress: float,
            decrease: float) -> Optional[NativeNewtonResult]:
        """Newton from x0 with the tests of PointwiseNewtonSolver.solve; None where the numpy
        iteration must decide (see fem_dual.native.newton)."""
        local, kd = self.local, self.local.kd
        self.expr.pack()
        if self.dtp is not None:
            self.dtp.begin()
        done = self._loop.run(x0, self.expr.constants(), local._initial_rows(),
                              local.factor_solution, atol, check_start, rtol, stol, max_it,
                              patience, no_progress, decrease)
        if self.dtp is not None:
            self.dtp.end(done is not None)
        if done is None:
            return None
        lu = BandedLU.of_cholesky(done.chol, kd) if done.iterations > 0 else None
        at_x = (BandedLU.of_cholesky(done.final, kd) if done.final is not None
                else lu if done.last_step <= FACTORS_KEPT_STEP else None)
        return NativeNewtonResult(done.reason, done.x, done.F, done.history, lu, done.backward,
                                  done.last_step, at_x)


class _ImplicitMap:
    """What NativeNewton's C loop needs to solve an implicit DtP map
    (fem_dual.slab.pointwise_dtp.PointwiseDtP) inside each evaluation: its expression's packed
    rows, where the dual state, X and G_x^-1 sit in them and in the density's rows
    (fem_dual.native.dtp.DtpMap).

    Args:
        local: the slab's pointwise assembly.
        both: the packed expression of the density's gradient and Hessian.
        free: each dual state value's free unknown (-1: none).
    """

    def __init__(self, local: "LocalAction", both: PackedExpression, free: np.ndarray):
        from fem_dual.slab.pointwise_dtp import BRANCH_TOL, LAST_STEP, MAX_IT

        p = local.problem
        self.map = dtp = p.pointwise
        self.local = local
        self.expr = expr = PackedExpression(dtp._eval.compiled, dtp.cells)
        index = expr.index(p.w)
        self.binding = DtpMap(
            expr.kernel, dtp.n, expr.packed, expr.coords, dtp.X.x.array, dtp.Ginv.x.array, {
                "wfree": free[index], "wslot": np.broadcast_to(expr.slot(p.w), index.shape),
                "xslot": expr.slot(dtp.X), "xdofs": dtp.dofs,
                "both_xslot": both.slot(dtp.X), "both_xindex": both.index(dtp.X),
                "both_gslot": both.slot(dtp.Ginv), "both_gindex": both.index(dtp.Ginv)},
            MAX_IT, LAST_STEP, BRANCH_TOL)
        self._start: Optional[np.ndarray] = None

    def begin(self) -> None:
        """Pack the map's rows at the current state and constants; keep X to go back to."""
        self.expr.pack()
        self.binding.use_constants(self.expr.constants())
        self._start = self.map.X.x.array.copy()

    def end(self, solved: bool) -> None:
        """After the C loop: the map is held at its last state, or X as it was (the numpy
        iteration solves the map again)."""
        if solved:  # (LocalAction.native_newton holds it at the last iterate)
            self.map.iterations = self.binding.iterations
        else:
            self.map.X.x.array[:] = self._start
            self.local._held = None
