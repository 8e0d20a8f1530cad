"""`fem-dual bench`: error against run time, fem-dual beside the integrators a user would pick.

One problem, one reference (the scene's: matrix exponential or DOP853 at 1e-13). Rows:
fem-dual at degrees 2, 3, 4 over a range of cells per slab, fem-dual with --rtol (adaptive slab
lengths) at the tolerances of `--rtols`, and scipy's RK45, DOP853, its Fortran DOP853
(`ode('dop853')`, "DOP853-f"), Radau and LSODA (both with the exact Jacobian for linear
scenes) over a range of tolerances (the `--rtols` among them), and for linear scenes the
matrix-exponential propagator ("expm": exp(A h) once per step, a product per output time),
measured in the same process. The peers answer at fem-dual's output times (the vertices of its
run with the fewest of them, so no peer pays for more output or is judged at more times than a
fem-dual row; 1001 equispaced times when there is no fem-dual row); each row also reports the
error at the final time. Wall times are medians of `repeats` runs;
fem-dual's set-up (form compilation, mesh, spaces, solver objects: `Simulation`, built once per
degree and cells) and the reference are excluded (the timed runs compare with none: each row's
error is measured after them), and the set-up time is reported on its own as compile_s. Each
timed fem-dual run assembles, factors and solves afresh.
"""
from __future__ import annotations

import csv
import math
import time
from pathlib import Path
from typing import Dict, List, Optional, Sequence

import numpy as np
from mpi4py import MPI
from scipy.integrate import solve_ivp

from fem_dual.config import RunConfig
from fem_dual.integrate.simulation import Simulation
from fem_dual.errors import InputError, SolveError
from fem_dual.scenes import Scene

__all__ = ["COLUMNS", "bench", "write_csv", "read_csv", "plot", "table", "ratio_at",
           "ratio_same_times"]

COLUMNS = ["method", "degree", "cells", "slabs", "rtol", "max_error", "final_error", "wall_s",
           "compile_s", "samples", "estimate", "slabs_solved", "expm_wall_s"]
TOLERANCES = {"RK45": [1e-4, 1e-6, 1e-8, 1e-10], "DOP853": [1e-6, 1e-8, 1e-10, 1e-12],
              "DOP853-f": [1e-6, 1e-8, 1e-10, 1e-12], "Radau": [1e-4, 1e-6, 1e-8],
              "LSODA": [1e-6, 1e-8, 1e-10, 1e-12]}


def _state_error(x, v, x_ref, v_ref) -> np.ndarray:
    return np.maximum(np.abs(x - x_ref).max(axis=1), np.abs(v - v_ref).max(axis=1))


def _fem_row(sim: Simulation, config: RunConfig, repeats: int, compile_s: float,
             skipped: Optional[List[str]], what: str) -> Optional[Dict]:
    """One fem-dual row: median wall time of `repeats` runs, every attempt (rejected slabs
    included) counted; None (and a line in `skipped`) when the run stops."""
    walls, result = [], None
    try:  # configurations the tool refuses are left out, and said so
        sim.run(config)  # warms the caches
    except SolveError as exc:
        if skipped is not None:
            skipped.append(f"{what}: {exc}")
        return None
    for _ in range(repeats):  # every run assembles, factors and solves afresh
        result = sim.run(config)
        walls.append(result.timings["total_s"] - result.timings["reference_s"]
                     - result.timings["compile_s"])
    flow = config.scene.reference(config.x0, config.v0)
    x_ref, v_ref = flow(result.t)
    err = _state_error(result.x, result.v, x_ref, v_ref)
    expm_wall = None
    if config.scene.linear:  # the exact propagator at this row's own output times
        A, z0 = config.scene.first_order_matrix(), np.concatenate([config.x0, config.v0])
        expm_wall = float(np.median([_timed(lambda: _expm_propagator(A, z0, result.t))
                                     for _ in range(repeats)]))
    return {"method": "fem-dual" if config.rtol is None else "fem-dual-rtol",
            "degree": config.degree, "cells": config.cells,
            "slabs": config.slabs if config.rtol is None else len(result.slab_lengths),
            "slabs_solved": len(result.slab_lengths),
            "rtol": config.rtol, "max_error": float(err.max()), "final_error": float(err[-1]),
            "wall_s": float(np.median(walls)), "compile_s": compile_s,
            "samples": len(result.t), "estimate": result.error_estimate, "_t": result.t,
            "expm_wall_s": expm_wall}


