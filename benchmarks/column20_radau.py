"""The 20-link follower column (P = 4) over one period of its slowest mode, from that mode at
rest: `fem-dual run --rtol R` with its defaults against scipy's Radau with the exact Jacobian,
at fem-dual's output times, errors against the matrix exponential (relative to the motion's
scales, the larger of x's and v's).

    .venv/bin/python benchmarks/column20_radau.py [--repeats 5]

Prints one line per fem-dual tolerance and per Radau tolerance: best wall time of the repeats
(compilation and reference excluded for fem-dual) and the relative error.
"""
from __future__ import annotations

import argparse
import time

import numpy as np
import scipy.linalg as sla
from scipy.integrate import solve_ivp

from fem_dual import RunConfig, run
from fem_dual.integrate.simulation import Simulation
from fem_dual.scenes.column import lowest_mode, scaled_column


def best_of(repeats: int, action) -> float:
    best = np.inf
    for _ in range(repeats):
        tic = time.perf_counter()
        action()
        best = min(best, time.perf_counter() - tic)
    return best


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args(argv)
    scene = scaled_column(20, 4.0)
    M, K = scene.mass_matrix(), scene.stiffness_matrix()
    n = scene.n
    T = 2 * np.pi / np.sqrt(np.abs(np.linalg.eigvals(np.linalg.solve(M, K))).min())
    x0 = lowest_mode(scene)
    A = np.block([[np.zeros((n, n)), np.eye(n)], [-np.linalg.solve(M, K), np.zeros((n, n))]])
    z0 = np.concatenate([x0, np.zeros(n)])
    for rtol in (1e-6, 1e-8):
        timed = RunConfig.create(scene, T=T, x0=x0, v0=np.zeros(n), rtol=rtol,
                                 reference="none")
        sim = Simulation.for_config(timed)
        sim.run(timed)
        wall = best_of(args.repeats, lambda: sim.run(timed))
        sim.close()
        r = run(RunConfig.create(scene, T=T, x0=x0, v0=np.zeros(n), rtol=rtol))
        sx, sv = r.tolerance["scale_x"], r.tolerance["scale_v"]
        err = max(r.error["x_max"] / sx, r.error["v_max"] / sv)
        print(f"fem-dual --rtol {rtol:g}: {wall * 1e3:.1f} ms, relative error {err:.2g} "
              f"(p = {r.degree}, {len(r.slab_lengths)} slabs, base {r.solver['base']})")
        t = np.asarray(r.t)
        exact = np.array([sla.expm(A * s) @ z0 for s in t])
        for tol in (1e-6, 1e-7, 1e-8, 1e-9, 1e-10):
            def radau():
                return solve_ivp(lambda _t, z: A @ z, (0, T), z0, method="Radau", jac=A,
                                 rtol=tol, atol=tol * 1e-3, t_eval=t)
            wall_r = best_of(max(1, args.repeats // 2), radau)
            y = radau().y.T
            err_r = max(np.abs(y[:, :n] - exact[:, :n]).max() / sx,
                        np.abs(y[:, n:] - exact[:, n:]).max() / sv)
            print(f"    Radau rtol {tol:g}: {wall_r * 1e3:.1f} ms, relative error {err_r:.2g}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
