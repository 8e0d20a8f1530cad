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
from __future__ import annotations

import signal
import time
import warnings
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Tuple

import numpy as np
import ufl
from dolfinx import fem
from mpi4py import MPI
from scipy import sparse
from scipy.sparse import linalg as spla

from fem_dual import faults
from fem_dual.compat import (CellPointEvaluator, constant, destroy_petsc, quiet_jit_logging,
                             vector_space)
from fem_dual.errors import InputError, SolveError
from fem_dual.analysis.floquet import (FLOW_MAX_CELLS, FLOW_START_CELLS, FLOW_TARGET, MAX_FOLD,
                              MULTIPLIER_TOL, SlabFlow, floquet_multipliers, monodromy,
                              multiplier_distance, stop_if_asked, vector_field)
from fem_dual.analysis.orbit_input import MODES, Energy, parse_mode
from fem_dual.slab.problem import SlabProblem
from fem_dual.slab.recovery import CellMomenta
from fem_dual.meshes import slab_mesh

__all__ = ["OrbitProblem", "OrbitResult", "OrbitSolver", "Orbits", "orbit_family",
           "orbit_summary", "write_orbit_files", "plot_orbit", "Energy", "MODES", "parse_mode"]

NEWTON_MAX_IT = 30
BASE_RESTARTS = 4  # a failed Newton starts again on its last iterate's image, at most this often
STEP_CUTS = 10  # a Newton step whose end has no DtP image is halved at most this often
NEWTON_TOL = 1e-12  # Newton step: relative change of the orbit's vertex states and period
NEWTON_STAGNATION = 1e-9  # ... or below this, a step no longer 4x smaller than the last
CLOSURE_TOL = 1e-6  # closure / max|z| above this: the orbit does not close
MU_TOL = 1e-6  # |mu| T above this: an orbit of the damped system only
COLLAPSE_TOL = 1e-10  # an orbit that moves by less than this times its size: an equilibrium
# (its extent at the level of the Newton's resolution of its offset, not of the origin); one
# that does not close and moves by less than SMALL_TOL times its size is collapsing
SMALL_TOL = 1e-4
OFFSET_RATIO = 100.0  # an orbit this many times its extent from the origin: its multipliers'
# uncertainty is round-off in the tangents (measured: 5e-6 at 2000x, 1e-3 at 2e5x), not the mesh
ENERGY_HALVINGS = 8  # mode energy: a step in energy halved at most this often in a row
ENERGY_STAGES = 100  # ... and at most this many steps
AMPLITUDE_STEPS = 60  # mode energy: closest orbits scaled in amplitude, at most this many,
AMPLITUDE_HALVINGS = 6  # ... a scale step halved at most this often in a row where Newton fails
ANCHOR_TOL = 1e-4  # ... the last from a base state scaled by at most this from an orbit
GUESS_RTOLS = (1e-9, 1e-6)  # the guess's run: this tolerance, or the next where it fails
ENERGY_TOL = 1e-8  # mode energy: the orbit's energy (at its start) within this of E, relative


class OrbitProblem(SlabProblem):
    """The periodic dual action of one orbit (see the module docstring), with its derivatives in
    the period T and the unfolding rate mu, compiled once per scene, degree and cells."""

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
        nodes = fem.FunctionSpace(msh, ("Lagrange", degree + 1))
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
        self.forms = {k: fem.form(v) for k, v in forms.items()}
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
    s = fem.FunctionSpace(msh, ("Lagrange", degree)).tabulate_dof_coordinates()[:, 0]
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


