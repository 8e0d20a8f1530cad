"""Whether an orbit found and checked is an orbit: the status rules, first failure first, each
with the message that says what to do."""
from __future__ import annotations

from typing import List, Tuple

import numpy as np

from fem_dual.analysis.floquet import MULTIPLIER_TOL
from fem_dual.analysis.orbit.energy import ENERGY_TOL, _kinetic_scale
from fem_dual.analysis.orbit.multipliers import MultiplierErrors
from fem_dual.analysis.orbit.result import OrbitResult

__all__ = ["verdict", "CLOSURE_TOL", "MU_TOL", "COLLAPSE_TOL", "SMALL_TOL", "OFFSET_RATIO"]

CLOSURE_TOL = 1e-6  # closure / max|z| above this: the orbit does not close
MU_TOL = 1e-6  # |mu| T above this: an orbit of the damped system only
COLLAPSE_TOL = 1e-10  # an orbit that moves by less than this times its size: an equilibrium
# (its extent at the level of the Newton's resolution of its offset, not of the origin); one
# that does not close and moves by less than SMALL_TOL times its size is collapsing
SMALL_TOL = 1e-4
OFFSET_RATIO = 100.0  # an orbit this many times its extent from the origin: its multipliers'
# uncertainty is round-off in the tangents (measured: 5e-6 at 2000x, 1e-3 at 2e5x), not the mesh


def verdict(result: OrbitResult, scene, v: np.ndarray, extent: float, scale: float,
            folds: List[int], errors: MultiplierErrors, Phi: np.ndarray) -> Tuple[str, str]:
    """(status, message) of the checked orbit `result` (velocities `v`, largest range in one
    component `extent`, largest state `scale`; closing already after T/k for k in `folds`; the
    errors of its multipliers, from fem-dual's monodromy `Phi`): ("ok", "") or ("failed", why)."""
    T, mu, closure, mode = result.period, result.mu, result.closure, result.mode
    orbit_energy, energy = result.energy, result.energy_target
    multipliers_error, multipliers_check, roundoff = errors.error, errors.check, errors.roundoff
    if not extent > COLLAPSE_TOL * scale:
        return "failed", (f"the orbit collapsed onto an equilibrium: it moves by "
                          f"{extent:.3g} around {scale:.3g}; give a guess near an orbit "
                          "(--period near one, a larger amplitude in --x0, --v0)")
    if extent <= SMALL_TOL * scale and not (
            abs(mu) * T <= MU_TOL and result.closure_relative <= CLOSURE_TOL):
        return "failed", (f"the orbit is collapsing onto an equilibrium: it moves by only "
                          f"{extent:.3g} around {scale:.3g}, and "
                          + (f"the unfolding damping converged to mu = {mu:.3g}, not 0"
                             if not abs(mu) * T <= MU_TOL else
                             f"it does not close (|z(T) - z(0)| = {closure:.3g} by DOP853)")
                          + "; give a guess near an orbit (--period near one, a larger "
                          "amplitude in --x0, --v0)")
    if not abs(mu) * T <= MU_TOL:
        return "failed", (f"the unfolding damping converged to mu = {mu:.3g}, not 0: the "
                          "guess is near no orbit of the undamped system (past flutter, or "
                          "a motion that is not periodic), or the mesh is too coarse for it; "
                          "give a better guess, or raise --cells or --degree")
    if mode == "energy" and not (
            orbit_energy is not None and abs(orbit_energy - energy)
            <= ENERGY_TOL * max(abs(energy), _kinetic_scale(scene, v))):
        return "failed", (f"the orbit's energy is {orbit_energy:.12g}, not {energy:.12g}; "
                          "raise --cells or give a guess nearer that energy")
    if folds:
        k = folds[-1]
        return "failed", (f"the orbit closes after T/{k} = {T / k:.12g} already: it runs "
                          f"{k} times around an orbit of period {T / k:.12g}; give --period "
                          f"near {T / k:.6g}")
    if not result.closure_relative <= CLOSURE_TOL:
        return "failed", (f"the orbit does not close: |z(T) - z(0)| = {closure:.3g} "
                          f"({result.closure_relative:.3g} relative) by DOP853 from its start; "
                          "raise --cells or --degree, or give a better guess")
    if not max(multipliers_error, multipliers_check, roundoff) <= MULTIPLIER_TOL \
            and roundoff > 0.1 * MULTIPLIER_TOL:
        return "failed", (f"the Floquet multipliers span more than double precision resolves: "
                          f"|monodromy| = {np.linalg.norm(Phi, 2):.3g}, so each multiplier "
                          f"is known only to about {roundoff:.3g} (degree p and p + 1 differ "
                          f"by {multipliers_error:.3g}, fem-dual and DOP853 by "
                          f"{multipliers_check:.3g}); no resolution helps: the orbit is this "
                          "unstable (a shorter orbit of the family is less so)")
    if not max(multipliers_error, multipliers_check) <= MULTIPLIER_TOL:
        return "failed", (f"the Floquet multipliers are uncertain: degree p and p + 1 differ "
                          f"by {multipliers_error:.3g}, fem-dual and DOP853 by "
                          f"{multipliers_check:.3g} (relative to 1 + |multiplier|); "
                          + (f"the orbit lies at {scale:.3g}, {scale / extent:.3g} times "
                             "its extent, where the tangents of fem-dual's slabs lose "
                             "digits to round-off: shift the coordinates to put its centre "
                             "near the origin (the force of x + c)"
                             if scale > OFFSET_RATIO * extent else
                             "raise --cells or --degree"))
    return "ok", ""
