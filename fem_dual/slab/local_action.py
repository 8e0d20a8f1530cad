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

from dataclasses import dataclass
from typing import Optional, Tuple

import basix
import numpy as np
import ufl
from dolfinx import fem
from scipy.linalg import lapack

from fem_dual.compat import CellPointEvaluator
from fem_dual.quiet import _quiet, quiet_numpy  # noqa: F401 (quiet_numpy: re-exported)
from fem_dual.slab.problem import SlabProblem

__all__ = ["LocalAction", "BandedLU", "quiet_numpy"]


# The factors of Newton's last Jacobian serve the tangents at its last iterate when that step
# moved the state by at most this much (relative): the Jacobians differ by as little, and the
# tangents feed estimates (a factorisation less per slab: 85 us of 3 ms on curl3d T = 8, p = 6,
# 8 cells); after a longer step the compiled Newton factors the Jacobian there itself, from
# the band it assembles anyway
FACTORS_KEPT_STEP = 1e-8


class BandedLU:
    """The factors of a symmetric banded matrix for later solves: Cholesky, which the slab
    Jacobians admit near their solution (positive definite there), else LU with pivoting
    (LAPACK's dgbtrf). The Cholesky factor is in LAPACK's upper band storage (dpbtrf's): the
    compiled one of fem_dual.native (twice the reference LAPACK's speed here) where it is
    available, else dpbtrf.

    Args:
        band: the matrix in dgbtrf's storage with kl = ku = `kd` (band[2 kd + i - j, j]); rows
            kd .. 2 kd of it are dpbtrf's upper storage.
    """

    def __init__(self, band: np.ndarray, kd: int):
        from fem_dual import native

        self.kd = kd
        self.piv = None
        self._native = native.library()
        if self._native is not None:
            ffi, lib = self._native
            upper = np.array(band[kd:2 * kd + 1], dtype=float, order="F")
            info = lib.fem_dual_band_cholesky(upper.shape[1], kd,
                                              ffi.from_buffer("double[]", upper.T), kd + 1,
                                              ffi.from_buffer("double[]", np.empty(kd + 1)))
            self.cholesky = upper
        else:
            self.cholesky, info = lapack.dpbtrf(band[kd:2 * kd + 1])
        if info != 0:  # not positive definite
            self.cholesky = None
            self.lu, self.piv, info = lapack.dgbtrf(band, kd, kd, overwrite_ab=1)
        self.singular = info != 0

    @classmethod
    def of_cholesky(cls, cholesky: np.ndarray, kd: int, built=None) -> "BandedLU":
        """The Cholesky factor computed elsewhere (fem_dual.native's Newton, `built` its
        (ffi, lib)): upper storage, (kd + 1, N), Fortran order."""
        if built is None:
            from fem_dual import native

            built = native.library()
        lu = cls.__new__(cls)
        lu.kd, lu.cholesky, lu.piv, lu.singular = kd, cholesky, None, False
        lu._native = built
        return lu

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        if self.cholesky is not None and self._native is not None:
            return self.solve_in_place(np.array(rhs, dtype=float, order="C"))
        if self.cholesky is not None:
            x, info = lapack.dpbtrs(self.cholesky, rhs)
        else:
            x, info = lapack.dgbtrs(self.lu, self.kd, self.kd, rhs, self.piv)
        if info != 0:
            raise ValueError(f"banded solve: illegal argument {-info}")
        return x

    def solve_in_place(self, x: np.ndarray) -> np.ndarray:
        """The solution in x, a C-contiguous float array (N,) or (N, columns) of right-hand
        sides (no copy where the compiled solve runs); returns x."""
        if self.cholesky is None or self._native is None:
            x[...] = self.solve(x)
            return x
        ffi, lib = self._native
        N = self.cholesky.shape[1]
        lib.fem_dual_band_solve(N, self.kd, ffi.from_buffer("double[]", self.cholesky.T),
                                self.kd + 1, x.size // N if N else 0,
                                ffi.from_buffer("double[]", x))
        return x