@dataclass
class OrbitResult:
    """What `fem-dual orbit` computed (its JSON object)."""

    scene: str
    parameters: Dict[str, Any]
    mode: str
    period: float
    mu: float
    t: List[float]
    x: List[List[float]]
    v: List[List[float]]
    multipliers: List[List[float]]
    nontrivial_multipliers: List[List[float]]  # without the pair at 1 (flow and family)
    closure: float
    closure_relative: float
    newton: Dict[str, Any]
    timings: Dict[str, float]
    degree: int
    cells: int
    guess: Dict[str, Any]
    status: str = "ok"
    message: str = ""
    energy: Optional[float] = None  # at the orbit's start (V(0) = 0)
    energy_target: Optional[float] = None  # mode energy: the E asked for
    estimate: Dict[str, Any] = field(default_factory=dict)
    # the independent check by DOP853 (the multipliers of its monodromy, and their largest
    # distance to fem-dual's, relative to 1 + |multiplier|)
    check: Dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> Dict[str, Any]:
        from dataclasses import asdict

        return asdict(self)


class OrbitSolver:
    """Newton on the bordered, periodic dual problem of an OrbitProblem."""

    def __init__(self, problem: OrbitProblem):
        self.p = problem
        self.A = fem.petsc.create_matrix(problem.forms["J"])
        self.vecs = {k: fem.petsc.create_vector(problem.forms[k])
                     for k in ("R", "R_T", "R_mu", "R_E") if k in problem.forms}
        self.target_energy = 0.0  # mode "energy"

    def close(self) -> None:
        destroy_petsc(self.A, *self.vecs.values())
        self.p.close()

    def _vector(self, name: str) -> np.ndarray:
        vec = self.vecs[name]
        with vec.localForm() as local:
            local.set(0.0)
        fem.petsc.assemble_vector(vec, self.p.forms[name])
        return vec.array_r.copy()

    def _scalar(self, name: str) -> float:
        return float(fem.assemble_scalar(self.p.forms[name]))

    def _matrix(self) -> sparse.csr_matrix:
        self.A.zeroEntries()
        fem.petsc.assemble_matrix(self.A, self.p.forms["J"])
        self.A.assemble()
        indptr, indices, data = self.A.getValuesCSR()
        return sparse.csr_matrix((data, indices, indptr), shape=self.A.getSize())

    def _update_dtp(self) -> None:
        pointwise = self.p.pointwise
        if pointwise is not None:
            message = pointwise.solve(self.p.comm)
            if message:
                raise SolveError(_orbit_advice(message))

    def system(self, mode: str):
        """(H, g): the bordered Hessian and gradient in the unknowns of `mode`."""
        self._update_dtp()
        P = self.p._periodic
        J = (P.T @ self._matrix() @ P).tocsr()
        R = P.T @ self._vector("R")
        cols = {"T": P.T @ self._vector("R_T"), "mu": P.T @ self._vector("R_mu")}
        names = ["mu"] if mode == "period" else ["T", "mu"]
        rows = [sparse.csr_matrix(cols[a][None, :]) for a in names]
        corner = np.array([[self._scalar(f"S_{a}{b}") for b in names] for a in names])
        grad = [self._scalar(f"S_{a}") for a in names]
        if mode == "energy":  # the row of T: the energy, not the action's stationarity in T
            rows[0] = sparse.csr_matrix((P.T @ self._vector("R_E"))[None, :])
            corner[0] = [self._scalar(f"E_{b}") for b in names]
            grad[0] = self._scalar("E") - self.target_energy
        H = sparse.bmat([[J, sparse.csr_matrix(np.column_stack([cols[a] for a in names]))],
                         [sparse.vstack(rows), sparse.csr_matrix(corner)]], format="csc")
        return H, np.concatenate([R, grad]), names

    def solve(self, mode: str) -> Dict[str, Any]:
        """Newton from the current state; returns its history. Raises SolveError."""
        p = self.p
        steps: List[float] = []
        residuals: List[float] = []
        self._update_dtp()
        z_last = np.hstack(self.orbit_vertices()[1:])
        for it in range(NEWTON_MAX_IT):
            stop_if_asked("the orbit's Newton")
            H, g, names = self.system(mode)
            residuals.append(float(np.abs(g).max()))
            if not np.isfinite(g).all():
                raise SolveError("the orbit's Newton met a non-finite residual; give a better "
                                 "guess (--period, --x0, --v0)")
            try:
                with np.errstate(all="raise"), warnings.catch_warnings():
                    warnings.simplefilter("error", spla.MatrixRankWarning)
                    # a symmetric-pattern ordering keeps the banded periodic system and its
                    # border sparse (COLAMD, spsolve's: 3.7 s and 30x the fill at 512 cells;
                    # this: 0.03 s)
                    delta = spla.splu(H, permc_spec="MMD_AT_PLUS_A").solve(-g)
            except (RuntimeError, FloatingPointError, spla.MatrixRankWarning) as exc:
                raise SolveError(f"the orbit's Newton system is singular ({exc}); the orbit is "
                                 "not isolated in this mode, or the guess is too far") from exc
            if not np.isfinite(delta).all():
                raise SolveError("the orbit's Newton system is singular; the orbit is not "
                                 "isolated in this mode, or the guess is too far")
            T = float(p.T_c.value)
            delta = self._step(delta, names)
            k = len(names)
            if not float(p.T_c.value) > 0:
                raise SolveError(f"the period went to {float(p.T_c.value):.6g} in Newton; give a "
                                 "better guess (--period)")
            z = np.hstack(self.orbit_vertices()[1:])
            scale = float(np.abs(z).max())
            if not np.isfinite(z).all() or not scale > 0:
                raise SolveError("the orbit's Newton left the orbit (a non-finite or zero "
                                 "state); give a better guess (--period, --x0, --v0)")
            # the step: how far the orbit (its vertex states) and the period moved
            step = max(float(np.abs(z - z_last).max()) / scale,
                       abs(delta[-k]) / T if "T" in names else 0.0)
            z_last = z
            # converged: a step at the tolerance, or steps that stopped shrinking (round-off)
            stagnant = bool(steps) and step > 0.25 * steps[-1] and step <= NEWTON_STAGNATION
            steps.append(step)
            if step <= NEWTON_TOL or stagnant:
                self._update_dtp()
                return {"iterations": it + 1, "steps": steps, "residuals": residuals}
        raise SolveError(f"the orbit's Newton did not converge in {NEWTON_MAX_IT} iterations "
                         f"(last relative step {steps[-1]:.3g}); give a better guess (--period, "
                         "--x0, --v0)")

    def _step(self, delta: np.ndarray, names: List[str]) -> np.ndarray:
        """Take the Newton step `delta` (merged dual dofs, then the unknowns `names`), halved
        while the DtP map has no solution at its end (at most STEP_CUTS times); returns the step
        taken. Raises SolveError when no cut helps."""
        p, k = self.p, len(names)
        targets = [p.T_c if name == "T" else p.mu_c for name in names]
        w0, values0 = p.w.x.array.copy(), [float(c.value) for c in targets]
        for cut in range(STEP_CUTS + 1):
            taken = delta * 0.5 ** cut
            p.w.x.array[:] = w0 + p._periodic @ taken[:-k]
            for target, value, d in zip(targets, values0, taken[-k:]):
                target.value = value + d
            try:
                self._update_dtp()
                return taken
            except SolveError:
                if cut == STEP_CUTS:
                    p.w.x.array[:] = w0
                    for target, value in zip(targets, values0):
                        target.value = value
                    self._update_dtp()
                    raise

    def orbit_vertices(self) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(s, x, v) at the vertices from s = 0 to 1 (the momenta of the cells, averaged)."""
        p, n = self.p, self.p.n
        ends = p.momenta()  # (cells, 2, 2n)
        msh = p.mesh.msh
        cells = msh.topology.index_map(1).size_local
        vertices = msh.geometry.dofmap.array.reshape(-1, 2)[:cells]
        s_cells = msh.geometry.x[vertices, 0]
        s = np.unique(s_cells.round(15))
        index = np.searchsorted(s, s_cells.round(15))
        sums = np.zeros((len(s), 2 * n))
        counts = np.zeros(len(s))
        np.add.at(sums, index.ravel(), ends.reshape(-1, 2 * n))
        np.add.at(counts, index.ravel(), 1.0)
        sums[0] += sums[-1]  # periodic: s = 0 and s = 1 are one point
        counts[0] += counts[-1]
        sums[-1], counts[-1] = sums[0], counts[0]
        z = sums / counts[:, None]
        M = p.c["M"].value
        v = np.linalg.solve(M, z[:, n:].T).T
        return s, z[:, :n], v


class OrbitGuess:
    """An orbit found as the guess of another (its vertex values, Hermite-interpolated at the
    base nodes: fem_dual.integrate.dense, order 8), in place of a run's motion."""

    def __init__(self, scene, t: np.ndarray, x: np.ndarray, v: np.ndarray):
        self.scene, self.t, self.x, self.v = scene, t, x, v

    def at(self, times: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        from fem_dual.integrate.dense import hermite_at

        return hermite_at(self.scene, self.t, self.x, self.v, times)


class GuessMotion:
    """The guess of an orbit: the motion from (x0, v0) over T0, by fem-dual (p = 4, 4 cells per
    slab, --rtol GUESS_RTOLS[0], or the next where a run cannot vouch for that: a guess need not
    be accurate, a motion near a separatrix over a long T0 is not to 1e-9), on one compiled
    simulation reused for every guess of a family."""

    def __init__(self):
        self.sim = None

    def __call__(self, scene, x0: np.ndarray, v0: np.ndarray, T0: float):
        """The run's result (its `at(times)` gives the motion anywhere in [0, T0])."""
        from fem_dual.config import RunConfig
        from fem_dual.integrate.simulation import Simulation

        for rtol in GUESS_RTOLS:
            config = RunConfig.create(scene, T=T0, x0=x0, v0=v0, cells=4, degree=4, rtol=rtol,
                                      reference="none")
            if self.sim is None:
                self.sim = Simulation.for_config(config, MPI.COMM_SELF)
            try:
                result = self.sim.run(config)
            except faults.Interrupted:
                raise
            except SolveError as exc:
                result = getattr(exc, "partial", None)
                message = str(exc)
            else:
                message = result.message
            if result is not None and result.status == "interrupted":
                stop_if_asked("the guess")
            if result is not None and result.status == "ok":
                return result
        reason = message.split("; ")[0]  # without a run's advice (--rtol, slabs)
        raise SolveError(f"the guess (the motion from x0, v0 over {T0:g}) could not be "
                         f"computed: {reason}; give another guess (--x0, --v0, --period)")

    def close(self) -> None:
        if self.sim is not None:
            self.sim.close()


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

    def _reach_energy(self, scene, guess, T0: float, energy: float, has: Energy):
        """Newton in mode energy from the guess; when that fails, the closest orbit first, then
        steps in energy, each from the orbit before (its motion as the base state), halved when
        Newton fails and doubled after a success. Raises SolveError naming the energy reached."""
        try:
            return self._newton(guess, T0, "energy", energy, restarts=0)
        except faults.Interrupted:  # a signal is no failure to work around
            raise
        except SolveError:
            pass
        history, s, x, v = self._newton(guess, T0, "closest")
        reached, period = has.value(x[0], v[0]), float(self.problem.T_c.value)
        if reached is None:
            raise SolveError("mode energy: the potential (the line integral of the force from "
                             "the origin) cannot be integrated at the closest orbit's start")
        _below_centre(scene, has, x, energy, reached)
        try:
            return self._scale_to_energy(scene, s, x, v, period, reached, energy, has)
        except faults.Interrupted:  # a signal is no failure to work around
            raise
        except SolveError as exc:  # steps in energy from the orbit it reached
            s, x, v, period, reached = getattr(exc, "reached", (s, x, v, period, reached))
        step, stages, halvings = energy - reached, 0, 0
        while True:
            goal = energy if abs(step) >= abs(energy - reached) else reached + step
            start = OrbitGuess(scene, period * s, x, v)
            try:
                history, s, x, v = self._newton(start, period, "energy", goal, restarts=0)
            except faults.Interrupted:  # a signal is no failure to work around
                raise
            except SolveError as exc:
                halvings += 1
                if halvings > ENERGY_HALVINGS or stages >= ENERGY_STAGES:
                    raise SolveError(f"mode energy reached E = {reached:.10g} on the way to "
                                     f"{energy:.10g} and could not go on ({exc}); give a guess "
                                     "nearer that energy") from None
                step /= 2
                continue
            stages, halvings = stages + 1, 0
            reached, period = goal, float(self.problem.T_c.value)
            if goal == energy:
                return {**history, "energy_stages": stages}, s, x, v
            step *= 1.5

    def _scale_to_energy(self, scene, s, x, v, period: float, reached: float, energy: float,
                         has: Energy):
        """The closest orbit from an orbit scaled about its mean (the anchor): while E is far,
        by sqrt((E - E_centre) / (E_orbit - E_centre)) (E - E_centre ~ amplitude^2 near a
        centre; at most 2x), each orbit the next anchor; then by the factor that secant steps
        find, until the orbit's energy is E within ENERGY_TOL / 1000. A scaled orbit is only a
        guess of the next one (an orbit nearing a separatrix changes its shape): where Newton
        fails, the last orbit becomes the anchor and the step is halved (at most
        AMPLITUDE_HALVINGS times in a row). Near a linear limit (small amplitudes) the energy
        row is nearly singular (condition ~ 1 / amplitude^2, as for linear scenes), the
        closest orbit is not. Raises SolveError, whose `reached` is the last orbit (s, x, v,
        period, energy)."""
        bottom = _centre_energy(has, x, v)
        anchor = (s, x, v, period)
        points = [(1.0, reached)]  # (the anchor's scale, the closest orbit's energy)
        iterations = steps = halvings = 0
        while steps < AMPLITUDE_STEPS:
            stop_if_asked("the energy's amplitude steps")
            c, E = points[-1]
            if abs(E - energy) <= 1e-3 * ENERGY_TOL * max(abs(energy), _kinetic_scale(scene, v)):
                if abs(c - 1.0) <= ANCHOR_TOL:
                    return {"iterations": iterations, "amplitude_steps": steps}, s, x, v
                # its base state was far from it (the discrete orbit's error grows with that
                # distance): again from this orbit
                anchor, points, c = (s, x, v, period), [(1.0, E)], 1.0
            q = (energy - bottom) / (E - bottom) if bottom < min(E, energy) else (
                0.25 if energy < E else 4.0)  # the centre's energy is only about the bottom's
            if not 0.5 <= q <= 2.0 and len(points) > 1:  # far: the last orbit as the anchor
                anchor, points, c = (s, x, v, period), [(1.0, E)], 1.0
                bottom = _centre_energy(has, x, v)
            if len(points) > 1:  # secant in the anchor's scale
                c0, E0 = points[-2]
                target = c + (energy - E) * (c - c0) / (E - E0) if E != E0 else c
            else:
                target = c * float(np.sqrt(q))
            target = float(np.clip(target, 0.5 * c, 2.0 * c))
            target = c + (target - c) * 0.5 ** halvings
            s_a, x_a, v_a, period_a = anchor
            x_mid, v_mid = x_a.mean(axis=0), v_a.mean(axis=0)
            start = OrbitGuess(scene, period_a * s_a, x_mid + target * (x_a - x_mid),
                               v_mid + target * (v_a - v_mid))
            try:
                history, s_new, x_new, v_new = self._newton(start, period_a, "closest")
                E_new = has.value(x_new[0], v_new[0])
                if E_new is None:
                    raise SolveError("no energy at the orbit's start")
            except faults.Interrupted:  # a signal is no failure to work around
                raise
            except SolveError as exc:
                halvings += 1
                if halvings > AMPLITUDE_HALVINGS:
                    exc.reached = (s, x, v, period, E)
                    raise
                anchor, points = (s, x, v, period), [(1.0, E)]  # on from the last orbit
                continue
            s, x, v, E = s_new, x_new, v_new, E_new
            iterations += history["iterations"]
            steps, halvings, period = steps + 1, 0, float(self.problem.T_c.value)
            points.append((target, E))
        error = SolveError(f"the amplitude steps did not reach E = {energy:.10g}")
        error.reached = (s, x, v, period, points[-1][1])
        raise error

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
            history, s, x, v = self._reach_energy(scene, guess, T0, energy, has)
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


def _below_centre(scene, has: Energy, x: np.ndarray, energy: float, reached: float) -> None:
    """SolveError when E lies below the energy of the equilibrium that the orbit (of energy
    `reached`) surrounds, at rest (a minimum of the potential, found from the orbit's mean):
    no orbit of its family has that energy."""
    from scipy.optimize import root

    with np.errstate(all="ignore"):
        found = root(scene.force_numpy, x.mean(axis=0), tol=1e-13)
    if not found.success or not np.all(np.isfinite(found.x)):
        return
    from fem_dual.slab.base_state import force_jacobian

    with np.errstate(all="ignore"):
        stiffness = -force_jacobian(scene.force_numpy, found.x)
    if not (np.all(np.isfinite(stiffness))
            and np.linalg.eigvalsh(0.5 * (stiffness + stiffness.T)).min() > 0):
        return  # no minimum of the potential (a saddle between two wells): no centre
    floor = has.value(found.x, np.zeros(len(found.x)))
    if floor is not None and energy < floor < reached:
        raise SolveError(f"E = {energy:.10g} lies below the energy {floor:.10g} of the "
                         f"equilibrium x = {list(map(float, found.x))} that the orbit from the "
                         "guess surrounds: no orbit of its family has that energy (theirs lie "
                         "above); give a guess near another family, or a larger E")


def _off_one(trivial: np.ndarray) -> float:
    """The trivial pair's largest distance from 1, relative to 1 + |1| as the others'."""
    return float(np.abs(trivial - 1).max() / 2)


def _centre_energy(has: Energy, x: np.ndarray, v: np.ndarray) -> float:
    """About the energy at an orbit's centre (its mean position at rest); raises SolveError
    where the potential cannot be integrated."""
    bottom = has.value(x.mean(axis=0), np.zeros(v.shape[1]))
    if bottom is None:
        raise SolveError("no energy at the orbit's centre")
    return bottom


def _kinetic_scale(scene, v: np.ndarray) -> float:
    """The largest kinetic energy along an orbit: the scale of its energy (which can be 0 or
    negative with a potential from V(0) = 0)."""
    M = scene.mass_matrix()
    return float(max(0.5 * w @ M @ w for w in np.asarray(v)))


# a run's advice (options `fem-dual orbit` does not have) and what to do for an orbit instead
_RUN_ADVICE = ("use smaller slabs or larger alpha", "use smaller slabs (more --slabs)",
               "loosen --rtol, or raise --cells or --degree",
               "use more slabs or cells per slab, a higher degree, or --rtol to choose the slab "
               "lengths")
ORBIT_ADVICE = "give a better guess (--period, --x0, --v0), or raise --cells or --degree"


def _orbit_advice(message: str) -> str:
    """A slab solver's or a run's advice, turned into an orbit's."""
    for advice in _RUN_ADVICE:
        message = message.replace(advice, ORBIT_ADVICE)
    return message


def _differences(result: OrbitResult, other: OrbitResult) -> Dict[str, float]:
    """The differences in period, vertex states and energy (where both have one) of the same
    orbit at two degrees."""
    out = {"period": abs(other.period - result.period),
           "state": float(np.abs(np.hstack([np.array(other.x) - np.array(result.x),
                                            np.array(other.v) - np.array(result.v)])).max())}
    if result.energy is not None and other.energy is not None:
        out["energy"] = abs(other.energy - result.energy)
    return out


def orbit_family(scene, params: Dict[str, Any], x0: np.ndarray, v0: np.ndarray, T0: float,
                 degree: int, cells: int, mode: str = "closest", energy: Optional[float] = None,
                 continuation: Optional[Tuple[str, np.ndarray]] = None,
                 with_estimate: bool = True, progress=None) -> Dict[str, Any]:
    """One orbit (`continuation` None) or a family along a parameter, each orbit started from
    the previous one; `progress(line)` hears of each step of a continuation. Returns the JSON
    object; its "status" is "ok" or "failed" (with "message"), what was computed before a
    failure kept."""
    from fem_dual.config import _scene

    has = Energy.of(scene, x0) if mode == "energy" else None
    orbits = Orbits(scene, degree, cells, has)
    companion = Orbits(scene, degree + 1, cells, has) if with_estimate else None
    out: Dict[str, Any] = {}
    steps: List[Dict[str, Any]] = []
    try:
        values = [None] if continuation is None else continuation[1]
        for k, value in enumerate(values):
            signum = faults.requested()
            if k > 0 and signum:  # SIGINT/SIGTERM: stop after the orbit at hand
                out["status"], out["message"] = "interrupted", (
                    f"interrupted by {signal.Signals(signum).name} before "
                    f"{continuation[0]}={value:.6g}; the {k} orbits done are kept")
                break
            member = scene if value is None else _scene(scene.name, {**params,
                                                                     continuation[0]: value})
            try:
                tic = time.perf_counter()
                guess = orbits.guess(member, x0, v0, T0)
                guess_s = time.perf_counter() - tic
                result = orbits.solve(member, x0, v0, T0, mode, energy, guess=guess,
                                      companion=companion)
                result.timings["guess_s"] = guess_s
                if companion is not None and k == 0:
                    result.timings["compile_s"] += companion.compile_s
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
                          "v0": record["v"][0], **{
                key: record[key] for key in ("period", "mu", "multipliers",
                                             "nontrivial_multipliers", "check", "closure",
                                             "closure_relative", "energy", "estimate", "status",
                                             "message", "newton", "timings")}})
            out.update(record)  # the last orbit in full
            if progress is not None:
                progress(f"orbit {k + 1}/{len(values)}: {continuation[0]}={value:.6g}, period "
                         f"{result.period:.12g}, {result.status}")
            if result.status != "ok":
                out["message"] = (f"continuation stopped at {continuation[0]}={value:.6g}: "
                                  f"{result.message}")
                break
            x0, v0, T0 = np.array(result.x[0]), np.array(result.v[0]), result.period
    finally:
        orbits.close()
        if companion is not None:
            companion.close()
    if continuation is not None:
        out["continuation"] = steps
        out["continuation_parameter"] = continuation[0]
        out.setdefault("status", "ok")
    return out


