"""The input of `fem-dual orbit` that is checked before anything heavy is imported: the mode,
the continuation, the resolution of the guess, and the energy of a scene (fem_dual.analysis.orbit builds
on them). Bad input answers here without loading DOLFINx or PETSc.
"""
from __future__ import annotations

from typing import List, Optional, Tuple

import numpy as np

from fem_dual.errors import InputError
from fem_dual.scenes.base import STATE_MAX

__all__ = ["MODES", "parse_mode", "parse_continuation", "check_resolution", "Energy",
           "energy_matrices"]

MODES = ("closest", "period", "energy")


def parse_mode(text: str) -> Tuple[str, Optional[float]]:
    """("closest" | "period" | "energy", E or None) from --mode; InputError naming the value."""
    from fem_dual.scenes.base import parse_number

    name, sep, value = str(text).partition("=")
    if name not in MODES or (name == "energy") != bool(sep):
        raise InputError(f"mode={text!r} is not one of closest, period, energy=E")
    # any finite E: a potential from V(0) = 0 can be negative (a linear scene's E > 0 is
    # checked with the scene)
    return name, parse_number("energy", value) if sep else None


def energy_matrices(scene) -> Optional[Tuple[np.ndarray, np.ndarray]]:
    """(M, K) of a scene whose motion keeps E = 1/2 v.M v + 1/2 x.K x (linear, K symmetric,
    undamped), or None."""
    if not getattr(scene, "linear", False):
        return None
    K, D = scene.stiffness_matrix(), scene.damping_matrix()
    if np.any(D) or not np.allclose(K, K.T, rtol=0.0, atol=1e-14 * np.abs(K).max()):
        return None
    return scene.mass_matrix(), 0.5 * (K + K.T)


# The potential of a force with a symmetric Jacobian is the line integral from the origin,
# V(x) = -int_0^1 F(s x).x ds. In the forms it is a Gauss-Legendre rule on [0, 1]: the fewest of
# POTENTIAL_RULES points that agrees with adaptive quadrature (scipy's quad) to POTENTIAL_TOL at
# the sample points (fast forces need more; a force singular at the origin has no potential
# from there: no energy). The reported energy is quad's.
POTENTIAL_RULES = (12, 24, 48, 96)
POTENTIAL_TOL = 1e-11  # relative to |V| + |F(x)| |x|, the integrand's scale
SYMMETRY_TOL = 1e-6  # |DF - DF^T| / (1 + |DF|) above this at a sample point: no potential


def _gauss_01(points: int) -> Tuple[np.ndarray, np.ndarray]:
    s, w = np.polynomial.legendre.leggauss(points)
    return 0.5 * (s + 1.0), 0.5 * w


def _potential(force, x: np.ndarray) -> Optional[Tuple[float, float]]:
    """(V(x), the integrand's scale) by adaptive quadrature, or None when the line integral
    from the origin is not finite or quad cannot vouch for it (a divergent or badly behaved
    integrand; round-off that stops it short of its tolerance is fine when its error is)."""
    import warnings

    from scipy.integrate import quad

    x = np.asarray(x, float)
    with warnings.catch_warnings(record=True) as caught, np.errstate(all="ignore"):
        warnings.simplefilter("always")
        try:
            value, error = quad(lambda s: -float(force(s * x) @ x), 0.0, 1.0, limit=200,
                                epsabs=0.0, epsrel=1e-13)
        except (ArithmeticError, ValueError):
            return None
        scale = abs(value) + float(np.abs(force(x)).max() * np.abs(x).max())
    if any("roundoff error is detected, which prevents" not in str(w.message) for w in caught):
        return None
    if not (np.isfinite(value) and np.isfinite(scale)
            and error <= POTENTIAL_TOL * max(scale, 1e-300)):
        return None
    return value, scale


def _gauss_potential(force, x: np.ndarray, points: int) -> float:
    s, w = _gauss_01(points)
    with np.errstate(all="ignore"):
        return -float(sum(wq * force(sq * x) @ x for sq, wq in zip(s, w)))


