"""fem-dual orbit beside AUTO-07p (orthogonal collocation) on one periodic orbit of a curl force.

    .venv/bin/python benchmarks/auto_orbits.py [--json]     (needs: apt-get install auto-07p)

The force F = (-x - 0.5 y^2, -2y - 0.5 x^2) (curl -> x - y, unit mass) has a family of
symmetric orbits near its x-mode. AUTO (IPS = 2, NCOL = 4) starts from the motion from
(0.3, 0, 0, 0) over 6.3 and, with the unfolding parameter mu (force - mu v) and the period free,
takes two continuation steps along the family; its second point is a converged orbit. fem-dual
then starts from AUTO's finest orbit, so both describe the same member of the family (the
period varies by about 1e-5 per unit of amplitude along it). Reference: fem-dual at p = 6, 64
cells, whose closure under DOP853 (rtol = atol = 1e-13) is printed. AUTO prints its solutions
with 11 significant digits and its multipliers with 6: its errors cannot be read below that.
Times: AUTO's own "Total Time" (its compiled solver, without compiling the equations) and
fem-dual's Newton solve (`timings.solve_s`, forms compiled beforehand), both per orbit.
"""
from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import re
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np
from scipy.integrate import solve_ivp

AUTO_PYTHON = Path("/usr/lib/auto-07p/python")
A, X0, T0 = 0.5, (0.3, 0.0, 0.0, 0.0), 6.3

EQUATIONS = r"""
#include "auto_f2c.h"
int func (integer ndim, const doublereal *u, const integer *icp, const doublereal *par,
          integer ijac, doublereal *f, doublereal *dfdu, doublereal *dfdp)
{
  double x = u[0], y = u[1], a = par[0], mu = par[1];
  f[0] = u[2]; f[1] = u[3];
  f[2] = -x - a * y * y - mu * u[2];
  f[3] = -2.0 * y - a * x * x - mu * u[3];
  return 0;
}
int stpnt (integer ndim, doublereal t, doublereal *u, doublereal *par) { return 0; }
int bcnd (integer ndim, const doublereal *par, const integer *icp, integer nbc,
          const doublereal *u0, const doublereal *u1, integer ijac, doublereal *fb,
          doublereal *dbc) { return 0; }
int icnd (integer ndim, const doublereal *par, const integer *icp, integer nint,
          const doublereal *u, const doublereal *uold, const doublereal *udot,
          const doublereal *upold, integer ijac, doublereal *fi, doublereal *dint) { return 0; }
int fopt (integer ndim, const doublereal *u, const integer *icp, const doublereal *par,
          integer ijac, doublereal *fs, doublereal *dfdu, doublereal *dfdp) { return 0; }
int pvls (integer ndim, const void *u, doublereal *par) { return 0; }
"""

CONSTANTS = """NDIM=   4, IPS =   2, IRS =   0, ILP =   0
ICP =  [2, 11]
NTST=  {ntst}, NCOL=   4, IAD =   3, ISP =   2, ISW = 1, IPLT= 0, NBC= 0, NINT= 0
NMX=    3, NPR=  100, MXBF=   0, IID =   2, ITMX= 8, ITNW= 10, NWTN= 5, JAC= 0
EPSL= 1e-12, EPSU = 1e-12, EPSS =1e-8
DS  =   1e-4, DSMIN=  1e-6, DSMAX=   1e-3, IADS=   1
THL =  {{11: 0.0}}, THU =  {{}}
UZSTOP = {{}}
"""


def rhs(_t, z):
    x, y = z[:2]
    return [z[2], z[3], -x - A * y * y, -2 * y - A * x * x]


