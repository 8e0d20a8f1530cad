"""One orbit, or a family of orbits along a scene parameter (each from the one before): the JSON
object of `fem-dual orbit`."""
from __future__ import annotations

import signal
import time
from typing import Any, Dict, List, Optional, Tuple

import numpy as np

from fem_dual import faults
from fem_dual.errors import SolveError
from fem_dual.analysis.orbit_input import Energy
from fem_dual.analysis.orbit.advice import _orbit_advice
from fem_dual.analysis.orbit.orbits import Orbits
from fem_dual.analysis.orbit.result import OrbitResult

__all__ = ["orbit_family"]

# what a continuation keeps of each orbit, besides its parameter's value and its start
_STEP_KEYS = ("period", "mu", "multipliers", "nontrivial_multipliers", "check", "closure",
              "closure_relative", "energy", "estimate", "status", "message", "newton", "timings")


def orbit_family(scene, params: Dict[str, Any], x0: np.ndarray, v0: np.ndarray, T0: float,
                 degree: int, cells: int, mode: str = "closest", energy: Optional[float] = None,
                 continuation: Optional[Tuple[str, np.ndarray]] = None,
                 with_estimate: bool = True, progress=None) -> Dict[str, Any]:
    """One orbit (`continuation` None) or a family along a parameter, each orbit started from
    the previous one; `progress(line)` hears of each step of a continuation. Returns the JSON
    object; its "status" is "ok" or "failed" (with "message"), what was computed before a
    failure kept."""
    has = Energy.of(scene, x0) if mode == "energy" else None
    orbits = Orbits(scene, degree, cells, has)
    companion = Orbits(scene, degree + 1, cells, has) if with_estimate else None
    try:
        out, steps = _follow(orbits, companion, scene, params, (x0, v0, T0), mode, energy,
                             continuation, progress)
    finally:
        orbits.close()
        if companion is not None:
            companion.close()
    if continuation is not None:
        out["continuation"] = steps
        out["continuation_parameter"] = continuation[0]
        out.setdefault("status", "ok")
    return out


def _follow(orbits: Orbits, companion: Optional[Orbits], scene, params: Dict[str, Any], start,
            mode: str, energy: Optional[float], continuation: Optional[Tuple[str, np.ndarray]],
            progress) -> Tuple[Dict[str, Any], List[Dict[str, Any]]]:
    """(out, steps): the orbits along `continuation` (or the one orbit) from the guess `start`
    (x0, v0, T0), each from the one before; `out` holds the last in full, or why the
    continuation stopped. Raises for the one orbit."""
    from fem_dual.inputs import scene_of

    x0, v0, T0 = start
    out: Dict[str, Any] = {}
    steps: List[Dict[str, Any]] = []
    values = [None] if continuation is None else continuation[1]
    for k, value in enumerate(values):
        signum = faults.requested()
        if k > 0 and signum:  # SIGINT/SIGTERM: stop after the orbit at hand
            out["status"], out["message"] = "interrupted", (
                f"interrupted by {signal.Signals(signum).name} before "
                f"{continuation[0]}={value:.6g}; the {k} orbits done are kept")
            break
        member = scene if value is None else scene_of(scene.name, {**params,
                                                                 continuation[0]: value})
        try:
            result = _member_orbit(orbits, companion, member, (x0, v0, T0), mode, energy, k == 0)
        except faults.Interrupted as exc:
            if continuation is None:
                raise
            out["status"], out["message"] = "interrupted", (
                f"{exc} at {continuation[0]}={value:.6g}; the {k} orbits done are kept")
            out.setdefault("scene", scene.name)
            break
        except SolveError as exc:
            exc = SolveError(_orbit_advice(str(exc)))
            if continuation is None:
                raise exc from None
            out["status"], out["message"] = "failed", (
                f"continuation stopped at {continuation[0]}={value:.6g} (its first value): "
                f"{exc}" if not steps else
                f"continuation stopped at {continuation[0]}={value:.6g} (last orbit at "
                f"{continuation[0]}={values[k - 1]:.6g}): {exc}; a smaller step may pass "
                "it, or this is a fold or bifurcation")
            out.setdefault("scene", scene.name)
            break
        record = result.to_dict()
        if continuation is None:
            out.update(record)
            break
        steps.append({continuation[0]: float(value), "x0": record["x"][0],
                      "v0": record["v"][0], **{key: record[key] for key in _STEP_KEYS}})
        out.update(record)  # the last orbit in full
        if progress is not None:
            progress(f"orbit {k + 1}/{len(values)}: {continuation[0]}={value:.6g}, period "
                     f"{result.period:.12g}, {result.status}")
        if result.status != "ok":
            out["message"] = (f"continuation stopped at {continuation[0]}={value:.6g}: "
                              f"{result.message}")
            break
        x0, v0, T0 = np.array(result.x[0]), np.array(result.v[0]), result.period
    return out, steps


def _member_orbit(orbits: Orbits, companion: Optional[Orbits], member, start, mode: str,
                  energy: Optional[float], first: bool) -> OrbitResult:
    """The orbit of the scene `member` from the guess `start` (x0, v0, T0), with its companion;
    the first of a family counts the companion's compilation."""
    x0, v0, T0 = start
    tic = time.perf_counter()
    guess = orbits.guess(member, x0, v0, T0)
    guess_s = time.perf_counter() - tic
    result = orbits.solve(member, x0, v0, T0, mode, energy, guess=guess, companion=companion)
    result.timings["guess_s"] = guess_s
    if companion is not None and first:
        result.timings["compile_s"] += companion.compile_s
    return result
