"""Stiff systems beside the integrators a user would pick: `fem-dual bench` rows for
three stiff cases, on equal terms (same output times, same reference, compilation excluded).

    .venv/bin/python benchmarks/stiff.py [--case NAME]... [--repeats 3] [--out DIR]

Cases: two-modes (omega 1 and 1e3, shear-coupled, T = 10), column40 (40-link follower column at
P = 9.5 from its lowest mode, T = 2.5, fastest mode 1e4 times the slowest), curl3d-spring (the
curl force on a spring of omega = 1e3 in z, from the slow manifold, T = 10). Writes
DIR/stiff_<case>.csv and .png and prints each table with the wall-time ratios of the fastest
fem-dual row reaching 1e-6 and 1e-8 to Radau, LSODA, DOP853 and the matrix exponential.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from mpi4py import MPI

from fem_dual import RunConfig
from fem_dual.analysis import bench as bm
from fem_dual.mpi import print0
from fem_dual.analysis.stress import _scaled_column

CASES = {
    "two-modes": (lambda: RunConfig.create(
        "linear", {"dofs": "2", "M": "1,-1,-1,2", "K": "1,-1,-1,1000001"}, T=10.0,
        x0="1,0", v0="0,0"), [10, 20, 40], [1, 2, 4]),
    "column40": (lambda: _scaled_column(40, 9.5, T=2.5), [5, 10, 20], [2, 4, 8]),
    "curl3d-spring": (lambda: RunConfig.create(
        "curl3d", {"K": "0,0,0,0,0,0,0,0,1e6"}, T=10.0, x0="0.3,0.2,-6e-8"), [25, 50], [2, 4]),
}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", action="append", choices=sorted(CASES))
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", default="benchmarks/results")
    args = ap.parse_args(argv)
    comm = MPI.COMM_WORLD
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for name in args.case or list(CASES):
        make, slabs, cells = CASES[name]
        base = make()
        rows = bm.bench(base, degrees=(4,), cells=cells, repeats=args.repeats, comm=comm,
                        slabs=slabs)
        if comm.rank == 0:
            bm.write_csv(rows, out / f"stiff_{name}.csv")
            bm.plot(rows, out / f"stiff_{name}.png", f"{name}, T = {base.T:g}")
        print0(comm, f"== {name} (base {base.base_state}"
               f"{', modal' if base.scene.linear and base.modal else ''})")
        print0(comm, bm.table(rows))
        for peer in ("Radau", "LSODA", "DOP853", "expm"):
            for target in (1e-6, 1e-8):
                ratio = bm.ratio_at(rows, target, peer)
                text = "not reached by both" if ratio is None else f"{ratio:.2f}"
                print0(comm, f"wall-time ratio fem-dual / {peer} at max error <= {target:g}: "
                       f"{text}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