def auto_solutions(path: Path):
    """The solutions of an AUTO fort.8 file: label, parameters, the first mesh row."""
    lines = path.read_text().splitlines()
    i, out = 0, []
    while i < len(lines):
        head = [int(v) for v in lines[i].split()]
        rows, npar, ntpl, ndim = head[8], head[11], head[6], head[7] - 1
        block = lines[i + 1:i + 1 + rows]
        par = np.array(" ".join(block[-((npar + 6) // 7):]).split(), float)
        data = np.array(" ".join(block[:ntpl]).split(), float).reshape(ntpl, ndim + 1)
        out.append({"label": head[3], "par": par, "start": data[0, 1:]})
        i += 1 + rows
    return out


def auto_multipliers(path: Path, label_point: int) -> np.ndarray:
    """The Floquet multipliers AUTO printed (fort.9) for the point `label_point` of branch 1."""
    values = []
    for line in path.read_text().splitlines():
        m = re.match(r"\s*1\s+(\d+)\s+Multiplier\s+\d+\s+(\S+)\s+(\S+)", line)
        if m and int(m.group(1)) == label_point:
            values.append(complex(float(m.group(2)), float(m.group(3))))
    return np.array(values)


def run_auto(ntst: int, work: Path):
    """(period, start state, multipliers, AUTO's Total Time) of the converged orbit."""
    sys.path.insert(0, str(AUTO_PYTHON))
    import auto  # noqa: F401 -- AUTO-07p's own Python interface

    (work / "c.orb").write_text(CONSTANTS.format(ntst=ntst))
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        auto.run(e="orb", c="orb", dat="guess.dat", PAR={1: A, 2: 0.0})
    total = float(re.search(r"Total Time\s+(\S+)", printed.getvalue()).group(1))
    solution = auto_solutions(work / "fort.8")[1]  # the converged second point
    if abs(solution["par"][1]) > 1e-8:
        raise RuntimeError(f"AUTO's unfolding parameter is {solution['par'][1]}, not 0")
    return solution["par"][10], solution["start"], auto_multipliers(work / "fort.9", 3), total


def fem_dual_orbit(start: np.ndarray, period: float, degree: int, cells: int):
    from fem_dual.inputs import scene_of
    from fem_dual.analysis.orbit import Orbits

    scene = scene_of("force", {"F": f"-x - {A}*y**2, -2*y - {A}*x**2"})
    orbits, companion = Orbits(scene, degree, cells), Orbits(scene, degree + 1, cells)
    try:  # the first solve compiles what a solve needs; the second is timed
        for _ in range(2):
            result = orbits.solve(scene, start[:2], start[2:], period, companion=companion)
    finally:
        orbits.close()
        companion.close()
    return result


def nontrivial(values) -> np.ndarray:
    values = np.asarray(values)
    return np.sort_complex(np.array(sorted(values, key=lambda z: abs(z - 1))[2:]))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    if shutil.which("auto-07p") is None or not AUTO_PYTHON.is_dir():
        print("auto_orbits: AUTO-07p is not installed (apt-get install auto-07p)",
              file=sys.stderr)
        return 2
    rows = []
    home = Path.cwd()
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        (work / "orb.c").write_text(EQUATIONS)
        t = np.linspace(0.0, T0, 200)
        motion = solve_ivp(rhs, (0.0, T0), X0, t_eval=t, rtol=1e-12, atol=1e-12)
        np.savetxt(work / "guess.dat", np.column_stack([t, motion.y.T]), fmt="%.17g")
        os.chdir(work)
        try:
            autos = {ntst: run_auto(ntst, work) for ntst in (8, 16, 32, 64)}
        finally:
            os.chdir(home)
    period, start, _, _ = autos[64]
    reference = fem_dual_orbit(start, period, 6, 64)
    z0 = np.concatenate([reference.x[0], reference.v[0]])
    closure = np.abs(solve_ivp(rhs, (0, reference.period), z0, method="DOP853", rtol=1e-13,
                               atol=1e-13).y[:, -1] - z0).max()
    # the reference multipliers: DOP853 on the variational equation (fem-dual's check)
    ref_mult = nontrivial([complex(*m) for m in reference.check["multipliers_dop853"]])
    for ntst, (T, _, mult, total) in autos.items():
        rows.append({"tool": "AUTO-07p", "resolution": f"NTST={ntst}, NCOL=4", "period": T,
                     "period_error": abs(T - reference.period),
                     "multiplier_error": float(np.abs(nontrivial(mult) - ref_mult).max()),
                     "seconds": total})
    for cells in (8, 16, 32, 64):
        r = fem_dual_orbit(start, period, 4, cells)
        # seconds: the orbit's Newton and the monodromy of fem-dual's own slabs (AUTO's time
        # includes its multipliers), without the guess, the DOP853 check and the estimate
        rows.append({"tool": "fem-dual", "resolution": f"p=4, {cells} cells", "period": r.period,
                     "period_error": abs(r.period - reference.period),
                     "multiplier_error": float(np.abs(nontrivial(
                         [complex(*m) for m in r.multipliers]) - ref_mult).max()),
                     "multiplier_estimate": r.estimate.get("multipliers"),
                     "monodromy_cells": r.timings["monodromy_cells"],
                     "seconds": r.timings["solve_s"] + r.timings["monodromy_s"]})
    if args.json:
        print(json.dumps({"reference_period": reference.period, "reference_closure": closure,
                          "rows": rows}))
        return 0
    print(f"reference (fem-dual p = 6, 64 cells): period {reference.period:.15g}, closure "
          f"{closure:.1e} (DOP853), nontrivial multipliers {ref_mult.round(10)}")
    print(f"{'tool':10} {'resolution':18} {'period':>18} {'period error':>13} "
          f"{'mult. error':>12} {'seconds':>9}")
    for r in rows:
        print(f"{r['tool']:10} {r['resolution']:18} {r['period']:18.13f} "
              f"{r['period_error']:13.1e} {r['multiplier_error']:12.1e} {r['seconds']:9.4f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
