"""The solver of the Kronecker slab problem (fem_dual.slab.kronecker): CG on the slab's dual
action, applied matrix-free, preconditioned by the fast diagonalisation of its symmetric,
undamped, energy-weighted model (exact for that model: n independent 1D systems in the modes of
the pencil (Ke, M))."""
from __future__ import annotations

import weakref
from typing import Dict, Mapping, Optional, Tuple

import numpy as np
import scipy.linalg as sla
from petsc4py import PETSc

from fem_dual.errors import SolveError
from fem_dual.slab.kronecker import KroneckerProblem, _RightFactor, _is_diagonal
from fem_dual.slab.petsc_solvers import check_true_residual

__all__ = ["KroneckerSolver", "KRONECKER_DEFAULTS", "INVERSE_ENTRIES"]

INVERSE_ENTRIES = 4_000_000  # the preconditioner keeps explicit block inverses up to 32 MB
KRONECKER_DEFAULTS: Dict[str, str] = {"ksp_type": "cg", "ksp_rtol": "1e-13", "ksp_atol": "1e-300",
                                      "ksp_max_it": "2000"}


class KroneckerSolver:
    """CG on the slab's dual action (matrix-free), fast-diagonalisation preconditioner."""

    def __init__(self, problem: KroneckerProblem, prefix: str,
                 overrides: Optional[Mapping[str, str]] = None):
        from fem_dual.slab.petsc_solvers import SolverOptions

        self.problem = p = problem
        comm = p.comm
        # checked first: the options this path cannot honour (PETSc preconditioners, which need
        # matrix entries; Krylov methods that need a transpose) are InputErrors, not crashes
        self.options = SolverOptions(prefix, KRONECKER_DEFAULTS, overrides, "kronecker", comm)
        local = p.nf * 2 * len(p.mine)
        size = p.nf * 2 * p.n
        self.A = PETSc.Mat().createPython([(local, size), (local, size)], _Operator(p), comm=comm)
        self.A.setUp()
        self.ksp = PETSc.KSP().create(comm)
        self.ksp.setOperators(self.A)
        self.ksp.setOptionsPrefix(prefix)
        self._pc: Optional[_FastDiagonalisation] = None
        if "pc_type" not in self.options.given:  # pc_type=none is the only one taken
            pc = self.ksp.getPC()  # ours, before setFromOptions: the options it reads are its own
            pc.setType(PETSc.PC.Type.PYTHON)
            self._pc = _FastDiagonalisation(p)
            pc.setPythonContext(self._pc)
        self.x, self.b = self.A.createVecs()
        # PETSc objects with Python contexts must go before PETSc finalises (at exit too)
        self._finalizer = weakref.finalize(self, _destroy, self.ksp, self.A, self.x, self.b)
        with self.options.setup():
            # (no setUp here: chebyshev's would apply the preconditioner before setup_dt)
            self.ksp.setFromOptions()
        self.iterations: List[int] = []
        self._dt: Optional[float] = None

    def close(self) -> None:
        """Destroy the PETSc objects now (collective; the finalizer would at collection)."""
        self._finalizer()

    def reset(self) -> None:
        self.iterations = []
        self._dt = None

    def solve(self) -> None:
        p = self.problem
        if self._dt != p.dt:
            if self._pc is not None:
                self._pc.setup_dt(p.dt)
            self._dt = p.dt
        r_xi, r_eta = p.base_terms(p.time_free, p.mine)
        r_xi[0] -= p.x0[p.mine]  # the initial conditions, natural at s = 0
        r_eta[0] -= (p.c["M"] @ p.v0)[p.mine]
        self.b.array[:] = -_pack(r_xi, r_eta)
        self.x.set(0.0)
        try:
            with self.options.solving():
                self.ksp.solve(self.b, self.x)
        except PETSc.Error as exc:
            raise SolveError(f"CG failed (PETSc error {exc.ierr})") from None
        reason = self.ksp.getConvergedReason()
        if reason < 0:
            raise SolveError(f"CG did not converge (KSP reason {reason}, "
                             f"{self.ksp.getIterationNumber()} iterations)")
        its = self.ksp.getIterationNumber()
        self.iterations.append(its + check_true_residual(self.ksp, self.A, self.x, self.b))
        p.W[p.free] = _gather(p, self.x.array_r)