def _timed(action) -> float:
    tic = time.perf_counter()
    action()
    return time.perf_counter() - tic


def _fem_rows(base: RunConfig, degrees: Sequence[int], cells: Sequence[int],
              slabs: Sequence[int], repeats: int, comm: MPI.Comm,
              skipped: Optional[List[str]] = None,
              rtols: Sequence[float] = ()) -> List[Dict]:
    """fem-dual's rows: fixed slabs over the degrees and cells asked, and one `--rtol` row per
    tolerance with the defaults of `fem-dual run --rtol` (its cells and degree)."""
    # the timed runs compare with no reference: the row's error is measured after them,
    # against the same reference (_fem_row), so the run does not pay for it
    common = dict(T=base.T, x0=base.x0, v0=base.v0, staging="off", base=base.base,
                  coordinates=base.coordinates, reference="none")
    configs = [RunConfig.create(base.scene, slabs=k, cells=n, degree=degree, **common)
               for degree in degrees for n in sorted(set(cells)) for k in slabs]
    configs += [RunConfig.create(base.scene, rtol=tol, **common) for tol in rtols]
    rows, sim = [], None  # compiled once per degree, cells and base state
    try:
        for config in configs:
            if sim is None or not sim.matches(config):
                if sim is not None:
                    sim.close()
                sim = Simulation.for_config(config, comm)
                compile_s = sim.setup_s
            what = (f"p={config.degree} cells={config.cells} " + (
                f"slabs={config.slabs}" if config.rtol is None else f"rtol={config.rtol:g}"))
            row = _fem_row(sim, config, repeats, compile_s, skipped, what)
            if row is not None:
                rows.append(row)
    finally:
        if sim is not None:
            sim.close()  # petsc4py keeps what is dropped (Simulation.close)
    return rows


def _compiled_dop853(rhs, z0: np.ndarray, t: np.ndarray, tol: float) -> np.ndarray:
    """scipy's Fortran DOP853 (`ode('dop853')`) at the sample times: states (samples, 2n)."""
    from scipy.integrate import ode

    solver = ode(rhs).set_integrator("dop853", rtol=tol, atol=tol, nsteps=10**7)
    solver.set_initial_value(z0, t[0])
    out = np.empty((len(t), len(z0)))
    out[0] = z0
    for i in range(1, len(t)):
        out[i] = solver.integrate(t[i])
        if not solver.successful():
            raise RuntimeError("dop853 failed")
    return out


def _expm_propagator(A: np.ndarray, z0: np.ndarray, t: np.ndarray) -> np.ndarray:
    """z at the times t by exp(A h) once per distinct step h (to 1e-9), then one product per
    output time: the matrix-exponential propagator."""
    from scipy.linalg import expm

    out = np.empty((len(t), len(z0)))
    out[0] = z0
    steps: Dict[float, np.ndarray] = {}
    for i, h in enumerate(np.diff(t)):
        key = next((k for k in steps if abs(k - h) <= 1e-9 * abs(h)), None)
        if key is None:
            key = float(h)
            steps[key] = expm(h * A)
        out[i + 1] = steps[key] @ out[i]
    return out