def orbit_summary(record: Dict[str, Any]) -> str:
    """The text `fem-dual orbit` prints (the JSON holds everything)."""
    if record.get("period") is None:
        return f"{record.get('scene', '')}: no orbit ({record.get('status')})"
    lines = []
    for step in record.get("continuation", []):
        name = record["continuation_parameter"]
        mods = ", ".join(f"{abs(complex(*m)):.6g}" for m in step["nontrivial_multipliers"])
        lines.append(f"{name} = {step[name]:<10.6g} period {step['period']:.12g}  "
                     f"|multipliers| {mods}  closure {step['closure']:.2g}")
    est = record.get("estimate") or {}
    mult = ", ".join(f"{re:.10g}{im:+.10g}i" for re, im in record["nontrivial_multipliers"])
    verdict = "" if record.get("status") == "ok" else " -- NOT AN ORBIT (status failed)"
    lines += [f"{record['scene']}: periodic orbit ({record['mode']}), p = {record['degree']}, "
              f"{record['cells']} cells{verdict}",
              f"  period     {record['period']:.15g}" + (
                  f"  (estimated error {est['period']:.2g})" if "period" in est else ""),
              f"  mu         {record['mu']:.3g}",
              f"  x(0)       {record['x'][0]}",
              f"  v(0)       {record['v'][0]}",
              f"  multipliers {mult} (and the pair at 1; fem-dual's slab maps" + (
                  f", estimated error {est['multipliers']:.2g}" if "multipliers" in est else "")
              + (f", DOP853 differs by {record['check']['multipliers']:.2g}"
                 if record.get("check") else "") + ")",
              f"  closure    {record['closure']:.3g} (DOP853 over one period from x(0), v(0))",
              f"  Newton     {record['newton']['iterations']} iterations; solve "
              f"{record['timings']['solve_s'] * 1e3:.1f} ms"]
    if record.get("energy") is not None:
        target = record.get("energy_target")
        lines.append(f"  energy     {record['energy']:.15g}" + (
            f"  (asked {target:.15g}, off by {abs(record['energy'] - target):.2g})"
            if target is not None else "") + (
            f"  (estimated error {est['energy']:.2g})" if "energy" in est else ""))
    return "\n".join(lines)


