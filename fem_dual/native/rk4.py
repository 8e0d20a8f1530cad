"""Bindings of rk4.c: classical RK4 in Nystrom form on a compiled force, and the cubic Hermite
of its step ends (fem_dual.slab.base_state.FlowPredictor's compiled twin)."""
from __future__ import annotations

from typing import Optional

import numpy as np

from fem_dual.native import pointer, require

__all__ = ["Rk4", "HermiteTable"]


class HermiteTable:
    """The rows and weights of a cubic Hermite read (fem_dual_hermite), with their C pointers.

    Args:
        rows: (m, 4) int64: rows of [states; h rates] (states' rows first, steps + 1 of them).
        weights: (m, 4): their weights.
    """

    def __init__(self, rows: np.ndarray, weights: np.ndarray):
        ffi, _ = require()
        self.rows = np.ascontiguousarray(rows, dtype=np.int64)
        self.weights = np.ascontiguousarray(weights, dtype=float)
        self._pointers = (pointer(ffi, self.rows), pointer(ffi, self.weights))


class Rk4:
    """`steps` classical RK4 steps of x' = v, v' = a(x) with a = scale F(x), or minv F(x), F the
    compiled force's kernel (fem_dual_rk4), into step ends reused by every run, and their cubic
    Hermite (fem_dual_hermite).

    Args:
        kernel: the force's tabulate_tensor_float64 (fem_dual.native.force.CompiledForce).
        constants: the kernel's constants (kept: their pointer is made once).
        n: the dimension of x.
        steps: steps a run.
        scale: a = scale F where `minv` is None.
        minv: M^-1 (n, n), or None.
    """

    def __init__(self, kernel: int, constants: np.ndarray, n: int, steps: int, scale: float,
                 minv: Optional[np.ndarray]):
        ffi, self._lib = require()
        self._ffi, self._kernel, self.n, self.steps, self._scale = ffi, kernel, n, steps, scale
        # what every run reads, as C pointers (each keeps its array alive)
        self._fixed = (pointer(ffi, np.ascontiguousarray(constants, dtype=float)),
                       pointer(ffi, None if minv is None else np.ascontiguousarray(minv)),
                       pointer(ffi, np.empty(7 * n)))
        ends = np.zeros((2, steps + 1, 2 * n))
        self.states, self.rates = ends[0], ends[1]  # (steps + 1, 2n) each: (x, v), (v, a)
        self._ends = (pointer(ffi, self.states), pointer(ffi, self.rates))

    def run(self, z0: np.ndarray, h: float) -> bool:
        """Steps of length h from z0 = (x, v) into `states` and `rates`; whether a value was
        not finite (the loop stops there, and the last state's first value is then NaN)."""
        constants, minv, work = self._fixed
        z0 = np.ascontiguousarray(z0, dtype=float)
        failed = self._lib.fem_dual_rk4(self._kernel, constants, self.n, self.steps, h,
                                        self._scale, minv, pointer(self._ffi, z0),
                                        *self._ends, work)
        if failed:
            self.states[-1, 0] = np.nan
        return bool(failed)

    def read(self, table: HermiteTable, h: float) -> np.ndarray:
        """The cubic Hermite of the last run's step ends at the table's times: (m, 2n)."""
        out = np.empty((len(table.rows), self.states.shape[1]))
        self._lib.fem_dual_hermite(len(table.rows), out.shape[1], self.steps, h,
                                   *table._pointers, *self._ends, pointer(self._ffi, out))
        return out
