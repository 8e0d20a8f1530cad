"""fem-dual against Newmark's average acceleration on a continuum, at matched error.

    .venv/bin/python benchmarks/continuum_newmark.py [--scene cauchy2d] [--param elements=16]
        [--T 1] [--degree P] [--rtol 1e-2 1e-4 1e-6] [--target 1e-4 1e-6 1e-8] [--scheme newmark|alpha]

For each rtol: `fem-dual run SCENE --rtol R --out DIR --json` (its time: the whole run less its
reference and output; the set-up included: loading DOLFINx and PETSc, assembling M and K, the
modal coordinates, the compile), its error measured as benchmarks/newmark.py measures
Newmark's (|u(T) - u_ref(T)|_2 / |u_ref(T)|_2, the reference the matrix exponential of the
exported `<scene>_system.npz`). Then for each target error: the cheapest of those runs that
meets it, and Newmark with its step halved from 16 until it meets it. Prints markdown tables;
the ratio is fem-dual's time over Newmark's, each the best of `--repeats` runs. Newmark's time holds neither its imports nor the
assembly of M and K (it reads them); the last column is fem-dual's ratio without the imports of
its stack (DOLFINx, PETSc, UFL, scipy; timed in a fresh process), which its set-up holds.
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

_HERE = Path(__file__).resolve().parent
_spec = importlib.util.spec_from_file_location("newmark_benchmark", _HERE / "newmark.py")
nm = sys.modules[_spec.name] = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(nm)


def fem_dual_row(scene, params, T, rtol, out: Path, degree=None):
    cmd = [str(Path(sys.executable).parent / "fem-dual"), "run", scene, "--T", str(T),
           "--rtol", str(rtol), "--out", str(out), "--json"]
    if degree is not None:
        cmd += ["--degree", str(degree)]
    for p in params:
        cmd += ["--param", p]
    data = json.loads(subprocess.run(cmd, capture_output=True, text=True, check=True).stdout)
    tm = data["timings"]
    wall = tm["total_s"] - tm.get("reference_s", 0.0) - tm.get("output_s", 0.0)
    return data, wall


def import_seconds() -> float:
    """The imports a continuum run's set-up pays, timed in a fresh process (best of 3) with
    the MPI defaults the command line takes for itself."""
    code = ("import time; from fem_dual.cli import _singleton_mpi_defaults; "
            "_singleton_mpi_defaults(); t = time.perf_counter(); import dolfinx, "
            "dolfinx.fem.petsc, ufl, petsc4py.PETSc, mpi4py.MPI, scipy.linalg, scipy.sparse; "
            "print(time.perf_counter() - t)")
    return min(float(subprocess.run([sys.executable, "-c", code], capture_output=True,
                                    text=True, check=True).stdout) for _ in range(3))


REPEAT_BELOW = 5.0  # seconds: a longer Newmark run is timed once (its noise is small)


def best_peer(row, M, D, K, u0, v0, T: float, scheme, repeats: int):
    """The row with the best wall time of `repeats` runs at its step count."""
    wall = row.wall
    for _ in range(repeats - 1 if row.wall < REPEAT_BELOW else 0):
        start = time.perf_counter()
        nm.integrate(M, D, K, u0, v0, [T], row.steps, scheme)
        wall = min(wall, time.perf_counter() - start)
    return nm.Row(row.steps, wall, row.error)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="cauchy2d")
    ap.add_argument("--param", action="append", default=[])
    ap.add_argument("--T", type=float, default=1.0)
    ap.add_argument("--degree", type=int, help="fem-dual's degree in time (default: --rtol's)")
    ap.add_argument("--rtol", type=float, nargs="+", default=[1e-2, 1e-4, 1e-6])
    ap.add_argument("--target", type=float, nargs="+", default=[1e-4, 1e-6, 1e-8])
    ap.add_argument("--halvings", type=int, default=17, help="Newmark's step halvings from 16 "
                    "steps (17: up to 2,097,152 steps)")
    ap.add_argument("--scheme", choices=("newmark", "alpha"), default="newmark")
    ap.add_argument("--repeats", type=int, default=3, help="best of this many runs on each "
                    "side (a Newmark run over REPEAT_BELOW seconds once)")
    args = ap.parse_args(argv)
    scheme = nm.newmark_average() if args.scheme == "newmark" else nm.generalized_alpha(0.8)
    print(f"{args.scene} {' '.join(args.param)} T = {args.T}, {scheme.name}")
    print("| fem-dual --rtol | slabs | its error | estimate | time |")
    print("| --- | --- | --- | --- | --- |")
    rows = []
    for rtol in args.rtol:
        with tempfile.TemporaryDirectory() as tmp:
            data, wall = fem_dual_row(args.scene, args.param, args.T, rtol, Path(tmp),
                                      args.degree)
            M, D, K, u0, v0 = nm.load_npz(str(Path(tmp) / f"{args.scene}_system.npz"))
        for _ in range(args.repeats - 1):  # (the same run: only its time moves)
            with tempfile.TemporaryDirectory() as tmp:
                wall = min(wall, fem_dual_row(args.scene, args.param, args.T, rtol, Path(tmp),
                                              args.degree)[1])
        ref, _ = nm.expm_reference(M, D, K, u0, v0, [args.T])
        error = float(np.linalg.norm(np.array(data["final"]["x"]) - ref[0])
                      / np.linalg.norm(ref[0]))
        rows.append((rtol, error, wall))
        print(f"| {rtol:g} | {len(data['solver']['estimates'])} | {error:.1e} | "
              f"{data['error_estimate']:.1e} | {wall:.2f} s |", flush=True)
    imports = import_seconds()
    print(f"\nimports: {imports:.2f} s")
    print(f"\n| error at most | fem-dual (the cheapest run above) | {scheme.name} | ratio | "
          "without imports |")
    print("| --- | --- | --- | --- | --- |")
    for target in args.target:
        meeting = [r for r in rows if r[1] <= target]
        peer_rows, met = nm.converge(M, D, K, u0, v0, [args.T], ref, target, scheme, 16,
                                     args.halvings)
        peer = best_peer(peer_rows[-1], M, D, K, u0, v0, args.T, scheme, args.repeats)
        fem = min(meeting, key=lambda r: r[2]) if meeting else None
        fem_text = f"--rtol {fem[0]:g}: {fem[1]:.1e} in {fem[2]:.2f} s" if fem else "none"
        peer_text = (f"{peer.steps} steps: {peer.error:.1e} in {peer.wall:.3g} s" if met else
                     f"not within {peer.steps} steps ({peer.error:.1e}, {peer.wall:.3g} s)")
        ratios = []
        for seconds in ([fem[2], fem[2] - imports] if fem else []):
            ratios.append(f"{seconds / peer.wall:.2g}" if met else
                          f"< {seconds / peer.wall:.2g}")
        ratio, bare = ratios if ratios else ("—", "—")
        print(f"| {target:g} | {fem_text} | {peer_text} | {ratio} | {bare} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