def write_orbit_files(record: Dict[str, Any], dirs: Dict[str, Any]) -> Optional[str]:
    """orbit.csv and orbit.json into dirs["out"], orbit.png (and continuation.png) into
    dirs["plot"]; the reason a write failed, or None. orbit.json comes last and says what
    failed when a write before it did (status "failed", never an "ok" beside a failure)."""
    import json
    from pathlib import Path

    problem = None
    try:
        if dirs.get("out") is not None:
            out = Path(dirs["out"])
            n = len(record["x"][0])
            head = ",".join(["t"] + [f"x{i + 1}" for i in range(n)] + [f"v{i + 1}" for i in
                                                                       range(n)])
            table = np.column_stack([record["t"], record["x"], record["v"]])
            np.savetxt(out / "orbit.csv", table, delimiter=",", header=head, comments="",
                       fmt="%.17g")
        if dirs.get("plot") is not None:
            plot_orbit(record, Path(dirs["plot"]))
    except OSError as exc:
        problem = f"writing the output failed: {exc}"
    if dirs.get("out") is None:
        return problem
    written = record if problem is None else {**record, "status": "failed", "message": problem}
    try:
        (Path(dirs["out"]) / "orbit.json").write_text(json.dumps(written, allow_nan=False)
                                                      + "\n")
    except OSError as exc:
        problem = problem or f"writing the output failed: {exc}"
    return problem


