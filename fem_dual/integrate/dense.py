"""Dense output: the state at any time from the vertex values.

The vertex values converge at order 2p; values inside a cell taken from the DtP map converge at
order p only. Between two output vertices the state is instead interpolated by Hermite
polynomials of degree 7 that use the equation of motion at both ends: x from (x, v, a, j) and v
from (v, a, j, snap), with a = M^-1 (F(x) - D v) and j, snap its time derivatives. The
interpolation error is O(h^8) with h the spacing of the vertices, so up to degree p = 4 the
dense values keep the vertex order 2p (measured in tests/test_force.py; README, "Your own
force").
"""
from __future__ import annotations

import math
from typing import Tuple

import numpy as np


__all__ = ["rates", "hermite_at", "hermite_estimate", "slab_interpolation_gaps",
           "GAP_ORDER"]

GAP_ORDER = 8  # the interpolation error estimate is O(h^8), as the error of H7
GAP_SAFETY = 2.0  # on the contraction of successive Hermites (see _interpolate)
GAP_POINTS = (0.25, 0.5, 0.75)  # where within each vertex interval a slab's gap is measured


def rates(scene, x: np.ndarray, v: np.ndarray) -> Tuple[np.ndarray, ...]:
    """(a, j, snap) at each row of (x, v): the acceleration and its first two time derivatives
    along the motion (exact for linear scenes; for a force, its derivatives along v and along a
    by central differences and its second derivative along v by a second difference, all rows
    at once where the force takes them (`_forces`))."""
    if scene.linear:  # a = -M^-1 (K x + D v), j = -M^-1 (K v + D a), snap = -M^-1 (K a + D j)
        a = scene.accelerations(x, v)
        j = scene.accelerations(v, a)
        return a, j, scene.accelerations(a, j)
    Minv = np.linalg.inv(scene.mass_matrix())
    with np.errstate(over="ignore", invalid="ignore"):  # (array products: inf, no raise)
        F0 = _forces(scene, x)
        a = F0 @ Minv.T
        reach = np.maximum(1.0, np.abs(x).max(axis=1, initial=0.0))[:, None]
        j = _along(scene, x, v, 1e-6 * reach, F0, first=True) @ Minv.T
        # along the unit direction of v, then scaled: no overflow for |v| ~ 1e-300
        curvature = _along(scene, x, v, 1e-4 * reach, F0, first=False)
        snap = (curvature + _along(scene, x, a, 1e-6 * reach, F0, first=True)) @ Minv.T
    return a, j, snap


def _along(scene, x: np.ndarray, d: np.ndarray, h: np.ndarray, F0: np.ndarray,
           first: bool) -> np.ndarray:
    """Per row, the first (J d) or second (F''[d, d]) derivative of the force along d, by a
    central difference of step h (rows, 1) along d's unit direction."""
    size = np.abs(d).max(axis=1, initial=0.0)[:, None]
    u = np.divide(d, size, out=np.zeros_like(d), where=size > 0)
    plus, minus = _forces(scene, x + h * u), _forces(scene, x - h * u)
    if first:
        return size * (plus - minus) / (2 * h)
    return size * (size * ((plus - 2 * F0 + minus) / h ** 2))


def _forces(scene, x: np.ndarray) -> np.ndarray:
    """scene.force_numpy at each row of x (rows, n): in one call on the columns where the force
    is written with array operations (checked against single calls at the first and the last
    row), else row by row."""
    F = scene.force_numpy
    rows, n = x.shape
    if rows > 1:
        try:
            out = np.asarray(F(x.T), dtype=float)
        except Exception:  # noqa: BLE001 -- a force written for one point only
            out = None
        if out is not None and out.shape == (n, rows):
            out = out.T
            ends = np.array([np.asarray(F(x[i]), dtype=float) for i in (0, rows - 1)])
            gap = np.abs(out[[0, -1]] - ends)
            if bool(((gap <= 1e-13 * np.abs(ends)) | (np.isnan(gap) & np.isnan(ends))).all()):
                return out
    return np.array([np.asarray(F(row), dtype=float) for row in x]).reshape(rows, n)


def _hermite_basis(m: int) -> np.ndarray:
    """Monomial coefficients (2m, 2m) of the Hermite basis on [0, 1] with m derivatives
    (0..m-1) at each end: column k gives the polynomial whose k-th datum is 1."""
    A = np.zeros((2 * m, 2 * m))
    for end, s in enumerate((0.0, 1.0)):
        for k in range(m):  # k-th derivative of s^j at s
            for jj in range(k, 2 * m):
                coef = math.factorial(jj) / math.factorial(jj - k)
                A[end * m + k, jj] = coef * (s ** (jj - k) if jj > k else 1.0)
    return np.linalg.inv(A)


_BASES = {m: _hermite_basis(m) for m in (2, 3, 4)}  # degrees 3, 5 and 7


def _hermite(s: np.ndarray, h: np.ndarray, left, right) -> np.ndarray:
    """The polynomial of degree 2m - 1 with the m derivatives `left`, `right` (value and time
    derivatives, rows per point) at s = 0 and 1 of intervals of length h."""
    m = len(left)
    powers = h[:, None] ** np.arange(m)  # the time derivatives in units of the interval
    weights = ((s[:, None] ** np.arange(2 * m)) @ _BASES[m]) * np.hstack([powers, powers])
    return np.einsum("rk,krn->rn", weights, np.stack(list(left) + list(right)))


