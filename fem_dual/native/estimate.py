"""Bindings of estimate.c: a slab's error estimate (fem_dual.integrate.simulation._estimates)
and what the run's accumulator keeps of accepted slabs (fem_dual.integrate.sinks.Accumulator),
the compiled twins of their numpy code."""
from __future__ import annotations

from typing import Optional, Tuple

import numpy as np

from fem_dual.native import require

__all__ = ["estimates", "summaries"]


def estimates(z: np.ndarray, zc: np.ndarray, alg: Optional[np.ndarray],
              psi: Optional[np.ndarray], lost: Optional[np.ndarray], safety: float,
              roundoff: float, atol: float, rtol: float, scale_x: float, scale_v: float,
              per_time: Optional[float], per_slab: Optional[np.ndarray]) -> Optional[tuple]:
    """fem_dual_estimate of S slabs of V vertices: (local, glob, scales, floor, err_local,
    err_global) as `_estimates` has them (glob is local where psi is None); None where a value
    is not finite or a weight is not positive (the numpy code judges those).

    Args:
        z, zc: (S, V, 2n) the answer's and the companion's vertex states, x then v.
        alg, psi: (S, V, 2n) the Newton change and the propagated error, or None.
        lost: (S, 2n) the part damped by a zero base (from the second vertex on), or None.
        safety, roundoff: the estimate's safety factor and relative round-off floor.
        atol, rtol, scale_x, scale_v: the tolerance and the error weights' running scales.
        per_time: dt / T of every slab, where per_slab (S,) is None.
    """
    ffi, lib = require()
    S, V, m = z.shape
    size = S * V * m
    states = np.empty((2,) + z.shape)  # (one buffer, one pointer: the call's own arrays)
    states[0], states[1] = z, zc
    out = np.empty(2 * size + 6 * S)  # local, glob, scales, floors, local and global errors
    at, to = ffi.from_buffer("double[]", states), ffi.from_buffer("double[]", out)
    d = (lambda a: ffi.NULL if a is None else
         ffi.from_buffer("double[]", np.ascontiguousarray(a, dtype=float)))
    failed = lib.fem_dual_estimate(
        S, V, m // 2, at, at + size, d(alg), d(psi), d(lost), safety, roundoff, atol, rtol,
        scale_x, scale_v, 0.0 if per_time is None else per_time, d(per_slab), to, to + size,
        to + 2 * size, to + 2 * size + 2 * S, to + 2 * size + 4 * S, to + 2 * size + 5 * S)
    if failed:
        return None
    local = out[:size].reshape(S, V, m)
    glob = local if psi is None else out[size:2 * size].reshape(S, V, m)
    rest = out[2 * size:]
    return (local, glob, rest[:2 * S].reshape(S, 2), rest[2 * S:4 * S].reshape(S, 2),
            rest[4 * S:5 * S], rest[5 * S:])


def summaries(glob: np.ndarray, local: np.ndarray, floor: np.ndarray, H: np.ndarray,
              first: bool, tiny: float) -> Optional[Tuple[np.ndarray, ...]]:
    """fem_dual_summary of S accepted slabs of V vertices: what `_summaries` gives (the
    reported error at the kept vertices as rows, its peak of x's and of v's, the last
    vertex's, each slab's largest reported and local error, H's low, high and drift); None
    where a value is not finite.

    Args:
        glob, local: (S, V, 2n) the global and local errors.
        floor: (S, 2) the round-off floors of x and v.
        H: (S, V) the Hamiltonian at the vertices.
        first: whether the run's first vertex is among them (kept).
        tiny: the smallest size of H that scales its drift.
    """
    ffi, lib = require()
    S, V, m = glob.shape
    rows = S * (V - 1) + first
    out = np.empty(rows + 6 + 5 * S)  # rows, peaks, final, per slab: glob, local, H's three
    to = ffi.from_buffer("double[]", out)
    d = (lambda a: ffi.from_buffer("double[]", np.ascontiguousarray(a, dtype=float)))
    at = rows + 6
    if lib.fem_dual_summary(S, V, m // 2, int(first), d(glob), d(local), d(floor), d(H), tiny,
                            to, to + rows, to + rows + 2, to + at, to + at + S, to + at + 2 * S,
                            to + at + 3 * S, to + at + 4 * S):
        return None
    per_slab = out[at:].reshape(5, S)
    return (out[:rows], out[rows:rows + 2], out[rows + 2:rows + 4], *per_slab)
