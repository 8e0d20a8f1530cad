"""Kinks of the force inside a slab.

Where the argument of a non-smooth function of the force (abs) changes sign, the force's
derivative jumps and so does the motion's third derivative: a slab that contains that point loses
its order, and its degree p + 1 companion loses it alike, so that their difference (the error
estimate) does not see it. As scipy's event location ends a step at an event, the slab loop
ends a slab at the kink (`SlabSchedule.cut`): on either side of it the force is smooth.

The kinks' arguments are checked at the slab's vertices and at SAMPLES points between each two,
on the motion's Hermite interpolation (fem_dual.integrate.dense); the first sign change is
located by bisection on the same interpolation.
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from fem_dual.integrate.dense import hermite_at
from fem_dual.slab.values import VertexValues

__all__ = ["kink_time", "predicted_kink_time", "SAMPLES"]

SAMPLES = 4  # points between each two vertices where the kinks' arguments are checked
BISECTIONS = 40  # the kink located to 2^-40 of a vertex interval
PREDICTION_STEPS = 64  # classical Runge-Kutta steps of the prediction over a slab, at least
PREDICTION_MARGIN = 1e-6  # a predicted kink this close to the slab's end is left to the check


def predicted_kink_time(scene, z: np.ndarray, t0: float, dt: float,
                        steps: int = PREDICTION_STEPS) -> Optional[float]:
    """The first kink in (t0, t0 + dt (1 - PREDICTION_MARGIN)) along classical Runge-Kutta from
    the start state z, or None. A slab across a kink may not be solvable at all (the DtP map's
    Newton fails where the force bends), so the slab is first cut where the motion is predicted
    to reach the kink; `kink_time` on the solved slab then places the end exactly."""
    n = len(z) // 2
    if scene.kinks(z[None, :n]) is None:
        return None
    minv = np.linalg.inv(scene.mass_matrix())

    def rhs(y):
        return np.concatenate([y[n:], minv @ scene.force_numpy(y[:n])])

    def rk4(y, h):
        k1 = rhs(y)
        k2 = rhs(y + 0.5 * h * k1)
        k3 = rhs(y + 0.5 * h * k2)
        return y + h / 6 * (k1 + 2 * k2 + 2 * k3 + rhs(y + h * k3))

    h = dt / steps
    y, g = np.asarray(z, dtype=float), scene.kinks(np.asarray(z)[None, :n])[0]
    for i in range(steps):
        y_next = rk4(y, h)
        g_next = scene.kinks(y_next[None, :n])[0]
        if not np.isfinite(g_next).all():
            return None
        change = np.sign(g) * np.sign(g_next) < 0
        if change.any():
            k = int(np.flatnonzero(change)[0])
            a, b = 0.0, h
            for _ in range(BISECTIONS):
                middle = 0.5 * (a + b)
                if np.sign(scene.kinks(rk4(y, middle)[None, :n])[0, k]) == np.sign(g[k]):
                    a = middle
                else:
                    b = middle
            at = t0 + i * h + 0.5 * (a + b)
            return at if at < t0 + dt * (1 - PREDICTION_MARGIN) else None
        y, g = y_next, g_next
    return None


def kink_time(scene, t0: float, dt: float, values: VertexValues) -> Optional[float]:
    """The first time in (t0, t0 + dt) where an argument of the scene's kinks changes sign along
    the slab's motion (its vertex values `values`), or None (no kink, or a smooth force)."""
    if scene.kinks(values.x[:1]) is None:
        return None
    t = t0 + dt * np.asarray(values.s)
    fractions = np.arange(SAMPLES + 1) / (SAMPLES + 1)
    times = np.append((t[:-1, None] + np.diff(t)[:, None] * fractions).ravel(), t[-1])
    x, _ = hermite_at(scene, t, values.x, values.v, times)
    g = scene.kinks(x)
    if not np.isfinite(g).all():
        return None  # (a motion that is not finite is the judge's)
    change = np.sign(g[:-1]) * np.sign(g[1:]) < 0  # (samples - 1, kinks)
    if not change.any():
        return None
    i = int(np.flatnonzero(change.any(axis=1))[0])
    k = int(np.flatnonzero(change[i])[0])
    return _bisect(scene, t, values, times[i], times[i + 1], k, np.sign(g[i, k]))


def _bisect(scene, t: np.ndarray, values: VertexValues, a: float, b: float, k: int,
            sign_a: float) -> float:
    """The time in [a, b] where kink k's argument changes sign (its sign at a is `sign_a`)."""
    for _ in range(BISECTIONS):
        middle = 0.5 * (a + b)
        x, _ = hermite_at(scene, t, values.x, values.v, np.array([middle]))
        if np.sign(scene.kinks(x)[0, k]) == sign_a:
            a = middle
        else:
            b = middle
    return 0.5 * (a + b)
