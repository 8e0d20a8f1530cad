"""Orbits of one scene kind, degree and cells: from a guess to an orbit, and from the orbit to
its result: its companion at degree p + 1 (the error estimate), its multipliers, DOP853's check
and its status."""
from __future__ import annotations

import time
from typing import Optional

import numpy as np

from fem_dual import faults
from fem_dual.compat import quiet_jit_logging
from fem_dual.errors import InputError, SolveError
from fem_dual.analysis.floquet import (FLOW_MAX_CELLS, FLOW_START_CELLS, FLOW_TARGET, MAX_FOLD,
                                       MULTIPLIER_TOL, SlabFlow, floquet_multipliers, monodromy,
                                       multiplier_distance, vector_field)
from fem_dual.analysis.orbit_input import Energy
from fem_dual.analysis.orbit.advice import _orbit_advice
from fem_dual.analysis.orbit.energy import ENERGY_TOL, _kinetic_scale, reach_energy
from fem_dual.analysis.orbit.guess import GuessMotion, OrbitGuess
from fem_dual.analysis.orbit.newton import OrbitSolver
from fem_dual.analysis.orbit.problem import OrbitProblem
from fem_dual.analysis.orbit.result import OrbitResult, _differences

__all__ = ["Orbits", "BASE_RESTARTS", "CLOSURE_TOL", "MU_TOL", "COLLAPSE_TOL", "SMALL_TOL",
           "OFFSET_RATIO"]

BASE_RESTARTS = 4  # a failed Newton starts again on its last iterate's image, at most this often
CLOSURE_TOL = 1e-6  # closure / max|z| above this: the orbit does not close
MU_TOL = 1e-6  # |mu| T above this: an orbit of the damped system only
COLLAPSE_TOL = 1e-10  # an orbit that moves by less than this times its size: an equilibrium
# (its extent at the level of the Newton's resolution of its offset, not of the origin); one
# that does not close and moves by less than SMALL_TOL times its size is collapsing
SMALL_TOL = 1e-4
OFFSET_RATIO = 100.0  # an orbit this many times its extent from the origin: its multipliers'
# uncertainty is round-off in the tangents (measured: 5e-6 at 2000x, 1e-3 at 2e5x), not the mesh


