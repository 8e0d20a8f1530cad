"""Newmark's average acceleration and the generalized-alpha method (Chung & Hulbert 1993) for
M u'' + D u' + K u = 0 with scipy.sparse matrices: the integrators computational mechanicians
use, beside which fem-dual's continua are measured.

    .venv/bin/python benchmarks/newmark.py SYSTEM.npz [--T 1] [--target 1e-6]
        [--scheme newmark|alpha] [--rho-inf 0.8] [--steps 16]

SYSTEM.npz is what ``SpatialSystem.export_npz`` writes (M, K, D in CSR, u0, v0), or the
``<scene>_system.npz`` of a run's --out (dense M, K, D). The reference is
the matrix exponential of the first-order system (dense, n <= 2000). The step count is doubled
from --steps until the relative error at T is below --target; each row prints steps, wall time
(factorisation included) and error.

One step of length h (alpha_m = alpha_f = 0, beta = 1/4, gamma = 1/2 is Newmark's average
acceleration; Chung-Hulbert take alpha_m = (2 rho_inf - 1)/(rho_inf + 1),
alpha_f = rho_inf/(rho_inf + 1), gamma = 1/2 - alpha_m + alpha_f,
beta = (1 - alpha_m + alpha_f)^2 / 4, second order with high-frequency amplification rho_inf):

    M a_(n+1-alpha_m) + D v_(n+1-alpha_f) + K u_(n+1-alpha_f) = 0,
    x_(n+1-a) = (1 - a) x_(n+1) + a x_n,
    u_(n+1) = u_n + h v_n + h^2 ((1/2 - beta) a_n + beta a_(n+1))
    v_(n+1) = v_n + h ((1 - gamma) a_n + gamma a_(n+1))

solved for a_(n+1) with S = (1 - alpha_m) M + (1 - alpha_f) gamma h D + (1 - alpha_f) beta h^2 K,
factorised (splu) once per step size.
"""
from __future__ import annotations

import argparse
import time
from dataclasses import dataclass
from typing import List, Sequence, Tuple

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sps
import scipy.sparse.linalg as spla

__all__ = ["Scheme", "newmark_average", "generalized_alpha", "integrate", "Row", "converge",
           "expm_reference", "load_npz"]


@dataclass(frozen=True)
class Scheme:
    """The four parameters of a generalized-alpha step (module docstring)."""

    name: str
    alpha_m: float
    alpha_f: float
    beta: float
    gamma: float


def newmark_average() -> Scheme:
    """Newmark's average acceleration (trapezoidal rule): second order, no dissipation."""
    return Scheme("newmark", 0.0, 0.0, 0.25, 0.5)


def generalized_alpha(rho_inf: float) -> Scheme:
    """Chung-Hulbert generalized-alpha with high-frequency spectral radius rho_inf in [0, 1]."""
    if not 0.0 <= rho_inf <= 1.0:
        raise ValueError(f"rho_inf must lie in [0, 1], got {rho_inf}")
    am = (2 * rho_inf - 1) / (rho_inf + 1)
    af = rho_inf / (rho_inf + 1)
    return Scheme(f"alpha({rho_inf:g})", am, af, 0.25 * (1 - am + af) ** 2, 0.5 - am + af)


def _on_grid(times: Sequence[float], steps: int) -> Tuple[float, np.ndarray]:
    """h = max(times) / steps and the step index of each requested time (which must be one)."""
    times = np.asarray(times, dtype=float)
    h = times.max() / steps
    index = np.rint(times / h).astype(int)
    if np.any(np.abs(index * h - times) > 1e-9 * times.max()):
        raise ValueError("integrate: every requested time must be a multiple of T / steps")
    return h, index


def integrate(M, D, K, u0, v0, times: Sequence[float], steps: int,
              scheme: Scheme) -> Tuple[np.ndarray, np.ndarray]:
    """u, v (len(times), n) at the requested times, from t = 0 with `steps` equal steps up to
    max(times). M, D, K: scipy.sparse (or dense) n x n; D may be None."""
    M, K = sps.csc_matrix(M), sps.csc_matrix(K)
    D = sps.csc_matrix(K.shape) if D is None else sps.csc_matrix(D)
    h, index = _on_grid(times, steps)
    am, af, beta, gamma = scheme.alpha_m, scheme.alpha_f, scheme.beta, scheme.gamma
    S = spla.splu(((1 - am) * M + (1 - af) * gamma * h * D + (1 - af) * beta * h**2 * K).tocsc())
    u, v = np.array(u0, dtype=float), np.array(v0, dtype=float)
    a = spla.splu(M).solve(-(D @ v) - K @ u)
    out_u, out_v = np.zeros((len(index), u.size)), np.zeros((len(index), u.size))
    for k in np.flatnonzero(index == 0):
        out_u[k], out_v[k] = u, v
    for n in range(1, index.max() + 1):
        u_pred = u + h * v + h**2 * (0.5 - beta) * a
        v_pred = v + h * (1 - gamma) * a
        rhs = -(am * (M @ a) + D @ ((1 - af) * v_pred + af * v) + K @ ((1 - af) * u_pred + af * u))
        a_new = S.solve(rhs)
        u, v, a = u_pred + h**2 * beta * a_new, v_pred + h * gamma * a_new, a_new
        for k in np.flatnonzero(index == n):
            out_u[k], out_v[k] = u, v
    return out_u, out_v