def _destroy(*objects) -> None:
    for obj in objects:
        obj.destroy()


def _pack(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.concatenate([a, b], axis=1).ravel()


def _gather(p: KroneckerProblem, local: np.ndarray) -> np.ndarray:
    """The whole (free time dofs x 2n) array from every rank's (free x 2 x own) block."""
    parts = p.comm.allgather(np.asarray(local).reshape(p.nf, 2, -1))
    xi = np.concatenate([q[:, 0] for q in parts], axis=1)
    eta = np.concatenate([q[:, 1] for q in parts], axis=1)
    return np.concatenate([xi, eta], axis=1)


class _Operator:
    """The Hessian of the slab's action, applied matrix-free (PETSc MATPYTHON context)."""

    def __init__(self, problem: KroneckerProblem):
        self.p = problem

    def mult(self, mat, x, y) -> None:
        p = self.p
        W = _gather(p, x.array_r)
        r_xi, r_eta = p.residual(p.time_operator, W[:, :p.n], W[:, p.n:], affine=False,
                                 cols=p.mine)
        y.array[:] = _pack(r_xi, r_eta)


class _FastDiagonalisation:
    """Exact inverse of the slab Hessian of the symmetric, undamped, energy-weighted problem
    (K -> Ke, D -> 0, A = Ke, B = M, with Ke the scene's energy stiffness: sym K, or a column's
    springs), which decouples into the modes of the pencil (Ke, M): with Phi^T M Phi = I,
    Phi^T Ke Phi = Omega^2, z_xi = Phi^T xi, z_eta = Phi^-1 eta,
    each mode is one symmetric 2 x 2-block banded 1D system

        [ S / (dt w^2) + dt Mm      G - C           ] [z_xi ]   [r_xi ]
        [ C - G                     dt w^2 Mm + S / dt ] [z_eta] = [r_eta].

    For the scene's own problem (non-symmetric K, damping, other weights) it is a preconditioner
    for CG (PETSc PCPYTHON context)."""

    def __init__(self, problem: KroneckerProblem):
        self.p = problem
        self._w2: Optional[np.ndarray] = None
        self._constants: Optional[dict] = None  # the scene products _w2 belongs to

    def _modes(self) -> np.ndarray:
        """w^2 of the pencil (Ke, M), and the four products of apply, with this rank's columns
        cut once (scalings in modal coordinates, where Phi is diagonal): once per scene (a
        simulation run again with other parameters gets new products), for every slab
        length."""
        if self._w2 is None or self._constants is not self.p.c:
            p, c = self.p, self.p.c
            self._constants = c
            w2, Phi, Phi_inv = _pencil_modes(c["Ke"], c["M"])
            self.in_xi = _RightFactor(Phi_inv.T, p.mine)
            self.in_eta = _RightFactor(Phi, p.mine)
            self.out_xi = _RightFactor(Phi_inv, p.mine)
            self.out_eta = _RightFactor(Phi.T, p.mine)
            self._w2 = np.maximum(np.abs(w2), 1e-12 * np.abs(w2).max())  # near flutter: SPD
        return self._w2

    def setup_dt(self, dt: float) -> None:
        p = self.p
        w2 = self._modes()[p.mine]
        T = p.time_free
        time = (T["S"].toarray(), T["Mm"].toarray(), T["G"].toarray() - T["C"].toarray())
        # small blocks: their inverses L^-T L^-1 (block = L L^T), applied to all modes at once
        # (no loop per mode); larger ones: banded Cholesky factors, solved mode by mode
        self.inverses, self.factors = None, []
        if len(w2) * (2 * p.nf) ** 2 <= INVERSE_ENTRIES:
            L_inv = np.linalg.inv(np.linalg.cholesky(_mode_blocks(*time, dt, w2)))
            self.inverses = np.matmul(np.swapaxes(L_inv, 1, 2), L_inv)
        else:
            self.factors = [sla.cholesky_banded(_banded(_mode_blocks(*time, dt, w2[k:k + 1])[0],
                                                        2 * p.degree + 1), lower=False)
                            for k in range(len(w2))]

    def apply(self, pc, x, y) -> None:
        p = self.p
        R = _gather(p, x.array_r)
        r_xi = self.in_xi(R[:, :p.n])  # R_xi Phi^-T
        r_eta = self.in_eta(R[:, p.n:])  # R_eta Phi
        if self.inverses is not None:
            rhs = np.empty((len(p.mine), 2 * p.nf))
            rhs[:, 0::2], rhs[:, 1::2] = r_xi.T, r_eta.T
            z = np.matmul(self.inverses, rhs[:, :, None])[:, :, 0]
            z_xi, z_eta = np.ascontiguousarray(z[:, 0::2].T), np.ascontiguousarray(z[:, 1::2].T)
        else:
            z_xi = np.empty_like(r_xi)
            z_eta = np.empty_like(r_eta)
            rhs = np.empty(2 * p.nf)
            for i, factor in enumerate(self.factors):
                rhs[0::2], rhs[1::2] = r_xi[:, i], r_eta[:, i]
                z = sla.cho_solve_banded((factor, False), rhs)
                z_xi[:, i], z_eta[:, i] = z[0::2], z[1::2]
        Z_xi, Z_eta = _allgather_columns(p, z_xi), _allgather_columns(p, z_eta)
        y.array[:] = _pack(self.out_xi(Z_xi), self.out_eta(Z_eta))


def _pencil_modes(Ke: np.ndarray, M: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(w^2, Phi, Phi^-1) of the pencil (Ke, M), Phi^T M Phi = I: in closed form where both are
    diagonal (modal coordinates), else by eigh."""
    if _is_diagonal(Ke) and _is_diagonal(M):
        m = np.diag(M)
        return np.diag(Ke) / m, np.diag(1.0 / np.sqrt(m)), np.diag(np.sqrt(m))
    w2, Phi = sla.eigh(Ke, M)
    return w2, Phi, np.linalg.inv(Phi)


def _mode_blocks(S: np.ndarray, Mm: np.ndarray, skew: np.ndarray, dt: float,
                 w2: np.ndarray) -> np.ndarray:
    """(modes, 2 nf, 2 nf): the symmetric model's 1D system of each mode w^2 (w2), interleaved
    (xi_i, eta_i) (see _FastDiagonalisation); SolveError where dt w^2 leaves float64."""
    nf = len(S)
    with np.errstate(over="ignore", invalid="ignore"):
        blocks = np.zeros((len(w2), 2 * nf, 2 * nf))
        blocks[:, 0::2, 0::2] = S / (dt * w2[:, None, None]) + dt * Mm
        blocks[:, 0::2, 1::2] = skew
        blocks[:, 1::2, 0::2] = skew.T
        blocks[:, 1::2, 1::2] = dt * w2[:, None, None] * Mm + S / dt
    finite = np.isfinite(blocks).all(axis=(1, 2))
    if not finite.all():  # dt w^2 beyond float64 (a horizon of 1e300)
        k = int(np.flatnonzero(~finite)[0])
        raise SolveError(f"the slab of length {dt:.3g} overflows float64 in its time matrices "
                         f"(frequency {np.sqrt(w2[k]):.3g}); shorten --T or use more slabs")
    return blocks


def _allgather_columns(p: KroneckerProblem, local: np.ndarray) -> np.ndarray:
    return np.concatenate(p.comm.allgather(local), axis=1)


def _banded(matrix: np.ndarray, bandwidth: int) -> np.ndarray:
    """Upper banded storage of a symmetric matrix for scipy's cholesky_banded."""
    n = matrix.shape[0]
    band = np.zeros((bandwidth + 1, n))
    for d in range(bandwidth + 1):
        band[bandwidth - d, d:] = np.diagonal(matrix, d)
    return band
