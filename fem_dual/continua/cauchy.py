"""Plane-strain Cauchy elasticity without major symmetry on the unit square.

Displacement u = (u1, u2), clamped on the whole boundary, in vector Lagrange of `degree` on an
`elements` x `elements` triangle mesh. In Voigt order eps_v = (eps11, eps22, 2 eps12) the stress
is sigma_v = (sigma11, sigma22, sigma12) = C eps_v with

        [ lam + 2 mu   lam + delta   0  ]
    C = [ lam - delta  lam + 2 mu    0  ] = C_s + delta C_a,   C_a = [[0, 1, 0], [-1, 0, 0],
        [ 0            0             mu ]                               [0, 0, 0]]

and the forms are

    k(u, w) = int (C eps_v(u)) . eps_v(w),     m(u, w) = rho int u . w,

so K = K_s + delta K_a with K_a antisymmetric: for delta != 0 K is not symmetric and the
stress does work around a closed strain cycle, -2 delta times the area the cycle encloses in
the (eps11, eps22) plane, per unit area. C_s is positive definite for mu > 0, lam + mu > 0, so
every eigenvalue of K x = lambda M x has Re lambda > 0 (x* K x has real part x* K_s x > 0): the
clamped square cannot diverge; it can flutter (complex lambda).

Real spectrum for |delta| <= lam + mu (on this clamped problem, any mesh, any degree). For
a, b in H^1_0, int a_,1 b_,2 = int a_,2 b_,1 (integrate by parts twice), and the discrete
functions are in H^1_0 and integrated exactly, so in blocks by component (test, trial)

    K = [[A_1, (lam + mu + delta) B], [(lam + mu - delta) B, A_2]],   M = rho [[M_0, 0], [0, M_0]]

with B_ij = int phi_j,2 phi_i,1 = B_ji symmetric, A_1, A_2 symmetric. For |delta| < lam + mu
the scaling S = diag(I, s I), s = sqrt((lam + mu - delta) / (lam + mu + delta)) gives
S^-1 K S = [[A_1, c B], [c B, A_2]] with c = sqrt((lam + mu)^2 - delta^2) <= lam + mu,
symmetric and positive definite (u^T S^-1 K S u >= mu int |grad u|^2), while S^-1 M S = M:
every eigenvalue is real and positive. At |delta| = lam + mu, K is block triangular and its
eigenvalues are those of (A_1, M) and (A_2, M), real and positive too
(:func:`real_spectrum_guaranteed`, :func:`symmetrizing_scale`). The plane-wave symbol of
-div(C eps(u)), [[(lam + 2 mu) k1^2 + mu k2^2, (lam + mu + delta) k1 k2], [(lam + mu - delta)
k1 k2, mu k1^2 + (lam + 2 mu) k2^2]], has real eigenvalues for every wave vector under the same
bound and complex ones beyond it. :func:`fem_dual.continua.spectrum.spectrum_check` computes
the spectrum itself.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import ufl
from dolfinx import fem, mesh
from mpi4py import MPI

from fem_dual.compat import constant, equispaced_coordinates
from fem_dual.continua.parameters import check_fields
from fem_dual.continua.spectrum import SpectrumCheck, spectrum_check
from fem_dual.continua.system import SpatialSystem
from fem_dual.errors import InputError

__all__ = ["CauchyParameters", "CauchyElasticity", "elasticity_matrix", "voigt_strain",
           "cauchy_forms", "real_spectrum_guaranteed", "symmetrizing_scale", "spectrum_check",
           "SpectrumCheck", "ANTISYMMETRIC"]

#: C_a: the part of C that delta multiplies
ANTISYMMETRIC = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])


@dataclass(frozen=True)
class CauchyParameters:
    """Lame constants lam, mu, the non-symmetric modulus delta, density rho; elements per side
    of the unit square, Lagrange degree."""

    lam: float = 1.0
    mu: float = 1.0
    delta: float = 0.0
    rho: float = 1.0
    elements: int = 16
    degree: int = 1

    def __post_init__(self):
        check_fields(self, "cauchy")
        if self.mu <= 0 or self.lam + self.mu <= 0 or self.rho <= 0:
            raise InputError("cauchy: needs mu > 0, lam + mu > 0 (positive symmetric part of C) "
                             f"and rho > 0, got lam={self.lam}, mu={self.mu}, rho={self.rho}")


def elasticity_matrix(lam: float, mu: float, delta: float) -> np.ndarray:
    """C of the module docstring (Voigt order eps11, eps22, 2 eps12)."""
    return np.array([[lam + 2 * mu, lam + delta, 0.0],
                     [lam - delta, lam + 2 * mu, 0.0],
                     [0.0, 0.0, mu]])


def real_spectrum_guaranteed(lam: float, mu: float, delta: float) -> bool:
    """|delta| <= lam + mu: the sufficient condition of the module docstring for a real,
    positive spectrum of the clamped problem."""
    return abs(delta) <= lam + mu


def symmetrizing_scale(lam: float, mu: float, delta: float) -> float:
    """s with diag(I, s I)^-1 K diag(I, s I) symmetric (module docstring), |delta| < lam + mu."""
    if not abs(delta) < lam + mu:
        raise ValueError(f"symmetrizing_scale: needs |delta| < lam + mu, got delta={delta}")
    return math.sqrt((lam + mu - delta) / (lam + mu + delta))


def voigt_strain(u) -> ufl.core.expr.Expr:
    """(eps11, eps22, 2 eps12) of a 2D displacement."""
    return ufl.as_vector([u[0].dx(0), u[1].dx(1), u[0].dx(1) + u[1].dx(0)])


def cauchy_forms(V: fem.FunctionSpace, C: fem.Constant, rho: fem.Constant):
    """(m, k): rho int u . w and int (C eps_v(u)) . eps_v(w) on V (2D vector space)."""
    u, w = ufl.TrialFunction(V), ufl.TestFunction(V)
    m = rho * ufl.inner(u, w) * ufl.dx
    k = ufl.inner(ufl.dot(C, voigt_strain(u)), voigt_strain(w)) * ufl.dx
    return m, k


class CauchyElasticity:
    """The clamped unit square: mesh, space, constants and :class:`SpatialSystem`.

    Attributes:
        msh, V: the triangle mesh and the vector Lagrange space.
        C, rho: the ``fem.Constant`` in the forms (C a 3 x 3 matrix); after changing them,
            ``system.refresh()`` assembles M and K again.
        system: M, K (no damping) on the free (interior) dofs.
    """

    def __init__(self, params: CauchyParameters = CauchyParameters(),
                 comm: MPI.Comm = MPI.COMM_WORLD):
        self.params = params
        n = params.elements
        self.msh = mesh.create_unit_square(comm, n, n)
        equispaced_coordinates(self.msh)  # (stable signatures: fem_dual.compat)
        self.V = fem.FunctionSpace(self.msh, ufl.VectorElement("Lagrange", self.msh.ufl_cell(),
                                                               params.degree))
        self.C = constant(self.msh, elasticity_matrix(params.lam, params.mu, params.delta))
        self.rho = constant(self.msh, params.rho)
        m, k = cauchy_forms(self.V, self.C, self.rho)
        self.system = SpatialSystem(self.V, [self._clamp()], m, k)

    def _clamp(self) -> fem.DirichletBCMetaClass:
        tdim = self.msh.topology.dim
        self.msh.topology.create_connectivity(tdim - 1, tdim)
        facets = mesh.exterior_facet_indices(self.msh.topology)
        dofs = fem.locate_dofs_topological(self.V, tdim - 1, facets)
        return fem.dirichletbc(np.zeros(2), dofs, self.V)

    def stiffness(self, C: np.ndarray):
        """The free-dof stiffness of another elasticity matrix C (the system keeps its own)."""
        saved = self.C.value.copy()
        self.C.value = np.asarray(C, dtype=np.float64)
        try:
            return self.system.assemble(self.system.forms["k"])
        finally:
            self.C.value = saved
