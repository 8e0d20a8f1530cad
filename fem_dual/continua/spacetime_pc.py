"""The preconditioner of the space-time slab (fem_dual.continua.spacetime): the symmetric model
diagonalised in time, each time mode a shifted spatial problem solved by AMG.

The symmetric model of the slab Hessian (K -> Ke, D -> 0) is, blockwise in (xi, eta),

    H0 = [ S/dt (x) Ke^-1 + dt Mm (x) M^-1    (G - C) (x) I           ]
         [ (C - G) (x) I                      dt Mm (x) Ke + S/dt (x) M ],

with the 1D matrices of the free time dofs. The generalised eigen-decomposition of the time
pencil, S V = Mm V Lambda, V^T Mm V = I, gives H0 = (V^-T (x) I) H^ (V^-1 (x) I) with

    H^ = [ Lambda/dt (x) Ke^-1 + dt I (x) M^-1    Q (x) I                     ]
         [ Q^T (x) I                              dt I (x) Ke + Lambda/dt (x) M ],

Q = V^T (G - C) V (dense, skew, nf x nf), so H0^-1 = (V (x) I) H^^-1 (V^T (x) I). Both diagonal
blocks decouple into the time modes k, with L_k = sigma_k/dt M + dt Ke (SPD):

    eta block: (dt Ke + sigma_k/dt M)^-1 = L_k^-1,
    xi block:  (sigma_k/dt Ke^-1 + dt M^-1)^-1 = M L_k^-1 Ke
                 = M L_k^-1 (a_k Ke + dt Ke M^-1 Ke) L_k^-1 M,   a_k = sigma_k/dt

(the last form, from Ke M^-1 L_k = a_k Ke + dt Ke M^-1 Ke, is symmetric positive definite
whatever symmetric positive definite operator replaces L_k^-1: Y^T N Y with Y = P_k M). L_k^-1
is either exact (shifted="direct": one sparse Cholesky factorisation per time mode, then
P_x = M L_k^-1 Ke with one solve) or one V-cycle of algebraic multigrid (shifted="amg": hypre
BoomerAMG, shifted="gamg": PETSc GAMG with the near null space), a fixed symmetric positive
definite operator, one hierarchy per time mode. The KSP of every time mode reads its options
under `<prefix>shifted_` (shifted_defaults); all are set up once per slab length.

The coupling Q: with "sgs" (default) a symmetric block Gauss-Seidel sweep, eta first,

    z_e = P_e r_e,  z_x = P_x (r_x - Q z_e),  y_e = P_e (r_e - Q^T z_x),  y_x = z_x,

the operator W^T diag(P_e, P_x) W, W = [[I, 0], [-Q P_e, I]] in the order (eta, xi):
symmetric positive definite whenever P_e and P_x are (2 applications of P_e and 1 of P_x per
time mode); with "jacobi" the coupling is dropped (y = diag(P_x, P_e) r).

What the coupling costs: the coupled part of the symmetric model is near-singular at time
resolution resonances (spatial frequency w with w dt near a frequency the slab's time mesh
resolves, 1.5 <= w dt <= 155 for P_4 on 8 cells): relative to its diagonal blocks the coupling
has norm up to 0.998 there, a condition number of 1088 with "jacobi", 272 with "sgs" (exact
spatial solves). An exact treatment needs the inverse of a rational function of the pencil
(Ke, M) with poles next to the positive axis, i.e. spatial solves that are not positive
definite (or the pencil's eigenvectors, as the dense path uses); the time-mode preconditioner
keeps to positive definite spatial solves and leaves these resonances to CG.

`model_condition` computes that condition number over the spatial frequencies up to a mesh's
fastest: it predicts how CG counts grow with the mesh for a fixed slab, and where they stop.
For P_4 on 8 cells (sgs), with tau = w_max dt the radians the fastest mode turns per slab:
cond 2.2, 5.6, 19, 74 and 258 for tau up to 1.7, 3.4, 6.8, 13.6 and 27.2, and 272 from 29.6
on (the worst resonance, 3.7 radians per cell; slabs beyond 32 radians, 4 per cell, are
refused), whatever the mesh. The ratio of the square roots at tau = 13.6 and 27.2, 1.87,
predicts the CG counts of one slab of length 0.025 at 64 and 128 elements a side
(w_max = 543 and 1086): 107 and 207 iterations, ratio 1.93. "jacobi": 293, 1027, 1088.
"""
from __future__ import annotations

