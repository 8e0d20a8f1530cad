"""Slabs of a linear scene by superposition.

A slab of a linear scene starts from z = (x0, v0), which is also its base state (xbar, vbar). The
slab's dual action is quadratic with a right-hand side linear in z, so its solution, the DtP image
and the dual fields at the vertices are linear in z, and the auxiliary dual Hamiltonian is a
quadratic form in z. Solving the slab for the 2n unit start states gives every slab of that
length: a slab then costs a (2n x rows) product instead of an assembly, a solve and a sampling.
The numbers are those of solving each slab (tested to round-off); `--superpose no` solves each.

Only the slab length enters (linear scenes are time-invariant), so one basis serves every slab
of a run with equal slabs, plus one for a shorter last slab.
"""
from __future__ import annotations

from typing import Any, Dict, Optional, Tuple

import numpy as np

from fem_dual.errors import SolveError
from fem_dual.mpi import bcast
from fem_dual.slab.problem import SlabProblem
from fem_dual.slab.recovery import VertexSampler, VertexValues

__all__ = ["Superposition", "check_slab_map", "stable_or_raise", "first", "select", "refused", "checked",
           "share"]

SPURIOUS_GROWTH = 1e-3  # largest spurious amplification over the run (relative)
ROUNDOFF_GROWTH = 1e-13  # per slab: below this the eigenvalue solver cannot tell growth


def stable_or_raise(comm, scene, end_states: Optional[np.ndarray], dt: float, T: float,
                    blocks: Optional[np.ndarray] = None) -> None:
    """check_slab_map on rank 0 (which holds the end states), raised on every rank."""
    message = None
    if end_states is not None:
        try:
            check_slab_map(scene, end_states, dt, T / dt, blocks)
        except SolveError as exc:
            message = str(exc)
    message = bcast(comm, message)
    if message:
        raise SolveError(message)


def _block_eigenvalues(A: np.ndarray, end_states: np.ndarray,
                       blocks: np.ndarray) -> Tuple[np.ndarray, float]:
    """(eigenvalues of A, spectral radius of the map) over the blocks that `blocks` labels:
    the blocks of one size in one stacked eigvals (450 modes of a square: 10 ms, not 0.5 s)."""
    n = len(blocks)
    labels, sizes = np.unique(blocks, return_counts=True)
    lam, rho = [], 0.0
    for size in np.unique(sizes):
        both = []
        for label in labels[sizes == size]:
            where = np.flatnonzero(blocks == label)
            both.append(np.concatenate([where, where + n]))
        both = np.array(both)  # (blocks, 2 size)
        cut = (both[:, :, None], both[:, None, :])
        rho = max(rho, float(np.abs(np.linalg.eigvals(end_states[cut])).max()))
        lam.append(np.linalg.eigvals(A[cut]).ravel())
    return np.concatenate(lam), rho


def check_slab_map(scene, end_states: np.ndarray, dt: float, slabs: float,
                   blocks: Optional[np.ndarray] = None) -> None:
    """SolveError when the slab map Phi (columns: end states of the unit start states) grows
    faster than the exact flow, exp(max Re lambda dt), or than 1 where that decays, by more than
    SPURIOUS_GROWTH over the run: modes the slabs do not resolve are amplified (the dual slab
    map is stable only up to some tens of radians of the fastest mode per cell), and noise would
    grow without bound. A slab within one radian of the fastest mode resolves every mode: its
    radius's distance from the exact one is round-off of the basis solves and truncation error,
    which the estimate carries (a slab of 4.5e-12 chosen by rtol 1e-10 was refused for an excess
    of 3e-12 times 1e12 slabs). `blocks` (n,) labels components that only couple within their
    block (modal coordinates): the eigenvalues are then those of the blocks, far cheaper than
    of the whole map."""
    if blocks is None:
        lam = scene.spectrum[0]
        rho = float(np.abs(np.linalg.eigvals(end_states)).max())
    else:
        lam, rho = _block_eigenvalues(scene.first_order_matrix(), end_states, blocks)
    if float(np.abs(lam).max()) * dt <= 1.0:
        return
    sigma = float(lam.real.max())
    # against growth, not against the exact decay: a map that decays (rho <= 1) amplifies no
    # noise, and its radius's distance from the exact decay is truncation error, which the
    # error estimate carries (an excess of 1e-7 per slab times the slab count refused the
    # accurate maps of damped scenes)
    excess = np.log(max(rho, 1e-300)) - max(sigma * dt, 0.0)
    # an excess at round-off (a unit spectral radius computed as 1 + 1e-15) is no growth
    if excess > ROUNDOFF_GROWTH and excess * max(slabs, 1.0) > np.log1p(SPURIOUS_GROWTH):
        raise SolveError(f"the slab map amplifies modes the slabs do not resolve (spectral "
                         f"radius {rho:.6g}, exact {np.exp(sigma * dt):.6g} per slab); use more "
                         "slabs or cells per slab")


