"""One slab's dual action assembled from the pointwise derivatives of its density.

The action of a slab (fem_dual.slab.problem) is S[w] = int_0^1 l(U, U_s) ds + (initial terms at
s = 0), with l = L_d dt the density, U = w and U_s = dw/ds at a point. Its residual and
Jacobian are

    R_i = int l_U . phi_i + l_Us . phi_i' ds,
    J_ij = int [phi_i, phi_i'] . Hess l . [phi_j, phi_j'] ds,

so one compiled expression of the gradient and the Hessian of l in (U, U_s) at the quadrature
points of all cells (one fem.Expression call), basis tables tabulated once, and two small array
products replace the assembly of the residual and Jacobian forms through DOLFINx and PETSc: the
same quadrature, the same discrete system to round-off (tests/test_local_action.py). UFL
differentiates the same density in the same variables, so the action stays the single source.

The unknowns are numbered in time order with the Dirichlet values xi(1) = eta(1) = 0 left out,
so the Jacobian is banded (a cell couples p + 1 consecutive nodes) and factored by LAPACK's
banded LU. The slab mesh is held whole by one process (comm of size 1): a slab's unknowns are
a few hundred, which one core factors in microseconds.
"""
from __future__ import annotations

from typing import Optional, Tuple

import basix
import numpy as np
import ufl

from fem_dual import native
from fem_dual.compat import CellPointEvaluator, function_space
from fem_dual.native.band import MAX_BASIS_PAIRS, Band
from fem_dual.native.tangents import Tangents
from fem_dual.quiet import _quiet, quiet_numpy  # noqa: F401 (quiet_numpy: re-exported)
from fem_dual.slab.band_layout import band_layout, hessian_pattern
from fem_dual.slab.banded import BandedLU
from fem_dual.slab.native_newton import NativeNewton, NativeNewtonResult
from fem_dual.slab.problem import SlabProblem

__all__ = ["LocalAction", "quiet_numpy"]


