"""Kinks of the force inside a slab.

Where the argument of a non-smooth function of the force (abs) changes sign, the force's
derivative jumps and so does the motion's third derivative: a slab that contains that point loses
its order, and its degree p + 1 companion loses it alike, so that their difference (the error
estimate) does not see it. As scipy's event location ends a step at an event, the slab loop
ends a slab at the kink (`SlabSchedule.cut`): on either side of it the force is smooth.

The kinks' arguments are checked at the slab's vertices (or at the step ends of a classical
Runge-Kutta prediction, before the slab is solved) and at SAMPLES points between each two, on
the motion's Hermite interpolation (fem_dual.integrate.dense); the first sign change is located
by bisection on the same interpolation.
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from fem_dual.errors import SolveError
from fem_dual.integrate.dense import hermite_at
from fem_dual.slab.values import VertexValues

__all__ = ["kink_time", "predicted_kink_time", "SAMPLES"]

SAMPLES = 4  # points between each two vertices where the kinks' arguments are checked
BISECTIONS = 40  # the kink located to 2^-40 of a vertex interval
PREDICTION_STEPS = 64  # classical Runge-Kutta steps of the prediction over a slab
PREDICTION_MARGIN = 1e-6  # a predicted kink this close to the slab's end is left to the check


def predicted_kink_time(scene, flow, z: np.ndarray, t0: float, dt: float) -> Optional[float]:
    """The first kink in (t0, t0 + dt (1 - PREDICTION_MARGIN)) along the motion from the start
    state z that `flow` (fem_dual.slab.base_state.FlowPredictor, PREDICTION_STEPS steps a slab)
    steps, or None. A slab across a kink may not be solvable at all (the DtP map's Newton fails
    where the force bends), so the slab is first cut where the motion is predicted to reach the
    kink; `kink_time` on the solved slab then places the end exactly."""
    fractions = np.linspace(0.0, 1.0, flow.steps + 1)
    try:
        states = flow.along(z, fractions, dt)
    except SolveError:  # (a prediction that overflows: the slab's own solve judges the motion)
        return None
    n = len(z) // 2
    at = _first_kink(scene, t0 + dt * fractions, states[:, :n], states[:, n:])
    return at if at is not None and at < t0 + dt * (1 - PREDICTION_MARGIN) else None


def kink_time(scene, t0: float, dt: float, values: VertexValues) -> Optional[float]:
    """The first time in (t0, t0 + dt) where an argument of the scene's kinks changes sign along
    the slab's motion (its vertex values `values`), or None (no kink, or a smooth force)."""
    return _first_kink(scene, t0 + dt * np.asarray(values.s), values.x, values.v)


def _first_kink(scene, t: np.ndarray, x: np.ndarray, v: np.ndarray) -> Optional[float]:
    """The first time where a kink's argument changes sign along the Hermite interpolation
    (fem_dual.integrate.dense) of the motion through (t, x, v): checked at SAMPLES points
    between each two of the times, located by bisection on the same interpolation."""
    if scene.kinks(x[:1]) is None:
        return None
    fractions = np.arange(SAMPLES + 1) / (SAMPLES + 1)
    times = np.append((t[:-1, None] + np.diff(t)[:, None] * fractions).ravel(), t[-1])
    g = scene.kinks(hermite_at(scene, t, x, v, times)[0])
    if not np.isfinite(g).all():
        return None  # (a motion that is not finite is the judge's)
    change = np.sign(g[:-1]) * np.sign(g[1:]) < 0  # (samples - 1, kinks)
    if not change.any():
        return None
    i = int(np.flatnonzero(change.any(axis=1))[0])
    k = int(np.flatnonzero(change[i])[0])
    a, b, sign_a = times[i], times[i + 1], np.sign(g[i, k])
    for _ in range(BISECTIONS):
        middle = 0.5 * (a + b)
        inside, _ = hermite_at(scene, t, x, v, np.array([middle]))
        if np.sign(scene.kinks(inside)[0, k]) == sign_a:
            a = middle
        else:
            b = middle
    return 0.5 * (a + b)
