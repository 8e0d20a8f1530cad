"""The dual action of one slab, built once per run from a scene's forms.

Unknown: w = (xi, eta) in one blocked Lagrange space of degree p on the reference slab mesh
s in [0, 1] (xi = first n components, eta = the next n). Physical time t = t0 + dt s, so
d/dt = (1/dt) d/ds and dt enters the forms as a fem.Constant, like the initial state (x0, v0) and
the base state (xbar, vbar) of H: changing slabs never recompiles a form.

    S[w] = int_0^1 L_d(xi, eta, xi', eta') dt ds - x0.xi(0) - (M v0).eta(0),
    residual = dS/dw [w_test],  Jacobian = d residual/dw [w_trial],   xi(1) = eta(1) = 0.
"""
from __future__ import annotations

import functools

from typing import Dict, Optional

import basix
import numpy as np
import ufl
from dolfinx import fem
from mpi4py import MPI
from petsc4py import PETSc

from fem_dual.slab.base_state import RK4_STEPS_PER_NODE, predictor
from fem_dual.compat import (constant, function_space, release_function_vector,
                             vector_space)
from fem_dual.slab.pointwise_dtp import PointwiseDtP
from fem_dual.scenes.base import Scene
from fem_dual.forms.predual import boundary_term, dual_hamiltonian, predual_lagrangian
from fem_dual.meshes import START, slab_mesh

__all__ = ["SlabProblem", "BASES"]

# The base state (xbar, vbar) of H on a slab: the slab's start state held constant ("start", the
# reference's time staging), or zero ("zero", the reference's own examples). Only the residual
# of the base state enters the slab action: a constant start state leaves the residual
# (-v0, -F(x0)/m), an O(omega) forcing that modes the cells do not resolve turn into growth;
# zero is an exact solution of a linear system, and its slab map damps unresolved modes.
# "predictor" (fem_dual.slab.base_state) is a function of time near the motion with a small residual;
# "rk4" one closer still, for motions that are not stiff (explicit Runge-Kutta).
from fem_dual.choices import BASES  # noqa: E402 -- named here, validated in config


