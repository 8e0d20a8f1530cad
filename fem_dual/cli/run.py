"""`fem-dual run`: one scene, its summary or JSON, its CSV and pictures."""
from __future__ import annotations

import os
import sys
from typing import TYPE_CHECKING, Any, Dict, Optional

from fem_dual import faults
from fem_dual.cli.parser import key_value
from fem_dual.cli.streams import escaped, json_out, print0, stdout_to_stderr, world
from fem_dual.errors import InputError, SolveError

if TYPE_CHECKING:
    from mpi4py import MPI

    from fem_dual.integrate.result import RunResult

__all__ = ["run", "summary"]


def _check_files(comm: MPI.Comm, args) -> dict:
    """--csv FILE and --plot DIR checked before anything runs (bad paths are bad input)."""
    from pathlib import Path

    from fem_dual.output import check_output_dir_on_root

    files = {}
    if args.csv is not None:
        csv = Path(args.csv)
        if (not str(args.csv).strip() or not csv.parent.is_dir() or csv.is_dir()
                or not os.access(csv.parent, os.W_OK)):
            raise InputError(f"--csv {args.csv!r}: not a writable file in an existing directory")
        if args.plot is not None and csv.resolve() == Path(args.plot).resolve():
            raise InputError(f"--csv and --plot name the same path {args.csv!r}")
        files["csv"] = csv
    if args.plot is not None:
        files["plot"] = check_output_dir_on_root(comm, args.plot, "--plot", create=False)
    return files


def _write_files(comm: MPI.Comm, result: RunResult, files: dict) -> Optional[str]:
    """The CSV and the pictures of a run (rank 0), also of the completed part of a failed run;
    why they could not be written (the same on every rank), or None."""
    problem = None
    if comm.rank == 0 and len(result.t) > 0:
        try:
            if "csv" in files:
                result.write_csv(files["csv"])
                result.output_files.append(str(files["csv"]))
            if "plot" in files:
                from fem_dual.plots import write_plots

                files["plot"].mkdir(parents=True, exist_ok=True)
                result.output_files += [str(p) for p in write_plots(result, files["plot"])]
        except OSError as exc:
            problem = f"could not write {exc.filename or 'the output'}: {exc.strerror or exc}"
    problem = comm.bcast(problem, root=0)
    if problem:  # the JSON says so too
        result.status = "failed"
        result.message = f"{result.message}; {problem}" if result.message else problem
    return problem


def _kept(result: RunResult) -> str:
    """What a stopped or failed run kept: its slabs, their span and where they are."""
    if len(result.t) == 0:
        return "; no slab was completed"
    slabs = len(result.slab_lengths)
    text = f"; kept {slabs} slabs (t = {result.t[0]:g} .. {result.t[-1]:g})"
    if result.output_slabs is None:
        return text
    where = os.path.dirname(result.output_files[0]) if result.output_files else "--out"
    if result.output_slabs == slabs:
        return f"{text} in {where}"
    return f"{text}; {where} holds the first {result.output_slabs}"


def _reference_line(e: Dict[str, Any]) -> str:
    if e["x_max"] is None:
        return "          reference: none (--reference none)"
    line = f"          reference x_max={e['x_max']:.3e}  v_max={e['v_max']:.3e}  "
    if e.get("reference_lost_at") is None:
        return line + f"final={e['final']:.3e}"
    return line + f"until t={e['reference_lost_at']:g}, where the reference overflowed"