def hermite_at(scene, t: np.ndarray, x: np.ndarray, v: np.ndarray,
               times: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """(x, v) at `times` (within [t[0], t[-1]]) from the vertex values (t, x, v)."""
    return _dense(scene, t, x, v, times)[:2]


def hermite_estimate(scene, t: np.ndarray, x: np.ndarray, v: np.ndarray,
                     times: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(x, v, interpolation error estimate) at `times`: the distance to the Hermite of degree 5
    (one derivative fewer at each end) scaled by the contraction of the successive Hermites
    (`_interpolate`), an estimate of the degree-7 error, which matters where the vertices are
    more accurate than O(h^8) (p >= 5)."""
    return _dense(scene, t, x, v, times, estimate=True)


def slab_interpolation_gaps(scene, s: np.ndarray, dt, x: np.ndarray,
                            v: np.ndarray) -> np.ndarray:
    """The interpolation error estimate of `hermite_estimate` between the vertices of slabs
    (x, v: (slabs, vertices, n) at the points s of [0, 1]; length dt each, or (slabs,)) at
    GAP_POINTS of every vertex interval, for x and v apart: (slabs, 2), the max over each slab.
    What an output time between vertices adds to the vertex error (the slab loop judges it
    when output times are asked for)."""
    slabs, vertices, n = x.shape
    if vertices < 2 or slabs == 0:
        return np.zeros((slabs, 2))
    dts = np.broadcast_to(np.asarray(dt, dtype=float), (slabs,))
    a, j, snap = (r.reshape(slabs, vertices, n)
                  for r in rates(scene, x.reshape(-1, n), v.reshape(-1, n)))
    h = (dts[:, None] * np.diff(np.asarray(s, dtype=float))[None, :]).ravel()  # (slabs * cells)
    lo, hi = (slice(None), slice(None, -1)), (slice(None), slice(1, None))
    left = [q[lo].reshape(-1, n) for q in (x, v, a, j, snap)]
    right = [q[hi].reshape(-1, n) for q in (x, v, a, j, snap)]
    points = len(GAP_POINTS)  # every interval at every point at once
    at = np.repeat(np.asarray(GAP_POINTS, dtype=float)[None, :], len(h), axis=0).ravel()
    _, _, gap_x, gap_v = _interpolate(at, np.repeat(h, points),
                                      [np.repeat(q, points, axis=0) for q in left],
                                      [np.repeat(q, points, axis=0) for q in right],
                                      estimate=True)
    return np.column_stack([gap_x.reshape(slabs, -1).max(axis=1),
                            gap_v.reshape(slabs, -1).max(axis=1)])


def _interpolate(s, h, left, right, estimate: bool):
    """x and v at the points s of intervals of length h from the vertex data left, right
    ([x, v, a, j, snap] rows at each end), and with `estimate` the interpolation error estimate
    of each (rows,): |H7 - H5| times the observed contraction |H7 - H5| / |H5 - H3| of the
    successive Hermites (with GAP_SAFETY, at most 1). Where the interpolation converges
    (a contraction below 1) the error of H7 is about 0.5 times the contraction times |H7 - H5|
    (Hermite remainders of a harmonic motion, whose ratio is 30/56 at every s); where it does
    not, |H7 - H5| itself."""
    xs = _hermite(s, h, left[:4], right[:4])
    vs = _hermite(s, h, left[1:5], right[1:5])
    if not estimate:
        return xs, vs, None, None
    gaps = []
    for start, top in ((0, xs), (1, vs)):
        h5 = _hermite(s, h, left[start:start + 3], right[start:start + 3])
        h3 = _hermite(s, h, left[start:start + 2], right[start:start + 2])
        d7 = np.abs(top - h5).max(axis=1)
        d5 = np.abs(h5 - h3).max(axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            contraction = np.where(d5 > 0, d7 / np.where(d5 > 0, d5, 1.0), np.inf)
        gaps.append(d7 * np.minimum(1.0, GAP_SAFETY * contraction))
    return xs, vs, gaps[0], gaps[1]


def _dense(scene, t, x, v, times, estimate: bool = False):
    times = np.asarray(times, dtype=float)
    k = np.clip(np.searchsorted(t, times, side="right") - 1, 0, len(t) - 2)
    h = t[k + 1] - t[k]
    s = np.where(h > 0, (times - t[k]) / np.where(h > 0, h, 1.0), 0.0)
    ends = np.unique(np.concatenate([k, k + 1]))
    a, j, snap = (np.empty_like(x) for _ in range(3))
    a[ends], j[ends], snap[ends] = rates(scene, x[ends], v[ends])
    data = (x, v, a, j, snap)
    xs, vs, gap_x, gap_v = _interpolate(s, h, [q[k] for q in data], [q[k + 1] for q in data],
                                        estimate)
    return xs, vs, None if gap_x is None else np.maximum(gap_x, gap_v)
