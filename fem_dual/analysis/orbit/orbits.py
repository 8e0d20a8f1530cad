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
from fem_dual.analysis.floquet import (CHECK_TOL, FLOW_START_CELLS, MAX_FOLD, SlabFlow,
                                      monodromy)
from fem_dual.analysis.orbit_input import Energy
from fem_dual.analysis.orbit.advice import _orbit_advice
from fem_dual.analysis.orbit.energy import reach_energy
from fem_dual.analysis.orbit.guess import GuessMotion, OrbitGuess
from fem_dual.analysis.orbit.multipliers import (FlowMultipliers, MultiplierErrors,
                                                 multiplier_errors, refine_multipliers,
                                                 sorted_multipliers)
from fem_dual.analysis.orbit.newton import OrbitSolver
from fem_dual.analysis.orbit.problem import OrbitProblem
from fem_dual.analysis.orbit.result import OrbitResult, _differences
from fem_dual.analysis.orbit.verdict import CLOSURE_TOL, verdict

__all__ = ["Orbits", "BASE_RESTARTS"]

BASE_RESTARTS = 4  # a failed Newton starts again on its last iterate's image, at most this often


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
        _check_mode(scene, mode, energy, has, p.forms)
        if scene is not self.scene:
            p.set_scene_constants(scene)
            self.scene = scene
        tic = time.perf_counter()
        if guess is None:
            guess = self.guess(scene, x0, v0, T0)
        guess_s = time.perf_counter() - tic
        tic = time.perf_counter()
        history, s, x, v, orbit_energy = self._find(scene, guess, T0, mode, energy, has)
        solve_s = time.perf_counter() - tic
        T, mu = float(p.T_c.value), float(p.mu_c.value)
        z0 = np.concatenate([x[0], v[0]])
        tic = time.perf_counter()
        other = None  # the same orbit at degree p + 1, from the same guess
        if companion is not None and check:
            other = _companion_orbit(companion, scene, (x0, v0, T0, guess), history, (s, x, v, T),
                                     mode, energy)
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
        flow = refine_multipliers(self.flow, scene, z0, T, min(p.mesh.cells, FLOW_START_CELLS),
                                  other, extent, Phi_check, check)
        flow_compile_s = self.flow.new_setup_s()
        flow_s = time.perf_counter() - tic - flow_compile_s
        closure = float(np.abs(zT - z0).max())
        folds = [k for k, z in enumerate(parts, start=2)
                 if np.abs(z - z0).max() <= CLOSURE_TOL * extent]
        errors = multiplier_errors(flow, Phi_check, check)
        lam = sorted_multipliers(flow.trivial, flow.nontrivial)
        result = OrbitResult(
            scene=scene.name, parameters=scene.parameters(), mode=mode, period=T, mu=mu,
            t=list(T * s), x=x.tolist(), v=v.tolist(),
            multipliers=[[float(z.real), float(z.imag)] for z in lam],
            nontrivial_multipliers=[[float(z.real), float(z.imag)] for z in
                                    sorted(flow.nontrivial, key=lambda z: abs(z - 1))],
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
            _record_check(result, flow, errors, z0, zT)
            result.status, result.message = verdict(result, scene, v, extent, scale, folds,
                                                    errors, flow.Phi)
        return result

    def _find(self, scene, guess, T0: float, mode: str, energy: Optional[float],
              has: Optional[Energy]):
        """(history, s, x, v, energy): the orbit from the guess (a run over T0) in `mode`, polished
        on itself, and its energy (None without one)."""
        # a linear family has one period: its orbits of energy E are the closest one scaled
        linear_energy = mode == "energy" and has.linear
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
        return history, s, x, v, orbit_energy


def _check_mode(scene, mode: str, energy: Optional[float], has: Optional[Energy],
                forms) -> None:
    """InputError where `mode` cannot run for `scene` (energy `has`) on orbits compiled with
    `forms`."""
    if mode == "energy" and has is None:
        raise InputError(f"mode energy needs a scene with an energy (linear with K "
                         f"symmetric and no damping, or a force with a potential); "
                         f"{scene.name} has none")
    if mode == "energy" and has.linear and not energy > 0:
        raise InputError(f"energy={energy:g} must be positive for {scene.name} (its energy "
                         "1/2 v.M v + 1/2 x.K x)")
    if mode == "energy" and not has.linear and "E" not in forms:
        raise InputError("mode energy: these orbits were compiled without the energy row")


def _companion_orbit(companion: Orbits, scene, start, history, found, mode: str,
                     energy: Optional[float]) -> OrbitResult:
    """The orbit at degree p + 1 (`companion`), unchecked: from the guess `start` (x0, v0, T0,
    guess), or from the orbit `found` (s, x, v, T) where that was reached in stages."""
    x0, v0, T0, guess = start
    s, x, v, T = found
    if history.get("energy_stages") or "amplitude_steps" in history or \
            "base_restarts" in history:  # from the orbit found, not again in stages
        return companion.solve(scene, x[0], v[0], T, mode, energy, check=False,
                               guess=OrbitGuess(scene, T * s, x, v))
    return companion.solve(scene, x0, v0, T0, mode, energy, check=False, guess=guess)


def _record_check(result: OrbitResult, flow: FlowMultipliers, errors: MultiplierErrors,
                  z0: np.ndarray, zT: np.ndarray) -> None:
    """Into `result`: the estimates that the checks give (period, multipliers) and DOP853's
    multipliers and period (its motion from z0 reached zT at the period)."""
    T, field, direction = result.period, flow.field, flow.direction
    # the period of the exact orbit through the reported start (the return time of
    # DOP853's motion to the section through z(0) across the flow): the discrete orbit's
    # states differ in energy by its error, and periods by dT/dE times that (a pendulum
    # at p = 2: 126 times the degree p + 1 difference), so the estimate takes it in, with the
    # return time's own error (DOP853's tolerance, ten times, over the period)
    crossing = float(field(zT) @ direction)
    returned = (T - float((zT - z0) @ direction) / crossing) if crossing > 0 else None
    if returned is not None:
        result.estimate["period"] = max(result.estimate.get("period", 0.0),
                                        abs(returned - T) + 10 * CHECK_TOL * abs(T))
    result.estimate["multipliers"] = max(errors.error, errors.roundoff)
    result.estimate["multipliers_roundoff"] = errors.roundoff
    result.timings["monodromy_cells"] = flow.cells
    result.estimate["trivial_multipliers"] = errors.trivial
    result.check = {"multipliers_dop853": [[float(z.real), float(z.imag)]
                                           for z in errors.dop853],
                    "multipliers": errors.check, "period": returned}
