"""The whole-process time of a short run, and where it goes.

    .venv/bin/python benchmarks/startup.py [--repeats 15] [RUN ARGS ...]

Runs `fem-dual run RUN ARGS --json` (default: `curl3d --T 2`) `--repeats` times as a fresh
process each, as a user's shell would (FFCx's cache warm, bytecode writable), and prints the
minimum and median wall time of the process beside the medians of the run's own timings
(set-up, compile, solve and estimate, reference); "outside the run" is the rest: starting
Python, importing the command line, writing the JSON. A second row times a bare
`import mpi4py.MPI, dolfinx` in a fresh process, the floor that any DOLFINx program pays.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path


def _timed(cmd, env) -> tuple:
    tic = time.perf_counter()
    done = subprocess.run(cmd, stdout=subprocess.PIPE, env=env, check=True, text=True)
    return time.perf_counter() - tic, done.stdout


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("run", nargs=argparse.REMAINDER,
                        help="the scene and options of `fem-dual run` (default: curl3d --T 2)")
    args = parser.parse_args()
    args.run = args.run or ["curl3d", "--T", "2"]
    env = dict(os.environ)
    env.pop("PYTHONDONTWRITEBYTECODE", None)  # as a user's shell: bytecode is cached
    exe = str(Path(sys.executable).parent / "fem-dual")
    cmd = [exe, "run", *args.run, "--json"]
    _timed(cmd, env)  # warms FFCx's cache and the bytecode
    walls, keys = [], ("setup_s", "compile_s", "solve_s", "estimate_s", "reference_s",
                       "total_s")
    timings = {k: [] for k in keys}
    for _ in range(args.repeats):
        wall, out = _timed(cmd, env)
        walls.append(wall)
        record = json.loads(out)["timings"]
        for k in keys:
            timings[k].append(record[k])
    med = {k: statistics.median(v) for k, v in timings.items()}
    bare = [_timed([sys.executable, "-c", "import mpi4py.MPI, dolfinx"], env)[0]
            for _ in range(args.repeats)]
    print(f"`fem-dual run {' '.join(args.run)} --json`, {args.repeats} processes:")
    print("| process, min | process, median | set-up | compile | solve + estimate | "
          "reference | outside the run |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    print(f"| {min(walls):.3f} s | {statistics.median(walls):.3f} s | {med['setup_s']:.3f} s "
          f"| {med['compile_s']:.3f} s | {med['solve_s'] + med['estimate_s']:.3f} s | "
          f"{med['reference_s']:.3f} s | {statistics.median(walls) - med['total_s']:.3f} s |")
    print(f"\n`python -c 'import mpi4py.MPI, dolfinx'`: min {min(bare):.3f} s, median "
          f"{statistics.median(bare):.3f} s")


if __name__ == "__main__":
    main()