class Orbits:
    """Compiled orbit problems of one scene kind, degree and cells; solves orbits and families."""

    def __init__(self, scene, degree: int, cells: int, energy: Optional[Energy] = None):
        """energy: compile the energy row of mode "energy" (a force with a potential)."""
        tic = time.perf_counter()
        with quiet_jit_logging():
            self.problem = OrbitProblem(scene, degree, cells, energy=energy)
            self.solver = OrbitSolver(self.problem)
        self.compile_s = time.perf_counter() - tic
        self.scene = scene
        self.guess = GuessMotion()
        self.flow = SlabFlow(degree)
        self._energy = (scene, energy) if energy is not None else None

    def energy_of(self, scene, x0: np.ndarray) -> Optional[Energy]:
        """Energy.of(scene, x0), once per scene (its sample quadratures take 10-100 ms, and
        every orbit and its companion ask)."""
        if self._energy is None or self._energy[0] is not scene:
            self._energy = (scene, Energy.of(scene, x0))
        return self._energy[1]

    def close(self) -> None:
        self.solver.close()
        self.guess.close()
        self.flow.close()

    def _newton(self, guess, T0: float, mode: str, energy: float = 0.0,
                restarts: int = BASE_RESTARTS):
        """(history, s, x, v): the orbit's Newton from zero dual fields on the base state
        `guess` (a run over T0). When Newton fails, it starts again from zero dual fields on
        the DtP image of its last iterate as the base state (at most `restarts` times): a
        base state far from the orbit (a guess over a period 7 % short, a pendulum near its
        separatrix) leaves the DtP map singular before Newton gets there, while the image is
        nearer. Raises SolveError with advice."""
        p = self.problem
        for restart in range(restarts + 1):
            p.set_base(np.hstack(guess.at(T0 * p.base_nodes)))
            p.w.x.array[:] = 0.0
            p.T_c.value, p.mu_c.value = T0, 0.0
            p.start_dtp()
            self.solver.target_energy = energy
            try:
                history = self.solver.solve(mode)
                if restart:
                    history["base_restarts"] = restart
                return (history, *self.solver.orbit_vertices())
            except faults.Interrupted:  # a signal is no failure to work around
                raise
            except SolveError as exc:
                failure = exc
            if not np.any(p.w.x.array):  # no step taken: its image is this base state
                break
            try:  # the last iterate, whose image is the next base state
                s, x, v = self.solver.orbit_vertices()
            except SolveError:
                break
            T0 = float(p.T_c.value)
            if not (np.isfinite(x).all() and np.isfinite(v).all() and T0 > 0):
                break
            guess = OrbitGuess(self.scene, T0 * s, x, v)
        raise SolveError(_orbit_advice(str(failure))) from None

    def _polish(self, history, found, mode: str, energy: float):
        """The orbit solved once more on itself as the base state. The base state's distance
        from the orbit sets the discrete orbit's error (zero dual fields solve an exact orbit
        as base state); on itself it converges faster: Ziegler's slow mode at p = 2, 32 / 64
        cells, period error 5.8e-6 / 3.6e-7 (order 4) before, 7.6e-9 / 1.2e-10 (order 6)
        after; Duffing from a guess 15 % long (restarts), 2.2e-8 before, 5e-14 after. Keeps
        the orbit as found where this Newton fails."""
        p = self.problem
        s, x, v = found
        kept = (float(p.T_c.value), float(p.mu_c.value))
        p.set_base(np.hstack(OrbitGuess(self.scene, kept[0] * s, x, v).at(kept[0] *
                                                                           p.base_nodes)))
        p.w.x.array[:] = 0.0
        p.start_dtp()
        self.solver.target_energy = energy
        try:
            again = self.solver.solve(mode)
        except faults.Interrupted:  # a signal is no failure to work around
            raise
        except SolveError:
            p.T_c.value, p.mu_c.value = kept
            return (history, s, x, v)
        history = {**history, "polish_iterations": again["iterations"]}
        return (history, *self.solver.orbit_vertices())


    def solve(self, scene, x0: np.ndarray, v0: np.ndarray, T0: float, mode: str = "closest",
              energy: Optional[float] = None, check: bool = True,
              guess=None, companion: Optional["Orbits"] = None) -> OrbitResult:
        """The orbit near the motion from (x0, v0) over T0 (`guess`: that motion, a RunResult,
        if already computed). `check`: the closure by DOP853 and the multipliers by fem-dual's
        flow; `companion`: the orbits of degree p + 1, whose orbit from the same guess is the
        error estimate. Raises SolveError."""
        p = self.problem
        has = self.energy_of(scene, x0)
        if mode == "energy" and has is None:
            raise InputError(f"mode energy needs a scene with an energy (linear with K "
                             f"symmetric and no damping, or a force with a potential); "
                             f"{scene.name} has none")
        if mode == "energy" and has.linear and not energy > 0:
            raise InputError(f"energy={energy:g} must be positive for {scene.name} (its energy "
                             "1/2 v.M v + 1/2 x.K x)")
        if mode == "energy" and not has.linear and "E" not in p.forms:
            raise InputError("mode energy: these orbits were compiled without the energy row")
        # a linear family has one period: its orbits of energy E are the closest one scaled
        linear_energy = mode == "energy" and has.linear
        if scene is not self.scene:
            p.set_scene_constants(scene)
            self.scene = scene
        tic = time.perf_counter()
        if guess is None:
            guess = self.guess(scene, x0, v0, T0)
        guess_s = time.perf_counter() - tic
        tic = time.perf_counter()
        if mode == "energy" and not linear_energy:
            history, s, x, v = reach_energy(self, scene, guess, T0, energy, has)
        else:
            history, s, x, v = self._newton(guess, T0, "closest" if linear_energy else mode)
        history, s, x, v = self._polish(history, (s, x, v), "closest" if linear_energy else mode,
                                        energy or 0.0)
        orbit_energy = has.value(x[0], v[0]) if has is not None else None
        if linear_energy:  # the amplitude sets E
            if not orbit_energy > 0:
                raise SolveError("the orbit found has no energy to scale to E")
            scale = np.sqrt(energy / orbit_energy)
            x, v, orbit_energy = x * scale, v * scale, has.value(x[0] * scale, v[0] * scale)
        solve_s = time.perf_counter() - tic
        T, mu = float(p.T_c.value), float(p.mu_c.value)
        z0 = np.concatenate([x[0], v[0]])
        tic = time.perf_counter()
        other = None  # the same orbit at degree p + 1, from the same guess
        if companion is not None and check:
            if history.get("energy_stages") or "amplitude_steps" in history or \
                    "base_restarts" in history:  # from the orbit
                # found, not again in stages
                other = companion.solve(scene, x[0], v[0], T, mode, energy, check=False,
                                        guess=OrbitGuess(scene, T * s, x, v))
            else:
                other = companion.solve(scene, x0, v0, T0, mode, energy, check=False,
                                        guess=guess)
        estimate_s = time.perf_counter() - tic
        scale = float(np.abs(np.hstack([x, v])).max())
        # closures relative to the orbit's extent (its largest range in one component), not to
        # its offset: an orbit around x = 1 of amplitude 1e-7 is no orbit of size 1; so are the
        # difference steps of the tangents
        extent = float(np.ptp(np.hstack([x, v]), axis=0).max())
        tic = time.perf_counter()
        zT, Phi_check, parts = (monodromy(scene, z0, T, max(MAX_FOLD, p.mesh.cells * p.degree),
                                          float(np.ptp(x, axis=0).max()))
                                if check
                                else (z0, np.eye(len(z0)), np.zeros((0, len(z0)))))
        check_s = time.perf_counter() - tic
        tic = time.perf_counter()
        flow_cells = min(p.mesh.cells, FLOW_START_CELLS)
        Phi = Phi_c = Phi_check
        # the companion flow (degree p + 1) runs along the degree p + 1 orbit: the multipliers'
        # estimate sees the error of the orbit's start as well as the flow's
        other_z0, other_T = ((np.concatenate([other.x[0], other.v[0]]), other.period)
                             if other is not None else (z0, T))
        field = vector_field(scene)
        direction, other_direction = field(z0), field(other_z0)
        # multipliers: the pair at 1 (the flow's direction and the family's), the nontrivial
        trivial, lam_n = trivial_c, lam_c_n = floquet_multipliers(Phi, direction)
        off_before = np.inf
        while check:  # finer slabs until the multipliers' estimate meets FLOW_TARGET
            _, Phi, Phi_c = self.flow(scene, z0, T, flow_cells, other_z0, other_T, extent)
            trivial, lam_n = floquet_multipliers(Phi, direction)
            trivial_c, lam_c_n = floquet_multipliers(Phi_c, other_direction)
            error = multiplier_distance(lam_n, lam_c_n)
            # the pair at 1 is held to MULTIPLIER_TOL only, and only while finer slabs bring it
            # nearer: it carries the orbit's own error too (4e-11 where the nontrivial agree to
            # 1e-12), and round-off far from the origin (3e-4 at 1e4, 5e6 times the extent)
            off = max(_off_one(trivial), _off_one(trivial_c))
            settled = off <= MULTIPLIER_TOL or off > 0.5 * off_before
            if (error <= FLOW_TARGET and settled) or 2 * flow_cells > FLOW_MAX_CELLS:
                break
            flow_cells, off_before = 2 * flow_cells, off
        flow_compile_s = self.flow.new_setup_s()
        flow_s = time.perf_counter() - tic - flow_compile_s
        closure = float(np.abs(zT - z0).max())
        folds = [k for k, z in enumerate(parts, start=2)
                 if np.abs(z - z0).max() <= CLOSURE_TOL * extent]
        trivial_check, lam_check_n = floquet_multipliers(Phi_check, direction)
        lam = np.concatenate([trivial, lam_n])
        lam = lam[np.lexsort((lam.imag, -np.abs(lam)))]
        multipliers_error = multiplier_distance(lam_n, lam_c_n)
        multipliers_check = multiplier_distance(lam_n, lam_check_n)
        # the pair's distance from 1: its error, known exactly (estimate.trivial_multipliers);
        # the nontrivial ones are vouched for by degree p + 1 and DOP853, not by it (far from
        # the origin the pair is off by round-off in tangents that the others do not need)
        trivial_error = _off_one(trivial) if check else 0.0
        # eigenvalues carry round-off of about eps |Phi| each: a multiplier far below the
        # largest (its inverse, in a reversible system) is known no better than that
        roundoff = float(len(Phi) * np.finfo(float).eps * np.linalg.norm(Phi, 2)) if check else 0.0
        result = OrbitResult(
            scene=scene.name, parameters=scene.parameters(), mode=mode, period=T, mu=mu,
            t=list(T * s), x=x.tolist(), v=v.tolist(),
            multipliers=[[float(z.real), float(z.imag)] for z in lam],
            nontrivial_multipliers=[[float(z.real), float(z.imag)] for z in
                                    sorted(lam_n, key=lambda z: abs(z - 1))],
            closure=closure, closure_relative=closure / (extent if extent > 0 else scale),
            newton=history, timings={"compile_s": self.compile_s + flow_compile_s,
                                     "guess_s": guess_s,
                                     "solve_s": solve_s, "check_s": check_s,
                                     "monodromy_s": flow_s},
            degree=p.degree, cells=p.mesh.cells,
            guess={"x0": list(map(float, x0)), "v0": list(map(float, v0)), "period": T0},
            energy=orbit_energy, energy_target=energy if mode == "energy" else None)
        if other is not None:
            result.estimate.update(_differences(result, other), degree=other.degree)
            result.timings["estimate_s"] = estimate_s
        if check:
            # the period of the exact orbit through the reported start (the return time of
            # DOP853's motion to the section through z(0) across the flow): the discrete orbit's
            # states differ in energy by its error, and periods by dT/dE times that (a pendulum
            # at p = 2: 126 times the degree p + 1 difference), so the estimate takes it in
            crossing = float(field(zT) @ direction)
            returned = (T - float((zT - z0) @ direction) / crossing) if crossing > 0 else None
            if returned is not None:
                result.estimate["period"] = max(result.estimate.get("period", 0.0),
                                                abs(returned - T))
            result.estimate["multipliers"] = max(multipliers_error, roundoff)
            result.estimate["multipliers_roundoff"] = roundoff
            result.timings["monodromy_cells"] = flow_cells
            result.estimate["trivial_multipliers"] = trivial_error
            lam_check = np.concatenate([trivial_check, lam_check_n])
            lam_check = lam_check[np.lexsort((lam_check.imag, -np.abs(lam_check)))]
            result.check = {"multipliers_dop853": [[float(z.real), float(z.imag)]
                                                   for z in lam_check],
                            "multipliers": multipliers_check, "period": returned}
        if check and not extent > COLLAPSE_TOL * scale:
            result.status = "failed"
            result.message = (f"the orbit collapsed onto an equilibrium: it moves by "
                              f"{extent:.3g} around {scale:.3g}; give a guess near an orbit "
                              "(--period near one, a larger amplitude in --x0, --v0)")
        elif check and extent <= SMALL_TOL * scale and not (
                abs(mu) * T <= MU_TOL and result.closure_relative <= CLOSURE_TOL):
            result.status = "failed"
            result.message = (f"the orbit is collapsing onto an equilibrium: it moves by only "
                              f"{extent:.3g} around {scale:.3g}, and "
                              + (f"the unfolding damping converged to mu = {mu:.3g}, not 0"
                                 if not abs(mu) * T <= MU_TOL else
                                 f"it does not close (|z(T) - z(0)| = {closure:.3g} by DOP853)")
                              + "; give a guess near an orbit (--period near one, a larger "
                              "amplitude in --x0, --v0)")
        elif check and not abs(mu) * T <= MU_TOL:
            result.status = "failed"
            result.message = (f"the unfolding damping converged to mu = {mu:.3g}, not 0: the "
                              "guess is near no orbit of the undamped system (past flutter, or "
                              "a motion that is not periodic), or the mesh is too coarse for it; "
                              "give a better guess, or raise --cells or --degree")
        elif check and mode == "energy" and not (
                orbit_energy is not None and abs(orbit_energy - energy)
                <= ENERGY_TOL * max(abs(energy), _kinetic_scale(scene, v))):
            result.status = "failed"
            result.message = (f"the orbit's energy is {orbit_energy:.12g}, not {energy:.12g}; "
                              "raise --cells or give a guess nearer that energy")
        elif check and folds:
            k = folds[-1]
            result.status = "failed"
            result.message = (f"the orbit closes after T/{k} = {T / k:.12g} already: it runs "
                              f"{k} times around an orbit of period {T / k:.12g}; give --period "
                              f"near {T / k:.6g}")
        elif check and not result.closure_relative <= CLOSURE_TOL:
            result.status = "failed"
            result.message = (f"the orbit does not close: |z(T) - z(0)| = {closure:.3g} "
                              f"({result.closure_relative:.3g} relative) by DOP853 from its start; "
                              "raise --cells or --degree, or give a better guess")
        elif check and not max(multipliers_error, multipliers_check, roundoff) <= MULTIPLIER_TOL \
                and roundoff > 0.1 * MULTIPLIER_TOL:
            result.status = "failed"
            result.message = (f"the Floquet multipliers span more than double precision resolves: "
                              f"|monodromy| = {np.linalg.norm(Phi, 2):.3g}, so each multiplier "
                              f"is known only to about {roundoff:.3g} (degree p and p + 1 differ "
                              f"by {multipliers_error:.3g}, fem-dual and DOP853 by "
                              f"{multipliers_check:.3g}); no resolution helps: the orbit is this "
                              "unstable (a shorter orbit of the family is less so)")
        elif check and not max(multipliers_error, multipliers_check) <= MULTIPLIER_TOL:
            result.status = "failed"
            result.message = (f"the Floquet multipliers are uncertain: degree p and p + 1 differ "
                              f"by {multipliers_error:.3g}, fem-dual and DOP853 by "
                              f"{multipliers_check:.3g} (relative to 1 + |multiplier|); "
                              + (f"the orbit lies at {scale:.3g}, {scale / extent:.3g} times "
                                 "its extent, where the tangents of fem-dual's slabs lose "
                                 "digits to round-off: shift the coordinates to put its centre "
                                 "near the origin (the force of x + c)"
                                 if scale > OFFSET_RATIO * extent else
                                 "raise --cells or --degree"))
        return result



def _off_one(trivial: np.ndarray) -> float:
    """The trivial pair's largest distance from 1, relative to 1 + |1| as the others'."""
    return float(np.abs(trivial - 1).max() / 2)