def _ode_rows(scene: Scene, T: float, x0: np.ndarray, v0: np.ndarray, t: np.ndarray,
              repeats: int, rtols: Sequence[float] = ()) -> List[Dict]:
    n = scene.n
    Minv = np.linalg.inv(scene.mass_matrix())
    if scene.linear:
        A = scene.first_order_matrix()
        rhs = lambda _t, z: A @ z  # noqa: E731
        jac = A
    else:
        rhs = lambda _t, z: np.concatenate([z[n:], Minv @ scene.force_numpy(z[:n])])  # noqa
        jac = None
    x_ref, v_ref = scene.reference(x0, v0)(t)
    z0 = np.concatenate([x0, v0])
    rows = []
    if scene.linear:  # the exact propagator: what a user of a linear model would pick
        walls = []
        for _ in range(repeats):
            tic = time.perf_counter()
            y = _expm_propagator(A, z0, t)
            walls.append(time.perf_counter() - tic)
        err = _state_error(y[:, :n], y[:, n:], x_ref, v_ref)
        rows.append({"method": "expm", "degree": None, "cells": None, "slabs": None,
                     "rtol": None, "max_error": float(err.max()), "final_error": float(err[-1]),
                     "wall_s": float(np.median(walls)), "compile_s": 0.0, "samples": len(t),
                     "estimate": None, "slabs_solved": None, "expm_wall_s": None})
    for method, tolerances in TOLERANCES.items():
        for tol in sorted(set(tolerances) | set(rtols)):
            walls, y = [], None
            for _ in range(repeats):
                tic = time.perf_counter()
                if method == "DOP853-f":
                    try:
                        y = _compiled_dop853(rhs, z0, t, tol)
                    except RuntimeError:
                        y = None
                else:
                    kwargs = {}
                    if jac is not None and method in ("Radau", "LSODA"):  # LSODA: callable
                        kwargs["jac"] = (lambda _t, _z: jac) if method == "LSODA" else jac
                    sol = solve_ivp(rhs, (0.0, T), z0, method=method, t_eval=t, rtol=tol,
                                    atol=tol, **kwargs)
                    y = sol.y.T if sol.status == 0 else None
                walls.append(time.perf_counter() - tic)
            if y is None:
                continue
            err = _state_error(y[:, :n], y[:, n:], x_ref, v_ref)
            rows.append({"method": method, "degree": None, "cells": None, "slabs": None,
                         "rtol": tol, "max_error": float(err.max()), "final_error": float(err[-1]),
                         "wall_s": float(np.median(walls)), "compile_s": 0.0, "samples": len(t),
                         "estimate": None, "slabs_solved": None, "expm_wall_s": None})
    return rows


def bench(base: RunConfig, degrees: Sequence[int] = (2, 3, 4),
          cells: Sequence[int] = (2, 4, 8, 16, 32), repeats: int = 3, samples: int = 1001,
          comm: MPI.Comm = MPI.COMM_WORLD, slabs: Optional[Sequence[int]] = None,
          skipped: Optional[List[str]] = None, rtols: Sequence[float] = ()) -> List[Dict]:
    """All rows of the study (the same list on every rank); `slabs` defaults to base.slabs.
    Configurations the tool refuses are left out and listed in `skipped`. `rtols` adds
    fem-dual --rtol rows (the defaults of `fem-dual run --rtol`: cells and degree from the
    tolerance) and the peers at the same tolerances."""
    if not isinstance(base, RunConfig):
        raise InputError(f"base must be a RunConfig (RunConfig.create(...)), not "
                         f"{type(base).__name__}")
    rows = _fem_rows(base, degrees, cells, slabs or [base.slabs], repeats, comm, skipped, rtols)
    # the peers answer at fem-dual's output times: those of its run with the fewest of them,
    # so no peer pays for more output (nor is judged at more times) than any fem-dual row
    times = [row.pop("_t") for row in rows]
    t = min(times, key=len) if times else np.linspace(0.0, base.T, samples)
    if comm.rank == 0:
        rows += _ode_rows(base.scene, base.T, base.x0, base.v0, t, repeats, rtols)
    return comm.bcast(rows if comm.rank == 0 else None)


def write_csv(rows: List[Dict], path: Path) -> None:
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=COLUMNS)
        writer.writeheader()
        for row in rows:
            writer.writerow({k: ("" if row[k] is None else row[k]) for k in COLUMNS})


