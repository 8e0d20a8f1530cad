"""A follower-load column of many links at scale: Kronecker assembly, matrix-free CG
with the fast-diagonalisation preconditioner, serial or under mpirun.

    .venv/bin/python benchmarks/column_scale.py [--links 200] [--periods 10] [--P-ratio 0.5]
        [--slabs-per-period 16] [--max-radians-per-cell R] [--cells 4] [--degree 4] [--json]
    mpirun -n 2 .venv/bin/python benchmarks/column_scale.py ...

The column is scaled like a continuous one (length L = 1, EI = 1, mu = 1): l = 1/N, c = EI/l,
m = mu L/N, so its lowest frequency and flutter load approach Beck's column. The load is
P-ratio times the column's eigenvalue flutter load; the start state is the lowest mode (so the
motion stays in the resolved part of the spectrum), the horizon a number of periods of that
mode. Reports size, run time, CG iterations, peak memory (max over ranks) and the error against
the matrix exponential.
"""
from __future__ import annotations

import argparse
import json
import resource
import sys
import time

from fem_dual import RunConfig  # first: it sets one BLAS thread per rank under mpirun

import numpy as np  # noqa: E402
from mpi4py import MPI  # noqa: E402
from fem_dual.integrate.simulation import Simulation
from fem_dual.analysis.flutter import critical_load, eigen_rate, eigen_tolerance
from fem_dual.mpi import allreduce, print0
from fem_dual.scenes.column import lowest_mode, scaled_column, scaled_column_params


column_params = scaled_column_params  # the name benchmarks/hp_reference imports


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--links", type=int, default=200)
    ap.add_argument("--periods", type=float, default=10.0)
    ap.add_argument("--P-ratio", type=float, default=0.5)
    ap.add_argument("--slabs-per-period", type=int, default=16)
    ap.add_argument("--max-radians-per-cell", type=float, default=None,
                    help="more slabs until the fastest mode turns at most this much per cell")
    ap.add_argument("--cells", type=int, default=4)
    ap.add_argument("--degree", type=int, default=4)
    ap.add_argument("--base", default="auto", help="base state of H (auto, zero, start)")
    ap.add_argument("--coordinates", default="auto", help="auto, modal, physical")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--no-peer", action="store_true", help="skip the matrix-exponential peer")
    args = ap.parse_args(argv)
    comm = MPI.COMM_WORLD
    tic = time.perf_counter()
    unloaded = scaled_column(args.links)
    P_cr = critical_load(eigen_rate(unloaded), eigen_tolerance(unloaded), first=1.0,
                         rel_width=1e-6)  # a threshold above the eigenvalues' round-off
    scene = scaled_column(args.links, args.P_ratio * P_cr)
    lam = np.linalg.eigvals(np.linalg.solve(scene.mass_matrix(), scene.stiffness_matrix()))
    omega = float(np.sqrt(abs(lam[int(np.argmin(np.abs(lam)))].real)))
    x0 = lowest_mode(scene)
    T = args.periods * 2 * np.pi / omega
    slabs = int(np.ceil(args.periods * args.slabs_per_period))
    if args.max_radians_per_cell:  # the whole spectrum resolved (the slab map is stable)
        fastest = scene.fastest_rate()
        slabs = max(slabs, int(np.ceil(fastest * T / (args.max_radians_per_cell * args.cells))))
    config = RunConfig.create(scene, T=T, slabs=slabs, cells=args.cells, degree=args.degree,
                              x0=x0, v0=np.zeros(args.links), assembly="kronecker",
                              base=args.base, coordinates=args.coordinates)
    prep_s = time.perf_counter() - tic
    comm.Barrier()  # ranks start up to 1 s apart: that launch skew is not the run's set-up
    sim = Simulation.for_config(config, comm)
    result = sim.run(config)
    rss = allreduce(comm, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, "max")
    its = result.solver["ksp_iterations"]
    out = {"links": args.links, "ranks": comm.size, "P": args.P_ratio * P_cr, "P_cr": P_cr,
           "omega_lowest": omega, "T": T, "slabs": slabs, "cells": args.cells,
           "degree": args.degree, "unknowns_per_slab": result.dofs_per_slab,
           "unknowns_total": result.dofs_per_slab * slabs,
           "cg_iterations_mean": float(np.mean(its)), "cg_iterations_max": int(max(its)),
           "run_s": result.timings["total_s"] - result.timings["reference_s"],
           "setup_s": result.timings["compile_s"], "prepare_s": prep_s,
           "peak_rss_mb": rss, "error_x_max": result.error["x_max"],
           "relative_error": result.error["x_max"] / np.abs(x0).max(),
           "error_v_max": result.error["v_max"],
           "relative_error_v": result.error["v_max"] / np.abs(result.v).max(),
           "error_estimate": result.error_estimate, "base": config.base_state,
           "coordinates": "modal" if config.modal else "physical"}
    if comm.rank == 0 and not args.no_peer:  # the peer at the same output times, same process
        out.update(_expm_peer(scene, x0, result, out["run_s"] - out["setup_s"]))
    if args.json:
        print0(comm, json.dumps(out))
    else:
        for key, value in out.items():
            print0(comm, f"{key:20s} {value:.6g}" if isinstance(value, float)
                   else f"{key:20s} {value}")
    return 0


def _expm_peer(scene, x0, result, solve_s: float, repeats: int = 3) -> dict:
    """The matrix-exponential propagator (fem_dual.analysis.bench) at fem-dual's output times: best of
    `repeats` wall times, its error against the reference, and fem-dual's wall time (set-up
    excluded) over it."""
    from fem_dual.analysis.bench import _expm_propagator

    A = scene.first_order_matrix()
    z0 = np.concatenate([x0, np.zeros_like(x0)])
    walls = []
    for _ in range(repeats):
        tic = time.perf_counter()
        z = _expm_propagator(A, z0, result.t)
        walls.append(time.perf_counter() - tic)
    x_ref, _ = scene.reference(x0, np.zeros_like(x0))(result.t)
    n = len(x0)
    from fem_dual.modes import compute_real_modes

    tic = time.perf_counter()  # fem-dual's set-up for modal coordinates, once per scene
    compute_real_modes(scene.mass_matrix(), scene.stiffness_matrix())
    modal_s = time.perf_counter() - tic
    return {"expm_s": min(walls), "modal_decomposition_s": modal_s, "expm_error_x_max": float(np.abs(z[:, :n] - x_ref).max()),
            "fem_dual_solve_s": solve_s, "ratio_to_expm": solve_s / min(walls)}


if __name__ == "__main__":
    sys.exit(main())