import time
import weakref
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
import scipy.linalg as sla
from mpi4py import MPI
from petsc4py import PETSc
from scipy import sparse

from fem_dual.slab.petsc_solvers import petsc_options

__all__ = ["TimeModePreconditioner", "MassChebyshev", "SHIFTED", "shifted_defaults",
           "near_nullspace", "node_block_size", "model_condition"]

#: the choices for the shifted spatial problems L_k
SHIFTED = ("amg", "gamg", "direct")


def shifted_defaults(kind: str, comm: MPI.Comm) -> Dict[str, str]:
    """The PETSc options of the time modes' KSPs for `kind` (SHIFTED) on `comm`.

    amg: one V-cycle of hypre BoomerAMG with two sweeps of Chebyshev relaxation on every level
    (a polynomial smoother: symmetric positive definite on any number of processes, with the
    exact coarsest solve). CG iterations for 64 elements, dt = 0.05: 194 on one and on two
    processes; one sweep of Chebyshev: 295 on two; hypre's default hybrid symmetric
    Gauss-Seidel: 220 on one, 720 on two.
    gamg: one V-cycle of PETSc GAMG, Chebyshev-Jacobi smoothing, the near null space.
    direct: a Cholesky factorisation (PETSc's own on one process, MUMPS on more).
    """
    if kind == "amg":
        return {"ksp_type": "preonly", "pc_type": "hypre", "pc_hypre_type": "boomeramg",
                "pc_hypre_boomeramg_relax_type_all": "Chebyshev",
                "pc_hypre_boomeramg_grid_sweeps_all": "2"}
    if kind == "gamg":
        return {"ksp_type": "preonly", "pc_type": "gamg", "mg_levels_ksp_type": "chebyshev",
                "mg_levels_pc_type": "jacobi", "mg_levels_esteig_ksp_type": "cg"}
    if kind == "direct":
        out = {"ksp_type": "preonly", "pc_type": "cholesky"}
        if comm.size == 1:
            out.update(pc_factor_mat_solver_type="petsc", pc_factor_mat_ordering_type="nd")
        else:
            out["pc_factor_mat_solver_type"] = "mumps"
        return out
    raise ValueError(f"shifted={kind!r}: expected one of {', '.join(SHIFTED)}")


