"""Real modes of a pencil (K, M) (M SPD, K any): columns U spanning the modes, one per real
eigenvector, an M-orthonormal pair for a complex pair, one block for modes about to coalesce,
and the block diagonal Kr of U^-1 M^-1 K U. The modal coordinates of the slabs
(fem_dual.slab.modal), the reference of undamped linear scenes near flutter (fem_dual.reference)
and the data floor of the error estimate (fem_dual.integrate.conditioning) stand on them.
"""
from __future__ import annotations

import functools
import hashlib
from typing import List, Optional, Tuple

import numpy as np
import scipy.linalg as sla

__all__ = ["real_modes", "condition_1", "finite_real_modes", "refined_blocks", "compute_real_modes",
           "block_slices", "block_motion", "cancelling", "coupling", "decoupled", "CANCELLATION", "GROUP_COSINE", "MAX_BLOCK_SCALING",
           "CHOLESKY_COND"]

GROUP_COSINE = 0.9999  # modes whose spans meet at an M-cosine above this share a block (kept
# apart, the two would give U a condition number above 140)
#: M's condition number (LAPACK's estimate in the 1-norm) up to which the modes come from the
#: standard eigenproblem of R^-T K R^-1, M = R^T R (see compute_real_modes)
CHOLESKY_COND = 100.0
MAX_BLOCK_SCALING = 1e3  # a block's basis vectors differ in length by at most this
CANCELLATION = 1e2  # a block whose K Ub cancels more than this is refined (refinement)


def real_modes(M: np.ndarray, K: np.ndarray) -> Tuple[np.ndarray, ...]:
    """`compute_real_modes` once per pencil: the slabs' modal coordinates, the data floor and
    the reference of a run share it (read-only arrays; 23 s for n = 1000)."""
    return _cached(_Pencil(M, K))


def finite_real_modes(M: np.ndarray, K: np.ndarray) -> Optional[Tuple[np.ndarray, ...]]:
    """`real_modes`, or None where they cannot be used: the pencil overflows to inf or NaN, or
    the modes are incomplete (fewer than n columns) or not finite."""
    try:
        with np.errstate(all="ignore"):
            modes = real_modes(M, K)
    except (np.linalg.LinAlgError, ValueError):  # overflow to inf or NaN in the pencil
        return None
    if modes[0].shape != M.shape or not all(np.isfinite(a).all() for a in modes):
        return None
    return modes


#: the modes hold where their componentwise backward error in (K, M),
#: max_ij |K U - M U Kr|_ij / (|K| |U| + |M| |U Kr|)_ij, is at most this. Measured: 1e-16 ..
#: 1e-12 for Ziegler, Beck's column (near flutter too), cauchy2d up to 16 elements a side and
#: N-link columns up to 1000 links, masses graded by 1e4 or 1e6 included; a repeated frequency
#: whose modes are defective (cauchy2d at |delta| = lam + mu) gives 0.17 .. 0.98, and 1e-10
#: short of it (delta = -1.9999999999 at 8 elements) 4.4e-9: grouped blocks that are not
#: invariant, whose coupling left out resonates (the motion was off by 50 to 350 times its
#: estimate). Componentwise, the measure does not see how unevenly rows are scaled.
HOLD_BACKWARD = 1e-9


def modes_hold(M: np.ndarray, K: np.ndarray) -> Tuple[bool, float]:
    """(whether the modes of `real_modes(M, K)` reproduce the pencil within HOLD_BACKWARD,
    their componentwise backward error)."""
    error = _backward_error(_Pencil(M, K))
    return bool(error <= HOLD_BACKWARD), error


