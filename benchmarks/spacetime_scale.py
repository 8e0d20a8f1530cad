"""Scaling of the sparse, distributed space-time slab (fem_dual.continua.spacetime) on the
clamped Cauchy square (delta = 0.5, P1): one slab of 8 cells at degree 4 from the start field
u0 = (0.01 sin(pi x) sin(pi y), 0.01 sin(pi x) sin(2 pi y)), v0 = 0, for dt = 0.05 and for
about one period of the slowest mode (2 pi / w_min, w_min^2 the smallest eigenvalue of the
pencil (Ke, M) by inverse iteration). Per mesh: free space dofs, space-time unknowns, CG
iterations, set-up time (the slab: Ke, factorisations; the preconditioner of the slab length),
solve time (CG and the vertex values) and per CG iteration (weak scaling: the same unknowns
per rank on 1 and 2 ranks, e.g. --elements 45 serially and 64 on two), peak RSS per rank;
where affordable the slab's end state against the exact semi-discrete motion, scipy's
expm_multiply of the first-order system.

    mpirun -n 2 python benchmarks/spacetime_scale.py [--elements 32 64 128]
        [--shifted amg|gamg|direct] [--rtol 1e-10] [--reference-max-elements 32]
"""
from __future__ import annotations

import argparse
import resource
import time

import numpy as np
from mpi4py import MPI

from fem_dual.continua.cauchy import CauchyElasticity, CauchyParameters
from fem_dual.continua.spacetime import SpaceTimeSlab
from fem_dual.continua.spacetime_pc import SHIFTED

U0 = ["0.01*sin(pi*x)*sin(pi*y)", "0.01*sin(pi*x)*sin(2*pi*y)"]
DEGREE, CELLS = 4, 8


def slowest_period(slab: SpaceTimeSlab, steps: int = 40) -> float:
    """2 pi / w_min, w_min^2 the smallest eigenvalue of (Ke, M) by inverse iteration with the
    slab's factorisation of Ke. Collective."""
    comm = slab.comm
    x = np.random.default_rng(comm.rank).standard_normal(slab.n_local)
    lam = 0.0
    for _ in range(steps):
        mx = slab.rows.mult(slab.M, x[None])[0]
        x = slab.rows.solve(slab.ke_solver, mx[None])[0]
        kx = slab.rows.mult(slab.Ke, x[None])[0]
        mx = slab.rows.mult(slab.M, x[None])[0]
        lam = comm.allreduce(float(x @ kx)) / comm.allreduce(float(x @ mx))
        x /= np.sqrt(comm.allreduce(float(x @ x)))
    return 2.0 * np.pi / np.sqrt(lam)


def exact_end(system, x0: np.ndarray, v0: np.ndarray, dt: float):
    """(x, v) at t = dt of M q'' + D q' + K q = 0 by expm_multiply of the first-order system
    (a LinearOperator with a sparse LU of M), global vectors on rank 0 (None elsewhere).
    Collective."""
    from scipy.sparse.linalg import LinearOperator, expm_multiply, splu

    mats, x, v = system.to_scipy(), system.gather(x0), system.gather(v0)
    if mats is None:
        return None
    M, K, D = mats["M"].tocsc(), mats["K"].tocsr(), mats["D"].tocsr()
    lu, n = splu(M), M.shape[0]

    def mv(z):
        z = np.asarray(z).ravel()
        return np.concatenate([z[n:], -lu.solve(K @ z[:n] + D @ z[n:])])

    def rmv(z):
        z = np.asarray(z).ravel()
        w = lu.solve(z[n:])  # (M symmetric)
        return np.concatenate([-(K.T @ w), z[:n] - D.T @ w])

    A = LinearOperator((2 * n, 2 * n), matvec=mv, rmatvec=rmv, dtype=float)
    z = expm_multiply(A * dt, np.concatenate([x, v]), traceA=-dt * float(
        lu.solve(D.toarray()).trace()) if D.nnz else 0.0)
    return z[:n], z[n:]


def run_mesh(elements: int, args, comm: MPI.Comm) -> list:
    """The rows of the table for one mesh (one per slab length)."""
    t0 = time.perf_counter()
    system = CauchyElasticity(CauchyParameters(elements=elements, degree=1, delta=0.5),
                              comm).system
    x0 = system.interpolate(U0)
    v0 = np.zeros_like(x0)
    slab = SpaceTimeSlab.from_system(system, DEGREE, CELLS, shifted=args.shifted,
                                     options={"ksp_rtol": str(args.rtol)})
    build = time.perf_counter() - t0
    period = slowest_period(slab)
    rows = []
    for label, dt in (("0.05", 0.05), ("period", period)):
        slab.set_slab(x0, v0, dt)
        t1 = time.perf_counter()
        slab.setup_preconditioner()
        setup = build + (time.perf_counter() - t1)
        t2 = time.perf_counter()
        its = slab.solve()
        x, v = slab.vertex_values()
        solve = time.perf_counter() - t2
        rss = comm.gather(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, root=0)
        error = "-"
        if elements <= args.reference_max_elements:
            error = _reference_error(system, x0, v0, dt, x[-1], v[-1], comm)
        rows.append((elements, system.n, slab.num_dofs, f"{dt:.4g} ({label})", its,
                     setup, solve, rss, error))
        build = 0.0  # (the slab's own set-up counts once)
        if comm.rank == 0:
            _print_row(rows[-1])
    slab.close()
    system.destroy()
    return rows


def _reference_error(system, x0, v0, dt, x_end, v_end, comm) -> str:
    exact = exact_end(system, x0, v0, dt)
    xs, vs = system.gather(x_end), system.gather(v_end)
    if comm.rank != 0:
        return "-"
    ex = np.abs(xs - exact[0]).max() / np.abs(exact[0]).max()
    ev = np.abs(vs - exact[1]).max() / np.abs(exact[1]).max()
    return f"x {ex:.1e} v {ev:.1e}"


HEADER = (f"{'E':>4} {'space dofs':>10} {'unknowns':>10} {'dt':>16} {'CG its':>6} "
          f"{'setup s':>8} {'solve s':>8} {'s/it':>7} {'peak RSS MB per rank':>22}  "
          "vs expm_multiply")


def _print_row(row) -> None:
    elements, n, unknowns, dt, its, setup, solve, rss, error = row
    rss_text = "/".join(f"{r:.0f}" for r in rss)
    print(f"{elements:>4} {n:>10} {unknowns:>10} {dt:>16} {its:>6} {setup:>8.1f} "
          f"{solve:>8.1f} {solve / max(its, 1):>7.3f} {rss_text:>22}  {error}", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--elements", type=int, nargs="+", default=[32, 64, 128])
    parser.add_argument("--shifted", choices=SHIFTED, default="amg")
    parser.add_argument("--rtol", type=float, default=1e-10)
    parser.add_argument("--reference-max-elements", type=int, default=32)
    args = parser.parse_args()
    comm = MPI.COMM_WORLD
    if comm.rank == 0:
        print(f"space-time slab: P{DEGREE} in time, {CELLS} cells, delta = 0.5, shifted = "
              f"{args.shifted}, ksp_rtol = {args.rtol:g}, {comm.size} rank(s)")
        print(HEADER, flush=True)
    start = time.perf_counter()
    for elements in args.elements:
        run_mesh(elements, args, comm)
    if comm.rank == 0:
        print(f"total {time.perf_counter() - start:.1f} s", flush=True)


if __name__ == "__main__":
    main()