class LocalAction:
    """Residual and banded Jacobian of a slab problem over its free unknowns (time order).

    Args:
        problem: the slab problem, on a mesh of one process.
    """

    def __init__(self, problem: SlabProblem):
        if problem.comm.size != 1:
            raise ValueError("the pointwise assembly holds the whole slab mesh on one process")
        self.problem = p = problem
        self._w = p.w.x.array  # the dual state's values (a view of its vector: stays valid)
        msh = p.mesh.msh
        self.bs = p.W.dofmap.index_map_bs
        self._n2 = 2 * p.n  # the dual fields with end values (a lifted scene's multipliers: free)
        self.nd = p.degree + 1
        cell_count = msh.topology.index_map(1).size_local
        self.cells = np.arange(cell_count, dtype=np.int32)
        points, weights = basix.make_quadrature(basix.CellType.interval, p.quadrature_degree)
        self.nq = len(weights)
        self._compile_density(points)
        scalar, dofs, T, Tw, ends = self._basis_tables(points, weights)
        rows = self._number_unknowns(scalar, dofs)
        self._layout = band_layout(T, Tw, self.pairs, self.bs, rows, self.size)
        self.kd = self._layout.kd
        self._compiled_band()
        self._native_newton: Optional[NativeNewton] = None
        if self._native_band is not None and (p.pointwise is None
                                              or p.pointwise.Ginv is not None):
            self._native_newton = NativeNewton(self)

        # the momenta at the cell ends (fem_dual.slab.recovery): the cell residual at the vertex
        # basis functions (local dofs 0 and 1 sit at reference points 0 and 1), signed by the
        # cell's orientation
        left_first = (ends[:, 0] < ends[:, 1])[:, None]
        self._sign = np.where(left_first, [1.0, -1.0], [-1.0, 1.0])[:, :, None]
        self._Tg_ends = np.ascontiguousarray(self._Tg[:, :2])  # (the vertex basis functions)

        # the vertices of the cell ends, in the order of s (fem_dual.slab.recovery's vertex order)
        _, vertex, counts = np.unique(ends.ravel(), return_inverse=True, return_counts=True)
        # the mean of the one-sided values at each vertex: (vertices, cells * 2)
        self._vertex_mean = np.zeros((len(counts), 2 * cell_count))
        self._vertex_mean[vertex, np.arange(2 * cell_count)] = 1.0 / counts[vertex]
        self._T = T  # (cells, q, 2, nd)
        self._native_tangents = self._tangents_loop()

        self._held: Optional[Tuple[int, bytes]] = None
        self.error: Optional[str] = None  # why the implicit DtP map failed at the state
        self._initial_at: Optional[Tuple[int, np.ndarray]] = None
        self._both_at: Optional[tuple] = None  # (version, state, R) of the last evaluation
        self._tangent_at: Optional[tuple] = None  # (state, LU, tangent matrix)
        self._factors_at: Optional[tuple] = None  # (version, state, factors of J there)
        # whether a compiled Newton factors the Jacobian at its solution for the tangents (an
        # error companion, which takes none, does without: fem_dual.integrate.simulation.Simulation)
        self.factor_solution = True
        self._mass_at: Optional[tuple] = None  # (M, M^-1, d initial rows / d z0)

    def _compile_density(self, points: np.ndarray) -> None:
        """The density's gradient and the Hessian's upper triangle in Z = (U, U_s) as compiled
        expressions at the quadrature `points`, the Hessian pairs that enter the Jacobian, the
        derivative by the base state (for the exact tangents) and the initial terms'."""
        p, bs, nq = self.problem, self.bs, self.nq
        cell_count = len(self.cells)
        # the gradient of the density in Z = (U, U_s) (derivative k of component c at k bs + c),
        # and the Hessian's upper triangle, of which only the entries that are not zero
        # whatever the state and the constants enter the contraction (half for curl3d; all are
        # compiled: a second expression of the nonzero ones alone cost as much to evaluate)
        U, Us = p.U, p.Us
        grad = [ufl.diff(p.density, U), ufl.diff(p.density, Us)]
        flat_grad = [g[c] for g in grad for c in range(bs)]
        hess = {(k, l): ufl.diff(grad[k], V) for k in range(2) for l, V in enumerate((U, Us))}
        upper = [(K, L) for K in range(2 * bs) for L in range(K, 2 * bs)]
        entry = {(K, L): hess[K // bs, L // bs][K % bs, L % bs] for K, L in upper}
        self._both = CellPointEvaluator(ufl.as_vector(flat_grad + [entry[kl] for kl in upper]),
                                        points)
        self._out_both = np.zeros((cell_count, nq * (2 * bs + len(upper))))
        pairs = hessian_pattern(self._both, self.cells, upper, bs)
        self._hess_cols = 2 * bs + np.array([upper.index(kl) for kl in pairs], dtype=np.int64)
        self._points, self._flat_grad, self.pairs = points, flat_grad, pairs
        self._pair_index = (np.array([k for k, _ in pairs], dtype=np.int64),  # the Hessian's
                            np.array([l for _, l in pairs], dtype=np.int64))  # row, column
        # d grad / d zbar for the exact tangents, compiled now (with the rest: under MPI every
        # rank holds the slab, and rank 0 compiles first, see
        # fem_dual.integrate.simulation.Simulation)
        self._base_derivative: Optional[CellPointEvaluator] = None
        if p.Zbar is not None:
            G = ufl.diff(ufl.as_vector(flat_grad), p.Zbar)
            self._base_derivative = CellPointEvaluator(
                ufl.as_vector([G[i, j] for i in range(2 * bs) for j in range(2 * p.n)]), points)
        self._grad = CellPointEvaluator(ufl.as_vector(flat_grad), points)
        self._initial = CellPointEvaluator(ufl.diff(p.initial, U), np.zeros(1))
        self._out_grad = np.zeros((cell_count, nq * 2 * bs))
        self.hessian_entries = len(pairs)

    def _basis_tables(self, points: np.ndarray, weights: np.ndarray) -> tuple:
        """(the scalar space, the dofs of each cell, its basis values and derivatives at the
        points T (cells, q, 2, nd), T weighted by the quadrature and the cell length, the cell
        ends (cells, 2) in s); the residual's weighted table Tg kept."""
        p, nd, nq = self.problem, self.nd, self.nq
        msh = p.mesh.msh
        cell_count = len(self.cells)
        # basis values and derivatives d/ds at the points of every cell: (cells, q, 2, nd)
        scalar = function_space(msh, ("Lagrange", p.degree))
        dofs = p.W.dofmap.list.array.reshape(cell_count, nd)
        if not np.array_equal(scalar.dofmap.list.array.reshape(cell_count, nd), dofs):
            raise RuntimeError("the scalar space's dofmap differs from the dual space's blocks")
        phi = ufl.TestFunction(scalar)
        table = CellPointEvaluator(ufl.as_vector([phi, phi.dx(0)]), points)
        T = table(self.cells).reshape(cell_count, nq, 2, nd)
        vertices = msh.geometry.dofmap.array.reshape(-1, 2)[:cell_count]
        ends = msh.geometry.x[vertices, 0]
        size = np.abs(ends[:, 1] - ends[:, 0])  # cell length in s
        Tw = T * (weights[None, :, None, None] * size[:, None, None, None])
        # residual: r[e, a, c] = Tg[e] @ g[e] with Tg (nd, (q, k)) and g ((q, k), c)
        self._Tg = np.ascontiguousarray(Tw.transpose(0, 3, 1, 2).reshape(cell_count, nd,
                                                                          nq * 2))
        return scalar, dofs, T, Tw, ends

    def _number_unknowns(self, scalar, dofs: np.ndarray) -> np.ndarray:
        """Number the free unknowns in time order (the Dirichlet values at s = 1 left out);
        returns the row of each cell unknown (cells, nd, bs), -1 where it is fixed."""
        bs, n2 = self.bs, self._n2
        # unknowns in time order, without the Dirichlet values at s = 1
        s = scalar.tabulate_dof_coordinates()[:, 0]
        blocks = len(s)
        order = np.argsort(s, kind="stable")
        fixed = np.zeros((blocks, bs), dtype=bool)
        fixed[np.isclose(s, 1.0), :n2] = True
        free = ~fixed[order]
        index = np.full((blocks, bs), -1, dtype=np.int64)
        index[order] = np.where(free, np.cumsum(free).reshape(blocks, bs) - 1, -1)
        self.size = N = int(free.sum())
        self.free_global = np.flatnonzero((index >= 0).ravel())[np.argsort(
            index.ravel()[index.ravel() >= 0])]
        self.start_rows = index[np.isclose(s, 0.0)].ravel()  # the initial terms' rows
        # (a slice where they are consecutive, as in time order: a view instead of a gather)
        first, count = (int(self.start_rows[0]) if len(self.start_rows) else 0,
                        len(self.start_rows))
        consecutive = np.array_equal(self.start_rows, np.arange(first, first + count))
        self._start_rows = slice(first, first + count) if consecutive else self.start_rows

        rows = index[dofs]  # (cells, nd, bs): the row of each cell unknown, -1 if fixed
        self._cell_rows = np.where(rows >= 0, rows, N)  # (fixed: row N, kept zero)
        self._r_rows = rows.ravel()
        self._r_keep = np.flatnonzero(self._r_rows >= 0)
        self._r_rows = self._r_rows[self._r_keep]
        return rows

    # -- the state --------------------------------------------------------------------------

    def set_state(self, x: np.ndarray) -> Optional[str]:
        """Put the free unknowns `x` into the problem's dual state (the Dirichlet values stay
        zero) and solve the implicit DtP map there; returns why that failed, or None."""
        self._w[self.free_global] = x
        return self.sync()

    def state(self) -> np.ndarray:
        """The free unknowns of the problem's dual state."""
        return self._w[self.free_global].copy()

    def sync(self) -> Optional[str]:
        """The implicit DtP map solved at the current dual state and constants; skipped when
        it is held there already (every residual and Jacobian would otherwise solve it)."""
        p = self.problem
        if p.pointwise is None:
            return None
        if not self._current(self._held):
            self.error = p.pointwise.solve(p.comm)
            self._held = self._key()
        return self.error

    def _current(self, kept: Optional[tuple]) -> bool:
        """Whether `kept`, (version, dual state, ...), was made at the problem's current
        version and dual state (what the held DtP map, evaluation, factors and tangents are
        kept against)."""
        return (kept is not None and kept[0] == self.problem.version
                and kept[1] == self._w.tobytes())

    def _key(self) -> Tuple[int, bytes]:
        """(version, dual state) of the current state, as `_current` compares them (the
        state's bytes: equal bits, equal evaluations)."""
        return self.problem.version, self._w.tobytes()

    # -- residual and Jacobian --------------------------------------------------------------

    def _initial_rows(self) -> np.ndarray:
        """d/dU of the initial terms -x0.xi(0) - (M v0).eta(0) (constants only)."""
        version = self.problem.version
        if self._initial_at is None or self._initial_at[0] != version:
            self._initial_at = (version, self._initial(self.cells[:1])[0, 0].copy())
        return self._initial_at[1]

    def _residual(self, g: np.ndarray) -> np.ndarray:
        r = np.matmul(self._Tg, g.reshape(len(self.cells), self.nq * 2, self.bs))
        R = np.bincount(self._r_rows, r.ravel()[self._r_keep], minlength=self.size)
        R[self.start_rows] += self._initial_rows()
        return R

    @_quiet
    def residual(self) -> np.ndarray:
        """R at the current state (NaN where the implicit DtP map has no solution)."""
        if self.sync():
            return np.full(self.size, np.nan)
        g = self._grad.into(self.cells, self._out_grad)
        return self._residual(g)

    @_quiet
    def residual_and_jacobian(self) -> Tuple[np.ndarray, Optional[np.ndarray]]:
        """(R, the Jacobian's band in dgbtrf's storage) at the current state; (NaN, None) where
        the implicit DtP map has no solution."""
        if self.sync():
            return np.full(self.size, np.nan), None
        out = self._both.into(self.cells, self._out_both)
        cells, nq, bs = len(self.cells), self.nq, self.bs
        out = out.reshape(cells, nq, -1)
        R = self._residual(np.ascontiguousarray(out[..., :2 * bs]))
        self._both_at = self._key() + (R,)
        return R, self._band(out)

    @property
    def compiled_newton(self) -> bool:
        """Whether Newton's iterations run in compiled code (fem_dual.native), with the
        implicit DtP map's pointwise Newton inside each evaluation."""
        return self._native_newton is not None

    def native_newton(self, x: np.ndarray, **tests) -> Optional["NativeNewtonResult"]:
        """Newton from the free unknowns x in compiled code (NativeNewton.run); None where
        the numpy iteration must decide, or where it is not compiled. The state is left at
        the last iterate, its evaluation held."""
        if self._native_newton is None:
            return None
        result = self._native_newton.run(x, **tests)
        if result is None:
            self._both_at = None
            return None
        p = self.problem
        self._w[self.free_global] = result.x
        self._both_at = self._key() + (result.F,)
        if p.pointwise is not None:  # X and G_x^-1 solved there by the C loop
            self._held, self.error = self._both_at[:2], None
        if result.at_x is not None:
            self._factors_at = self._both_at[:2] + (result.at_x,)
        return result

    @property
    def compiled_band(self) -> bool:
        """Whether the Jacobian's band is assembled in compiled code (fem_dual.native)."""
        return self._native_band is not None

    @property
    def compiled_tangents(self) -> bool:
        """Whether a solved slab's exact tangents come from compiled code (fem_dual.native)."""
        return self._native_tangents is not None

    def _compiled_band(self) -> None:
        """Hold the compiled band (fem_dual.native.band) where the compiled loops are
        available."""
        self._native_band: Optional[Band] = None
        if native.library() is None or self.nd ** 2 > MAX_BASIS_PAIRS:
            return
        products, scale, total = self._layout.products
        self._native_band = Band(self._hess_cols, scale, [lo for lo, _, _, _, _ in products],
                                 [hi for _, hi, _, _, _ in products],
                                 [start for _, _, _, start, _ in products],
                                 np.stack([P.T for _, _, P, _, _ in products]), self._layout.j_flat,
                                 self._layout.j_source, total)

    def _tangents_loop(self) -> Optional[Tangents]:
        """The compiled tangents (fem_dual.native.tangents) where the compiled loops are
        available, else None (the numpy branch of _tangent_matrix)."""
        if native.library() is None:
            return None
        cells = len(self.cells)
        return Tangents(self._T, self._Tg, self._hess_cols, *self._pair_index, self._cell_rows,
                        self.size, self._sign.reshape(cells, 2),
                        self._out_both.reshape(cells, self.nq, -1), self.problem.n)

    def _band(self, out: np.ndarray) -> np.ndarray:
        """The Jacobian's band (dgbtrf's storage) from an evaluation (cells, q, columns)."""
        if self._native_band is not None and out.flags.c_contiguous:
            return self._native_band(out, np.empty((self._layout.band_rows, self.size)))
        products, scale, total = self._layout.products
        H = out.transpose(1, 0, 2)[:, :, self._hess_cols] * scale  # (q, cells, pairs)
        B = np.empty(total)
        for lo, hi, P, start, end in products:
            np.matmul(P, H[:, :, lo:hi].reshape(self.nq, -1), out=B[start:end].reshape(len(P), -1))
        band = np.bincount(self._layout.j_flat, B.ravel()[self._layout.j_source],
                           minlength=self._layout.band_rows * self.size)
        return band.reshape(self._layout.band_rows, self.size)

    def factor(self, band: np.ndarray) -> BandedLU:
        return BandedLU(band, self.kd)

    @_quiet
    def momenta(self) -> np.ndarray:
        """(cells, 2, 2n): x^ then M v^ at reference points 0 and 1 of each cell, from the
        cell residuals of the current state (fem_dual.slab.recovery.CellMomenta, without the form
        assembly)."""
        from fem_dual.errors import SolveError

        message = self.sync()
        if message:
            raise SolveError(message)
        held = self._held_evaluation()  # (a solved slab's last evaluation holds the gradient)
        g = (self._grad.into(self.cells, self._out_grad) if held is None
             else held[0][..., :2 * self.bs])
        r = np.matmul(self._Tg_ends, g.reshape(len(self.cells), self.nq * 2, self.bs))
        return self._sign * r[..., :self._n2]

    # -- the exact tangent of the slab map ---------------------------------------------------

    def _held_evaluation(self) -> Optional[Tuple[np.ndarray, np.ndarray]]:
        """(the evaluation (cells, q, columns), R) at the current state if the last evaluation
        was there."""
        if not self._current(self._both_at):
            return None
        return self._out_both.reshape(len(self.cells), self.nq, -1), self._both_at[2]

    def _held_factors(self) -> Optional[BandedLU]:
        """Factors of the Jacobian at the current state to round-off, where Newton's last step
        ended there (fem_dual.native's Newton, its step within FACTORS_KEPT_STEP)."""
        return self._factors_at[2] if self._current(self._factors_at) else None

    def _hessian(self, out: np.ndarray) -> np.ndarray:
        """The full symmetric Hessian of the density at the points: (cells, q, 2 bs, 2 bs)."""
        m = 2 * self.bs
        H = np.zeros(out.shape[:2] + (m, m))
        K, L = self._pair_index
        entries = out[..., self._hess_cols]
        H[..., K, L] = entries
        H[..., L, K] = entries
        return H

    @_quiet
    def vertex_tangent(self, dz: np.ndarray) -> Tuple[np.ndarray, "BandedLU"]:
        """d(x, v)/dz0 . dz at the vertices (in the order of s; (vertices, 2n)) of the slab
        solved at the current state, exactly: J dw = -dR/dz0 dz with J at the solution, and the
        momenta's derivative. z0 enters through the initial terms and, where the base state is
        the start state, through the base state in the density (its derivative by UFL; for an
        implicit DtP map the Newton-linearised map has the exact derivative at the root). A
        base state that is a function of time (the flow predictor's) is held: it moves the
        answer only by the discretisation error, so the tangent with it held is the slab
        map's to that order."""
        if self.sync():
            raise ValueError(self.error)
        lu, matrix, _ = self._tangents()
        return matrix @ np.asarray(dz, dtype=float), lu

    @_quiet
    def tangent_matrix(self) -> np.ndarray:
        """d(x, v)/dz0 at the vertices, (vertices, 2n, 2n), of the slab solved at the current
        state (see vertex_tangent)."""
        if self.sync():
            raise ValueError(self.error)
        return self._tangents()[1]

    @_quiet
    def newton_change(self) -> np.ndarray:
        """How far the vertex values (vertices, 2n) of the current state would move with one
        more Newton step, -J^-1 R, to first order in the step (the momenta's derivative, as
        the tangents'): the algebraic error of a solved slab, from the tangents' solve."""
        if self.sync():
            raise ValueError(self.error)
        return self._tangents()[2]

    def _tangents(self) -> Tuple["BandedLU", np.ndarray, np.ndarray]:
        """(factors, tangent matrix, Newton change) at the current state, kept while it is
        current."""
        if not self._current(self._tangent_at):
            key = self._key()
            self._tangent_at = key + self._tangent_matrix()
        return self._tangent_at[2:]

    def _tangent_matrix(self) -> Tuple["BandedLU", np.ndarray, np.ndarray]:
        """(the Jacobian's factors, d(x, v)/dz0 at the vertices: (vertices, 2n, 2n), the
        vertex change of one more Newton step: (vertices, 2n)) at the current state, for all 2n
        unit changes of the start state and the Newton step at once (one banded solve with
        2n + 1 right-hand sides: the tangent along the estimate's error, the volume check of
        fem_dual.integrate.simulation and the algebraic error then cost a product and a
        determinant)."""
        p = self.problem
        n, bs, cells, nq = p.n, self.bs, len(self.cells), self.nq
        K = 2 * n
        held = self._held_evaluation()
        if held is None:
            R, band = self.residual_and_jacobian()
            out = self._out_both.reshape(cells, nq, -1)
            lu = self.factor(band)
        else:
            out, R = held
            lu = self._held_factors() or self.factor(self._band(out))
        # -d R / d z0, then -R (the Newton step's), and a zero row for the fixed unknowns
        with_base = p.base == "start" and self._base_derivative is not None
        compiled = (self._native_tangents is not None and not with_base
                    and out.flags.c_contiguous)
        rhs = self._native_tangents.dw if compiled else np.empty((self.size + 1, K + 1))
        rhs.fill(0.0)
        np.negative(R, out=rhs[:-1, K])
        dg_base = None
        if with_base:  # d grad / d zbar
            dg_base = self._base_derivative(self.cells).reshape(cells, nq, 2 * bs, K)
            r = np.matmul(self._Tg, dg_base.reshape(cells, nq * 2, bs * K))  # (cells, nd, bs K)
            rows = r.reshape(-1, K)[self._r_keep]
            for k in range(K):
                rhs[:-1, k] = -np.bincount(self._r_rows, rows[:, k], minlength=self.size)
        Minv, initial = self._mass_derived()
        rhs[self._start_rows, :K] -= initial
        K1 = K + 1
        lu.solve_in_place(rhs[:-1])  # dw: (size, K + 1)
        if compiled:
            dm = self._compiled_tangents()
        else:
            cell_dw = rhs[self._cell_rows]  # (cells, nd, bs, K + 1)
            dZ = np.matmul(self._T.reshape(cells, nq * 2, -1),
                           cell_dw.reshape(cells, -1, bs * K1))
            dg = np.matmul(self._hessian(out), dZ.reshape(cells, nq, 2 * bs, K1))
            if dg_base is not None:
                dg[..., :K] += dg_base
            dm = np.matmul(self._Tg, dg.reshape(cells, nq * 2, bs * K1)).reshape(cells, -1, bs,
                                                                                K1)
            dm = self._sign[..., None] * dm[:, :2, :K]  # (cells, 2, 2n, K + 1): x then M v
            dm[:, :, n:] = np.matmul(Minv, dm[:, :, n:])
        vertices = (self._vertex_mean @ dm.reshape(cells * 2, K * K1)).reshape(-1, K, K1)
        return lu, np.ascontiguousarray(vertices[..., :K]), vertices[..., K].copy()

    def _compiled_tangents(self) -> np.ndarray:
        """The numpy branch of _tangent_matrix after its solve in compiled code
        (fem_dual.native.tangents): dm (cells, 2, 2n, 2n + 1) from the solved unknowns dw
        (the loop's own right-hand sides, solved in place: (size + 1, 2n + 1), the last row
        zero) and the evaluation in `_out_both`."""
        return self._native_tangents()

    def _mass_derived(self) -> Tuple[np.ndarray, np.ndarray]:
        """(M^-1, d/dz0 of the initial terms' rows: (start rows, 2n)), kept while M is: the
        initial terms are linear in (x0, v0), with M their only constant."""
        p = self.problem
        M = p.c["M"].value
        if self._mass_at is None or self._mass_at[0] != M.tobytes():
            n = p.n
            columns = []
            saved = p.x0.value.copy(), p.v0.value.copy()
            try:
                for unit in np.eye(2 * n):
                    p.x0.value, p.v0.value = unit[:n], unit[n:]
                    columns.append(self._initial(self.cells[:1])[0, 0].copy())
            finally:
                p.x0.value, p.v0.value = saved
            Minv = np.ascontiguousarray(np.linalg.inv(M))
            if self._native_tangents is not None:
                self._native_tangents.use_mass_inverse(Minv)
            self._mass_at = (M.tobytes(), Minv, np.column_stack(columns))
        return self._mass_at[1], self._mass_at[2]

    def dense_jacobian(self) -> np.ndarray:
        """The Jacobian at the current state as a dense matrix (tests)."""
        _, band = self.residual_and_jacobian()
        N, kd = self.size, self.kd
        J = np.zeros((N, N))
        for offset in range(-kd, kd + 1):  # j - i; band[2 kd + i - j, j]
            idx = np.arange(max(0, offset), min(N, N + offset))
            J[idx - offset, idx] = band[2 * kd - offset, idx]
        return J