def expm_reference(M, D, K, u0, v0, times: Sequence[float]) -> Tuple[np.ndarray, np.ndarray]:
    """The exact u, v at `times`: exp(t A) of A = [[0, I], [-M^-1 K, -M^-1 D]] (dense)."""
    M, K = np.asarray(sps.csr_matrix(M).toarray()), np.asarray(sps.csr_matrix(K).toarray())
    D = np.zeros_like(K) if D is None else np.asarray(sps.csr_matrix(D).toarray())
    n = K.shape[0]
    A = np.block([[np.zeros((n, n)), np.eye(n)],
                  [-np.linalg.solve(M, K), -np.linalg.solve(M, D)]])
    z0 = np.concatenate([u0, v0])
    z = np.array([sla.expm(t * A) @ z0 for t in times])
    return z[:, :n], z[:, n:]


@dataclass(frozen=True)
class Row:
    """One run of :func:`converge`: steps, wall time in seconds (factorisation included) and
    the relative error max_t |u - u_ref| / max_t |u_ref| (2-norms over the dofs)."""

    steps: int
    wall: float
    error: float


def converge(M, D, K, u0, v0, times: Sequence[float], reference: np.ndarray, target: float,
             scheme: Scheme, steps: int = 16, max_halvings: int = 16) -> Tuple[List[Row], bool]:
    """Halve the step from `steps` until the error against `reference` (u at `times`) is below
    `target`. Returns the rows and whether the target was met."""
    rows = []
    scale = np.linalg.norm(reference, axis=1).max()
    for _ in range(max_halvings + 1):
        start = time.perf_counter()
        u, _ = integrate(M, D, K, u0, v0, times, steps, scheme)
        wall = time.perf_counter() - start
        rows.append(Row(steps, wall, float(np.linalg.norm(u - reference, axis=1).max() / scale)))
        if rows[-1].error <= target:
            return rows, True
        steps *= 2
    return rows, False


def load_npz(path: str):
    """(M, D, K, u0, v0) from a ``SpatialSystem.export_npz`` file (CSR parts) or a run's
    ``<scene>_system.npz`` (dense M, K, D)."""
    data = np.load(path)

    def csr(name):
        if name in data:
            return sps.csr_matrix(data[name])
        return sps.csr_matrix((data[f"{name}_data"], data[f"{name}_indices"],
                               data[f"{name}_indptr"]), shape=tuple(data[f"{name}_shape"]))

    return csr("M"), csr("D"), csr("K"), data["u0"], data["v0"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("system", help="an .npz written by SpatialSystem.export_npz")
    ap.add_argument("--T", type=float, default=1.0)
    ap.add_argument("--target", type=float, default=1e-6)
    ap.add_argument("--scheme", choices=("newmark", "alpha"), default="newmark")
    ap.add_argument("--rho-inf", type=float, default=0.8)
    ap.add_argument("--steps", type=int, default=16)
    args = ap.parse_args(argv)
    M, D, K, u0, v0 = load_npz(args.system)
    if K.shape[0] > 2000:
        raise SystemExit("newmark.py: the expm reference is dense; n <= 2000")
    scheme = newmark_average() if args.scheme == "newmark" else generalized_alpha(args.rho_inf)
    reference, _ = expm_reference(M, D, K, u0, v0, [args.T])
    rows, met = converge(M, D, K, u0, v0, [args.T], reference, args.target, scheme, args.steps)
    print(f"{scheme.name}: n = {K.shape[0]}, T = {args.T}, target {args.target:g}")
    print(f"{'steps':>8} {'wall [s]':>10} {'error':>10}")
    for row in rows:
        print(f"{row.steps:8d} {row.wall:10.4f} {row.error:10.3e}")
    print("target met" if met else "target not met within the halvings")
    return 0 if met else 1


if __name__ == "__main__":
    raise SystemExit(main())