@functools.lru_cache(maxsize=4)
def _backward_error(pencil: _Pencil) -> float:
    """max_ij |K U - M U Kr|_ij / (|K| |U| + |M| |U Kr|)_ij of the pencil's modes (n^3,
    once)."""
    U, Kr = real_modes(pencil.M, pencil.K)[:2]
    with np.errstate(all="ignore"):
        UKr = U @ Kr
        R = np.abs(pencil.K @ U - pencil.M @ UKr)
        size = np.abs(pencil.K) @ np.abs(U) + np.abs(pencil.M) @ np.abs(UKr)
        ratio = np.where(size > 0, R / np.where(size > 0, size, 1.0), np.where(R > 0, np.inf, 0))
        return float(ratio.max(initial=0.0))


def refined_blocks(M: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(blocks,) bool: `cancelling` of the blocks of `real_modes(M, K)` (those whose K Ub was
    formed in extended precision), once per pencil: the data floor and the reference both ask
    (K U is n^3: 0.1 s for 450 dofs)."""
    return _refined(_Pencil(M, K))


class _Pencil:
    """(M, K) hashable by a digest of their values."""

    def __init__(self, M: np.ndarray, K: np.ndarray):
        self.M, self.K = M, K
        self.key = (M.shape, K.shape, hashlib.sha256(np.ascontiguousarray(M).tobytes()).digest(),
                    hashlib.sha256(np.ascontiguousarray(K).tobytes()).digest())

    def __hash__(self) -> int:
        return hash(self.key)

    def __eq__(self, other) -> bool:
        return isinstance(other, _Pencil) and self.key == other.key


@functools.lru_cache(maxsize=4)
def _cached(pencil: _Pencil) -> Tuple[np.ndarray, ...]:
    modes = compute_real_modes(pencil.M, pencil.K)
    for array in modes:
        array.flags.writeable = False
    return modes


@functools.lru_cache(maxsize=4)
def _refined(pencil: _Pencil) -> np.ndarray:
    U, Kr = real_modes(pencil.M, pencil.K)[:2]
    refined = cancelling(pencil.K, U, block_slices(Kr), pencil.K @ U)
    refined.flags.writeable = False
    return refined


def _pencil_eig(K: np.ndarray, M: np.ndarray, R: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Eigenvalues and eigenvectors (complex) of the pencil (K, M), M = R^T R: by QZ, or where
    M is well conditioned (CHOLESKY_COND) by the standard eigenproblem of R^-T K R^-1."""
    rcond, info = sla.lapack.dpocon(R, float(np.abs(M).sum(axis=0).max()))
    if info != 0 or not rcond * CHOLESKY_COND >= 1.0:
        return sla.eig(K, M)
    C = sla.solve_triangular(R, sla.solve_triangular(R, K.T, trans="T").T, trans="T")
    lam, W = np.linalg.eig(C)
    return lam.astype(complex), sla.solve_triangular(R, W).astype(complex)


def compute_real_modes(M: np.ndarray, K: np.ndarray) -> Tuple[np.ndarray, ...]:
    """(U, Kr, Ar, omega): columns spanning the modes of M^-1 K, sorted by frequency, and Kr, the
    diagonal blocks of U^-1 M^-1 K U. A real eigenvector is one column of unit M-norm; a complex
    pair's two columns are an M-orthonormal basis of (Re u, Im u); modes whose spans are nearly
    parallel (M-cosine above GROUP_COSINE: eigenvalues about to coalesce, on either side of a
    flutter load) share one block with an M-orthonormal basis of their joint span. Ar is H's
    energy weight in these coordinates: Kr itself on a one-mode block, the mean of the block's
    eigenvalues (trace / size) times I on a larger one, whose Kr need not have a positive
    definite symmetric part (Beck's column at 20.05: eigenvalues 119.9, 122.8, coupling 281);
    a block with an eigenvalue of real part <= 0 gets that as its weight (not positive: the
    mode does not oscillate, and the modal coordinates refuse the scene). omega (n,): each
    coordinate's frequency, sqrt of the largest |eigenvalue| of its block.

    Near coalescence the eigenvectors of the two modes (or Re u and Im u of the pair) tend to
    one vector. Kept apart they make U ill-conditioned (condition number 4.7e6 for Beck's column
    at 20.06, 9e-3 past its flutter load), and every modal amplitude carries eps cond(U) of
    the state: in a fast mode, whose velocity is omega times that, round-off read as motion the
    slab cannot resolve. One block is exact (the span is invariant); its basis is balanced
    (_balanced) between U's condition number and the block's departure from normality, which
    the slab solves like any small coupled system.

    The blocks off the diagonal are round-off of size eps cond(U) |K| (7e-3 for a 200-link
    column, whose fastest mode has omega^2 = 2.6e10); kept, they couple the slow mode to the
    unresolved ones and cost 5 digits. Dropping them is exact for a K perturbed by that
    round-off (backward stable). The diagonal blocks are two-sided Rayleigh quotients, more
    accurate than the eigenvalues themselves.

    The modes come from QZ on the pencil (K, M), not from eig(M^-1 K): its backward error is
    relative to |K| and |M| instead of |M^-1 K| (2.6e10 for that column, whose M has condition
    number 6.5e4), so the slow eigenvalue is right to 1.9e-12 instead of 1.5e-8 (against a
    certified 500-bit eigen-decomposition), and the start state's share of each mode with it.
    Where M is well conditioned (at most CHOLESKY_COND; finite element mass matrices: 5 to 10)
    the standard eigenproblem of R^-T K R^-1 loses at most that factor against QZ and takes a
    quarter of its time (0.17 s against 0.71 s for the 450 dofs of `cauchy2d` at 16 elements
    a side)."""
    R = sla.cholesky(M)  # M = R^T R: the M-inner product is the Euclidean one of R u
    lam, vecs = _pencil_eig(K, M, R)
    order = np.argsort(np.abs(lam), kind="stable")
    # R u of every real eigenvector in one product, and its M-norm |R u| (one matrix-vector
    # product and an einsum per mode took 0.19 s of the 450 modes of a square)
    RV = R @ vecs.real
    norms = np.linalg.norm(RV, axis=0)
    blocks: list = []
    R_last = None  # R @ blocks[-1]
    for k in order:
        if lam[k].imag < 0:
            continue  # its conjugate brings the pair
        u = vecs[:, k]
        if lam[k].imag == 0:
            block = u.real[:, None] / norms[k]
            R_block = RV[:, k:k + 1] / norms[k]
        else:
            block = orthonormal(R, np.stack([u.real, u.imag], axis=1))
            R_block = R @ block
        if blocks and _norm2(R_last.T @ R_block) > GROUP_COSINE:
            block = orthonormal(R, np.hstack([blocks.pop(), block]))
            R_block = R @ block
        blocks.append(block)
        R_last = R_block
    blocks = [b if b.shape[1] == 1 else balanced(b, K) for b in blocks]
    U = np.hstack(blocks) if blocks else np.zeros((len(M), 0))
    if U.shape[1] != len(M):
        return U, np.zeros((0, 0)), np.zeros((0, 0)), np.zeros(0)
    sizes = np.cumsum([b.shape[1] for b in blocks])
    slices = [slice(int(a), int(b)) for a, b in zip(np.concatenate([[0], sizes[:-1]]), sizes)]
    KU = K @ U
    full = np.linalg.solve(U, np.linalg.solve(M, KU))  # U^-1 M^-1 K U
    refine = cancelling(K, U, slices, KU)
    if refine.any():
        U = decoupled(M, K, U, slices, refine, full)
    return (U,) + _diagonal_blocks(M, K, U, slices, refine, full)


def _norm2(matrix: np.ndarray) -> float:
    """The 2-norm of a small matrix (of 1 x 1 its entry's size, without an SVD: 450 modes of a
    square took 0.25 s of SVDs)."""
    if matrix.size == 1:
        return float(abs(matrix.item()))
    return float(np.linalg.norm(matrix, 2))


def _diagonal_blocks(M: np.ndarray, K: np.ndarray, U: np.ndarray, slices: List[slice],
                     refine: np.ndarray, full: np.ndarray) -> tuple:
    """(Kr, Ar, omega) of real_modes from its columns U and their blocks: the diagonal blocks of
    U^-1 M^-1 K U, `full` in float64 (of the columns before `decoupled` moved those in
    `refine`: the others' blocks change by the square of the step), refined where K Ub cancels
    (`refine`: `coupling` of the moved columns corrects full's block to theirs)."""
    C = coupling(M, K, U, slices, refine, full)
    Kr, Ar, omega = np.zeros_like(full), np.zeros_like(full), np.zeros(len(M))
    for here, refined in zip(slices, refine):
        Kr[here, here] = full[here, here] + (C[here, here] if refined else 0.0)
        lam = np.linalg.eigvals(Kr[here, here])
        omega[here] = np.sqrt(np.abs(lam).max())
        if len(lam) == 1:
            Ar[here, here] = Kr[here, here]
        else:  # not positive where an eigenvalue is not (a mode that does not oscillate)
            weight = lam.real.mean() if lam.real.min() > 0 else lam.real.min()
            Ar[here, here] = weight * np.eye(len(lam))
    return Kr, Ar, omega


class _Solver:
    """z -> U^-1 M^-1 z, both factored once."""

    def __init__(self, M: np.ndarray, U: np.ndarray):
        self.mass, self.lu = sla.cho_factor(M), sla.lu_factor(U)

    def __call__(self, z: np.ndarray) -> np.ndarray:
        return sla.lu_solve(self.lu, sla.cho_solve(self.mass, z))


def balanced(Q: np.ndarray, K: np.ndarray) -> np.ndarray:
    """The M-orthonormal basis Q of a block, its columns scaled so that the block's coupling
    is balanced (the norms of row i and column i off the diagonal equal: Osborne's iteration),
    the scales within MAX_BLOCK_SCALING of each other.

    In an orthonormal basis a block of modes about to coalesce is far from normal (Beck's
    column at 20.05: eigenvalues 119.9 and 122.8, coupling 281 and 1.1e-5), which the slab's
    preconditioner (the symmetric model) does not see: 180 CG iterations a solve. Balanced,
    the coupling falls to 0.28 and 0.01, U's condition number rises to 2.3e3."""
    T = Q.T @ K @ Q  # = Q^-1 M^-1 K Q, as Q^T M Q = I
    off = np.abs(T - np.diag(np.diag(T)))
    d = np.ones(len(T))
    for _ in range(50):
        largest = 0.0
        for i in range(len(T)):  # one index at a time (both at once would overshoot)
            row, col = off[i] @ d / d[i], off[:, i] @ (1.0 / d) * d[i]
            if row > 0 and col > 0:
                factor = np.sqrt(row / col)
                d[i] *= factor
                largest = max(largest, abs(np.log(factor)))
        if largest < 1e-3:
            break
    d = np.maximum(d / d.max(), 1.0 / MAX_BLOCK_SCALING)
    return Q * d


def condition_1(A: np.ndarray) -> float:
    """LAPACK's estimate of the 1-norm condition number of a square A (an LU and a few solves:
    within a factor n of cond_2, at a tenth of an SVD's cost; inf where A is singular)."""
    getrf, gecon = sla.get_lapack_funcs(("getrf", "gecon"), (A,))
    lu, _, info = getrf(A)
    if info != 0:
        return float("inf")
    rcond, info = gecon(lu, float(np.abs(A).sum(axis=0).max()), norm="1")
    return float("inf") if info != 0 or not rcond > 0 else 1.0 / float(rcond)


def orthonormal(R: np.ndarray, columns: np.ndarray) -> np.ndarray:
    """An M-orthonormal basis (M = R^T R) of the span of `columns`."""
    return sla.solve_triangular(R, np.linalg.qr(R @ columns)[0])


def block_slices(Kr: np.ndarray) -> List[slice]:
    """The diagonal blocks of a block-diagonal Kr (as real_modes builds it), in order: a block
    ends at i where no entry of the rows and columns up to i reaches beyond i."""
    n = len(Kr)
    if n == 0:
        return []
    nonzero, index = np.asarray(Kr) != 0, np.arange(n)
    row_last = np.where(nonzero.any(axis=1), n - 1 - np.argmax(nonzero[:, ::-1], axis=1), index)
    col_last = np.where(nonzero.any(axis=0), n - 1 - np.argmax(nonzero[::-1, :], axis=0), index)
    reach = np.maximum.accumulate(np.maximum(index, np.maximum(row_last, col_last)))
    ends = np.flatnonzero(reach == index)
    starts = np.concatenate([[0], ends[:-1] + 1])
    return [slice(int(a), int(b) + 1) for a, b in zip(starts, ends)]


def block_motion(Kr: np.ndarray, slices: List[slice], r0: np.ndarray, rv0: np.ndarray,
                 t: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """(r, r') at the times t (m,), each (m, n), of r'' + Kr r = 0 from (r0, rv0), block by
    block: a one-mode block in closed form (cos, sin; cosh, sinh for a negative stiffness), a
    larger one through the matrix exponential of its first-order system, whose norm is its own
    frequency squared, not the fastest mode's. Several Kr of the same blocks (samples, n, n)
    give (samples, m, n) each, the one-mode blocks of all at once."""
    t = np.asarray(t, dtype=float)
    stack = Kr[None] if Kr.ndim == 2 else Kr
    r = np.zeros((len(stack), len(t), len(r0)))
    rv = np.zeros_like(r)
    single = np.array([s.start for s in slices if s.stop - s.start == 1], dtype=int)
    if len(single):
        w = np.sqrt(stack[:, single, single].astype(complex))[:, None, :]  # (samples, 1, ns)
        wt = t[:, None] * w
        # sin(w t) / w, continuous through w = 0 (a free mode drifts: t)
        sinc = np.where(np.abs(w) > 0, np.sin(wt) / np.where(w != 0, w, 1.0), t[:, None])
        r[..., single] = (r0[single] * np.cos(wt) + rv0[single] * sinc).real
        rv[..., single] = (-r0[single] * w * np.sin(wt) + rv0[single] * np.cos(wt)).real
    for s in (s for s in slices if s.stop - s.start > 1):
        b = s.stop - s.start
        for k, K in enumerate(stack):
            A = np.block([[np.zeros((b, b)), np.eye(b)], [-K[s, s], np.zeros((b, b))]])
            z = sla.expm(np.multiply.outer(t, A)) @ np.concatenate([r0[s], rv0[s]])  # (m, 2b)
            r[k, :, s], rv[k, :, s] = z[:, :b], z[:, b:]
    return (r[0], rv[0]) if Kr.ndim == 2 else (r, rv)


def cancelling(K: np.ndarray, U: np.ndarray, slices: List[slice],
               KU: np.ndarray) -> np.ndarray:
    """(blocks,) bool: whether K Ub cancels, block by block: its entries more than
    CANCELLATION times smaller than those of |K| |Ub| (the slow modes of a stiff system), so
    that its float64 round-off, relative to |K| |Ub|, is a large error of the block (KU: K U)."""
    plain = np.abs(KU).max(axis=0, initial=0.0)
    size = (np.abs(K) @ np.abs(U)).max(axis=0, initial=0.0)
    return np.array([size[s].max() > CANCELLATION * plain[s].max() for s in slices], dtype=bool)


def coupling(M: np.ndarray, K: np.ndarray, U: np.ndarray, slices: List[slice],
             refine: np.ndarray, full: np.ndarray) -> np.ndarray:
    """(n, n): in the columns of the blocks in `refine` (zero elsewhere), the correction of
    full = U^-1 M^-1 K U as computed in float64: U^-1 M^-1 R, the residual R = K Ub - M Ub Kr_bb
    of each block (Kr_bb its diagonal block of `full`) formed in extended precision (numpy's
    longdouble). On the diagonal block it refines Kr_bb; in the other rows it is the block's
    coupling to the other blocks. K Ub cancels in the slow modes of a stiff system (Beck's
    column: |K| 7e6, the slow block's entries 120): its float64 round-off, eps |K| |Ub|, moves
    the motion near the flutter load by 1.6e-6 over T = 20 (50-digit reference); refined, by
    5.6e-10."""
    C = np.zeros_like(full)
    columns = np.concatenate([np.arange(s.start, s.stop) for s, r in zip(slices, refine) if r]
                             + [np.zeros(0, dtype=int)])
    if not len(columns):
        return C
    diagonal = np.zeros((len(columns), len(columns)))
    i = 0
    for here in (s for s, r in zip(slices, refine) if r):
        size = here.stop - here.start
        diagonal[i:i + size, i:i + size] = full[here, here]
        i += size
    ld = np.longdouble
    Uc = U[:, columns].astype(ld)
    R = K.astype(ld) @ Uc - (M.astype(ld) @ Uc) @ diagonal.astype(ld)
    C[:, columns] = _Solver(M, U)(np.asarray(R, dtype=float))
    return C


def decoupled(M: np.ndarray, K: np.ndarray, U: np.ndarray, slices: List[slice],
              refine: np.ndarray, full: np.ndarray) -> np.ndarray:
    """U with the columns of every block b in `refine` moved towards its invariant subspace
    (one Newton step): Ub + sum_c Uc X_cb, Kr_cc X_cb - X_cb Kr_bb = -C_cb, C_cb the block's
    coupling into block c (`coupling`; full = U^-1 M^-1 K U in float64). QZ's eigenvectors are
    exact for a K perturbed by eps |K|: in the slow modes of a stiff system that coupling (5e-7
    between Beck's two slowest modes at P = 20, 20 elements, 22 apart) would be dropped with the
    blocks off the diagonal, and nearly parallel columns multiply it into the motion (1.5e-7 of
    a state of 0.1 over T = 20; after the step 7e-10)."""
    C = coupling(M, K, U, slices, refine, full)
    X = np.zeros_like(full)
    single = np.array([s.stop - s.start == 1 for s in slices])
    rows = np.array([s.start for s in slices])[single]
    k = full[rows, rows]  # the one-mode blocks' stiffnesses
    for b in np.flatnonzero(refine):
        here = slices[b]
        block = full[here, here]
        X[rows, here] = _one_mode_steps(k, block, C[rows, here])
        for c in np.flatnonzero(~single):
            other = slices[c]
            if c != b:
                X[other, here] = sla.solve_sylvester(full[other, other], -block,
                                                     -C[other, here])
        X[here, here] = 0.0
    return U + U @ X


def _one_mode_steps(k: np.ndarray, block: np.ndarray, C: np.ndarray) -> np.ndarray:
    """X (modes, size) with k_c X_c - X_c block = -C_c for one-mode blocks of stiffness k_c;
    0 where k_c I - block is singular to round-off (the block itself, or a repeated
    frequency: no step). Round-off is 1e-12 of the two stiffnesses, or 100 eps of the largest
    (the float64 k_c of a slow mode): two slow modes 0.5 apart beside a fast one of 1e12 are
    apart, and their coupling (eps |K| / 0.5) is stepped away."""
    shift = k[:, None, None] * np.eye(len(block)) - block  # (modes, size, size)
    local = np.abs(k) + np.abs(block).max()
    floor = 100 * np.finfo(float).eps * (np.abs(k).max(initial=0.0) + np.abs(block).max())
    regular = np.abs(np.linalg.det(shift)) > (1e-12 * local + floor) ** len(block)
    X = np.zeros_like(C)
    if regular.any():  # X_c = -C_c shift_c^-1: solve shift_c^T X_c^T = -C_c^T
        X[regular] = -np.linalg.solve(np.swapaxes(shift[regular], 1, 2),
                                      C[regular][:, :, None])[:, :, 0]
    return X
