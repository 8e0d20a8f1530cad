"""Periodic orbits from the dual principle (`fem-dual orbit`).

Time is rescaled, s = t / T on [0, 1]: the slab problem of fem_dual.slab.problem with dt = T, dual
fields that are periodic (the dofs at s = 1 are those at s = 0) and no initial-condition term.
Varying the action then gives the equations of motion and x^(1) = x^(0), v^(1) = v^(0) as
natural conditions. The base state (xbar, vbar)(s) of H is the guess of the orbit; the
W-weighted integral phase condition against it is what periodic dual fields need to exist, so
the DtP map fixes the phase by itself, and an exact orbit as base state is solved by zero dual
fields.

Unknowns besides the dual fields: the period T (stationarity of the action in T), and mu, the
rate of an unfolding damping -mu M v added to the force (stationarity in mu). M x'' = F(x) is
reversible, so its symmetric orbits come in one-parameter families, where the system without mu
is singular; with mu, Newton converges to mu = 0 and the member of the family closest to the
base state. Modes:
- "closest": T and mu unknown, the rows dS/dT and dS/dmu (symmetric, indefinite);
- "period": T held at its guess, mu unknown;
- "energy": the energy E prescribed, for scenes that have one (Energy). A force with a
  potential (its Jacobian symmetric; V by the line integral from the origin, in UFL by
  Gauss-Legendre): the row of T becomes the energy averaged over the orbit minus E (one
  non-symmetric row); far from the guess's energy the closest orbit comes first, then steps in
  energy, each from the orbit before. A linear scene (K symmetric, undamped): its orbits of one
  period form families by amplitude, and the dual Hessian has a two-dimensional kernel there
  (both phases of the mode), where the energy row stays singular (measured: condition 2e16):
  the closest orbit is scaled to E, which is exact for a linear system.

Newton runs on the bordered second variation with the periodic dofs merged (sparse LU); it is
serial (an orbit's time mesh is small): under MPI rank 0 solves and the others wait.

The Floquet multipliers are the eigenvalues of the monodromy of fem-dual's own slabs
(SlabFlow): the product of the Jacobians of the slab maps along the orbit, with the degree p + 1
companion's product as their error estimate. An independent check follows: DOP853
(rtol = atol = 1e-13) integrates the undamped motion and its variational equation from the
orbit's start over one period; the closure |z(T) - z(0)| says whether the orbit closes, and its
monodromy's multipliers must agree with fem-dual's.
"""
from fem_dual.analysis.orbit_input import MODES, Energy, parse_mode
from fem_dual.analysis.orbit.advice import _orbit_advice  # noqa: F401 (its tests import it here)
from fem_dual.analysis.orbit.family import orbit_family
from fem_dual.analysis.orbit.newton import OrbitSolver
from fem_dual.analysis.orbit.orbits import Orbits
from fem_dual.analysis.orbit.problem import OrbitProblem
from fem_dual.analysis.orbit.report import orbit_summary, plot_orbit, write_orbit_files
from fem_dual.analysis.orbit.result import OrbitResult

__all__ = ["OrbitProblem", "OrbitResult", "OrbitSolver", "Orbits", "orbit_family",
           "orbit_summary", "write_orbit_files", "plot_orbit", "Energy", "MODES", "parse_mode"]
