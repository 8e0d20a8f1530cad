"""The run's own error estimate beside its error against the independent reference, over the
scenes, several tolerances and a fixed-slab setting: a run that says ok with an error above its
estimate (by more than --factor) is a wrong answer reported as a success, and is listed as BAD.

    .venv/bin/python benchmarks/estimate_sweep.py [--T 5] [--rtols 1e-4,1e-6,1e-8,1e-10]
        [--factor 1.5]

One line per run: flag, exit status, status, the command's arguments, error, estimate, slabs and
run time (`fem-dual run ... --json`). Exit status 1 when a run is BAD.
"""
import argparse
import json
import subprocess
import sys
from pathlib import Path

FEM_DUAL = [sys.executable, "-m", "fem_dual.cli"]
SCENES = [("ziegler", []), ("linear", []), ("column", ["--param", "links=6"]), ("curl2d", []),
          ("curl3d", []), ("curl2d-lifted", []),
          ("force", ["--F", "-x1 - 0.3*x2**3, -x2 + 0.5*x1", "--x0", "1,0", "--v0", "0,1"])]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--T", default="5")
    ap.add_argument("--rtols", default="1e-4,1e-6,1e-8,1e-10")
    ap.add_argument("--factor", type=float, default=1.5)
    args = ap.parse_args(argv)
    bad = 0
    for scene, extra in SCENES:
        settings = [["--rtol", r] for r in args.rtols.split(",")]
        settings.append(["--slabs", "10", "--cells", "8", "--degree", "3"])
        for setting in settings:
            cmd = [scene, *extra, "--T", args.T, *setting]
            done = subprocess.run(FEM_DUAL + ["run", *cmd, "--json"], capture_output=True,
                                  text=True, cwd=Path(__file__).resolve().parents[1])
            try:
                out = json.loads(done.stdout)
            except ValueError:
                print("NOJSON", done.returncode, " ".join(cmd), done.stderr.strip()[-160:])
                bad += 1
                continue
            e, s = out["error"], out["estimate"]
            err = None if e["x_max"] is None else max(e["x_max"], e["v_max"])
            est = None if s["x_max"] is None else max(s["x_max"], s["v_max"])
            flag = "BAD" if (out["status"] == "ok" and err is not None and est is not None
                             and err > args.factor * est) else "   "
            bad += flag == "BAD"
            print(f"{flag} {done.returncode} {out['status']:6s} {' '.join(cmd)}: error {err} "
                  f"estimate {est} slabs {len(out['slab_lengths'])} "
                  f"{out['timings']['total_s']:.2f} s", flush=True)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
