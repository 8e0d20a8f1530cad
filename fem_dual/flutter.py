"""Critical follower load of a linear scene, found two independent ways.

(a) eigen: the smallest load P at which an eigenvalue of the first-order system matrix crosses
    into the right half-plane (flutter or divergence);
(b) dual: from dual simulations alone. For each trial P, fem-dual solves the motion over a
    horizon; the growth rate of the recovered motion is read off the motion itself (the
    one-step map z_{k+1} = Phi z_k fitted by least squares to the vertex states, sigma =
    max log|eig Phi| / h), and P is bisected on the sign of sigma.

Both scan P = 0, P0, 2 P0, 4 P0, ... for the first unstable value, then bisect.
"""
from __future__ import annotations

import time
from dataclasses import replace
from typing import Callable, Dict, Optional

import numpy as np
from mpi4py import MPI

from fem_dual.config import RunConfig
from fem_dual.driver import run
from fem_dual.errors import InputError
from fem_dual.scenes.linear import LinearScene

__all__ = ["growth_rate", "critical_load", "eigen_rate", "dual_rate", "flutter"]


def growth_rate(t: np.ndarray, x: np.ndarray, v: np.ndarray) -> float:
    """Largest exponential rate of a sampled linear motion (uniform times), by a least-squares
    fit of the one-step map."""
    z = np.hstack([x, v]).T
    h = t[1] - t[0]
    Phi = z[:, 1:] @ np.linalg.pinv(z[:, :-1])
    return float(np.log(np.abs(np.linalg.eigvals(Phi))).max() / h)


def critical_load(rate: Callable[[float], float], tol: float, first: float = 0.25,
                  rel_width: float = 1e-5, max_load: float = 1e6) -> float:
    """Smallest P with rate(P) > tol: doubling scan from `first`, then bisection."""
    if rate(0.0) > tol:
        raise InputError("the system is already unstable without load (P = 0)")
    lo, hi = 0.0, first
    while rate(hi) <= tol:
        lo, hi = hi, 2 * hi
        if hi > max_load:
            raise InputError(f"no instability found for P up to {max_load:g}")
    while hi - lo > rel_width * hi:
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if rate(mid) > tol else (mid, hi)
    return 0.5 * (lo + hi)


def _with_load(scene: LinearScene, P: float) -> LinearScene:
    return replace(scene, P=P)


def eigen_rate(scene: LinearScene) -> Callable[[float], float]:
    return lambda P: float(np.linalg.eigvals(_with_load(scene, P).first_order_matrix()).real.max())


def dual_rate(base: RunConfig, comm: MPI.Comm) -> Callable[[float], float]:
    def rate(P: float) -> float:
        result = run(replace(base, scene=_with_load(base.scene, P)), comm)
        return growth_rate(result.t, result.x, result.v)
    return rate


def flutter(base: RunConfig, comm: MPI.Comm = MPI.COMM_WORLD,
            tol: Optional[float] = None) -> Dict[str, float]:
    """{eigen, dual, eigen_s, dual_s}: the critical loads and the seconds each search took."""
    if not isinstance(base.scene, LinearScene) or not hasattr(base.scene, "P"):
        raise InputError(f"flutter needs a linear scene with a load P, not {base.scene.name}")
    tic = time.perf_counter()
    eigen = critical_load(eigen_rate(base.scene), tol=1e-9)
    eigen_s = time.perf_counter() - tic
    tic = time.perf_counter()
    dual = critical_load(dual_rate(base, comm), tol=1e-6 if tol is None else tol)
    dual_s = time.perf_counter() - tic
    return {"eigen": eigen, "dual": dual, "eigen_s": eigen_s, "dual_s": dual_s}