def read_csv(path: Path) -> List[Dict]:
    """Rows of a bench.csv, typed as `bench` returns them."""
    rows = []
    with open(path) as f:
        for raw in csv.DictReader(f):
            row: Dict = {}
            for key, text in raw.items():
                if text == "":
                    row[key] = None
                elif key == "method":
                    row[key] = text
                elif key in ("degree", "cells", "slabs", "samples", "slabs_solved"):
                    row[key] = int(text)
                else:
                    row[key] = float(text)
            rows.append(row)
    return rows


def plot(rows: List[Dict], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(10, 5.5))
    ax.set_prop_cycle(color=plt.get_cmap("tab20").colors)  # 20 colours: no two curves alike
    curves: Dict[str, List[Dict]] = {}
    multi = len({r["slabs"] for r in rows if r["method"] == "fem-dual"}) > 1
    for row in rows:
        label = row["method"]
        if label == "fem-dual":
            label = f"fem-dual p={row['degree']}" + (f", {row['slabs']} slabs" if multi else "")
        elif label == "fem-dual-rtol":
            label = f"fem-dual --rtol, p={row['degree']}"
        curves.setdefault(label, []).append(row)
    for label, pts in curves.items():
        # in order of resolution: cells up, or tolerance down
        pts = sorted(pts, key=lambda r: -r["rtol"] if r["rtol"] is not None else r["cells"])
        ax.loglog([r["wall_s"] for r in pts], [max(r["max_error"], 1e-17) for r in pts],
                  "o-" if label.startswith("fem") else "s--", label=label)
    if max(r["max_error"] for r in rows) > 10:  # diverged configurations: keep the scale readable
        ax.set_ylim(top=10)
    ax.set_xlabel("wall time [s] (median, compilation excluded)")
    ax.set_ylabel("max error over the sample times")
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize="small")  # covers no curve
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def table(rows: List[Dict]) -> str:
    head = (f"{'method':13s} {'degree':>6s} {'cells':>6s} {'slabs':>6s} {'rtol':>8s} "
            f"{'max_error':>10s} {'final_error':>11s} {'wall_s':>9s}")
    lines = [head]
    for r in rows:
        def f(v, fmt):
            width = int("".join(ch for ch in fmt if ch.isdigit())[:1] or 0)
            return "-".rjust(width) if v is None else format(v, fmt)
        lines.append(f"{r['method']:13s} {f(r['degree'], '6d')} {f(r['cells'], '6d')} "
                     f"{f(r['slabs'], '6d')} {f(r['rtol'], '8.0e')} {r['max_error']:10.2e} "
                     f"{r['final_error']:11.2e} {r['wall_s']:9.4f}")
    return "\n".join(lines)


def ratio_same_times(rows: List[Dict], target: float) -> Optional[Dict]:
    """The fastest fem-dual row (fixed slabs or --rtol) reaching max_error <= target, with its
    wall time over the matrix-exponential propagator's at the same output times (linear scenes;
    None if no row reaches it)."""
    reached = [r for r in rows if r["method"] in ("fem-dual", "fem-dual-rtol")
               and r["max_error"] <= target and r.get("expm_wall_s")]
    if not reached:
        return None
    best = min(reached, key=lambda r: r["wall_s"])
    return {**best, "ratio": best["wall_s"] / best["expm_wall_s"]}


def ratio_at(rows: List[Dict], target: float, peer: str = "DOP853") -> Optional[float]:
    """fem-dual's fastest wall time (fixed slabs or --rtol) reaching max_error <= target over the
    peer's (None if either never reaches it)."""
    def fastest(*methods):
        times = [r["wall_s"] for r in rows if r["method"] in methods and r["max_error"] <= target]
        return min(times) if times else math.nan
    ours, theirs = fastest("fem-dual", "fem-dual-rtol"), fastest(peer)
    return None if math.isnan(ours) or math.isnan(theirs) else ours / theirs