def plot_orbit(record: Dict[str, Any], directory) -> List[Any]:
    """orbit.png: the orbit against t and its projection on (x1, x2) or (x, v); with a
    continuation, continuation.png: the period and the multipliers' moduli along it."""
    from pathlib import Path

    from fem_dual.plots import _axes, _save

    directory = Path(directory)
    t, x, v = (np.array(record[k]) for k in ("t", "x", "v"))
    n = x.shape[1]
    plt, fig, axes = _axes(1, 10.0)
    fig.clf()
    left, right = fig.add_subplot(1, 2, 1), fig.add_subplot(1, 2, 2)
    for i in range(n):
        left.plot(t, x[:, i], label=f"x{i + 1}")
    left.set_xlabel("t")
    left.set_title(f"{record['scene']}: period {record['period']:.10g}")
    left.legend(fontsize="small")
    if n >= 2:
        right.plot(x[:, 0], x[:, 1])
        right.set_xlabel("x1")
        right.set_ylabel("x2")
    else:
        right.plot(x[:, 0], v[:, 0])
        right.set_xlabel("x")
        right.set_ylabel("v")
    right.set_title("orbit")
    paths = [_save(plt, fig, directory / "orbit.png")]
    steps = record.get("continuation")
    if steps:
        name = record["continuation_parameter"]
        plt, fig, axes = _axes(2)
        p = [s[name] for s in steps]
        axes[0].plot(p, [s["period"] for s in steps], "o-")
        axes[0].set_ylabel("period")
        moduli = np.array([[abs(complex(*m)) for m in s["nontrivial_multipliers"]]
                           for s in steps])
        for j in range(moduli.shape[1]):
            axes[1].plot(p, moduli[:, j], ".-")
        axes[1].set_ylabel("|multiplier|")
        axes[1].set_xlabel(name)
        paths.append(_save(plt, fig, directory / "continuation.png"))
    return paths