def share(comm, bases: dict, shared: set, dt: float) -> None:
    """Rank 0's basis of slabs of length dt on every rank (once). Collective."""
    if comm.size > 1 and dt not in shared:
        bases[dt] = bcast(comm, bases[dt])
        shared.add(dt)


def refused(bases: dict, dt: float) -> bool:
    """Whether the basis of slabs of length dt is at hand; raises the SolveError of its slab
    map's check again (every slab of that length is refused, not only the first)."""
    if dt not in bases:
        return False
    if isinstance(bases[dt], SolveError):
        raise SolveError(str(bases[dt]))
    return True


def checked(bases: dict, dt: float, check) -> None:
    """Run the slab map's check of a new basis; a failure stays recorded for `refused`."""
    try:
        check()
    except SolveError as exc:
        bases[dt] = exc
        raise


class Bases:
    """The solved bases of a superposition, one per slab length (`_bases`), as every kind keeps
    them: built on rank 0, shared with the other ranks on demand."""

    problem: Any
    _bases: Dict[float, Any]
    _shared: set

    def has(self, dt: float) -> bool:
        """Whether the basis of slabs of length dt was built (or refused)."""
        return dt in self._bases

    def share(self, dt: float) -> None:
        """The basis of slabs of length dt on every rank (the values are then computed
        wherever asked, not only on rank 0). Collective."""
        share(self.problem.comm, self._bases, self._shared, dt)


