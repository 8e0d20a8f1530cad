"""Strong scaling of one large problem on 1 and 2 MPI ranks (and more with --ranks).

Runs `fem-dual run ... --json` under `mpirun -n R` for each R, in separate processes, and reports
the wall time of the whole command, the solve time the run measured, and the speed-up against one
rank; the numbers of every run must agree (max |x - x_serial| is printed).

    .venv/bin/python benchmarks/scaling.py --ranks 1,2 -- ziegler --T 10000 --cells 100000 --degree 4
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

FEM_DUAL = str(Path(sys.executable).with_name("fem-dual"))
ENV = {**os.environ, "OMPI_ALLOW_RUN_AS_ROOT": "1", "OMPI_ALLOW_RUN_AS_ROOT_CONFIRM": "1"}


def measure(ranks: int, run_args: list) -> dict:
    cmd = ["mpirun", "-n", str(ranks), FEM_DUAL, "run", *run_args, "--json"]
    tic = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, env=ENV, stdin=subprocess.DEVNULL)
    wall = time.perf_counter() - tic
    if proc.returncode != 0:
        sys.exit(f"scaling: {' '.join(cmd)} failed: {proc.stderr.strip().splitlines()[-1]}")
    data = json.loads(proc.stdout)
    return {"ranks": ranks, "wall_s": wall, "solve_s": data["timings"]["solve_s"],
            "total_s": data["timings"]["total_s"], "x_max": data["error"]["x_max"],
            "x": np.array(data["x"]), "dofs": data["dofs_per_slab"]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ranks", default="1,2")
    parser.add_argument("run_args", nargs=argparse.REMAINDER,
                        help="arguments of `fem-dual run` after --")
    args = parser.parse_args()
    run_args = [a for a in args.run_args if a != "--"]
    rows = [measure(int(r), run_args) for r in args.ranks.split(",")]
    base = rows[0]
    print(f"fem-dual run {' '.join(run_args)}  ({base['dofs']} dofs per slab)")
    print(f"{'ranks':>5s} {'wall_s':>8s} {'solve_s':>8s} {'speed-up(solve)':>16s} "
          f"{'error.x_max':>12s} {'max|x - x_1|':>13s}")
    for r in rows:
        gap = np.abs(r["x"] - base["x"]).max()
        print(f"{r['ranks']:5d} {r['wall_s']:8.2f} {r['solve_s']:8.2f} "
              f"{base['solve_s'] / r['solve_s']:16.2f} {r['x_max']:12.3e} {gap:13.2e}")


if __name__ == "__main__":
    main()