class SlabProblem:
    """UFL of one slab's dual action and of the DtP image, with the constants that change per slab.

    Args:
        scene: the validated scene.
        degree: polynomial degree of the dual fields.
        cells: number of time cells per slab.
        comm: communicator the time mesh is distributed over.
        base: the base state of H (BASES).
        mesh: a slab mesh of `cells` cells to share (the error companion uses its partner's,
            so that its Newton can start from the partner's solution).
        shared_predictor: the predictor of a base state that is a function of time, to use
            instead of a new one (fem_dual.integrate.simulation.Simulation.companion).
    """

    def __init__(self, scene: Scene, degree: int, cells: int, comm: MPI.Comm = MPI.COMM_WORLD,
                 base: str = "start", mesh=None, shared_predictor=None):
        if base not in BASES:
            raise ValueError(f"base={base!r} is not one of {BASES}")
        self.scene, self.degree, self.comm, self.base = scene, degree, comm, base
        n = scene.n
        self.n = n
        self.mesh = mesh if mesh is not None else slab_mesh(comm, cells)  # shared: companion
        msh = self.mesh.msh
        extra = getattr(scene.forms, "extra_dual", 0)  # multipliers of a lifted scene
        self.W = vector_space(msh, degree, 2 * n + extra)
        self.w = fem.Function(self.W, name="dual")

        # Run constants (scene parameters) and per-slab constants.
        self.c: Dict[str, fem.Constant] = {k: constant(msh, v)
                                           for k, v in scene.constants().items()}
        zero = np.zeros(n)
        self.dt = constant(msh, 1.0)
        self.t0 = constant(msh, 0.0)
        self.x0, self.v0 = constant(msh, zero), constant(msh, zero)
        # their values as numpy views of the C++ storage the kernels read (0.5.2's
        # Constant.value setter takes 0.55 us, a view 0.08-0.24; four to eight a slab solve)
        self._slab_values = tuple(c._cpp_object.value for c in (self.dt, self.t0, self.x0,
                                                                 self.v0))
        self._base_state(shared_predictor, cells)
        self._dual_variables(extra)
        self._action()

    def _base_state(self, shared_predictor, cells: int) -> None:
        """The base state (xbar, vbar) of H: constants, or functions of time one degree above
        the duals (the predictor's), and where set_start writes it."""
        msh, n, base, degree, scene = self.mesh.msh, self.n, self.base, self.degree, self.scene
        zero = np.zeros(n)
        self.predictor = None
        if base in ("predictor", "rk4"):  # a function of time, one degree above the duals
            self.predictor = shared_predictor or predictor(
                scene, base, cells * (degree + 1) * RK4_STEPS_PER_NODE)
            space = vector_space(msh, degree + 1, n)
            self.xbar, self.vbar = fem.Function(space), fem.Function(space)
            # node coordinates of the scalar space: the blocked space's nodes, in its order
            # (0.5.2 cannot tabulate them for a one-component VectorElement)
            nodes = function_space(msh, ("Lagrange", degree + 1))
            self._base_times = nodes.tabulate_dof_coordinates()[:, 0]
        else:
            self.xbar, self.vbar = constant(msh, zero), constant(msh, zero)
        # where set_start writes the base state: the constants' values, or the functions'
        # nodal values (n per node)
        self._base_values = tuple(
            b._cpp_object.value if self.predictor is None else b.x.array.reshape(-1, n)
            for b in (self.xbar, self.vbar))
        # the base state in the UFL: a variable where it is a constant, so that the pointwise
        # assembly can differentiate the density in it (exact tangents of the slab map)
        self.Zbar = None if self.predictor is not None else ufl.variable(
            ufl.as_vector([*(self.xbar[i] for i in range(n)), *(self.vbar[i] for i in range(n))]))
        self.xb, self.vb = ((self.xbar, self.vbar) if self.Zbar is None else
                            (ufl.as_vector([self.Zbar[i] for i in range(n)]),
                             ufl.as_vector([self.Zbar[n + i] for i in range(n)])))

    def _dual_variables(self, extra: int) -> None:
        """xi, eta (and a lifted scene's multipliers) and their time derivatives in UFL."""
        n = self.n
        # The dual fields at a point, U = w, and their derivatives in s, Us = dw/ds, are UFL
        # variables: the forms differentiate through them (ufl.derivative in w), and the
        # pointwise assembly (fem_dual.slab.local_action) differentiates the density in them.
        w, bs = self.w, 2 * n + extra
        self.U = U = ufl.variable(ufl.as_vector([w[i] for i in range(bs)]))
        self.Us = Us = ufl.variable(ufl.as_vector([w[i].dx(0) for i in range(bs)]))
        self.xi = ufl.as_vector([U[i] for i in range(n)])
        self.eta = ufl.as_vector([U[n + i] for i in range(n)])
        self.dxi = ufl.as_vector([Us[i] for i in range(n)]) / self.dt
        self.deta = ufl.as_vector([Us[n + i] for i in range(n)]) / self.dt
        self.extra = ufl.as_vector([U[2 * n + i] for i in range(extra)]) if extra else None

    def _action(self) -> None:
        """The slab's action, its residual and Jacobian (UFL derivatives of it), and the
        Dirichlet conditions xi(T) = eta(T) = 0."""
        scene, msh, n, w = self.scene, self.mesh.msh, self.n, self.w
        f, c = scene.forms, self.c
        M = c["M"]
        self.time = self.t0 + self.dt * ufl.SpatialCoordinate(msh)[0]
        qdeg = scene.quadrature_degree(self.degree)
        self.force = lambda x: f.force(x, c)  # noqa: E731
        self.aux = lambda dx_, dv_: f.aux_potential(dx_, dv_, c)  # noqa: E731
        self.pointwise: Optional[PointwiseDtP] = None
        self.xhat, self.vhat, self.L_d = self._reduced_lagrangian(qdeg)
        self.hamiltonian = self.hamiltonian_of(self.xhat, self.vhat)

        self.quadrature_degree = qdeg
        self.dx = ufl.Measure("dx", domain=msh, metadata={"quadrature_degree": qdeg})
        ds = ufl.Measure("ds", domain=msh, subdomain_data=self.mesh.tags)
        self.initial = boundary_term(self.xi, self.eta, M, self.x0, self.v0)
        self.density = self.L_d * self.dt  # the action per unit of s
        self.action = self.density * self.dx + self.initial * ds(START)
        self.residual = ufl.derivative(self.action, w, ufl.TestFunction(self.W))
        self.jacobian = ufl.derivative(self.residual, w, ufl.TrialFunction(self.W))

        # xi(T) = eta(T) = 0 on the 2n dual fields; multipliers of a lifted scene stay free.
        self.bcs = []
        for i in range(2 * n):
            sub = self.W.sub(i)
            dofs = fem.locate_dofs_topological(sub, 0, self.mesh.end_vertices)
            self.bcs.append(fem.dirichletbc(PETSc.ScalarType(0.0), dofs, sub))

    def _reduced_lagrangian(self, qdeg: int):
        """(x^, v^, L_d): the scene's DtP map and the pre-dual Lagrangian evaluated on it."""
        f, c, n = self.scene.forms, self.c, self.n
        args = (self.xi, self.eta, self.dxi, self.deta)
        damping = self.damping()
        # the DtP map of M v' + D v + mu M v = F: the velocity map sees eta' - mu eta
        dtp_args = (self.xi, self.eta, self.dxi, self.deta - self.mu * self.eta
                    if self.mu is not None else self.deta)
        if self.extra is not None:  # lifted scene: augmented Lagrangian, auxiliary primal
            xhat, vhat, lifted = f.dtp_map(*args, self.xb, self.vb, c, self.extra)
            L_d = f.lagrangian(xhat, vhat, lifted, *args, self.extra, self.xb, self.vb, c)
            return xhat, vhat, L_d
        if f.dtp == "explicit":
            xhat, vhat = f.dtp_map(*dtp_args, self.xb, self.vb, c)
        else:
            # Newton-linearised DtP map around the pointwise solution X of G(X) = 0 at the
            # quadrature points: x^ = X - G_x(X)^-1 G(X; xi, eta, xi'). Equal to X where G = 0,
            # with the exact derivative -G_x^-1 G_zeta, so the Jacobian of the action is the exact
            # second variation of the reduced action.
            msh = self.mesh.msh
            cell = msh.ufl_cell()
            Qx = function_space(msh, ufl.VectorElement("Quadrature", cell, qdeg, dim=n,
                                                       quad_scheme="default"))
            Qt = function_space(msh, ufl.TensorElement("Quadrature", cell, qdeg, shape=(n, n),
                                                       quad_scheme="default"))
            points = basix.make_quadrature(basix.CellType.interval, qdeg)[0]
            self.pointwise = PointwiseDtP(Qx, points, self.position_equations, self.time, Qt)
            X, Ginv = self.pointwise.X, self.pointwise.Ginv
            xhat = X - ufl.dot(Ginv, self.position_equations(X))
            vhat = f.velocity_map(self.xi, dtp_args[3], self.vb, c)
        L_d = predual_lagrangian(xhat, vhat, *args, c["M"], self.force, self.aux, self.xb,
                                 self.vb, damping)
        return xhat, vhat, L_d

    mu = None  # an unfolding damping -mu M v (fem_dual.analysis.orbit); slabs have none
    predictor = None  # a base state that is a function of time (orbits have none)
    _taken: Optional[tuple] = None  # (partner, its basis at our nodes, dofmaps)
    # bumped whenever a constant changes (start state, slab, parameters): a solver that saw the
    # same dual state at the same version has the same DtP image (fem_dual.slab.snes)
    version = 0

    def damping(self):
        """The damping matrix D of M v' + D v = F (UFL), or None: the scene's, plus mu M."""
        D = self.c.get("D")
        if self.mu is None:
            return D
        return self.mu * self.c["M"] if D is None else D + self.mu * self.c["M"]

    def position_equations(self, x):
        """G(x; xi, eta, xi') = 0, the implicit position part of the DtP map."""
        return self.scene.forms.position_equations(x, self.xi, self.eta, self.dxi, self.xb,
                                                   self.c)

    def set_scene_constants(self, scene: Scene) -> None:
        """Use the parameter values of `scene`, a scene of the same kind and size (the forms
        stay compiled: the parameters are fem.Constants)."""
        if type(scene) is not type(self.scene) or scene.n != self.n:
            raise ValueError(f"scene {scene.name} does not fit the compiled {self.scene.name}")
        for key, value in scene.constants().items():
            self.c[key].value = value
        self.scene = scene
        if self.predictor is not None:  # (the base steps the motion of these values)
            self.predictor.use_scene(scene)
        self.version += 1

    def hamiltonian_of(self, xhat, vhat):
        """The auxiliary dual Hamiltonian (eq. DualHamiltonian) at the DtP image (xhat, vhat).

        For a lifted scene, the Legendre transform p.V - L_d with p_xi = -x^, p_eta = -M v^.
        """
        if self.extra is not None:
            return -ufl.dot(xhat, self.dxi) - ufl.dot(ufl.dot(self.c["M"], vhat), self.deta) \
                - self.L_d
        return dual_hamiltonian(xhat, vhat, self.xi, self.eta, self.force, self.aux, self.xb,
                                self.vb, self.damping())

    def close(self) -> None:
        """Destroy the PETSc vector of the dual state (solvers made it); collective."""
        release_function_vector(self.w)

    @functools.cached_property
    def num_dofs(self) -> int:
        imap = self.W.dofmap.index_map
        return imap.size_global * self.W.dofmap.index_map_bs

    def set_slab(self, x0: np.ndarray, v0: np.ndarray, dt: float, t0: float = 0.0) -> None:
        """Start a slab [t0, t0 + dt] from (x0, v0), which is also the base state of H (base
        "start"); the dual state starts from zero, whose DtP image is the base state."""
        values = self._slab_values
        values[0][...], values[1][...] = dt, t0
        self.set_start(x0, v0)  # (bumps the version)
        self.w.x.array[:] = 0.0
        if self.pointwise is not None:
            self.pointwise.reset(x0)

    def take_dual_state(self, other: "SlabProblem") -> None:
        """w = other's dual state interpolated into this space (same mesh, e.g. degree p into
        the companion's p + 1). On one process by the Lagrange basis of `other` at this
        element's nodes, cell by cell (exact, as fem.Function.interpolate, in a product: that
        costs 60 us a call, a tenth of a small slab's solve)."""
        if self.comm.size > 1 or other.mesh is not self.mesh:
            self.w.interpolate(other.w)
            return
        if self._taken is None or self._taken[0] is not other:
            cells = self.mesh.msh.topology.index_map(1).size_local
            scalar = function_space(self.mesh.msh, ("Lagrange", other.degree))
            points = self.W.element.interpolation_points()
            table = scalar.element.basix_element.tabulate(0, points).reshape(len(points), -1)
            self._taken = (other, table, other.W.dofmap.list.array.reshape(cells, -1),
                           self.W.dofmap.list.array.reshape(cells, -1))
        _, table, theirs, mine = self._taken
        bs = self.W.dofmap.index_map_bs
        self.w.x.array.reshape(-1, bs)[mine] = np.matmul(
            table, other.w.x.array.reshape(-1, bs)[theirs])

    def set_start(self, x0: np.ndarray, v0: np.ndarray) -> None:
        """The slab's start state, which is also its base state unless the base is zero; the
        dual state is kept (the tangent of the slab map perturbs the start of a solved slab)."""
        self.version += 1
        values, (xbar, vbar) = self._slab_values, self._base_values
        values[2][:], values[3][:] = x0, v0
        if self.base == "start":
            xbar[:], vbar[:] = x0, v0
        elif self.predictor is not None:
            n = self.n
            zbar = self.predictor.along(np.concatenate([x0, v0]), self._base_times,
                                        float(values[0]))
            xbar[:], vbar[:] = zbar[:, :n], zbar[:, n:]
