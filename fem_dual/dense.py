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

__all__ = ["rates", "hermite_at", "hermite_estimate"]


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


_BASES = {m: _hermite_basis(m) for m in (3, 4)}  # degrees 5 and 7


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
    """(x, v, interpolation error estimate) at `times`: the estimate is the distance to the
    Hermite of degree 5 (one derivative fewer at each end), an upper estimate of the degree-7
    error, which matters where the vertices are more accurate than O(h^8) (p >= 5)."""
    return _dense(scene, t, x, v, times, estimate=True)


def _dense(scene, t, x, v, times, estimate: bool = False):
    times = np.asarray(times, dtype=float)
    k = np.clip(np.searchsorted(t, times, side="right") - 1, 0, len(t) - 2)
    h = t[k + 1] - t[k]
    s = np.where(h > 0, (times - t[k]) / np.where(h > 0, h, 1.0), 0.0)
    ends = np.unique(np.concatenate([k, k + 1]))
    a, j, snap = (np.empty_like(x) for _ in range(3))
    a[ends], j[ends], snap[ends] = rates(scene, x[ends], v[ends])
    xs = _hermite(s, h, (x[k], v[k], a[k], j[k]), (x[k + 1], v[k + 1], a[k + 1], j[k + 1]))
    vs = _hermite(s, h, (v[k], a[k], j[k], snap[k]),
                  (v[k + 1], a[k + 1], j[k + 1], snap[k + 1]))
    if not estimate:
        return xs, vs, None
    x5 = _hermite(s, h, (x[k], v[k], a[k]), (x[k + 1], v[k + 1], a[k + 1]))
    v5 = _hermite(s, h, (v[k], a[k], j[k]), (v[k + 1], a[k + 1], j[k + 1]))
    return xs, vs, np.maximum(np.abs(xs - x5).max(axis=1), np.abs(vs - v5).max(axis=1))
