"""Beck's column: a Timoshenko cantilever under a tangential follower load at its tip.

Transverse deflection w(x) and cross-section rotation theta(x) on 0 <= x <= L, clamped at
x = 0 (w = theta = 0), free at x = L, where a compressive load P acts along the tangent w'(L) of
the deflected axis. Linearised about the straight column, with dw, dtheta the test functions:

    m(u, du)   = int rhoA w dw + rhoI theta dtheta                               (mass)
    k_el(u, du) = int EI theta' dtheta' + int_red kGA (w' - theta)(dw' - dtheta)   (elastic)
    k_g(u, du)  = int w' dw'                          (geometric: the dead part of P)
    k_f(u, du)  = w'(L) dw(L)                         (follower: the load turns with w'(L))
    K(P) = K_el - P K_g + P K_f                       (follower load)
    K(P) = K_el - P K_g                               (dead load, for the buckling check)

The transverse component -P w'(L) of the follower force does the virtual work
-P w'(L) dw(L), hence +P K_f on the left-hand side; K_f is rank one and makes K(P)
non-symmetric. The dead-load column buckles at P = pi^2 EI / (4 L^2); the follower-load column
never diverges and flutters at P = 20.0509536 EI/L^2 (Beck 1952; Bolotin 1963) in the
Euler-Bernoulli limit kGA -> inf. The default kGA = 1e7 EI/L^2 is that limit to a few 1e-6:
its shear flexibility lowers omega_1 by 2.3e-7, omega_2 by 1.6e-6 and the flutter load by
3.1e-6 (relative).

Both fields are Lagrange of `degree` (default P2) on `elements` cells. int_red is Gauss
quadrature with `degree` points per cell (two for P2: quadrature degree 2 degree - 1), which
keeps the shear term from locking. With rhoI = 0 theta carries no mass and is condensed
statically (:mod:`fem_dual.continua.condense`).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Dict

import numpy as np
import ufl
from dolfinx import fem, mesh
from mpi4py import MPI
from petsc4py import PETSc

from fem_dual.compat import constant, equispaced_coordinates
from fem_dual.continua.parameters import check_fields
from fem_dual.continua.system import SpatialSystem
from fem_dual.errors import InputError

__all__ = ["BeckParameters", "BeckColumn", "LOADS", "TIP", "shear_quadrature_degree"]

LOADS = ("follower", "dead")
TIP = 1  # the facet tag of x = L


@dataclass(frozen=True)
class BeckParameters:
    """Beck's column. EI bending stiffness, rhoA mass per length, rhoI rotary inertia per length
    (0: theta massless, M singular, use the condensed system), kGA shear stiffness, L length,
    P the tip load (compressive > 0), elements cells of Lagrange `degree`, load "follower"
    (Beck) or "dead" (Euler).

    The default of 100 P2 cells puts the flutter load within 1e-4 of Beck's value and
    omega_1, omega_2 within 1e-5 (see tests/continua/test_beck.py).
    """

    EI: float = 1.0
    rhoA: float = 1.0
    rhoI: float = 0.0
    kGA: float = 1.0e7
    L: float = 1.0
    P: float = 0.0
    elements: int = 100
    degree: int = 2
    load: str = "follower"

    def __post_init__(self):
        check_fields(self, "beck", choices={"load": LOADS})
        for name in ("EI", "rhoA", "kGA", "L"):
            if getattr(self, name) <= 0:
                raise InputError(f"beck: {name} must be positive, got {getattr(self, name)!r}")
        if self.rhoI < 0:
            raise InputError(f"beck: rhoI must be >= 0, got {self.rhoI!r}")


def shear_quadrature_degree(degree: int) -> int:
    """The quadrature degree of `degree`-point Gauss on an interval (basix takes
    (q + 2) // 2 Gauss-Jacobi points for degree q)."""
    return 2 * degree - 1


class BeckColumn:
    """Mesh, space, clamping and forms of Beck's column, and its :class:`SpatialSystem`.

    Attributes:
        params: the :class:`BeckParameters`.
        msh, W: the interval mesh and the mixed space (w, theta) (field 0 is w, field 1 theta).
        constants: the ``fem.Constant`` of EI, rhoA, rhoI, kGA and P in the forms.
        forms: UFL forms ``m, k_el, k_b, k_g, k_f, k`` (k_b = the bending part of k_el; k is
            K(P) of the chosen load with P the constant ``constants["P"]``).
        system: M, K(P) (no damping) on the free dofs of W.
    """

    def __init__(self, params: BeckParameters = BeckParameters(), comm: MPI.Comm = MPI.COMM_WORLD):
        self.params = params
        self.msh = mesh.create_interval(comm, params.elements, [0.0, params.L])
        equispaced_coordinates(self.msh)  # (stable signatures: fem_dual.compat)
        element = ufl.FiniteElement("Lagrange", self.msh.ufl_cell(), params.degree)
        self.W = fem.FunctionSpace(self.msh, ufl.MixedElement([element, element]))
        self.constants = {name: constant(self.msh, getattr(params, name))
                          for name in ("EI", "rhoA", "rhoI", "kGA", "P")}
        self.forms = self._forms()
        self.system = SpatialSystem(self.W, self._clamped_dofs(), self.forms["m"],
                                    self.forms["k"])

    def _at(self, x0: float):
        tol = 1e-10 * self.params.L
        return mesh.locate_entities_boundary(self.msh, 0, lambda x: np.abs(x[0] - x0) < tol)

    def _clamped_dofs(self):
        left = self._at(0.0)
        return [fem.locate_dofs_topological(self.W.sub(i), 0, left) for i in range(2)]

    def measures(self) -> Dict[str, ufl.Measure]:
        """dx, the reduced shear measure dx_red, and ds with the tip tagged :data:`TIP`."""
        tip = self._at(self.params.L)
        tags = mesh.meshtags(self.msh, 0, tip, np.full(tip.size, TIP, dtype=np.int32))
        q = shear_quadrature_degree(self.params.degree)
        return {"dx": ufl.dx(domain=self.msh),
                "dx_red": ufl.dx(domain=self.msh, metadata={"quadrature_degree": q}),
                "ds": ufl.Measure("ds", domain=self.msh, subdomain_data=tags)}

    def _forms(self) -> Dict[str, ufl.Form]:
        c, d = self.constants, self.measures()
        w, theta = ufl.split(ufl.TrialFunction(self.W))
        dw, dtheta = ufl.split(ufl.TestFunction(self.W))
        forms = {
            "m": c["rhoA"] * w * dw * d["dx"] + c["rhoI"] * theta * dtheta * d["dx"],
            "k_b": c["EI"] * theta.dx(0) * dtheta.dx(0) * d["dx"],
            "k_s": c["kGA"] * (w.dx(0) - theta) * (dw.dx(0) - dtheta) * d["dx_red"],
            "k_g": w.dx(0) * dw.dx(0) * d["dx"],
            "k_f": w.dx(0) * dw * d["ds"](TIP),
        }
        forms["k_el"] = forms["k_b"] + forms["k_s"]
        forms["k"] = forms["k_el"] - c["P"] * forms["k_g"]
        if self.params.load == "follower":
            forms["k"] = forms["k"] + c["P"] * forms["k_f"]
        return forms

    def stiffness(self, P: float) -> PETSc.Mat:
        """K(P) on the free dofs (a new matrix; the system's K stays at ``params.P``)."""
        saved = self.constants["P"].value.copy()
        self.constants["P"].value = P
        try:
            return self.system.assemble(self.system.forms["k"])
        finally:
            self.constants["P"].value = saved

    def parts(self) -> Dict[str, PETSc.Mat]:
        """The free-dof matrices K_el, K_g, K_f (and K_b, the bending part of K_el)."""
        return {"K" + name[1:]: self.system.assemble(self.forms[name])
                for name in ("k_el", "k_b", "k_g", "k_f")}

    def w_dofs(self) -> np.ndarray:
        """Positions of the w dofs in this rank's free vector (field 0)."""
        return np.flatnonzero(self.system.field == 0)

    def theta_dofs(self) -> np.ndarray:
        """Positions of the theta dofs in this rank's free vector (field 1)."""
        return np.flatnonzero(self.system.field == 1)
