"""Where the delivered error lies against what was asked: for each run and --rtol, the true error
(the larger of x and v against the run's independent reference) over rtol x the motion's scale,
beside the run's own estimate and its time (solve and estimate, without start-up and reference). The aim: between 1/100 and 10, the time falling as the
tolerance loosens.

    .venv/bin/python benchmarks/tolerance_band.py [--rtols 1e-4,1e-6,1e-8,1e-10] [--markdown]

One row per run and tolerance (`fem-dual run RUN --rtol R --json`); exit status 1 when a run
fails or its error exceeds its estimate.
"""
import argparse
import json
import subprocess
import sys
from pathlib import Path

FEM_DUAL = [sys.executable, "-m", "fem_dual.cli"]
RUNS = [
    "curl3d --T 8 --x0 0.25,0.2,0.12",
    "curl2d --T 3 --x0 0.9,1.1 --param k=1.5",
    "curl2d --T 2",
    "force --F -x-2*x*y,-y-x**2+y**2 --x0 0.3,0.1 --T 30",
    "ziegler --param P=3",
    "column --param links=6",
    "linear --param M=1,0,0,1 --param K=1,0.5,-0.5,100 --x0 1,1 --T 10",
    "cauchy2d",
]
BAND = (1e-2, 10.0)


def measure(run: str, rtol: str) -> dict:
    done = subprocess.run(FEM_DUAL + ["run", *run.split(), "--rtol", rtol, "--json"],
                          capture_output=True, text=True, cwd=Path(__file__).resolve().parents[1])
    try:
        out = json.loads(done.stdout)
    except ValueError:
        return {"run": run, "rtol": rtol, "failed": done.stderr.strip()[-200:]}
    err = out["error"]
    tol = out["tolerance"]
    asked = float(rtol) * max(tol["scale_x"], tol["scale_v"])
    error = max(err["x_max"], err["v_max"])
    return {"run": run, "rtol": rtol, "p": out["degree"], "slabs": out["slabs"], "error": error,
            "estimate": out["error_estimate"], "ratio": error / asked,
            "seconds": out["timings"]["solve_s"] + out["timings"]["estimate_s"],
            "status": out["status"]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rtols", default="1e-4,1e-6,1e-8,1e-10")
    ap.add_argument("--markdown", action="store_true")
    args = ap.parse_args(argv)
    bad = 0
    if args.markdown:
        print("| run | rtol | p | slabs | error | estimate | error / (rtol · scale) | solve s |")
        print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for run in RUNS:
        for rtol in args.rtols.split(","):
            row = measure(run, rtol)
            if "failed" in row:
                bad += 1
                print(f"FAILED {run} --rtol {rtol}: {row['failed']}")
                continue
            flag = "" if BAND[0] <= row["ratio"] <= BAND[1] else " (outside)"
            if row["error"] > row["estimate"]:
                bad += 1
                flag += " (above its estimate)"
            if args.markdown:
                print(f"| `{run}` | {rtol} | {row['p']} | {row['slabs']} | {row['error']:.1e} | "
                      f"{row['estimate']:.1e} | {row['ratio']:.1e}{flag} | {row['seconds']:.3f} |")
            else:
                print(f"{run:58s} {rtol:6s} p={row['p']} slabs={row['slabs']:5d} "
                      f"err={row['error']:.1e} est={row['estimate']:.1e} "
                      f"ratio={row['ratio']:.1e} t={row['seconds']:.3f}s{flag}")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
