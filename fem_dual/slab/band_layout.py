"""The layout of a slab Jacobian's band (fem_dual.slab.local_action.LocalAction): which entries of
the density's Hessian enter it, the products of basis tables with each group of them (one
buffer), and where each product lands in LAPACK's band storages."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["BandLayout", "band_layout", "hessian_pattern"]


@dataclass
class BandLayout:
    """Where a slab Jacobian's entries come from and go.

    products: ([(lo, hi, P, start, end)] per group of Hessian pairs: its pairs, basis table
    P (nd^2, q) and span of the buffer; each pair's scale per cell (cells, pairs); the
    buffer's size). j_flat, j_source: each entry's place in dgbtrf's storage (band_rows x N,
    kl = ku = kd) and its product; u_flat, u_source: those on and above the diagonal in
    LAPACK's upper storage ((kd + 1) x N, Fortran order).
    """

    products: tuple
    kd: int
    band_rows: int
    j_flat: np.ndarray
    j_source: np.ndarray
    u_flat: np.ndarray
    u_source: np.ndarray


def band_layout(T: np.ndarray, Tw: np.ndarray, pairs: list, bs: int, rows: np.ndarray,
                N: int) -> BandLayout:
    """The band's layout for the Hessian `pairs` (hessian_pattern) of a slab.

    Args:
        T: (cells, q, 2, nd) the basis values and derivatives at the points of every cell.
        Tw: T weighted by the quadrature weights and the cell lengths.
        pairs: the Hessian pairs (K, L) that enter, grouped by (K // bs, L // bs).
        bs: the block size of the dual space.
        rows: (cells, nd, bs) the row of each cell unknown, -1 where it is fixed.
        N: the free unknowns.
    """
    products, groups, group_of, offsets = _group_products(T, Tw, pairs, bs)
    return _entries(products, rows, pairs, groups, group_of, offsets, N)


def _group_products(T: np.ndarray, Tw: np.ndarray, pairs: list, bs: int) -> tuple:
    """(the products of band_layout, groups (lo, hi, P), each pair's group, each pair's
    group's start in the buffer)."""
    cell_count, nq, _, nd = T.shape
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
    return (products, np.ascontiguousarray(scale[:, group_of]), start), groups, group_of, \
        offsets


def _entries(products: tuple, rows: np.ndarray, pairs: list, groups: list,
             group_of: np.ndarray, offsets: np.ndarray, N: int) -> BandLayout:
    """Where each product of the buffer goes in the band: dgbtrf's storage (the numpy and
    compiled band) and LAPACK's upper storage (the compiled Newton)."""
    cell_count, nd, bs = rows.shape
    # entry (e, a, b, pair) of B couples row (e, a, c) and column (e, b, d), and, off the
    # diagonal of the Hessian, row (e, b, d) and column (e, a, c) too
    c_of = np.array([K % bs for K, _ in pairs], dtype=int)
    d_of = np.array([L % bs for _, L in pairs], dtype=int)
    e_, a_, b_, m_ = np.meshgrid(np.arange(cell_count), np.arange(nd), np.arange(nd),
                                 np.arange(len(pairs)), indexing="ij")
    i = rows[e_, a_, c_of[m_]].ravel()
    j = rows[e_, b_, d_of[m_]].ravel()
    mirror = np.array([K != L for K, L in pairs])[m_].ravel()
    # the entry's place in its group's [nd^2, cells, members] (see LocalAction._band)
    lows = np.array([lo for lo, _, _ in groups], dtype=np.int64)[group_of]
    sizes = np.array([hi - lo for lo, hi, _ in groups], dtype=np.int64)[group_of]
    source = (offsets[m_] + ((a_ * nd + b_) * cell_count + e_) * sizes[m_]
              + m_ - lows[m_]).ravel()
    i, j, source = (np.concatenate([i, j[mirror]]), np.concatenate([j, i[mirror]]),
                    np.concatenate([source, source[mirror]]))
    keep = (i >= 0) & (j >= 0)
    i, j, source = i[keep], j[keep], source[keep]
    kd = int(np.abs(i - j).max(initial=0))
    up = i <= j  # the upper band alone, in LAPACK's storage (fem_dual.native's Newton)
    return BandLayout(products, kd, 3 * kd + 1,  # dgbtrf's storage: kd more rows, the fill-in
                      (2 * kd + i - j) * N + j, source,  # band[2 kd + i - j, j] = J[i, j]
                      (kd + i[up] - j[up]) + j[up] * (kd + 1), source[up])


def hessian_pattern(both, cells: np.ndarray, upper: list, bs: int) -> list:
    """The Hessian pairs (K, L) of `upper` whose entries are not zero at random dual states,
    constants and coefficients (zero there: zero whatever they are), ordered by the
    derivative parts (K // bs, L // bs).

    Args:
        both: the compiled expression of the density's gradient (2 bs columns) and Hessian
            entries `upper` at the points (a CellPointEvaluator).
        cells: the cells it is evaluated on.
        upper: the Hessian's upper pairs, in the expression's order.
        bs: the block size of the dual space.
    """
    m = len(upper)
    nonzero = np.zeros(m, dtype=bool)
    for values in _randomised(both.expression, lambda: both(cells)[..., 2 * bs:]):
        nonzero |= (values != 0).reshape(-1, m).any(axis=0)  # NaN counts as nonzero
    return sorted((key for key, nz in zip(upper, nonzero) if nz),
                  key=lambda KL: (KL[0] // bs, KL[1] // bs, KL))


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