def _randomised(expr, evaluate, draws: int = 3):
    """evaluate() with every constant and coefficient of `expr` set to random values, `draws`
    times (restored afterwards): arrays of the draws."""
    from ufl.algorithms import extract_coefficients
    from ufl.algorithms.analysis import extract_constants

    rng = np.random.default_rng(20261125)
    constants = extract_constants(expr)
    functions = extract_coefficients(expr)
    saved = [c.value.copy() for c in constants] + [f.x.array.copy() for f in functions]
    out = []
    try:
        for _ in range(draws):
            for c in constants:
                c.value = rng.uniform(0.5, 1.5, np.shape(c.value)) * rng.choice([-1, 1])
            for f in functions:
                f.x.array[:] = rng.uniform(-1.0, 1.0, f.x.array.shape)
            with np.errstate(all="ignore"):
                out.append(evaluate().copy())
    finally:
        for c, value in zip(constants, saved):
            c.value = value
        for f, value in zip(functions, saved[len(constants):]):
            f.x.array[:] = value
    return out


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
        self.bs = bs = p.W.dofmap.index_map_bs
        n2 = 2 * p.n  # the dual fields with end values; a lifted scene's multipliers are free
        self.nd = nd = p.degree + 1
        cell_count = msh.topology.index_map(1).size_local
        self.cells = np.arange(cell_count, dtype=np.int32)
        points, weights = basix.make_quadrature(basix.CellType.interval, p.quadrature_degree)
        nq = len(weights)
        self.nq = nq

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
        pairs = self._pattern(upper)
        self._hess_cols = 2 * bs + np.array([upper.index(kl) for kl in pairs], dtype=np.int64)
        self._points, self._flat_grad, self.pairs = points, flat_grad, pairs
        self._pair_index = (np.array([k for k, _ in pairs], dtype=np.int64),  # the Hessian's
                            np.array([l for _, l in pairs], dtype=np.int64))  # row, column
        # d grad / d zbar for the exact tangents, compiled now (with the rest: under MPI every
        # rank holds the slab, and rank 0 compiles first, see fem_dual.integrate.simulation.Simulation)
        self._base_derivative: Optional[CellPointEvaluator] = None
        if p.Zbar is not None:
            G = ufl.diff(ufl.as_vector(flat_grad), p.Zbar)
            self._base_derivative = CellPointEvaluator(
                ufl.as_vector([G[i, j] for i in range(2 * bs) for j in range(2 * p.n)]), points)
        self._grad = CellPointEvaluator(ufl.as_vector(flat_grad), points)
        self._initial = CellPointEvaluator(ufl.diff(p.initial, U), np.zeros(1))
        self._out_grad = np.zeros((cell_count, nq * 2 * bs))
        self.hessian_entries = len(pairs)

        # basis values and derivatives d/ds at the points of every cell: (cells, q, 2, nd)
        scalar = fem.FunctionSpace(msh, ("Lagrange", p.degree))
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
        # Jacobian: the entries of Hessian pair (K, L) = (k bs + c, l bs + d) at the basis
        # functions a, b: B[e, (a, b), pair] = P_kl[e] @ H[e, q, pair], P_kl[(a, b), q] =
        # w_q T[q, k, a] T[q, l, b], for the pairs of each (k, l) at once
        groups = []
        group_of = np.zeros(len(pairs), dtype=np.int64)  # each pair's group among those present
        for k, l in ((0, 0), (0, 1), (1, 1)):
            members = [i for i, (K, L) in enumerate(pairs) if (K // bs, L // bs) == (k, l)]
            if not members:
                continue
            if members != list(range(members[0], members[-1] + 1)):
                raise RuntimeError("the Hessian pairs of a group are not contiguous")
            group_of[members] = len(groups)
            P = np.einsum("eqa,eqb->eabq", Tw[:, :, k], T[:, :, l])
            groups.append((members[0], members[-1] + 1,
                           np.ascontiguousarray(P.reshape(cell_count, nd * nd, nq))))
        # On an interval every cell's P is its first cell's times a number (its length, and
        # its Jacobian per derivative): then each group takes one matrix product for all
        # cells, P (nd^2, q) @ H (q, cells members), after a scaling per cell and pair, into
        # one buffer ([nd^2, cells, members] per group, one after the other)
        scale = np.ones((cell_count, len(groups)))
        for g, (_, _, P) in enumerate(groups):
            first = P[0].ravel()
            scale[:, g] = P.reshape(cell_count, -1) @ first / (first @ first)
            if not np.allclose(P, scale[:, g, None, None] * P[0], rtol=1e-13,
                               atol=1e-13 * np.abs(first).max()):
                raise RuntimeError("a cell of the slab mesh is not an affine image of the first")
        offsets = np.zeros(len(pairs), dtype=np.int64)  # where each pair's group starts
        products, start = [], 0
        for lo, hi, P in groups:
            size = nd * nd * cell_count * (hi - lo)
            products.append((lo, hi, P[0], start, start + size))
            offsets[lo:hi] = start
            start += size
        self._products = (products, np.ascontiguousarray(scale[:, group_of]), start)
        self._native_band = None  # its compiled twin's pointers (_compiled_band)

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
        # entry (e, a, b, pair) of B couples row (e, a, c) and column (e, b, d), and, off the
        # diagonal of the Hessian, row (e, b, d) and column (e, a, c) too
        c_of = np.array([K % bs for K, _ in pairs], dtype=int)
        d_of = np.array([L % bs for _, L in pairs], dtype=int)
        e_, a_, b_, m_ = np.meshgrid(np.arange(cell_count), np.arange(nd), np.arange(nd),
                                     np.arange(len(pairs)), indexing="ij")
        i = rows[e_, a_, c_of[m_]].ravel()
        j = rows[e_, b_, d_of[m_]].ravel()
        mirror = np.array([K != L for K, L in pairs])[m_].ravel()
        # the entry's place in its group's [nd^2, cells, members] (see _band)
        lows = np.array([lo for lo, _, _ in groups], dtype=np.int64)[group_of]
        sizes = np.array([hi - lo for lo, hi, _ in groups], dtype=np.int64)[group_of]
        source = (offsets[m_] + ((a_ * nd + b_) * cell_count + e_) * sizes[m_]
                  + m_ - lows[m_]).ravel()
        i, j, source = (np.concatenate([i, j[mirror]]), np.concatenate([j, i[mirror]]),
                        np.concatenate([source, source[mirror]]))
        keep = (i >= 0) & (j >= 0)
        i, j, source = i[keep], j[keep], source[keep]
        self.kd = kd = int(np.abs(i - j).max(initial=0))
        up = i <= j  # the upper band alone, in LAPACK's storage (fem_dual.native's Newton)
        self._u_flat = (kd + i[up] - j[up]) + j[up] * (kd + 1)
        self._u_source = source[up]
        self._band_rows = 3 * kd + 1  # dgbtrf's storage: kd more rows for the fill-in
        self._j_source = source
        self._j_flat = (2 * kd + i - j) * N + j  # band[2 kd + i - j, j] = J[i, j]
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
        self._n2 = n2

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
        self._mass_at: Optional[tuple] = None  # (M, M^-1, d initial rows / d z0, M^-1's C)

    def _pattern(self, upper: list) -> list:
        """The Hessian pairs (K, L) of `upper` whose entries are not zero at random dual states,
        constants and coefficients (zero there: zero whatever they are), ordered by the
        derivative parts (K // bs, L // bs)."""
        bs, m = self.bs, len(upper)
        nonzero = np.zeros(m, dtype=bool)
        for values in _randomised(self._both.expression,
                                  lambda: self._both(self.cells)[..., 2 * bs:]):
            nonzero |= (values != 0).reshape(-1, m).any(axis=0)  # NaN counts as nonzero
        return sorted((key for key, nz in zip(upper, nonzero) if nz),
                      key=lambda KL: (KL[0] // bs, KL[1] // bs, KL))

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

    def _compiled_band(self) -> None:
        """Hold what the compiled band (fem_dual.native) reads, as C pointers, where the
        compiled loops are available."""
        from fem_dual import native

        built = native.library()
        if built is None or self.nd ** 2 > 1024:  # (the loop's sums are on its stack)
            return
        ffi, lib = built
        products, scale, total = self._products
        arrays = [np.ascontiguousarray(a, dtype=dtype) for a, dtype in (
            (self._hess_cols, np.int64), (scale, float),
            ([lo for lo, _, _, _, _ in products], np.int64),
            ([hi for _, hi, _, _, _ in products], np.int64),
            ([start for _, _, _, start, _ in products], np.int64),
            (np.stack([P.T for _, _, P, _, _ in products]), float),
            (self._j_flat, np.int64), (self._j_source, np.int64), (np.empty(total), float))]
        pointers = [native.pointer(ffi, a, "int64_t *" if a.dtype == np.int64 else "double *")
                    for a in arrays]  # (each keeps its array alive)
        self._native_band = (ffi, lib, pointers, len(products), arrays[5].shape[2],
                             len(self._j_flat))

    def _tangents_loop(self) -> Optional[tuple]:
        """(ffi, lib, what fem_dual.native's `tangents` reads as C pointers) where the compiled
        loops are available, else None (the numpy branch of _tangent_matrix)."""
        from fem_dual import native

        built = native.library()
        if built is None:
            return None
        ffi, _ = built
        cells = len(self.cells)
        arrays = [np.ascontiguousarray(a, dtype=dtype) for a, dtype in (
            (self._T, float), (self._Tg, float), (self._hess_cols, np.int64),
            *((index, np.int64) for index in self._pair_index),
            (self._cell_rows, np.int64), (self._sign.reshape(cells, 2), float))]
        pointers = [native.pointer(ffi, a, "int64_t *" if a.dtype == np.int64 else "double *")
                    for a in arrays]  # (each keeps its array alive)
        # its right-hand sides (solved in place), its output and work, reused by every call
        K1 = self._n2 + 1
        dw, dm = np.empty((self.size + 1, K1)), np.empty((cells, 2, self._n2, K1))
        buffers = (dw, dm) + tuple(native.pointer(ffi, a) for a in (
            self._out_both, dw, dm, np.empty(4 * self.bs * K1)))
        return built + (tuple(pointers), buffers)

    def _band(self, out: np.ndarray) -> np.ndarray:
        """The Jacobian's band (dgbtrf's storage) from an evaluation (cells, q, columns)."""
        if self._native_band is not None and out.flags.c_contiguous:
            ffi, lib, (cols, scale, lo, hi, start, P, flat, source, B), groups, nd2, \
                entries = self._native_band
            band = np.empty((self._band_rows, self.size))
            lib.fem_dual_band(out.shape[0], out.shape[1], out.shape[2],
                              ffi.from_buffer("double[]", out), len(self.pairs), cols, scale,
                              groups, lo, hi, start, P, nd2, entries, flat, source, B,
                              ffi.from_buffer("double[]", band), band.size)
            return band
        products, scale, total = self._products
        H = out.transpose(1, 0, 2)[:, :, self._hess_cols] * scale  # (q, cells, pairs)
        B = np.empty(total)
        for lo, hi, P, start, end in products:
            np.matmul(P, H[:, :, lo:hi].reshape(self.nq, -1), out=B[start:end].reshape(len(P), -1))
        band = np.bincount(self._j_flat, B.ravel()[self._j_source],
                           minlength=self._band_rows * self.size)
        return band.reshape(self._band_rows, self.size)

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
        fem_dual.integrate.simulation and the algebraic error then cost a product and a determinant)."""
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
        rhs = self._native_tangents[3][0] if compiled else np.empty((self.size + 1, K + 1))
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
            dm = self._compiled_tangents(out)
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

    def _compiled_tangents(self, out: np.ndarray) -> np.ndarray:
        """The numpy branch of _tangent_matrix after its solve in compiled code
        (fem_dual.native's `tangents`): dm (cells, 2, 2n, 2n + 1) from the solved unknowns dw
        (the loop's own right-hand sides, solved in place: (size + 1, 2n + 1), the last row
        zero) and the evaluation out (cells, q, columns), which is `_out_both`'s."""
        ffi, lib, fixed, (dw, dm, to_out, to_dw, to_dm, to_work) = self._native_tangents
        p, cells = self.problem, len(self.cells)
        T, Tg, cols, pk, pl, rows, sign = fixed
        lib.fem_dual_tangents(cells, self.nq, self.nd, self.bs, p.n, dw.shape[1], T, Tg,
                              to_out, out.shape[2], len(self.pairs), cols, pk, pl, to_dw, rows,
                              sign, self._mass_at[3], to_dm, to_work)
        return dm

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
            built = self._native_tangents
            self._mass_at = (M.tobytes(), Minv, np.column_stack(columns),
                             None if built is None else built[0].from_buffer("double[]", Minv))
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


@dataclass
class NativeNewtonResult:
    """How a compiled Newton (NativeNewton.run) ended: SNES's reason name, the last iterate
    and its residual, the residual history, the last step's factors (None without a step),
    the backward floor (fem_dual.slab.snes.backward_floor) at the last factored iterate and the
    last step's size relative to the iterate."""

    reason: str
    x: np.ndarray
    F: np.ndarray
    history: list
    lu: Optional[BandedLU]
    backward: float
    last_step: float  # |the last step| / |x| (inf without a step)
    at_x: Optional[BandedLU] = None  # the factors of the Jacobian at x (to round-off)


_REASONS = {1: "CONVERGED_FNORM_ABS", 2: "CONVERGED_FNORM_RELATIVE",
            3: "CONVERGED_SNORM_RELATIVE", -1: "DIVERGED_MAX_IT"}


class NativeNewton:
    """The Newton iteration of fem_dual.slab.pointwise_newton.PointwiseNewtonSolver in compiled code
    (fem_dual.native's fem_dual_slab_newton), an implicit DtP map solved inside each
    evaluation (_ImplicitMap): the same evaluations, band, banded Cholesky and tests, while
    every full step is taken; where the line search would shorten a step, or a factorisation,
    a value or the DtP map fails, `run` returns None and the numpy iteration starts over (the
    failure paths stay in one place). One call per solve instead of some 30 Python calls per
    Newton step.

    Args:
        local: the slab's pointwise assembly (with its compiled band).
    """

    def __init__(self, local: LocalAction):
        from fem_dual import native
        from fem_dual.native.force import PackedExpression

        self.local = local
        self.ffi, self.lib = native.library()
        p = local.problem
        self.expr = PackedExpression(local._both.compiled, local.cells)
        index = self.expr.index(p.w)  # (cells, nd bs): the dual state's values in each row
        free = np.full(p.w.x.array.size, -1, dtype=np.int64)
        free[local.free_global] = np.arange(local.size)
        self.wfree = np.ascontiguousarray(free[index])
        self.wslot = np.ascontiguousarray(np.broadcast_to(self.expr.slot(p.w), index.shape),
                                          dtype=np.int64)
        N, kd = local.size, local.kd
        self.u_flat = np.ascontiguousarray(local._u_flat, dtype=np.int64)
        self.u_source = np.ascontiguousarray(local._u_source, dtype=np.int64)
        self.r = np.empty(len(local.cells) * local.nd * local.bs)
        self.work = np.empty((4, N))
        self.history = np.empty(64)
        self.r_keep = np.ascontiguousarray(local._r_keep, dtype=np.int64)
        self.r_rows = np.ascontiguousarray(local._r_rows, dtype=np.int64)
        self.start_rows = np.ascontiguousarray(local.start_rows, dtype=np.int64)
        self.Tg = np.ascontiguousarray(local._Tg)
        self.ints = self.ffi.new("int[3]")  # iterations, reason, final factors made
        self.doubles = self.ffi.new("double[2]")  # the backward floor, the last step
        self.F, self.step, self.trial, self.Fnew = self.work
        cells = len(local.cells)
        (_, _, band_pointers, groups, nd2, _) = local._native_band
        cols, scale, lo, hi, start, PT, _, _, B = band_pointers
        packed = self.expr.pack()  # (its rows stay where they are: packed again per solve)
        ffi = self.ffi

        def d(a, kind="double *"):
            return native.pointer(ffi, a, kind)
        self.dtp = _ImplicitMap(self, free) if p.pointwise is not None else None
        # the call's arguments in order (the pointers keep their arrays alive); each solve
        # sets those given as a name here
        args = [
            self.expr.kernel, cells, local.nq, local._out_both.size // (cells * local.nq),
            packed.shape[1], d(packed), "constants", d(self.expr.coords), self.wfree.shape[1],
            d(self.wslot, "int64_t *"), d(self.wfree, "int64_t *"), local.nd, local.bs,
            d(self.Tg), len(self.r_keep), d(self.r_keep, "int64_t *"),
            d(self.r_rows, "int64_t *"), len(self.start_rows),
            d(self.start_rows, "int64_t *"), "initial", len(local.pairs), cols, scale, groups,
            lo, hi, start, PT, nd2, len(self.u_flat), d(self.u_flat, "int64_t *"),
            d(self.u_source, "int64_t *"), B, N, kd, "chol",
            d(np.empty(kd + 1)), "x", d(self.F), d(self.step), d(self.trial), d(self.Fnew),
            d(self.r), d(local._out_both), "atol", "check_start", "rtol", "stol", "max_it",
            "patience", "no_progress", "decrease", d(self.history), self.ints, self.doubles,
            self.doubles + 1, self.ints + 1,
            self.ffi.NULL if self.dtp is None else self.dtp.struct, "final",
            FACTORS_KEPT_STEP, self.ints + 2]
        self._slots = {a: i for i, a in enumerate(args) if isinstance(a, str)}
        self._tests = (self._slots["atol"], self._slots["decrease"] + 1)  # (in this order)
        self._args = args
        # the iterate and the factors (each solve's: the last solve's are dropped by the next,
        # its held factors and tangents with its version), the constants and initial rows
        # copied in: arrays with their C pointers, reused by every solve
        self._kept = {}
        for name, array in (("x", np.empty(N)), ("chol", np.empty((kd + 1, N), order="F")),
                            ("final", np.empty((kd + 1, N), order="F"))):
            self._kept[name] = (array, ffi.from_buffer("double[]", array.T))
            args[self._slots[name]] = self._kept[name][1]

    def _in(self, name: str, values: np.ndarray) -> None:
        """Copy `values` into the argument `name`'s kept array (made, with its pointer, at the
        first call and whenever the size changes)."""
        kept = self._kept.get(name)
        if kept is None or kept[0].shape != values.shape:
            array = np.array(values, dtype=float, order="C")
            self._kept[name] = (array, self.ffi.from_buffer("double[]", array))
            self._args[self._slots[name]] = self._kept[name][1]
        else:
            kept[0][...] = values
    def run(self, x0: np.ndarray, atol: float, check_start: bool, rtol: float, stol: float,
            max_it: int, patience: Optional[int], no_progress: float,
            decrease: float) -> Optional[NativeNewtonResult]:
        """Newton from x0 with the tests of PointwiseNewtonSolver.solve; None where the numpy
        iteration must decide (see fem_dual.native)."""
        ffi, local, kd = self.ffi, self.local, self.local.kd
        if max_it + 1 > len(self.history):
            raise ValueError(f"at most {len(self.history) - 1} Newton iterations")
        self.expr.pack()
        self._in("constants", self.expr.constants())
        self._in("initial", local._initial_rows())
        x, chol, final = (self._kept[name][0] for name in ("x", "chol", "final"))
        x[:] = x0
        args = self._args
        args[self._slots["final"]] = (self._kept["final"][1] if local.factor_solution
                                      else ffi.NULL)
        args[self._tests[0]:self._tests[1]] = (
            atol, int(check_start), rtol, stol, max_it, -1 if patience is None else patience,
            no_progress, decrease)
        if self.dtp is not None:
            self.dtp.begin()
        status = self.lib.fem_dual_slab_newton(*args)
        F = self.F
        if self.dtp is not None:
            self.dtp.end(status == 0)
        if status != 0:
            return None
        it, reason = self.ints[0], self.ints[1]
        last_step = float(self.doubles[1])
        lu = BandedLU.of_cholesky(chol, kd, (ffi, self.lib)) if it > 0 else None
        at_x = (BandedLU.of_cholesky(final, kd, (ffi, self.lib)) if self.ints[2]
                else lu if last_step <= FACTORS_KEPT_STEP else None)
        return NativeNewtonResult(_REASONS[reason], x, F.copy(),
                                  self.history[:it + 1].tolist(), lu,
                                  float(self.doubles[0]), last_step, at_x)


class _ImplicitMap:
    """What NativeNewton's C loop needs to solve an implicit DtP map (fem_dual.slab.pointwise_dtp.
    PointwiseDtP) inside each evaluation: its expression's packed rows, where the dual state,
    X and G_x^-1 sit in them and in the density's rows, as a fem_dual_dtp struct."""

    def __init__(self, newton: "NativeNewton", free: np.ndarray):
        from fem_dual import native
        from fem_dual.native.force import PackedExpression
        from fem_dual.slab.pointwise_dtp import BRANCH_TOL, LAST_STEP, MAX_IT

        local, ffi = newton.local, newton.ffi
        p = local.problem
        self.map = dtp = p.pointwise
        self.local = local
        self.expr = expr = PackedExpression(dtp._eval.compiled, dtp.cells)
        n, points, cells = dtp.n, len(dtp.points), len(dtp.cells)
        index = expr.index(p.w)
        both = newton.expr
        arrays = {
            "wfree": free[index], "wslot": np.broadcast_to(expr.slot(p.w), index.shape),
            "xslot": expr.slot(dtp.X), "xdofs": dtp.dofs,
            "both_xslot": both.slot(dtp.X), "both_xindex": both.index(dtp.X),
            "both_gslot": both.slot(dtp.Ginv), "both_gindex": both.index(dtp.Ginv)}
        self._keep = {k: np.ascontiguousarray(a, dtype=np.int64) for k, a in arrays.items()}
        self._keep.update(out=np.zeros(cells * points * (n + n * n + 1)),
                          step=np.zeros(cells * points * n), work=np.zeros(2 * n * n))
        D = self.struct = ffi.new("fem_dual_dtp *")
        D.kernel, D.points, D.n, D.wsize = expr.kernel, points, n, expr.packed.shape[1]
        D.nw, D.max_it, D.last_step, D.branch_tol = index.shape[1], MAX_IT, LAST_STEP, BRANCH_TOL
        D.nx, D.ng = len(both.slot(dtp.X)), len(both.slot(dtp.Ginv))
        self._pointers = {}
        for name, array in list(self._keep.items()) + [
                ("packed", expr.packed), ("coords", expr.coords), ("X", dtp.X.x.array),
                ("Ginv", dtp.Ginv.x.array)]:
            kind = "int64_t *" if array.dtype == np.int64 else "double *"
            self._pointers[name] = pointer = native.pointer(ffi, array, kind)
            setattr(D, name, pointer)
        self._ffi = ffi
        self._start: Optional[np.ndarray] = None

    def begin(self) -> None:
        """Pack the map's rows at the current state and constants; keep X to go back to."""
        self.expr.pack()
        self._constants = self.expr.constants()
        self.struct.c = self._ffi.from_buffer("double[]", self._constants)
        self._start = self.map.X.x.array.copy()

    def end(self, solved: bool) -> None:
        """After the C loop: the map is held at its last state, or X as it was (the numpy
        iteration solves the map again)."""
        local = self.local
        if solved:  # (LocalAction.native_newton holds it at the last iterate)
            self.map.iterations = self.struct.iterations
        else:
            self.map.X.x.array[:] = self._start
            local._held = None