def summary(result: RunResult) -> str:
    e, h, tm = result.error, result.hamiltonian, result.timings
    fin = result.final

    def fmt(values) -> str:
        return "[" + ", ".join(f"{v:.10g}" for v in values) + "]"

    lines = [f"fem-dual run {result.scene}: T={result.T:g} cells={result.cells} "
             f"degree={result.degree} slabs={result.slabs} ({result.dofs_per_slab} dofs per slab)"]
    stages = result.staging.get("stages_per_slab", 1)
    if stages > 1:
        lines.append(f"  staged  each slab solved as {stages} sub-slabs of "
                     f"{result.staging['cells_per_solved_slab']} cells (conditioning rule; "
                     "--staging off to disable)")
    tol = result.tolerance
    if tol.get("adaptive"):
        which = "" if tol.get("given", True) else " (a continuum's default)"
        lines.append(f"  slabs   {len(result.slab_lengths)} chosen for rtol={tol['rtol']:g} "
                     f"atol={tol['atol']:g}{which} ({result.solver['rejected_slabs']} rejected)")
    elif result.solver.get("rejected_slabs"):
        lines.append(f"  slabs   {len(result.slab_lengths)} solved: "
                     f"{result.solver['rejected_slabs']} attempts were retried shorter")
    if fin["t"] is not None:
        est = result.estimate
        lines += [f"  final   t={fin['t']:g}  x={fmt(fin['x'])}  v={fmt(fin['v'])}",
                  f"  error   estimated x_max={est['x_max']:.3e}  v_max={est['v_max']:.3e}  "
                  f"(no reference needed)",
                  _reference_line(e),
                  f"  H_d     min={h['min']:.6g}  max={h['max']:.6g}  " + (
                      f"drift per slab={h['drift']:.3e}"
                      if result.solver.get("base") in ("start", "zero")
                      else "(not conserved: the base state moves within a slab)")]
    lines.append(f"  time    total {tm['total_s']:.3f} s (set-up {tm.get('setup_s', 0.0):.3f} s, "
                 f"compile {tm['compile_s']:.3f} s, solve {tm['solve_s']:.3f} s, "
                 f"{result.solver['slab_solves']} slab solves)")
    if result.output_files:
        lines.append("  output  " + ", ".join(result.output_files))
    return "\n".join(lines)


def failure_line(exc: SolveError) -> str:
    """The one stderr line of a failed or stopped solve, with what it kept."""
    interrupted = isinstance(exc, faults.Interrupted)
    what = "stopped" if interrupted else "failed" if "writing the output" in str(exc) \
        else "solve failed"
    kept = _kept(exc.partial) if exc.partial is not None else ""
    return f"fem-dual: {what}: {escaped(exc)}{kept}"


def _config(args, params: Dict[str, Any]):
    """The run's validated configuration (bad input raises InputError before MPI loads)."""
    from fem_dual.config import RunConfig

    petsc = dict(key_value(p, "--petsc-option") for p in args.petsc_option)
    if args.F is not None:
        if args.scene != "force":
            raise InputError(f"--F gives the force of scene force, not of {args.scene}")
        if "F" in params:
            raise InputError("the force is given twice: --F and --param F=...")
        params["F"] = args.F
    config = RunConfig.create(args.scene, params, T=args.T, cells=args.cells,
                              degree=args.degree, slabs=args.slabs, x0=args.x0, v0=args.v0,
                              out=args.out, petsc=petsc, max_halvings=args.max_halvings,
                              superpose=args.superpose, staging=args.staging,
                              recovery=args.recovery, assembly=args.assembly,
                              rtol=args.rtol, atol=args.atol, base=args.base,
                              coordinates=args.coordinates, reference=args.reference,
                              t_eval=args.t_eval, max_slabs=args.max_slabs, u0=args.u0)
    if args.resume and args.out is None:
        raise InputError("--resume needs --out: the directory of the run to go on with")
    return config


def run(args, params: Dict[str, Any], comm: "Optional[MPI.Comm]") -> int:
    """`fem-dual run`: exit 0 ok, 3 a failed solve or write (what was kept is kept, in the
    files and in the JSON); InputError for bad input."""
    config = _config(args, params)
    comm = world(comm)  # after the values are checked: bad input answers before MPI loads
    from fem_dual.integrate.api import run as run_config

    files: Dict[str, Any] = {}
    try:
        with stdout_to_stderr(args.json):  # (--csv, --plot checked after every other input)
            result = run_config(config, comm, progress=not args.json and sys.stderr.isatty(),
                                resume=args.resume,
                                before=lambda: files.update(_check_files(comm, args)))
    except SolveError as exc:
        print0(comm, failure_line(exc), file=sys.stderr)
        if exc.partial is not None:
            problem = _write_files(comm, exc.partial, files)
            if problem:
                print0(comm, f"fem-dual: error: {escaped(problem)}", file=sys.stderr)
            if args.json and comm.rank == 0:
                exc.partial.write_json(json_out())
        return exc.exit_status
    problem = _write_files(comm, result, files)
    if problem:  # the run is done; its output is not: a failure, not bad input
        print0(comm, f"fem-dual: error: {escaped(problem)}", file=sys.stderr)
        if args.json and comm.rank == 0:
            result.write_json(json_out())
        return SolveError.exit_status
    if args.json:
        if comm.rank == 0:
            result.write_json(json_out())
    else:
        print0(comm, summary(result))
    return 0
