"""The space-time slab of a linear continuum, sparse and distributed: the dual action of
fem_dual.slab.kronecker on the free dofs of a DOLFINx space, without any dense n x n matrix.

For M q'' + D q' + K q = 0 (M SPD, K and D any, distributed PETSc AIJ matrices on the free dofs,
as :class:`fem_dual.continua.system.SpatialSystem` gives them), the weights of H are the energy
weights A = Ke, B = M (Ke the energy stiffness, by default sym K = (K + K^T) / 2, SPD), and the
base state is the slab's start state (xbar = x0, vbar = v0). The slab problem is the one of
:class:`fem_dual.slab.kronecker.KroneckerProblem` (same time discretisation: P_p on `cells`
equal cells of s in [0, 1], xi = eta = 0 at s = 1) and its residual is the same sum of
(1D time matrix) x (spatial operator) terms, with every product of Kronecker's dense path
applied as a chain of sparse operations on this rank's rows: Ke^-1 = A^-1 and M^-1 = B^-1 by
one sparse direct factorisation each (PETSc KSP preonly, Cholesky: PETSc's own on one process,
MUMPS on more; set up once per scene), exact to round-off so that CG sees a symmetric operator,
and K, K^T, D, D^T, M by MatMult. A block of rows is one dense PETSc matrix: one MatMatMult per
product, one MatMatSolve per factorisation. Written per time row (rows of the time matrices applied
to the dual fields' time rows),

    r_xi  = Ke^-1 (S xi / dt - K^T C eta) + dt M^-1 (Mm xi - D^T Mm eta) + G eta,
    r_eta = K Ke^-1 (dt K^T Mm eta - G xi) - D (R + G eta) - D^T C eta + C xi + M S eta / dt

with R = dt M^-1 (Mm xi - D^T Mm eta) (the term of r_xi that M^-1 carries): the Hessian of the
slab's action, symmetric positive definite. The dual unknowns are a PETSc Vec of local size
(free time dofs) x 2 x n_local: time row by time row, this rank's xi values, then its eta
values (the layout of the dense path's columns). Communication is only that of the spatial
MatMult and of the factorisations' solves.

CG solves it (ksp_rtol 1e-10 on the unpreconditioned residual by default; the true residual's
floor is about 2e-12), preconditioned by
:class:`fem_dual.continua.spacetime_pc.TimeModePreconditioner` (the symmetric model
diagonalised in time, spatial AMG). The vertex values x, v at the slab's
cells + 1 time vertices come from the cell residuals' momenta (order 2p), as
:meth:`fem_dual.slab.kronecker.KroneckerSampler.linear_part` computes them; v from M v by the
factorisation of M.
"""
from __future__ import annotations

import weakref
from typing import Dict, List, Mapping, Optional, Sequence, Tuple

import numpy as np
from mpi4py import MPI
from petsc4py import PETSc
from scipy import sparse

from fem_dual.errors import SolveError
from fem_dual.slab.time_space import TimeMatrices
from fem_dual.slab.petsc_solvers import petsc_options

__all__ = ["SpaceTimeSlab", "SPACETIME_DEFAULTS", "FACTOR_DEFAULTS", "factor_defaults",
           "direct_solver", "TRUE_RESIDUAL", "WARM_RESOLUTION"]

#: the outer CG (options under the slab's prefix override them)
SPACETIME_DEFAULTS: Dict[str, str] = {"ksp_type": "cg", "ksp_norm_type": "unpreconditioned",
                                      "ksp_rtol": "1e-10", "ksp_atol": "1e-300",
                                      "ksp_max_it": "3000"}
#: the factorisations of Ke and M (under the prefixes `<prefix>ke_` and `<prefix>m_`): PETSc's
#: own Cholesky on one process (its triangular solves took 3.6 ms for 32258 dofs, MUMPS's 9 to
#: 13 ms), MUMPS on more
FACTOR_DEFAULTS: Dict[str, str] = {"ksp_type": "preonly", "pc_type": "cholesky"}


def factor_defaults(comm: MPI.Comm) -> Dict[str, str]:
    """FACTOR_DEFAULTS with the factorisation package for `comm`'s size."""
    if comm.size == 1:
        return {**FACTOR_DEFAULTS, "pc_factor_mat_solver_type": "petsc",
                "pc_factor_mat_ordering_type": "nd"}
    return {**FACTOR_DEFAULTS, "pc_factor_mat_solver_type": "mumps"}


