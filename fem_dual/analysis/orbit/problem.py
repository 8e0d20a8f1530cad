"""The periodic dual action of one orbit (the method: fem_dual.analysis.orbit), compiled once per
scene, degree and cells, and the merge of its periodic dofs."""
from __future__ import annotations

from typing import Any, Dict, Optional

import numpy as np
import ufl
from dolfinx import fem
from mpi4py import MPI
from scipy import sparse

from fem_dual.compat import (CellPointEvaluator, compile_form, constant, function_space,
                             vector_space)
from fem_dual.errors import InputError
from fem_dual.analysis.orbit_input import Energy
from fem_dual.slab.problem import SlabProblem
from fem_dual.slab.recovery import CellMomenta
from fem_dual.meshes import slab_mesh

__all__ = ["OrbitProblem", "_periodic_merge"]


class OrbitProblem(SlabProblem):
    """The periodic dual action of one orbit (see fem_dual.analysis.orbit), with its derivatives
    in the period T and the unfolding rate mu, compiled once per scene, degree and cells."""

    def __init__(self, scene, degree: int, cells: int, comm: MPI.Comm = MPI.COMM_SELF,
                 energy: Optional[Energy] = None):
        if getattr(scene.forms, "extra_dual", 0):
            raise InputError(f"scene {scene.name} is lifted (extra dual fields); its orbits are "
                             "those of curl2d: use that scene")
        self.scene, self.degree, self.comm, self.base = scene, degree, comm, "orbit"
        self.n = n = scene.n
        self.mesh = slab_mesh(comm, cells)
        msh = self.mesh.msh
        self.W = vector_space(msh, degree, 2 * n)
        self.w = fem.Function(self.W, name="dual")
        self.c = {k: constant(msh, v) for k, v in scene.constants().items()}
        self.T_c, self.mu_c = constant(msh, 1.0), constant(msh, 0.0)
        T, mu = ufl.variable(self.T_c), ufl.variable(self.mu_c)
        self.dt, self.mu, self.extra = T, mu, None
        self.t0 = constant(msh, 0.0)
        base = vector_space(msh, degree + 1, n)
        self.xbar, self.vbar = fem.Function(base), fem.Function(base)
        self.xb, self.vb, self.Zbar = self.xbar, self.vbar, None  # the base state in the UFL
        nodes = function_space(msh, ("Lagrange", degree + 1))
        self.base_nodes = nodes.tabulate_dof_coordinates()[:, 0]  # s of the base state's nodes
        w = self.w
        self.xi = ufl.as_vector([w[i] for i in range(n)])
        self.eta = ufl.as_vector([w[n + i] for i in range(n)])
        self.dxi = ufl.as_vector([w[i].dx(0) for i in range(n)]) / T
        self.deta = ufl.as_vector([w[n + i].dx(0) for i in range(n)]) / T
        f, c = scene.forms, self.c
        self.time = T * ufl.SpatialCoordinate(msh)[0]
        qdeg = scene.quadrature_degree(degree)
        self.force = lambda x: f.force(x, c)  # noqa: E731
        self.aux = lambda dx_, dv_: f.aux_potential(dx_, dv_, c)  # noqa: E731
        self.pointwise = None
        self.xhat, self.vhat, self.L_d = self._reduced_lagrangian(qdeg)
        self.hamiltonian = self.hamiltonian_of(self.xhat, self.vhat)
        self.dx = ufl.Measure("dx", domain=msh, metadata={"quadrature_degree": qdeg})
        self.bcs = []

        density = self.L_d * T
        test, trial = ufl.TestFunction(self.W), ufl.TrialFunction(self.W)
        self.residual = ufl.derivative(density * self.dx, w, test)
        self.jacobian = ufl.derivative(self.residual, w, trial)
        params = {"T": T, "mu": mu}
        forms: Dict[str, Any] = {"R": self.residual, "J": self.jacobian}
        for a, va in params.items():
            first = ufl.diff(density, va)
            forms[f"S_{a}"] = first * self.dx
            forms[f"R_{a}"] = ufl.derivative(first * self.dx, w, test)
            for b, vb in params.items():
                forms[f"S_{a}{b}"] = ufl.diff(first, vb) * self.dx
        if energy is not None and not energy.linear:
            # the energy averaged over the orbit (constant along an exact one), and its
            # derivatives: the row of a prescribed energy
            E = energy.ufl(self.xhat, self.vhat, self.force, c["M"])
            forms["E"] = E * self.dx
            forms["R_E"] = ufl.derivative(E * self.dx, w, test)
            for a, va in params.items():
                forms[f"E_{a}"] = ufl.diff(E, va) * self.dx
        self.forms = {k: compile_form(v) for k, v in forms.items()}
        self.momenta = CellMomenta(self)
        self._periodic = _periodic_merge(self.W, degree)
        self._base_eval = None

    def set_base(self, z_nodes: np.ndarray) -> None:
        """The base state from the guess at the base nodes (rows in `base_nodes` order)."""
        n = self.n
        self.xbar.x.array.reshape(-1, n)[:] = z_nodes[:, :n]
        self.vbar.x.array.reshape(-1, n)[:] = z_nodes[:, n:]

    def start_dtp(self) -> None:
        """An implicit DtP map starts its pointwise Newton from the base state (the DtP image of
        the zero dual state)."""
        pw = self.pointwise
        if pw is None:
            return
        if self._base_eval is None:
            self._base_eval = CellPointEvaluator(ufl.as_vector(list(self.xbar)), pw.points)
        pw.X.x.array.reshape(-1, self.n)[pw.dofs] = self._base_eval(pw.cells)

    def close(self) -> None:
        self.momenta.close()


def _periodic_merge(W: fem.FunctionSpace, degree: int) -> sparse.csr_matrix:
    """P (dofs x periodic dofs): the dofs of the node at s = 1 are those of the node at s = 0."""
    msh = W.mesh
    s = function_space(msh, ("Lagrange", degree)).tabulate_dof_coordinates()[:, 0]
    bs = W.dofmap.index_map_bs
    first, last = int(np.argmin(s)), int(np.argmax(s))
    nodes = len(s)
    node_map = np.arange(nodes)
    node_map[last] = first
    keep = np.delete(np.arange(nodes), last)
    reduced = np.full(nodes, -1)
    reduced[keep] = np.arange(len(keep))
    target = reduced[node_map]
    rows = np.arange(nodes * bs)
    cols = (target[:, None] * bs + np.arange(bs)).ravel()
    return sparse.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(nodes * bs, len(keep) * bs))
