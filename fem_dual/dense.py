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

from fem_dual.base_state import force_jacobian

__all__ = ["rates", "hermite_at", "hermite_estimate", "slab_interpolation_gaps",
           "GAP_ORDER"]

GAP_ORDER = 8  # the interpolation error estimate is O(h^8), as the error of H7
GAP_SAFETY = 2.0  # on the contraction of successive Hermites (see _interpolate)
GAP_POINTS = (0.25, 0.5, 0.75)  # where within each vertex interval a slab's gap is measured


def rates(scene, x: np.ndarray, v: np.ndarray) -> Tuple[np.ndarray, ...]:
    """(a, j, snap) at each row of (x, v): the acceleration and its first two time derivatives
    along the motion (exact for linear scenes; for a force, its Jacobian by central differences
    and its second derivative along v by a second difference)."""
    Minv = np.linalg.inv(scene.mass_matrix())
    if scene.linear:
        K, D = scene.stiffness_matrix(), scene.damping_matrix()
        a = -(x @ K.T + v @ D.T) @ Minv.T
        j = -(v @ K.T + a @ D.T) @ Minv.T
        return a, j, -(a @ K.T + j @ D.T) @ Minv.T
    F = scene.force_numpy
    a, j, snap = (np.empty_like(x) for _ in range(3))
    for i, (xi, vi) in enumerate(zip(x, v)):
        J = force_jacobian(F, xi)
        a[i] = Minv @ F(xi)
        j[i] = Minv @ (J @ vi)
        size = float(np.abs(vi).max())
        curvature = np.zeros_like(xi)
        if size > 0:  # along the unit direction, then scaled: no overflow for |v| ~ 1e-300
            h = 1e-4 * max(1.0, float(np.abs(xi).max()))
            u = vi / size
            with np.errstate(over="ignore", invalid="ignore"):  # (array products: inf, no raise)
                curvature = size * (size * ((F(xi + h * u) - 2 * F(xi) + F(xi - h * u)) / h ** 2))
        snap[i] = Minv @ (curvature + J @ a[i])
    return a, j, snap


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
    hh = h[:, None]
    data = [d * hh ** k for k, d in enumerate(left)] + [d * hh ** k for k, d in enumerate(right)]
    weights = (s[:, None] ** np.arange(2 * m)) @ _BASES[m]  # the basis functions at s
    return sum(weights[:, [k]] * data[k] for k in range(2 * m))


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
    gaps = np.zeros((slabs, 2))
    for f in GAP_POINTS:
        _, _, gap_x, gap_v = _interpolate(np.full(len(h), f), h, left, right, estimate=True)
        gaps = np.maximum(gaps, np.column_stack([gap_x.reshape(slabs, -1).max(axis=1),
                                                 gap_v.reshape(slabs, -1).max(axis=1)]))
    return gaps


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
