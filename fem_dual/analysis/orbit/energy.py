"""Mode energy for a force with a potential: from the guess's orbit to the orbit of energy E,
by Newton in mode energy, or by the closest orbits scaled in amplitude, or by steps in energy."""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from fem_dual import faults
from fem_dual.errors import SolveError
from fem_dual.analysis.floquet import stop_if_asked
from fem_dual.analysis.orbit.guess import OrbitGuess
from fem_dual.analysis.orbit_input import Energy

if TYPE_CHECKING:
    from fem_dual.analysis.orbit.orbits import Orbits

__all__ = ["reach_energy", "scale_to_energy", "ENERGY_HALVINGS", "ENERGY_STAGES",
           "AMPLITUDE_STEPS", "AMPLITUDE_HALVINGS", "ANCHOR_TOL", "ENERGY_TOL", "_kinetic_scale"]

ENERGY_HALVINGS = 8  # mode energy: a step in energy halved at most this often in a row
ENERGY_STAGES = 100  # ... and at most this many steps
AMPLITUDE_STEPS = 60  # mode energy: closest orbits scaled in amplitude, at most this many,
AMPLITUDE_HALVINGS = 6  # ... a scale step halved at most this often in a row where Newton fails
ANCHOR_TOL = 1e-4  # ... the last from a base state scaled by at most this from an orbit
ENERGY_TOL = 1e-8  # mode energy: the orbit's energy (at its start) within this of E, relative


def reach_energy(orbits: "Orbits", scene, guess, T0: float, energy: float, has: Energy):
    """Newton (the `orbits`') in mode energy from the guess; when that fails, the closest orbit
    first, then steps in energy, each from the orbit before (its motion as the base state),
    halved when Newton fails and doubled after a success. Raises SolveError naming the energy
    reached."""
    try:
        return orbits._newton(guess, T0, "energy", energy, restarts=0)
    except faults.Interrupted:  # a signal is no failure to work around
        raise
    except SolveError:
        pass
    history, s, x, v = orbits._newton(guess, T0, "closest")
    reached, period = has.value(x[0], v[0]), float(orbits.problem.T_c.value)
    if reached is None:
        raise SolveError("mode energy: the potential (the line integral of the force from "
                         "the origin) cannot be integrated at the closest orbit's start")
    _below_centre(scene, has, x, energy, reached)
    try:
        return scale_to_energy(orbits, scene, s, x, v, period, reached, energy, has)
    except faults.Interrupted:  # a signal is no failure to work around
        raise
    except SolveError as exc:  # steps in energy from the orbit it reached
        s, x, v, period, reached = getattr(exc, "reached", (s, x, v, period, reached))
    step, stages, halvings = energy - reached, 0, 0
    while True:
        goal = energy if abs(step) >= abs(energy - reached) else reached + step
        start = OrbitGuess(scene, period * s, x, v)
        try:
            history, s, x, v = orbits._newton(start, period, "energy", goal, restarts=0)
        except faults.Interrupted:  # a signal is no failure to work around
            raise
        except SolveError as exc:
            halvings += 1
            if halvings > ENERGY_HALVINGS or stages >= ENERGY_STAGES:
                raise SolveError(f"mode energy reached E = {reached:.10g} on the way to "
                                 f"{energy:.10g} and could not go on ({exc}); give a guess "
                                 "nearer that energy") from None
            step /= 2
            continue
        stages, halvings = stages + 1, 0
        reached, period = goal, float(orbits.problem.T_c.value)
        if goal == energy:
            return {**history, "energy_stages": stages}, s, x, v
        step *= 1.5