class Energy:
    """E = 1/2 v.M v + V(x) of a scene that keeps it: linear (K symmetric, undamped; V =
    1/2 x.K x) or a force with a potential (its Jacobian symmetric: V by the line integral
    from the origin, `points` Gauss-Legendre points in the forms). `of` returns None for the
    others (curl forces, damping, a potential that is singular at the origin)."""

    def __init__(self, scene, matrices=None, points: int = POTENTIAL_RULES[0]):
        self.scene, self.matrices, self.points = scene, matrices, points
        self.linear = matrices is not None

    @classmethod
    def of(cls, scene, x0: np.ndarray) -> Optional["Energy"]:
        return cls.find(scene, x0)[0]

    @classmethod
    def find(cls, scene, x0: np.ndarray) -> Tuple[Optional["Energy"], str]:
        """(the scene's Energy, "") or (None, why it has none, in words)."""
        matrices = energy_matrices(scene)
        if matrices is not None:
            return cls(scene, matrices), ""
        if getattr(scene, "linear", True):
            return None, "a linear scene needs K symmetric and no damping"
        from fem_dual.slab.base_state import force_jacobian

        rng = np.random.default_rng(0)
        radius = max(1.0, float(np.abs(x0).max()))
        samples = [np.asarray(x0, float)] + list(radius * rng.uniform(-1, 1, (8, scene.n)))
        references = []
        for x in samples:
            where = f"at x = {[float(f'{c:.6g}') for c in x]}"
            with np.errstate(all="ignore"):
                J = force_jacobian(scene.force_numpy, x)
            if not np.all(np.isfinite(J)) or \
                    np.abs(J - J.T).max() > SYMMETRY_TOL * (1.0 + np.abs(J).max()):
                return None, (f"the force's Jacobian is not symmetric (or not finite) {where}: "
                              "no potential")
            reference = _potential(scene.force_numpy, x)
            if reference is None:
                return None, ("the potential V(x) = -int_0^1 F(sx).x ds (from the origin) is "
                              f"not finite {where}, or adaptive quadrature cannot vouch for it")
            references.append(reference)
        for points in POTENTIAL_RULES:
            if all(abs(_gauss_potential(scene.force_numpy, x, points) - value)
                   <= POTENTIAL_TOL * scale for x, (value, scale) in zip(samples, references)):
                return cls(scene, points=points), ""
        return None, ("the force varies too fast along the lines from the origin to the sample "
                      f"points (within {radius:.3g} of it) for a {POTENTIAL_RULES[-1]}-point "
                      f"Gauss rule of its potential (to {POTENTIAL_TOL:g}); a guess nearer the "
                      "origin may pass")

    def value(self, x: np.ndarray, v: np.ndarray) -> Optional[float]:
        """E at one state (numpy; None where the potential cannot be integrated)."""
        M = self.scene.mass_matrix()
        kinetic = 0.5 * float(v @ M @ v)
        if self.linear:
            return kinetic + 0.5 * float(x @ self.matrices[1] @ x)
        potential = _potential(self.scene.force_numpy, x)
        return None if potential is None else kinetic + potential[0]

    def ufl(self, x, v, force, M):
        """E(x, v) in UFL, `force` the scene's UFL force (a function of the position)."""
        import ufl

        s, w = _gauss_01(self.points)
        potential = -sum(float(wq) * ufl.dot(force(float(sq) * x), x) for sq, wq in zip(s, w))
        return 0.5 * ufl.dot(v, ufl.dot(M, v)) + potential


MAX_RADIANS_PER_CELL = 8.0  # a guess that turns faster than this per cell cannot be resolved


STATE_RANGE = (1e-150, STATE_MAX)  # an orbit's: it divides by its size as well


def check_resolution(scene, x0: np.ndarray, v0: np.ndarray, T0: float, cells: int) -> None:
    """InputError when the start state is beyond STATE_RANGE, or when the guess turns more than
    MAX_RADIANS_PER_CELL per cell at its start rate (its motion could not be resolved, and the
    guess run alone would take that long)."""
    from fem_dual.slab.base_state import motion_rate

    size = float(np.abs(np.concatenate([x0, v0])).max())
    if size > 0 and not STATE_RANGE[0] <= size <= STATE_RANGE[1]:
        raise InputError(f"x0={','.join(map(repr, map(float, x0)))}, v0="
                         f"{','.join(map(repr, map(float, v0)))}: a start of size {size:.3g} is "
                         f"beyond {STATE_RANGE[0]:g} .. {STATE_RANGE[1]:g}, where the action's "
                         "squares of the state stay in double precision; rescale the coordinates")

    if scene.linear:
        from fem_dual.reference import first_order_matrix

        A = first_order_matrix(scene.mass_matrix(), scene.stiffness_matrix(),
                               scene.damping_matrix())
        a0 = (A @ np.concatenate([x0, v0]))[scene.n:]
    else:
        a0 = np.linalg.solve(scene.mass_matrix(), scene.force_numpy(x0))
    if not np.any(v0) and not np.any(a0):
        raise InputError(f"x0={list(map(float, x0))}, v0=0 is an equilibrium: no orbit starts "
                         "there; give a start on the orbit")
    turns = motion_rate(x0, v0, a0) * T0 / cells
    if not turns <= MAX_RADIANS_PER_CELL:
        raise InputError(f"period={T0:g} spans {turns:.3g} radians per cell of the guess's "
                         f"motion over {cells} cells (at most {MAX_RADIANS_PER_CELL:g}); give the "
                         "period of one orbit, or raise --cells")


def parse_continuation(text: str, scene) -> Tuple[str, np.ndarray]:
    """(NAME, values) from NAME=a:b:steps (steps + 1 values from a to b); InputError naming the
    bad piece. NAME must be a number parameter of the scene."""
    from fem_dual.scenes.base import parse_number

    name, sep, rng = str(text).partition("=")
    name = name.strip()
    parts = rng.split(":")
    if not sep or len(parts) != 3:
        raise InputError(f"--continue {text!r} is not NAME=START:STOP:STEPS")
    if name not in _number_parameters(scene):
        raise InputError(f"--continue {name!r} is not a number parameter of {scene.name} "
                         f"(those are: {', '.join(_number_parameters(scene))})")
    a, b = parse_number("continuation start", parts[0]), parse_number("continuation stop",
                                                                       parts[1])
    steps = parse_number("continuation steps", parts[2])
    if not (steps >= 1 and steps == int(steps) and steps <= 10_000):
        raise InputError(f"continuation steps={parts[2]!r} must be a whole number in 1..10000")
    if a == b:
        raise InputError(f"--continue {text!r}: start and stop are equal")
    return name, np.linspace(a, b, int(steps) + 1)


def _number_parameters(scene) -> List[str]:
    """The scene's parameters that are one number (a user force's own ones included)."""
    return [k for k, v in scene.parameters().items()
            if isinstance(v, (int, float, np.floating)) and not isinstance(v, bool)]