#: a CG started from the answer's dual fields (the error companion) reduces its residual at
#: least by this factor
WARM_RESOLUTION = 1e-3

#: |b - H w| / |b| above which a converged CG is a SolveError (a preconditioner that is not
#: symmetric positive definite, or factorisations that lost their accuracy)
TRUE_RESIDUAL = 1e-6


class _Rows:
    """Spatial PETSc operations on blocks of rows (rows, n_local): row i is this rank's part of
    a free vector. A block is one dense PETSc matrix (n_local x rows, its columns the rows), so
    that a product is one MatMatMult (AIJ x dense) and a factorisation's solve one MatMatSolve
    (many right-hand sides at once). Collective: every rank passes the same number of rows."""

    def __init__(self, A: PETSc.Mat):
        self.u, self.w = A.createVecs()
        self.comm, self.sizes = A.getComm(), A.getSizes()[0]
        self._blocks: Dict[tuple, PETSc.Mat] = {}
        self._products: Dict[tuple, tuple] = {}

    def _block(self, key: str, rows: int) -> PETSc.Mat:
        block = self._blocks.get((key, rows))
        if block is None:
            block = PETSc.Mat().createDense((self.sizes, (PETSc.DECIDE, rows)), comm=self.comm)
            block.setUp()
            block.assemble()
            self._blocks[(key, rows)] = block
        return block

    def _load(self, X: np.ndarray) -> PETSc.Mat:
        block = self._block("in", len(X))
        block.getDenseArray()[:] = np.asarray(X).T
        return block

    def mult(self, A: PETSc.Mat, X: np.ndarray) -> np.ndarray:
        """A x for every row x of X (the product's dense matrix is kept per A and row count;
        the entry holds A, so that its handle is not reused while it is cached)."""
        if len(X) == 0:
            return np.zeros((0, self.sizes[0]))
        key = (A.handle, len(X))
        block = self._load(X)
        cached = self._products.get(key)
        if cached is None or cached[0] is not A:
            if cached is not None:
                cached[1].destroy()
            product = A.matMult(block)
            self._products[key] = (A, product)
        else:
            product = cached[1]
            A.matMult(block, product)
        return product.getDenseArray(readonly=True).T.copy()

    def solve(self, ksp: PETSc.KSP, X: np.ndarray) -> np.ndarray:
        """A^-1 x for every row x of X, A the operator of a KSP: by one MatMatSolve of the
        factored matrix where the KSP is a bare factorisation, else row by row."""
        if len(X) == 0:
            return np.zeros((0, self.sizes[0]))
        pc = ksp.getPC()
        if ksp.getType() == "preonly" and pc.getType() in ("cholesky", "lu"):
            out = self._block("out", len(X))
            pc.getFactorMatrix().matSolve(self._load(X), out)
            return out.getDenseArray(readonly=True).T.copy()
        Y = np.empty((len(X), self.w.getLocalSize()))
        for i, row in enumerate(X):
            self.u.array[:] = row
            ksp.solve(self.u, self.w)
            if ksp.getConvergedReason() < 0:
                raise SolveError(f"a spatial solve of the space-time slab failed (KSP reason "
                                 f"{ksp.getConvergedReason()}, prefix {ksp.getOptionsPrefix()})")
            Y[i] = self.w.array_r
        return Y

    def destroy(self) -> None:
        products = [product for _, product in self._products.values()]
        for obj in [self.u, self.w] + list(self._blocks.values()) + products:
            obj.destroy()
        self._blocks, self._products = {}, {}


def direct_solver(A: PETSc.Mat, prefix: str,
                  overrides: Optional[Mapping[str, str]] = None) -> PETSc.KSP:
    """A KSP that applies A^-1 (A SPD) by one sparse factorisation (factor_defaults under
    `prefix`; options given there win), factored now."""
    ksp = PETSc.KSP().create(A.getComm())
    ksp.setOperators(A)
    ksp.setOptionsPrefix(prefix)
    with petsc_options(prefix, factor_defaults(A.getComm().tompi4py()), overrides):
        ksp.setFromOptions()
        ksp.setUp()
    return ksp