def scale_to_energy(orbits: "Orbits", scene, s, x, v, period: float, reached: float,
                    energy: float, has: Energy):
    """The closest orbit from an orbit scaled about its mean (the anchor): while E is far,
    by sqrt((E - E_centre) / (E_orbit - E_centre)) (E - E_centre ~ amplitude^2 near a
    centre; at most 2x), each orbit the next anchor; then by the factor that secant steps
    find, until the orbit's energy is E within ENERGY_TOL / 1000. A scaled orbit is only a
    guess of the next one (an orbit nearing a separatrix changes its shape): where Newton
    fails, the last orbit becomes the anchor and the step is halved (at most
    AMPLITUDE_HALVINGS times in a row). Near a linear limit (small amplitudes) the energy
    row is nearly singular (condition ~ 1 / amplitude^2, as for linear scenes), the
    closest orbit is not. Raises SolveError, whose `reached` is the last orbit (s, x, v,
    period, energy)."""
    bottom = _centre_energy(has, x, v)
    anchor = (s, x, v, period)
    points = [(1.0, reached)]  # (the anchor's scale, the closest orbit's energy)
    iterations = steps = halvings = 0
    while steps < AMPLITUDE_STEPS:
        stop_if_asked("the energy's amplitude steps")
        c, E = points[-1]
        if abs(E - energy) <= 1e-3 * ENERGY_TOL * max(abs(energy), _kinetic_scale(scene, v)):
            if abs(c - 1.0) <= ANCHOR_TOL:
                return {"iterations": iterations, "amplitude_steps": steps}, s, x, v
            # its base state was far from it (the discrete orbit's error grows with that
            # distance): again from this orbit
            anchor, points, c = (s, x, v, period), [(1.0, E)], 1.0
        q = (energy - bottom) / (E - bottom) if bottom < min(E, energy) else (
            0.25 if energy < E else 4.0)  # the centre's energy is only about the bottom's
        if not 0.5 <= q <= 2.0 and len(points) > 1:  # far: the last orbit as the anchor
            anchor, points, c = (s, x, v, period), [(1.0, E)], 1.0
            bottom = _centre_energy(has, x, v)
        if len(points) > 1:  # secant in the anchor's scale
            c0, E0 = points[-2]
            target = c + (energy - E) * (c - c0) / (E - E0) if E != E0 else c
        else:
            target = c * float(np.sqrt(q))
        target = float(np.clip(target, 0.5 * c, 2.0 * c))
        target = c + (target - c) * 0.5 ** halvings
        s_a, x_a, v_a, period_a = anchor
        x_mid, v_mid = x_a.mean(axis=0), v_a.mean(axis=0)
        start = OrbitGuess(scene, period_a * s_a, x_mid + target * (x_a - x_mid),
                           v_mid + target * (v_a - v_mid))
        try:
            history, s_new, x_new, v_new = orbits._newton(start, period_a, "closest")
            E_new = has.value(x_new[0], v_new[0])
            if E_new is None:
                raise SolveError("no energy at the orbit's start")
        except faults.Interrupted:  # a signal is no failure to work around
            raise
        except SolveError as exc:
            halvings += 1
            if halvings > AMPLITUDE_HALVINGS:
                exc.reached = (s, x, v, period, E)
                raise
            anchor, points = (s, x, v, period), [(1.0, E)]  # on from the last orbit
            continue
        s, x, v, E = s_new, x_new, v_new, E_new
        iterations += history["iterations"]
        steps, halvings, period = steps + 1, 0, float(orbits.problem.T_c.value)
        points.append((target, E))
    error = SolveError(f"the amplitude steps did not reach E = {energy:.10g}")
    error.reached = (s, x, v, period, points[-1][1])
    raise error


def _below_centre(scene, has: Energy, x: np.ndarray, energy: float, reached: float) -> None:
    """SolveError when E lies below the energy of the equilibrium that the orbit (of energy
    `reached`) surrounds, at rest (a minimum of the potential, found from the orbit's mean):
    no orbit of its family has that energy."""
    from scipy.optimize import root

    with np.errstate(all="ignore"):
        found = root(scene.force_numpy, x.mean(axis=0), tol=1e-13)
    if not found.success or not np.all(np.isfinite(found.x)):
        return
    from fem_dual.slab.base_state import force_jacobian

    with np.errstate(all="ignore"):
        stiffness = -force_jacobian(scene.force_numpy, found.x)
    if not (np.all(np.isfinite(stiffness))
            and np.linalg.eigvalsh(0.5 * (stiffness + stiffness.T)).min() > 0):
        return  # no minimum of the potential (a saddle between two wells): no centre
    floor = has.value(found.x, np.zeros(len(found.x)))
    if floor is not None and energy < floor < reached:
        raise SolveError(f"E = {energy:.10g} lies below the energy {floor:.10g} of the "
                         f"equilibrium x = {list(map(float, found.x))} that the orbit from the "
                         "guess surrounds: no orbit of its family has that energy (theirs lie "
                         "above); give a guess near another family, or a larger E")


def _centre_energy(has: Energy, x: np.ndarray, v: np.ndarray) -> float:
    """About the energy at an orbit's centre (its mean position at rest); raises SolveError
    where the potential cannot be integrated."""
    bottom = has.value(x.mean(axis=0), np.zeros(v.shape[1]))
    if bottom is None:
        raise SolveError("no energy at the orbit's centre")
    return bottom


def _kinetic_scale(scene, v: np.ndarray) -> float:
    """The largest kinetic energy along an orbit: the scale of its energy (which can be 0 or
    negative with a potential from V(0) = 0)."""
    M = scene.mass_matrix()
    return float(max(0.5 * w @ M @ w for w in np.asarray(v)))
