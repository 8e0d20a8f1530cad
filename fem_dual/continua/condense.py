"""Static condensation of the rotation of Beck's column without rotary inertia (rhoI = 0).

Then the theta rows of M vanish, theta follows w at every instant, and with the free-dof blocks
of K_el (w, theta) the motion is M_ww w'' + K_c(P) w = 0 with

    K_c = K_ww - K_wt K_tt^-1 K_tw,   theta = G w,   G = -K_tt^-1 K_tw,
    K_c(P) = K_c - P (K_g - K_f)  (follower),   K_c - P K_g  (dead)

(K_g, K_f act on w alone). The Schur complement of the assembled matrix subtracts numbers of
size kGA/h to leave numbers of size EI/h^3, and the eigenvalue solvers then see K_c's norm: with
kGA = 1e7 and 200 P2 cells that route moves omega_1 by 1.6e-5 (relative) and the flutter load by
5e-5, ten times the discretisation error there. It is therefore evaluated in flexibility form.
Let the reduced shear quadrature have points x_g and weights a_g (cell Jacobian included),
B_w w = (w'(x_g))_g, B_t theta = (theta(x_g))_g, so that k_s = kGA (B_w w - B_t theta)^T A
(B_w dw - B_t dtheta) with A = diag(a_g), and K_b the bending stiffness of theta. By the
Woodbury identity

    K_c = B_w^T C^-1 B_w,   C = (kGA A)^-1 + B_t K_b^-1 B_t^T,   G = K_b^-1 B_t^T C^-1 B_w,

C being the compliance at the Gauss points (shear plus bending). With `degree` points per cell
and w in P_degree clamped at 0, B_w is square and invertible (w -> w' maps onto discontinuous
P_(degree-1), which its Gauss values determine), so the flexibility is

    F = K_c^-1 = B_w^-1 C B_w^-T,

computed without cancellation. The eigenvalue problems of :mod:`fem_dual.continua.flutter` use F.

All matrices here are dense, gathered on rank 0 and computed there, then broadcast: Beck's
column is one-dimensional (n_w = elements * degree).
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Tuple

import numpy as np
import scipy.linalg as sla
import ufl
from dolfinx import fem
from dolfinx.fem import petsc as fem_petsc
from petsc4py import PETSc

from fem_dual.compat import destroy_petsc
from fem_dual.continua.beck import BeckColumn, shear_quadrature_degree
from fem_dual.continua.dofs import gather_csr, gather_rows, index_set
from fem_dual.continua.system import compile_form

__all__ = ["CondensedBeck", "condense_rotation", "schur_complement"]


@dataclass(frozen=True)
class CondensedBeck:
    """Beck's column with theta condensed, dense, on every rank.

    Attributes:
        M: (n_w, n_w) mass of w. K_el: condensed elastic stiffness K_c; F_el = K_c^-1.
        K_g, K_f: geometric and follower matrices on w.
        theta_map: G (n_theta, n_w), theta = G w.
        w_index, theta_index: positions of the w and theta dofs in the system's global free
            vector (free-dof order).
        load: "follower" or "dead".
    """

    M: np.ndarray
    K_el: np.ndarray
    F_el: np.ndarray
    K_g: np.ndarray
    K_f: np.ndarray
    theta_map: np.ndarray
    w_index: np.ndarray
    theta_index: np.ndarray
    load: str

    @property
    def n(self) -> int:
        return self.M.shape[0]

    def load_matrix(self) -> np.ndarray:
        """G_P with K_c(P) = K_c - P G_P: K_g - K_f (follower) or K_g (dead)."""
        return self.K_g - self.K_f if self.load == "follower" else self.K_g

    @cached_property
    def flexibility_pencil(self) -> Tuple[np.ndarray, np.ndarray]:
        """(F G_P, F M): K_c(P) x = lambda M x is (I - P F G_P) x = lambda F M x."""
        return self.F_el @ self.load_matrix(), self.F_el @ self.M

    def stiffness(self, P: float) -> np.ndarray:
        """K_c(P)."""
        return self.K_el - P * self.load_matrix()

    def expand(self, w: np.ndarray) -> np.ndarray:
        """The system's global free vector of (w, theta = G w)."""
        full = np.zeros(self.w_index.size + self.theta_index.size)
        full[self.w_index] = w
        full[self.theta_index] = self.theta_map @ w
        return full