def _is_zero(A: Optional[PETSc.Mat]) -> bool:
    return A is None or A.norm(PETSc.NormType.FROBENIUS) == 0.0


def _recovery_rows(time: TimeMatrices) -> Dict[str, object]:
    """The rows of the element time matrices at both ends of every cell, as global (2 cells x
    size) matrices: row 2c is cell c's first row (s at its left end), row 2c + 1 its last."""
    p, cells = time.degree, time.cells
    rows = np.repeat(np.arange(2 * cells), p + 1)
    cols = np.repeat(time.cell_dofs, 2, axis=0).ravel()
    out: Dict[str, object] = {}
    for name in ("S", "C", "G", "Mm"):
        ends = time.element[name][[0, p]]  # (2, p + 1)
        out[name] = sparse.csr_matrix((np.tile(ends.ravel(), cells), (rows, cols)),
                                      shape=(2 * cells, time.size))
    for name in ("e", "m"):
        out[name] = np.tile(time.element[name][[0, p]], cells)
    return out


class SpaceTimeSlab:
    """The slab problem of M q'' + D q' + K q = 0 in sparse Kronecker form, distributed like
    the spatial matrices, solved by preconditioned CG (see the module docstring).

    Args:
        M, K: free-dof PETSc AIJ matrices (M SPD; K any), distributed alike.
        D: the damping matrix, or None / an empty matrix for none.
        degree, cells: the time degree p and the cells per slab.
        comm: the communicator (default: M's).
        prefix: PETSc options prefix: the CG under it (SPACETIME_DEFAULTS), the factorisations
            of Ke and M under `<prefix>ke_`, `<prefix>m_` (factor_defaults), the solvers of the
            preconditioner's shifted problems under `<prefix>shifted_`
            (spacetime_pc.shifted_defaults).
        Ke: the energy stiffness (SPD; default (K + K^T) / 2).
        near_nullspace: vectors (this rank's free values) that the AMG keeps exactly on its
            coarse levels (rigid-body modes for elasticity); see :meth:`from_system`.
        block_size: dofs per node for the AMG (1 unless every rank's free dofs come in whole
            nodes, as for a clamped vector field).
        options: PETSc options for the CG (under `prefix`; they win over the defaults).
        coupling: how the preconditioner treats the xi-eta coupling: "sgs" (symmetric block
            Gauss-Seidel) or "jacobi" (dropped).
        shifted: how the preconditioner solves its shifted spatial problems: "amg" (hypre
            BoomerAMG V-cycle), "gamg" (PETSc GAMG V-cycle) or "direct" (factorisations).

    Attributes:
        iterations: the CG iterations of every solve since construction.
        n, n_local: global and local number of free spatial dofs.
        nf: free time dofs (cells * degree).
    """

    def __init__(self, M: PETSc.Mat, K: PETSc.Mat, D: Optional[PETSc.Mat] = None,
                 degree: int = 4, cells: int = 8, comm: Optional[MPI.Comm] = None,
                 prefix: str = "spacetime_", Ke: Optional[PETSc.Mat] = None,
                 near_nullspace: Optional[Sequence[np.ndarray]] = None, block_size: int = 1,
                 options: Optional[Mapping[str, str]] = None, coupling: str = "sgs",
                 shifted: str = "amg"):
        from fem_dual.continua.spacetime_pc import TimeModePreconditioner

        self.comm = comm if comm is not None else M.getComm().tompi4py()
        self.prefix, self.degree = prefix, int(degree)
        self.n_local, self.n = M.getLocalSize()[0], M.getSize()[0]
        self.time = TimeMatrices(self.degree, int(cells))
        self.cells = self.time.cells
        self.nf = len(self.time.free)
        free = self.time.free
        self.time_free = {k: (v[free][:, free] if k not in ("e", "m") else v[free])
                          for k, v in self.time.glob.items()}
        self.recovery = _recovery_rows(self.time)
        self._interpolations: Dict[Tuple[int, int], np.ndarray] = {}
        self._owned: List[PETSc.Object] = []
        self.M, self.K = M, K
        self.Kt = self._own(K.transpose(PETSc.Mat()))  # (out given: not in place)
        if Ke is None:
            Ke = self._own(K.copy())
            Ke.axpy(1.0, self.Kt)
            Ke.scale(0.5)
        Ke.setOption(PETSc.Mat.Option.SYMMETRIC, True)
        M.setOption(PETSc.Mat.Option.SYMMETRIC, True)
        self.Ke = Ke
        self.damped = not _is_zero(D)
        self.D = D if self.damped else None
        self.Dt = self._own(D.transpose(PETSc.Mat())) if self.damped else None
        self.rows = _Rows(M)
        self.ke_solver = self._own(direct_solver(Ke, prefix + "ke_"))
        self.m_solver = self._own(direct_solver(M, prefix + "m_"))
        local, size = self.nf * 2 * self.n_local, self.nf * 2 * self.n
        self.H = self._own(PETSc.Mat().createPython([(local, size), (local, size)],
                                                    _Hessian(self), comm=self.comm))
        self.H.setUp()
        self.pc_context = TimeModePreconditioner(self, near_nullspace, block_size, coupling,
                                                 shifted)
        self.ksp = self._own(self._krylov(options))
        self.w, self.b = self.H.createVecs()
        self._owned += [self.w, self.b]
        self._finalizer = weakref.finalize(self, _destroy, self._owned, self.rows,
                                           self.pc_context)
        self.iterations: List[int] = []
        self.dt: Optional[float] = None
        self._pc_dt: Optional[float] = None
        self.x0 = self.v0 = np.zeros(self.n_local)

    @classmethod
    def from_system(cls, system, degree: int = 4, cells: int = 8, prefix: str = "spacetime_",
                    **kwargs) -> "SpaceTimeSlab":
        """The slab of a SpatialSystem's M, K, D, with the rigid-body modes (or constants) of
        its free dofs as the AMG's near null space (fem_dual.continua.spacetime_pc)."""
        from fem_dual.continua.spacetime_pc import near_nullspace, node_block_size

        kwargs.setdefault("near_nullspace", near_nullspace(system))
        kwargs.setdefault("block_size", node_block_size(system))
        D = system.D if system.has_damping else None
        return cls(system.M, system.K, D, degree, cells, system.comm, prefix, **kwargs)

    def _own(self, obj):
        self._owned.append(obj)
        return obj

    def _krylov(self, options: Optional[Mapping[str, str]]) -> PETSc.KSP:
        ksp = PETSc.KSP().create(self.comm)
        ksp.setOperators(self.H)
        ksp.setOptionsPrefix(self.prefix)
        pc = ksp.getPC()
        pc.setType(PETSc.PC.Type.PYTHON)
        pc.setPythonContext(self.pc_context)
        with petsc_options(self.prefix, SPACETIME_DEFAULTS, options):
            ksp.setFromOptions()
        return ksp

    def close(self) -> None:
        """Destroy the PETSc objects now (collective; the finalizer would at collection)."""
        self._finalizer()

    @property
    def num_dofs(self) -> int:
        """Global space-time unknowns of the CG: free time dofs x 2 x free spatial dofs."""
        return self.nf * 2 * self.n

    # --- spatial helpers --------------------------------------------------------------------

    def _vec_mult(self, A: PETSc.Mat, x: np.ndarray) -> np.ndarray:
        return self.rows.mult(A, np.asarray(x, float)[None])[0]

    def velocity(self, mv: np.ndarray) -> np.ndarray:
        """Rows v from rows of momenta M v (the factorisation of M)."""
        return self.rows.solve(self.m_solver, np.atleast_2d(mv))

    # --- the slab ---------------------------------------------------------------------------

    def set_slab(self, x0: np.ndarray, v0: np.ndarray, dt: float) -> None:
        """The start state (this rank's free values) and the slab length; the base state is
        the start state."""
        x0, v0 = np.asarray(x0, float), np.asarray(v0, float)
        if x0.shape != (self.n_local,) or v0.shape != (self.n_local,):
            raise ValueError(f"set_slab: start state of shapes {x0.shape}, {v0.shape}, "
                             f"expected ({self.n_local},)")
        self.x0, self.v0, self.dt = x0, v0, float(dt)
        self.xbar, self.vbar = x0, v0
        self.mv0 = self._vec_mult(self.M, v0)  # M vbar (= M v0)
        force = self._vec_mult(self.K, x0)
        if self.damped:
            force += self._vec_mult(self.D, v0)
        self.force = force  # K xbar + D vbar
        self.w.set(0.0)

    def residual_rows(self, T: Mapping, xi: np.ndarray, eta: np.ndarray
                      ) -> Tuple[np.ndarray, np.ndarray]:
        """The linear part of dS for the dual rows (xi, eta) tested with the rows of the time
        matrices T (`T[name] @ rows`): the module docstring's formulas."""
        dt, nr = self.dt, T["S"].shape[0]
        ce, me = T["C"] @ eta, T["Mm"] @ eta
        mx, gx, ge = T["Mm"] @ xi, T["G"] @ xi, T["G"] @ eta
        ktw = self.rows.mult(self.Kt, np.vstack([ce, dt * me]))  # K^T C eta, dt K^T Mm eta
        z = self.rows.solve(self.ke_solver, np.vstack([T["S"] @ xi / dt - ktw[:nr],
                                                        ktw[nr:] - gx]))
        r_xi = z[:nr] + ge
        r_eta = (self.rows.mult(self.K, z[nr:]) + T["C"] @ xi
                 + self.rows.mult(self.M, T["S"] @ eta) / dt)
        if self.damped:
            dtw = self.rows.mult(self.Dt, np.vstack([me, ce]))  # D^T Mm eta, D^T C eta
            R = dt * self.rows.solve(self.m_solver, mx - dtw[:nr])
            r_xi += R
            r_eta -= self.rows.mult(self.D, R + ge) + dtw[nr:]
        else:
            r_xi += dt * self.rows.solve(self.m_solver, mx)
        return r_xi, r_eta

    def base_rows(self, e: np.ndarray, m: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """The part of dS that the base state contributes, for the time vectors e, m."""
        dt = self.dt
        b_xi = -np.multiply.outer(e, self.xbar) - dt * np.multiply.outer(m, self.vbar)
        b_eta = dt * np.multiply.outer(m, self.force) - np.multiply.outer(e, self.mv0)
        return b_xi, b_eta

    def rhs(self) -> np.ndarray:
        """This rank's part of the right-hand side (free time dofs, 2, n_local): minus dS at
        the zero dual state, with the initial conditions (natural at s = 0)."""
        r_xi, r_eta = self.base_rows(self.time_free["e"], self.time_free["m"])
        r_xi[0] -= self.x0
        r_eta[0] -= self.mv0
        return -np.stack([r_xi, r_eta], axis=1)

    def setup_preconditioner(self) -> None:
        """Set the preconditioner up for the slab length of set_slab, unless it is (solve does
        it; a caller may, to time it apart). Collective."""
        if self.dt is None:
            raise ValueError("set_slab first")
        if self._pc_dt != self.dt:
            self.pc_context.setup_dt(self.dt)
            self._pc_dt = self.dt

    def solve(self, guess: Optional["SpaceTimeSlab"] = None) -> int:
        """Solve the slab (collective); the CG iterations. SolveError on failure.

        guess: a slab of no higher degree on the same cells, solved for the same start state and
        length (the answer whose degree p + 1 companion this is): CG starts from its dual fields,
        exact in this richer space, so that it begins at the residual of the difference between
        the two instead of that of the whole answer. It stops at the usual test (relative to
        |b|) or, when the difference is near that test, once its residual is WARM_RESOLUTION of
        the start's: what CG leaves unresolved would otherwise shrink the difference, the error
        estimate."""
        self.setup_preconditioner()
        self.b.array[:] = self.rhs().ravel()
        warm = (guess is not None and guess.dt == self.dt and guess.cells == self.cells
                and np.array_equal(guess.x0, self.x0) and np.array_equal(guess.v0, self.v0))
        if warm:
            fine = self._interpolation(guess.time)
            xi, eta = guess.dual_rows()
            start = np.stack([fine @ xi, fine @ eta], axis=1)[self.time.free]
            self.w.array[:] = start.ravel()
        else:
            self.w.set(0.0)
        self.ksp.setInitialGuessNonzero(warm)
        rtol = self.ksp.getTolerances()[0]
        if warm:  # resolve the difference, however small
            start_norm = self._residual_norm() / max(self.b.norm(), 1e-300)
            self.ksp.setTolerances(rtol=min(rtol, WARM_RESOLUTION * start_norm))
        try:
            self.ksp.solve(self.b, self.w)
        except PETSc.Error as exc:
            raise SolveError(f"space-time CG failed (PETSc error {exc.ierr})") from None
        finally:
            self.ksp.setTolerances(rtol=rtol)
        reason = self.ksp.getConvergedReason()
        its = self.ksp.getIterationNumber()
        if reason < 0:
            raise SolveError(f"space-time CG did not converge (KSP reason {reason}, {its} "
                             "iterations)")
        self.true_residual = self._true_residual()
        if not self.true_residual <= TRUE_RESIDUAL:
            raise SolveError(f"space-time CG converged to a wrong answer: true residual "
                             f"{self.true_residual:.3g} relative (preconditioner not SPD?)")
        self.iterations.append(its)
        return its

    def _interpolation(self, coarse) -> np.ndarray:
        """TimeMatrices.interpolation from `coarse` (built once per coarse degree: the same on
        every slab)."""
        key = (coarse.degree, coarse.cells)
        if key not in self._interpolations:
            self._interpolations[key] = self.time.interpolation(coarse)
        return self._interpolations[key]

    def _residual_norm(self) -> float:
        """|b - H w|."""
        r = self.b.duplicate()
        try:
            self.H.mult(self.w, r)
            r.aypx(-1.0, self.b)
            return r.norm()
        finally:
            r.destroy()

    def _true_residual(self) -> float:
        return self._residual_norm() / max(self.b.norm(), 1e-300)

    # --- the solution -----------------------------------------------------------------------

    def dual_rows(self) -> Tuple[np.ndarray, np.ndarray]:
        """xi, eta at all time dofs (size, n_local), the Dirichlet dof s = 1 included (zero)."""
        W = np.zeros((self.time.size, 2, self.n_local))
        W[self.time.free] = self.w.array_r.reshape(self.nf, 2, self.n_local)
        return W[:, 0], W[:, 1]

    def momenta(self) -> Tuple[np.ndarray, np.ndarray]:
        """x and M v at the cells + 1 vertices (cells + 1, n_local): the cell residuals' momenta,
        +r at a cell's left end, -r at its right end, averaged at interior vertices."""
        xi, eta = self.dual_rows()
        T = self.recovery
        r_xi, r_eta = self.residual_rows(T, xi, eta)
        b_xi, b_eta = self.base_rows(T["e"], T["m"])
        r_xi, r_eta = r_xi + b_xi, r_eta + b_eta
        x = np.empty((self.cells + 1, self.n_local))
        mv = np.empty_like(x)
        for out, r in ((x, r_xi), (mv, r_eta)):
            left, right = r[0::2], -r[1::2]
            out[0], out[-1] = left[0], right[-1]
            out[1:-1] = 0.5 * (left[1:] + right[:-1])
        return x, mv

    def vertex_values(self) -> Tuple[np.ndarray, np.ndarray]:
        """x, v at the slab's cells + 1 time vertices, this rank's free values (cells + 1,
        n_local). Collective."""
        x, mv = self.momenta()
        return x, self.velocity(mv)

    def dual_vertex_values(self) -> Tuple[np.ndarray, np.ndarray]:
        """xi, eta at the vertices (cells + 1, n_local)."""
        xi, eta = self.dual_rows()
        return xi[::self.degree], eta[::self.degree]


class _Hessian:
    """The Hessian of the slab's action, applied matrix-free (PETSc MATPYTHON context)."""

    def __init__(self, slab: SpaceTimeSlab):
        self.slab = weakref.proxy(slab)

    def mult(self, mat, x, y) -> None:
        s = self.slab
        W = x.array_r.reshape(s.nf, 2, s.n_local)
        r_xi, r_eta = s.residual_rows(s.time_free, W[:, 0], W[:, 1])
        out = y.array.reshape(s.nf, 2, s.n_local)
        out[:, 0], out[:, 1] = r_xi, r_eta


def _destroy(owned, rows, pc_context) -> None:
    pc_context.close()
    rows.destroy()
    for obj in reversed(owned):
        obj.destroy()
