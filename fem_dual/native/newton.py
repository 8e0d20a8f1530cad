"""Bindings of newton.c: a slab's Newton on the pointwise assembly in one call
(fem_dual.slab.native_newton.NativeNewton drives it)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from fem_dual.native import pointer, require
from fem_dual.native.band import Band
from fem_dual.native.dtp import DtpMap

__all__ = ["SlabNewton", "SlabNewtonRun"]

# fem_dual_slab_newton's *reason, as SNES names it
_REASONS = {1: "CONVERGED_FNORM_ABS", 2: "CONVERGED_FNORM_RELATIVE",
            3: "CONVERGED_SNORM_RELATIVE", -1: "DIVERGED_MAX_IT"}


@dataclass
class SlabNewtonRun:
    """How fem_dual_slab_newton ended. x, chol and final are the binding's own arrays: the next
    run overwrites them."""

    reason: str  # SNES's name of the reason
    iterations: int
    x: np.ndarray  # the last iterate
    F: np.ndarray  # its residual
    history: list  # the residual norms, from the start's
    chol: np.ndarray  # the last step's Cholesky factor, (kd + 1, N), Fortran order
    final: Optional[np.ndarray]  # the factor of the Jacobian at x, where it was made
    backward: float  # the backward floor at the last factored iterate
    last_step: float  # |the last step| / |x| (inf without a step)


class SlabNewton:
    """fem_dual_slab_newton for one slab: its evaluations, residual, band, banded Cholesky and
    tests on buffers made once, the call's arguments held in order.

    Args:
        kernel: the tabulate_tensor_float64 of the density's gradient and Hessian.
        packed: (cells, wsize) its packed rows (the state's columns written by each
            evaluation, the rest kept).
        coords: (cells, 6) the cells' coordinate dofs.
        out: (cells, nq, columns) the evaluation (written).
        wslot, wfree: (cells, nw) the dual state's columns in a row and their free unknowns
            (-1: a Dirichlet value, kept).
        Tg: (cells, nd, nq 2) the weighted basis table of the residual.
        bs: the block size of the dual space.
        r_keep, r_rows: the cell residual's entries that are free unknowns, and their rows.
        start_rows: the rows of the initial terms.
        band: the band's compiled assembly (its pairs, groups, tables and buffer).
        u_flat, u_source: the band's entries on and above the diagonal in LAPACK's upper
            storage, and their products.
        N, kd: the unknowns and the half-bandwidth.
        dtp: an implicit DtP map solved inside each evaluation, or None.
        kept_step: the last step (relative) within which its factors serve at x.
        max_iterations: the most Newton iterations a run may take.
    """

    def __init__(self, kernel: int, packed: np.ndarray, coords: np.ndarray, out: np.ndarray,
                 wslot: np.ndarray, wfree: np.ndarray, Tg: np.ndarray, bs: int,
                 r_keep: np.ndarray, r_rows: np.ndarray, start_rows: np.ndarray, band: Band,
                 u_flat: np.ndarray, u_source: np.ndarray, N: int, kd: int,
                 dtp: Optional[DtpMap], kept_step: float, max_iterations: int = 63):
        ffi, self._lib = require()
        self._ffi = ffi
        cells, nq, ncols = out.shape
        nd = Tg.shape[1]
        ints = {k: np.ascontiguousarray(a, dtype=np.int64) for k, a in (
            ("wslot", wslot), ("wfree", wfree), ("r_keep", r_keep), ("r_rows", r_rows),
            ("start_rows", start_rows), ("u_flat", u_flat), ("u_source", u_source))}
        work = np.empty((4, N))
        self.F = work[0]
        self.history = np.empty(max_iterations + 1)
        self.ints = ffi.new("int[3]")  # iterations, reason, final factors made
        self.doubles = ffi.new("double[2]")  # the backward floor, the last step
        b = band._pointers

        def d(a):
            return pointer(ffi, a)
        # the call's arguments in order (the pointers keep their arrays alive); each run sets
        # those given as a name here
        args = [
            kernel, cells, nq, ncols, packed.shape[1], d(packed), "constants", d(coords),
            ints["wfree"].shape[1], d(ints["wslot"]), d(ints["wfree"]), nd, bs,
            d(np.ascontiguousarray(Tg)), len(ints["r_keep"]), d(ints["r_keep"]),
            d(ints["r_rows"]), len(ints["start_rows"]), d(ints["start_rows"]), "initial",
            band.pairs, b["cols"], b["scale"], band.groups, b["lo"], b["hi"], b["start"],
            b["PT"], band.nd2, len(ints["u_flat"]), d(ints["u_flat"]), d(ints["u_source"]),
            b["B"], N, kd, "chol", d(np.empty(kd + 1)), "x", *(d(a) for a in work),
            d(np.empty(cells * nd * bs)), d(out), "atol", "check_start", "rtol", "stol",
            "max_it", "patience", "no_progress", "decrease", d(self.history), self.ints,
            self.doubles, self.doubles + 1, self.ints + 1,
            ffi.NULL if dtp is None else dtp.struct, "final", kept_step, self.ints + 2]
        self._slots = {a: k for k, a in enumerate(args) if isinstance(a, str)}
        self._tests = (self._slots["atol"], self._slots["decrease"] + 1)  # (in this order)
        self._args = args
        self._dtp = dtp  # (its struct is pointed to)
        # the iterate and the factors, the constants and initial rows copied in: arrays with
        # their C pointers, reused by every run
        self._kept = {}
        for name, array in (("x", np.empty(N)), ("chol", np.empty((kd + 1, N), order="F")),
                            ("final", np.empty((kd + 1, N), order="F"))):
            self._kept[name] = (array, ffi.from_buffer("double[]", array.T))
            args[self._slots[name]] = self._kept[name][1]

    def _in(self, name: str, values: np.ndarray) -> None:
        """Copy `values` into the argument `name`'s kept array (made, with its pointer, at the
        first call and whenever the size changes)."""
        kept = self._kept.get(name)
        if kept is None or kept[0].shape != values.shape:
            array = np.array(values, dtype=float, order="C")
            self._kept[name] = (array, self._ffi.from_buffer("double[]", array))
            self._args[self._slots[name]] = self._kept[name][1]
        else:
            kept[0][...] = values

    def run(self, x0: np.ndarray, constants: np.ndarray, initial: np.ndarray, factor_final: bool,
            atol: float, check_start: bool, rtol: float, stol: float, max_it: int,
            patience: Optional[int], no_progress: float,
            decrease: float) -> Optional[SlabNewtonRun]:
        """Newton from x0 with the kernel's `constants` and the initial terms' rows `initial`
        (the packed rows as they are), and the tests of
        fem_dual.slab.pointwise_newton.PointwiseNewtonSolver.solve; with `factor_final`, the
        Jacobian at x factored where the last step exceeded kept_step. None where the numpy
        iteration must decide (see newton.c)."""
        if max_it + 1 > len(self.history):
            raise ValueError(f"at most {len(self.history) - 1} Newton iterations")
        self._in("constants", constants)
        self._in("initial", initial)
        x, chol, final = (self._kept[name][0] for name in ("x", "chol", "final"))
        x[:] = x0
        args = self._args
        args[self._slots["final"]] = self._kept["final"][1] if factor_final else self._ffi.NULL
        args[self._tests[0]:self._tests[1]] = (
            atol, int(check_start), rtol, stol, max_it, -1 if patience is None else patience,
            no_progress, decrease)
        if self._lib.fem_dual_slab_newton(*args) != 0:
            return None
        it = self.ints[0]
        return SlabNewtonRun(_REASONS[self.ints[1]], it, x, self.F.copy(),
                             self.history[:it + 1].tolist(), chol,
                             final if self.ints[2] else None, float(self.doubles[0]),
                             float(self.doubles[1]))