def _quadrature_rows(column: BeckColumn):
    """(a, WB): the Gauss weights a_g and the matrix of (w' - theta)(x_g) a_g over the free
    dofs, gathered on rank 0."""
    msh, q = column.msh, shear_quadrature_degree(column.params.degree)
    Q = fem.FunctionSpace(msh, ufl.FiniteElement("Quadrature", msh.ufl_cell(), q,
                                                 quad_scheme="default"))
    dx_red = column.measures()["dx_red"]
    r = ufl.TestFunction(Q)
    w, theta = ufl.split(ufl.TrialFunction(column.W))
    weights = fem_petsc.assemble_vector(compile_form(r * dx_red))
    weights.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
    full = fem_petsc.assemble_matrix(compile_form((w.dx(0) - theta) * r * dx_red))
    full.assemble()
    imap = Q.dofmap.index_map
    rows = index_set(msh.comm, imap.local_range[0] + np.arange(imap.size_local))
    WB = full.createSubMatrix(rows, column.system.free_is)
    a, gathered = gather_rows(msh.comm, weights.array[:imap.size_local]), gather_csr(WB)
    destroy_petsc(weights, full, rows, WB)
    return a, gathered


def _dense(column: BeckColumn):
    """Every matrix the condensation needs, dense on rank 0 (None elsewhere)."""
    mats = column.parts()
    dense = {name: gather_csr(A) for name, A in mats.items()}
    destroy_petsc(*mats.values())
    mass = gather_csr(column.system.M)
    a, WB = _quadrature_rows(column)
    layout = column.system.free_layout()
    if layout is None:
        return None
    dense = {name: A.toarray() for name, A in dense.items()}
    return dense, mass.toarray(), a, WB.toarray(), layout[1]


def _flexibility(Kb, Bw, Bt, a, kGA):
    """(K_c, F, G) of the module docstring from K_b, B_w, B_t, the weights and kGA."""
    if Bw.shape[0] != Bw.shape[1]:
        raise ValueError(f"condense: {Bw.shape[0]} shear points for {Bw.shape[1]} w dofs")
    Kb_BtT = sla.cho_solve(sla.cho_factor(Kb), Bt.T)
    C = np.diag(1.0 / (kGA * a)) + Bt @ Kb_BtT
    C = 0.5 * (C + C.T)
    S = sla.cho_solve(sla.cho_factor(C), Bw)  # C^-1 B_w: the Gauss-point shear forces per w
    Kc = Bw.T @ S
    lu = sla.lu_factor(Bw)
    F = sla.lu_solve(lu, sla.lu_solve(lu, C).T)
    return 0.5 * (Kc + Kc.T), 0.5 * (F + F.T), Kb_BtT @ S


def condense_rotation(column: BeckColumn) -> CondensedBeck:
    """Condense theta out of Beck's column (rhoI = 0). Collective; the result on every rank."""
    if column.params.rhoI != 0:
        raise ValueError("condense: theta has rotary inertia (rhoI > 0); use the full system")
    comm = column.msh.comm
    parts = _dense(column)
    result = None
    if parts is not None:
        K, M, a, WB, field = parts
        iw, it = np.flatnonzero(field == 0), np.flatnonzero(field == 1)
        B = WB / a[:, None]
        Kc, F, G = _flexibility(K["K_b"][np.ix_(it, it)], B[:, iw], -B[:, it], a,
                                column.params.kGA)
        ww = np.ix_(iw, iw)
        result = CondensedBeck(M[ww], Kc, F, K["K_g"][ww], K["K_f"][ww], G, iw, it,
                               column.params.load)
    return result if comm.size == 1 else comm.bcast(result, root=0)


def schur_complement(K: np.ndarray, field: np.ndarray) -> np.ndarray:
    """K_ww - K_wt K_tt^-1 K_tw of a dense (w, theta) matrix, directly (the reference the
    flexibility form is checked against; see the module docstring for its round-off)."""
    iw, it = np.flatnonzero(field == 0), np.flatnonzero(field == 1)
    Ktt = K[np.ix_(it, it)]
    return K[np.ix_(iw, iw)] - K[np.ix_(iw, it)] @ np.linalg.solve(Ktt, K[np.ix_(it, iw)])