class Superposition(Bases):
    """The vertex values of a slab of a linear scene as a function of its start state.

    Args:
        problem: the slab problem of a linear scene.
        solver: its slab solver (solves into problem.w).
        sampler: the vertex sampler of the problem.
    """

    def __init__(self, problem: SlabProblem, solver, sampler: VertexSampler, T: float = 0.0,
                 hamiltonian: bool = True):
        self.problem, self.solver, self.sampler = problem, solver, sampler
        self.T = T  # the run's horizon, for the stability check of the slab map
        self.hamiltonian = hamiltonian  # H_d by polarisation (the error companion needs x, v)
        self._bases: Dict[float, Tuple[Optional[np.ndarray], Optional[np.ndarray]]] = {}
        self._shared: set = set()
        self.basis_solves = 0

    def _basis(self, dt: float):
        """Rows of the 2n unit start states (2n, rows, columns) and the Hamiltonian's quadratic
        form per row (rows, 2n, 2n), by polarisation of the sampled H_d. Collective; the arrays
        live on rank 0."""
        p, n = self.problem, self.problem.n
        unit = np.eye(2 * n)
        solutions, rows = [], []
        for z in unit:
            p.set_slab(z[:n], z[n:], dt)
            self.solver.solve()
            self.basis_solves += 1
            solutions.append(p.w.x.array.copy())
            rows.append(self.sampler.rows())
        h = 1 + 2 * n  # the H_d column
        quad = None
        if rows[0] is not None:
            quad = np.zeros((len(rows[0]), 2 * n, 2 * n))
            for i in range(2 * n):
                quad[:, i, i] = rows[i][:, h]
        for i in range(2 * n if self.hamiltonian else 0):
            for j in range(i + 1, 2 * n):
                z = unit[i] + unit[j]
                p.set_slab(z[:n], z[n:], dt)
                p.w.x.array[:] = solutions[i] + solutions[j]
                both = self.sampler.rows()
                if both is not None:
                    quad[:, i, j] = quad[:, j, i] = 0.5 * (both[:, h] - quad[:, i, i]
                                                           - quad[:, j, j])
        linear = np.stack(rows) if rows[0] is not None else None
        return linear, quad

    def ensure(self, dt: float) -> None:
        """Solve the basis of slabs of length dt unless it is at hand, and check its slab map.
        Collective."""
        if refused(self._bases, dt):
            return
        self._bases[dt] = self._basis(dt)
        linear = self._bases[dt][0]
        ends = None
        if linear is not None:
            values = [self.sampler.average(rows) for rows in linear]
            ends = np.array([np.concatenate([e.x[-1], e.v[-1]]) for e in values]).T
        checked(self._bases, dt, lambda: stable_or_raise(self.problem.comm, self.problem.scene,
                                                         ends, dt, self.T))

    def batch(self, Z: np.ndarray, dt: float, fields: bool = True,
              last: bool = False) -> Optional[VertexValues]:
        """Vertex values of the slabs of length dt from the start states Z (slabs, 2n), with a
        leading slab axis, on rank 0 (None elsewhere); without `fields` only x and v (H_d
        zero, no dual fields); with `last` only at the slab's end. Collective the first time
        a slab length is seen (its basis is solved then)."""
        self.ensure(dt)
        linear, quad = self._bases[dt]
        if linear is None:
            return None
        rows = np.tensordot(Z, linear, axes=1)
        rows[..., 0] = linear[0][:, 0]  # s is not linear in z
        h = 1 + 2 * self.problem.n
        rows[..., h] = quadratic_rows(quad, Z) if fields else 0.0
        return select(self.sampler.average(rows), fields, last)

    def __call__(self, x0: np.ndarray, v0: np.ndarray, dt: float) -> Optional[VertexValues]:
        """Vertex values of the slab of length dt from (x0, v0) on rank 0 (None elsewhere).
        Collective the first time a slab length is seen (its basis is solved then)."""
        return first(self.batch(np.concatenate([x0, v0])[None], dt))


QUADRATIC_BLOCK = 2**20  # doubles of the products of quadratic_rows held at once


def quadratic_rows(quad: np.ndarray, Z: np.ndarray) -> np.ndarray:
    """(slabs, rows): Z_k^T quad_r Z_k for the start states Z (slabs, m) and the forms quad
    (rows, m, m), through one matrix product (a three-operand einsum loops in C element by
    element: 7x slower for 250 slabs)."""
    m, flat = Z.shape[1], quad.reshape(-1, quad.shape[-1]).T
    out = np.empty((len(Z), len(quad)))
    step = max(1, QUADRATIC_BLOCK // max(1, flat.shape[1]))  # slabs whose products fit
    for a in range(0, len(Z), step):
        z = Z[a:a + step]
        left = (z @ flat).reshape(len(z), len(quad), m)  # (Z_k^T quad_r)_j
        out[a:a + step] = np.einsum("krj,kj->kr", left, z)
    return out


def select(values: VertexValues, fields: bool, last: bool) -> VertexValues:
    """Without `fields` no dual fields; with `last` the end vertex only."""
    if not fields:
        values.xi = values.eta = None
    if last:
        cut = slice(-1, None)
        values = values.apply(lambda a: a[:, cut])
        values.s = values.s[cut]
    return values


def first(values: Optional[VertexValues]) -> Optional[VertexValues]:
    """The first slab of batched vertex values (None stays None)."""
    if values is None:
        return None
    return values.apply(lambda a: a[0])
