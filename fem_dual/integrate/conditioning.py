"""The data floor of a linear run: how far the exact motion moves when M, K and the modal
blocks change by their own round-off (one unit in the last place; in extended precision where
fem_dual.modes formed a block's residual in it). No computation of the motion in those modes can
be closer to the exact one than that, whatever its time discretisation, and the companion's
difference does not see it (answer and companion share the modes). Near a flutter load it is
large: for Beck's column at 20 elements, P = 20.055, started in its two slowest modes, one-ulp
float64 perturbations of M and K move the exact motion by 4e-8 .. 5.4e-7 over T = 20 (a 50-digit
eigen-decomposition), which is why the slow blocks are refined; with them the floor is 8.7e-10
in v, the error 3.05e-9.

The floor is measured, not bounded: in the modes of the pencil (fem_dual.modes, U and the
block-diagonal Kr) a perturbation E of K and F of M changes Kr by U^-1 M^-1 (E U - F U Kr) to
first order; each block's motion is propagated exactly with and without the change (its
coupling to the other blocks is not secular: it stays of the size of the change itself). The
largest difference over SAMPLES random perturbations, times ESTIMATE_SAFETY, at TIMES times of
the horizon, is the floor; between them it is interpolated, never decreasing.

Undamped linear scenes with dense modes only (the modes of a damped one are not computed); for
the others `data_floor` is None.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from fem_dual.config import MODAL_MAX_DOFS
from fem_dual.integrate.estimate import ESTIMATE_SAFETY
from fem_dual.modes import block_motion, block_slices, refined_blocks
from fem_dual.slab.modal import modal_decomposition, modes_inverse

__all__ = ["DataFloor", "data_floor", "SAMPLES", "TIMES"]

SAMPLES = 3  # random perturbations of M and K (a fixed seed: the same floor every run)
TIMES = 32  # times of the horizon at which the perturbed motions are compared
EPS = float(np.finfo(float).eps)
EXTENDED_EPS = float(np.finfo(np.longdouble).eps)  # 1.1e-19 on x86-64: an 80-bit longdouble


@dataclass(frozen=True)
class DataFloor:
    """The floor of the |error| of x and of v at the times t (TIMES,), never decreasing."""

    t: np.ndarray  # (TIMES,)
    floor: np.ndarray  # (TIMES, 2)
    scale: np.ndarray  # (TIMES, 2): the running max of |x| and |v| of the motion, from the start

    def at(self, t: np.ndarray) -> np.ndarray:
        """(len(t), 2): the floor of x's and v's errors at the times t (0 at the start)."""
        t = np.asarray(t, dtype=float)
        times = np.concatenate([[0.0], self.t])
        return np.column_stack([np.interp(t, times, np.concatenate([[0.0], part]))
                                for part in self.floor.T])

    def final(self) -> np.ndarray:
        return self.floor[-1]


def _unit_round_off(M: np.ndarray, K: np.ndarray, slices) -> np.ndarray:
    """(n,): the unit round-off of each column's K Ub: extended precision where real_modes
    formed its residual there (`refined_blocks`), float64 elsewhere."""
    unit = np.full(len(M), EPS)
    for here, refined in zip(slices, refined_blocks(M, K)):
        if refined:
            unit[here] = EXTENDED_EPS
    return unit


def _sparse(matrix: np.ndarray):
    """The matrix as CSR where most of it is zero (a continuum's M and K: the products of
    data_floor then cost n^2 per nonzero column, not n^3), else itself."""
    if np.count_nonzero(matrix) < 0.1 * matrix.size:
        from scipy import sparse  # (not at import: `fem-dual --help` loads no scipy)

        return sparse.csr_matrix(matrix)
    return matrix


def data_floor(scene, x0: np.ndarray, v0: np.ndarray, T: float) -> Optional[DataFloor]:
    """The DataFloor of the scene's motion from (x0, v0) over [0, T]; None where the scene is
    not linear and undamped with dense modes (fem_dual.slab.modal)."""
    if not scene.linear or scene.sparse or scene.n > MODAL_MAX_DOFS or not T > 0:
        return None
    if np.any(scene.damping_matrix()):
        return None
    modes = modal_decomposition(scene)
    if modes is None:
        return None
    U, Kr = modes[0], modes[1]
    M, K = scene.mass_matrix(), scene.stiffness_matrix()
    slices = block_slices(Kr)
    Uinv = modes_inverse(scene)
    r0, rv0 = Uinv @ x0, Uinv @ v0
    t = T * np.arange(1, TIMES + 1) / TIMES
    inside = np.zeros(Kr.shape, dtype=bool)
    for s in slices:
        inside[s, s] = True
    rng = np.random.default_rng(0)
    scaled = U * _unit_round_off(M, K, slices)  # each column with the unit of its block's K Ub
    to_modal = Uinv @ scene.mass_inverse  # U^-1 M^-1, once for every sample
    scaled_kr = scaled @ Kr
    perturbed = np.empty((1 + SAMPLES,) + Kr.shape)  # the exact blocks first, then the samples
    perturbed[0] = Kr
    for k in range(1, 1 + SAMPLES):
        E = _sparse(K * rng.standard_normal(K.shape))
        F = _sparse(M * rng.standard_normal(M.shape))
        change = to_modal @ (E @ scaled - F @ scaled_kr)
        change += EPS * Kr * rng.standard_normal(Kr.shape)  # Kr's own rounding
        perturbed[k] = Kr + np.where(inside, change, 0.0)
    motions = block_motion(perturbed, slices, r0, rv0, t)  # (1 + SAMPLES, TIMES, n) each
    (r, rp), (rv, rvp) = ((m[0], m[1:]) for m in motions)
    worst = np.column_stack([np.abs((rp - r) @ U.T).max(axis=(0, 2), initial=0.0),
                             np.abs((rvp - rv) @ U.T).max(axis=(0, 2), initial=0.0)])
    x, v = np.abs(r @ U.T).max(axis=1), np.abs(rv @ U.T).max(axis=1)
    size = np.maximum.accumulate(np.column_stack([x, v]), axis=0)
    size = np.maximum(size, [np.abs(x0).max(initial=0.0), np.abs(v0).max(initial=0.0)])
    if not np.isfinite(size).all():  # the motion itself overflows: the slabs' guards judge it
        return None
    worst[~np.isfinite(worst)] = np.inf  # a perturbed block's exponential overflowed
    return DataFloor(t, ESTIMATE_SAFETY * np.maximum.accumulate(worst, axis=0), size)