def node_block_size(system) -> int:
    """The dofs per node of a SpatialSystem's free dofs: its number of scalar components c when
    on every rank the free dofs come in whole nodes (c consecutive local dofs, components 0 to
    c - 1), else 1."""
    c = system.components
    field, free = np.asarray(system.field), np.asarray(system.free)
    whole = c > 1 and field.size % c == 0
    if whole:
        whole = (np.array_equal(field, np.tile(np.arange(c), field.size // c))
                 and bool(np.all(np.diff(free.reshape(-1, c), axis=1) == 1)))
    whole = system.comm.allreduce(bool(whole), op=MPI.LAND)
    return c if whole else 1


def near_nullspace(system) -> List[np.ndarray]:
    """The near null space of a SpatialSystem's stiffness for AMG, this rank's free values:
    for a 2D vector field the rigid-body modes (two translations, the rotation (-y, x)), for a
    scalar field the constant; otherwise the constants of each component."""
    coords, field, c = system.coordinates, system.field, system.components
    gdim = coords.shape[1] if coords.ndim == 2 else 1
    vectors = []
    for k in range(c):
        vectors.append((field == k).astype(float))
    if c == 2 and gdim >= 2:
        rotation = np.where(field == 0, -coords[:, 1], coords[:, 0])
        vectors.append(rotation)
    return vectors


def _orthonormal(comm, vectors: Sequence[np.ndarray]) -> List[np.ndarray]:
    """Gram-Schmidt over the global inner product (collective)."""
    out: List[np.ndarray] = []
    for v in vectors:
        v = np.array(v, float)
        for u in out:
            v -= comm.allreduce(float(u @ v)) * u
        norm = np.sqrt(comm.allreduce(float(v @ v)))
        if norm > 1e-12:
            out.append(v / norm)
    return out


def _local_csr(A: PETSc.Mat) -> sparse.csr_matrix:
    """This rank's rows of a distributed AIJ matrix (global column indices)."""
    indptr, indices, data = A.getValuesCSR()
    return sparse.csr_matrix((data, indices, indptr), shape=(A.getLocalSize()[0],
                                                             A.getSize()[1]))


class _ShiftedOperators:
    """L_k = a_k M + b Ke as PETSc AIJ matrices with a given block size and near null space,
    from the local CSR rows of M and Ke (added with scipy once per shift)."""

    def __init__(self, M: PETSc.Mat, Ke: PETSc.Mat, block_size: int,
                 nullspace: Optional[PETSc.NullSpace]):
        self.Mloc, self.Kloc = _local_csr(M), _local_csr(Ke)
        self.sizes = (M.getSizes()[0], M.getSizes()[0])
        self.comm, self.bs, self.nullspace = M.getComm(), block_size, nullspace

    def build(self, a: float, b: float) -> PETSc.Mat:
        L = (a * self.Mloc + b * self.Kloc).tocsr()
        L.sort_indices()
        A = PETSc.Mat().createAIJ(self.sizes, bsize=self.bs,
                                  csr=(L.indptr.astype(PETSc.IntType),
                                       L.indices.astype(PETSc.IntType), L.data),
                                  comm=self.comm)
        A.setOption(PETSc.Mat.Option.SYMMETRIC, True)
        A.setOption(PETSc.Mat.Option.SPD, True)
        if self.nullspace is not None:
            A.setNearNullSpace(self.nullspace)
        A.assemble()
        return A


class MassChebyshev:
    """An approximate M^-1 for the preconditioner: the Chebyshev polynomial of Jacobi-scaled M
    (p(D^-1 M) D^-1, D = diag M) that reduces the error by `reduction`, applied to rows at once
    (one MatMatMult per degree). Symmetric positive definite: the interval [alpha, beta] ends at
    Gershgorin's bound on the eigenvalues of D^-1 M (none above), and below alpha the
    polynomial's residual stays within (0, 1]; alpha is estimated by power iteration (an
    estimate too high or too low costs accuracy only)."""

    def __init__(self, M: PETSc.Mat, rows, comm: MPI.Comm, reduction: float = 0.02,
                 steps: int = 40):
        local = _local_csr(M)
        self.d = local.diagonal(k=M.getOwnershipRange()[0]).copy()
        self.M, self.rows = M, rows
        gershgorin = np.abs(local).sum(axis=1).A1 / self.d if local.shape[0] else np.zeros(0)
        beta = comm.allreduce(float(gershgorin.max(initial=0.0)), op=MPI.MAX)
        # power iteration on beta - D^-1 M: its largest eigenvalue is beta - lambda_min
        x = np.random.default_rng(comm.rank).standard_normal(len(self.d))
        shifted = 0.0
        for _ in range(steps):
            x /= np.sqrt(comm.allreduce(float(x @ (self.d * x))))
            y = beta * x - rows.mult(M, x[None])[0] / self.d
            shifted = comm.allreduce(float(x @ (self.d * y)))
            x = y
        alpha = max(beta - shifted, 1e-3 * beta)
        self.alpha, self.beta = alpha, beta
        q = (np.sqrt(beta / alpha) - 1.0) / (np.sqrt(beta / alpha) + 1.0)
        self.degree = int(min(30, max(1, np.ceil(np.log(reduction / 2) / np.log(max(q, 1e-16))))))

    def __call__(self, B: np.ndarray) -> np.ndarray:
        """p(D^-1 M) D^-1 b for every row b of B (rows, n_local)."""
        theta, delta = 0.5 * (self.beta + self.alpha), 0.5 * (self.beta - self.alpha)
        sigma = theta / delta
        rho = 1.0 / sigma
        d = B / self.d / theta
        X = d.copy()
        R = B - self.rows.mult(self.M, d)
        for _ in range(self.degree - 1):
            rho_next = 1.0 / (2.0 * sigma - rho)
            d = rho_next * rho * d + (2.0 * rho_next / delta) * (R / self.d)
            X += d
            R -= self.rows.mult(self.M, d)
            rho = rho_next
        return X


class TimeModePreconditioner:
    """PCPYTHON context: the symmetric model of the slab Hessian, diagonalised in time, with
    positive definite spatial solves of the shifted problems (see the module docstring).

    Args:
        slab: the SpaceTimeSlab (its comm, M, Ke, factorisation of M, rows, time matrices,
            prefix).
        nullspace_vectors: this rank's free values of the AMG's near null space (or None).
        block_size: dofs per node for the AMG.
        coupling: "sgs" or "jacobi".
        shifted: how L_k^-1 is applied (SHIFTED).

    Attributes:
        sigma, V: the time pencil's eigenvalues and M_m-orthonormal eigenvectors.
        setup_seconds: the time the last setup_dt took.
    """

    def __init__(self, slab, nullspace_vectors: Optional[Sequence[np.ndarray]] = None,
                 block_size: int = 1, coupling: str = "sgs", shifted: str = "amg"):
        if coupling not in ("sgs", "jacobi"):
            raise ValueError(f"coupling={coupling!r}: expected 'sgs' or 'jacobi'")
        self.defaults = shifted_defaults(shifted, slab.comm)
        self.slab = weakref.proxy(slab)
        self.coupling, self.kind = coupling, shifted
        self.prefix = slab.prefix + "shifted_"
        self.sigma, self.V, self.Q = _time_modes(slab.time_free)
        self.nullspace, self._null_vecs = None, []
        if nullspace_vectors is not None and len(nullspace_vectors):
            for v in _orthonormal(slab.comm, nullspace_vectors):
                vec = slab.M.createVecRight()
                vec.array[:] = v
                self._null_vecs.append(vec)
            self.nullspace = PETSc.NullSpace().create(vectors=self._null_vecs, comm=slab.comm)
        self.shifted = _ShiftedOperators(slab.M, slab.Ke, block_size, self.nullspace)
        self.mass_inverse = MassChebyshev(slab.M, slab.rows, slab.comm)
        self.operators: List[PETSc.Mat] = []
        self.solvers: List[PETSc.KSP] = []
        self.dt: Optional[float] = None
        self.exact = False
        self.setup_seconds = 0.0

    def setup_dt(self, dt: float) -> None:
        """L_k = sigma_k/dt M + dt Ke and their solvers for the slab length dt."""
        start = time.perf_counter()
        self._clear()
        self.dt = float(dt)
        for sigma in self.sigma:
            L = self.shifted.build(sigma / dt, dt)
            ksp = PETSc.KSP().create(self.slab.comm)
            ksp.setOperators(L)
            ksp.setOptionsPrefix(self.prefix)
            with petsc_options(self.prefix, self.defaults):
                ksp.setFromOptions()
                ksp.setUp()
            self.operators.append(L)
            self.solvers.append(ksp)
        # factored shifted operators (pc_type cholesky or lu) are exact: P_x = M L_k^-1 Ke
        ksp = self.solvers[0]
        self.exact = (ksp.getType() == "preonly"
                      and ksp.getPC().getType() in ("cholesky", "lu"))
        self.setup_seconds = time.perf_counter() - start

    def _clear(self) -> None:
        for obj in self.solvers + self.operators:
            obj.destroy()
        self.solvers, self.operators = [], []

    def close(self) -> None:
        """Destroy the PETSc objects (collective)."""
        self._clear()
        if self.nullspace is not None:
            self.nullspace.destroy()
        for v in self._null_vecs:
            v.destroy()
        self.nullspace, self._null_vecs = None, []

    # --- the blocks -------------------------------------------------------------------------

    def _shifted_solve(self, X: np.ndarray) -> np.ndarray:
        """P_k X[k] for every time mode k (one row each)."""
        rows = self.slab.rows
        Y = np.empty_like(X)
        for k, ksp in enumerate(self.solvers):
            rows.u.array[:] = X[k]
            ksp.solve(rows.u, rows.w)
            Y[k] = rows.w.array_r
        return Y

    def eta_block(self, R: np.ndarray) -> np.ndarray:
        """P_e: L_k^-1 on each time mode's row."""
        return self._shifted_solve(R)

    def xi_block(self, R: np.ndarray) -> np.ndarray:
        """P_x on each time mode's row: M L_k^-1 Ke with exact (factored) L_k, else the
        symmetric form M P_k (a_k Ke + dt Ke M^-1 Ke) P_k M, M^-1 by MassChebyshev."""
        s, dt = self.slab, self.dt
        if self.exact:
            return s.rows.mult(s.M, self._shifted_solve(s.rows.mult(s.Ke, R)))
        U = self._shifted_solve(s.rows.mult(s.M, R))
        KU = s.rows.mult(s.Ke, U)
        N = (self.sigma / dt)[:, None] * KU + dt * s.rows.mult(s.Ke, self.mass_inverse(KU))
        return s.rows.mult(s.M, self._shifted_solve(N))

    def apply(self, pc, x, y) -> None:
        s = self.slab
        R = x.array_r.reshape(s.nf, 2, s.n_local)
        r_hat = _times(self.V.T, R)  # both fields at once
        z_x, y_e = _sweep(self.coupling, r_hat[:, 0], r_hat[:, 1], self.xi_block,
                          self.eta_block, self.Q)
        out = y.array.reshape(s.nf, 2, s.n_local)
        out[:, 0], out[:, 1] = _times(self.V, z_x), _times(self.V, y_e)


def _time_modes(T) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(sigma, V, Q) of the free time matrices T: S V = Mm V diag(sigma), V^T Mm V = I, and the
    coupling Q = V^T (G - C) V."""
    sigma, V = sla.eigh(T["S"].toarray(), T["Mm"].toarray())
    return sigma, V, V.T @ (T["G"] - T["C"]).toarray() @ V


def _sweep(coupling: str, r_x: np.ndarray, r_e: np.ndarray, xi_block, eta_block,
           Q: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """(y_x, y_e): the preconditioner in the time-mode basis applied to (r_x, r_e) (time rows
    first), with the diagonal blocks `xi_block`, `eta_block`: "jacobi" drops the coupling Q,
    "sgs" is one symmetric block Gauss-Seidel sweep, eta first (the module docstring)."""
    if coupling == "jacobi":
        return xi_block(r_x), eta_block(r_e)
    z_e = eta_block(r_e)
    z_x = xi_block(r_x - _times(Q, z_e))
    return z_x, eta_block(r_e - _times(Q.T, z_x))


def _times(A: np.ndarray, R: np.ndarray) -> np.ndarray:
    """A small dense time matrix times the time rows R (rows, ...): numpy's own loops (twice
    as fast as the reference BLAS this build links)."""
    return np.einsum("ij,j...->i...", A, R)


def model_condition(degree: int, cells: int, taus: Sequence[float],
                    coupling: str = "sgs") -> np.ndarray:
    """Condition numbers of the preconditioned symmetric model with exact spatial solves, the
    spatial frequencies w ranging up to tau / dt for each tau in `taus` (radians the fastest
    mode turns per slab): max over min of the eigenvalues over the spatial modes with
    w dt in (0, tau] (sampled; their union is the spectrum CG sees). Per spatial mode (M = 1,
    Ke = w^2, dt = 1) the model in the time-mode basis is
    [[Lambda/tau^2 + I, Q], [Q^T, tau^2 I + Lambda]] and the preconditioner that of
    `coupling` (see the module docstring)."""
    from fem_dual.slab.time_space import TimeMatrices

    if coupling not in ("sgs", "jacobi"):
        raise ValueError(f"coupling={coupling!r}: expected 'sgs' or 'jacobi'")
    T = TimeMatrices(int(degree), int(cells))
    free = T.free
    sigma, _, Q = _time_modes({k: T.glob[k][free][:, free] for k in ("S", "Mm", "G", "C")})
    nf = len(sigma)
    unit = np.eye(2 * nf)  # the preconditioner applied to the unit vectors, as columns
    grid = np.geomspace(1e-2, max(taus), 400)
    lo, hi = np.empty(len(grid)), np.empty(len(grid))
    for i, tau in enumerate(grid):
        w2 = tau * tau
        d_x, d_e = sigma / w2 + 1.0, w2 + sigma  # the diagonal blocks (time modes)
        H = np.block([[np.diag(d_x), Q], [Q.T, np.diag(d_e)]])
        B = np.vstack(_sweep(coupling, unit[:nf], unit[nf:], lambda R: R / d_x[:, None],
                             lambda R: R / d_e[:, None], Q))
        ev = np.linalg.eigvals(B @ H).real
        lo[i], hi[i] = ev.min(), ev.max()
    out = []
    for tau in taus:
        upto = grid <= tau * (1 + 1e-12)
        out.append(hi[upto].max() / lo[upto].min())
    return np.array(out)
