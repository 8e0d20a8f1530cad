"""Command line: `fem-dual run | orbit | bench | flutter | stress | scenes`.

Exit status: 0 success, 2 bad input (one line on stderr naming the value), 3 a failed solve or a
failed write (the slabs completed before it are kept, in the output files and in the JSON with
status "failed"), 130/143 stopped by SIGINT/SIGTERM after a slab (kept alike, status
"interrupted"), 1 an internal error (under MPI it ends every rank); `stress` exits 1 when a case
did not behave as it must.
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import sys
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any, Dict, Iterator, List, Optional, Sequence

from fem_dual import faults
from fem_dual.errors import InputError, SolveError

# What answers without DOLFINx, PETSc or MPI (--help, --version, bad options): only the modules
# above load at start; a command imports what it needs.
if TYPE_CHECKING:  # annotations only
    from mpi4py import MPI

    from fem_dual.integrate.simulation import RunResult

__all__ = ["main", "build_parser"]

# Options whose value may start with "-" (negative numbers): "--x0 -1,2" is joined to "--x0=-1,2".
_VALUE_OPTIONS = ("--T", "--x0", "--v0", "--param", "--cells", "--degree", "--slabs",
                  "--max-halvings", "--rtol", "--atol", "--F", "--t-eval", "--period",
                  "--mode", "--continue")


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, exit 2 (by the caller), no usage dump
        raise InputError(message)


def _key_value(text: str, what: str) -> tuple:
    key, sep, value = text.partition("=")
    if not sep or not key.strip():
        raise InputError(f"{what} {text!r} is not of the form NAME=VALUE")
    return key.strip(), value.strip()


def _add_problem_arguments(p: argparse.ArgumentParser, slabs_help: str) -> None:
    """The problem definition shared by `run` and `bench`: scene, horizon, parameters, state."""
    p.add_argument("scene", metavar="SCENE", help="a scene name (`fem-dual scenes` lists them)")
    p.add_argument("--T", help="final time (default: the scene's)")
    p.add_argument("--slabs", default="1", help=slabs_help)
    p.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                   help="scene parameter (repeatable); matrices as a11,a12,... or a scalar")
    p.add_argument("--x0", help="initial position a,b,...")
    p.add_argument("--v0", help="initial velocity a,b,...")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="fem-dual", description="Particle dynamics under curl forces through a "
                     "dual variational principle, solved in space-time with FEniCSx.")
    from fem_dual import __version__

    parser.add_argument("--version", action="version", version=f"fem-dual {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True
    r = sub.add_parser("run", help="solve one scene and compare it with its reference")
    _add_problem_arguments(r, "number of equal time slabs (default 1)")
    r.add_argument("--cells", default="100", help="time cells per slab (default 100)")
    r.add_argument("--degree", default="2", help="polynomial degree of the dual fields (default 2)")
    r.add_argument("--max-halvings", default="6", help="nonlinear scenes: a slab whose Newton "
                   "fails is retried halved, at most this many times (default 6)")
    r.add_argument("--superpose", default="auto", help="linear scenes: yes = every slab from "
                   "the 2n solved unit start states (same numbers, far fewer solves), no = solve "
                   "every slab, auto (default) = yes when slabs > 2n")
    r.add_argument("--staging", default="auto", help="auto (default) = a slab whose cells x "
                   "degree^2 exceeds 800 is solved as equal sub-slabs that keep its matrix well "
                   "conditioned (same total cells); off = solve the slabs as given")
    r.add_argument("--recovery", default="momentum", help="primal state at the vertices: "
                   "momentum (default, from the momenta of the dual Lagrangian, order 2p) or dtp "
                   "(the DtP map with one-sided derivatives, order p)")
    r.add_argument("--assembly", default="auto", help="pointwise (derivatives of L_d at the "
                   "quadrature points, banded LU and Newton, every rank solving each slab), "
                   "forms (UFL forms assembled by DOLFINx, PETSc KSP or SNES, distributed "
                   "under mpirun), kronecker (linear scenes: time x space Kronecker sums, "
                   "matrix-free CG); auto (default) = kronecker for linear scenes from 5 dofs, "
                   "forms with PETSc options or beyond 20000 dual unknowns per slab, else "
                   "pointwise")
    r.add_argument("--rtol", help="choose the slab lengths so that the estimated error stays "
                   "within atol + rtol * scale (scale: the largest |x|, |v| so far); excludes "
                   "--slabs")
    r.add_argument("--atol", help="absolute tolerance with --rtol (default 0)")
    r.add_argument("--base", default="auto", help="base state of H on each slab: zero "
                   "(residual-free for linear scenes: unresolved fast modes are damped), "
                   "predictor (linearly implicit Euler from the slab start: near the motion, "
                   "nearly residual-free), rk4 (nonlinear scenes that are not stiff: classical "
                   "Runge-Kutta from the slab start; Newton converges on longer slabs, --rtol "
                   "takes fewer), start (the slab's start state held constant), auto "
                   "(default) = zero for stiff linear scenes, predictor for nonlinear ones "
                   "stiff at the start, start otherwise")
    r.add_argument("--coordinates", default="auto", help="linear scenes: modal (solve in the "
                   "modes of (K, M): resolved modes keep order 2p under a follower load, "
                   "unresolved ones are damped), physical, auto (default) = modal on the zero "
                   "base when the modes are well conditioned")
    r.add_argument("--F", help='scene force: the force, one expression per component, e.g. '
                   '"-k*x*y**2, -k*x**3" (x, y, z or x1..xn; + - * / **; sin cos tan exp log '
                   "sqrt sinh cosh tanh atan abs; pi; parameters by --param)")
    r.add_argument("--scene-file", help="a Python file declaring your own scene (a ForceScene "
                   "subclass with forms, see README 'Your own force'); SCENE names it")
    r.add_argument("--reference", default="auto", help="auto (default): compare with the "
                   "scene's reference (matrix exponential or DOP853 at 1e-13); none: skip it "
                   "(the error estimate remains)")
    r.add_argument("--t-eval", help="also the state at these times: t1,t2,... or "
                   "START:STOP:COUNT (JSON t_eval; quintic Hermite between the vertices)")
    r.add_argument("--csv", help="write t, x1..xn, v1..vn at the output times to this file")
    r.add_argument("--plot", help="write PNG pictures of the motion, phase portrait, error and "
                   "H_d into this directory")
    r.add_argument("--out", help="write XDMF output into this directory (streamed: it covers "
                   "the completed slabs at every moment)")
    r.add_argument("--resume", action="store_true", help="go on from the last slab an earlier "
                   "run with the same options wrote into --out")
    r.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    r.add_argument("--petsc-option", action="append", default=[], metavar="KEY=VALUE",
                   help="PETSc option under the solver prefix dual_<scene>_, e.g. ksp_type=cg "
                   "(checked: bad or unused options exit 2)")
    o = sub.add_parser("orbit", help="a periodic orbit from the dual principle: period, "
                       "Floquet multipliers, continuation in a parameter")
    o.add_argument("scene", metavar="SCENE", help="a scene name (`fem-dual scenes` lists them)")
    o.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                   help="scene parameter (repeatable); matrices as a11,a12,... or a scalar")
    o.add_argument("--F", help="scene force: the force, one expression per component")
    o.add_argument("--x0", help="start of the guess: position a,b,...")
    o.add_argument("--v0", help="start of the guess: velocity a,b,... (default 0)")
    o.add_argument("--period", required=True, help="the guess's period T0: the guess is the "
                   "motion from x0, v0 over T0")
    o.add_argument("--mode", default="closest", help="closest (default: period and unfolding "
                   "unknown, the family member closest to the guess), period (T0 kept), "
                   "energy=E (energy E: linear scenes with symmetric K and no damping, "
                   "forces with a potential, whose V(0) = 0)")
    o.add_argument("--cells", default="64", help="time cells over one period (default 64)")
    o.add_argument("--degree", default="4", help="degree of the dual fields (default 4)")
    o.add_argument("--continue", dest="continuation", metavar="NAME=A:B:STEPS",
                   help="follow the orbit along a scene parameter from A to B in STEPS steps")
    o.add_argument("--no-estimate", action="store_true", help="skip the degree p+1 solve that "
                   "estimates the orbit's error")
    o.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    o.add_argument("--out", help="write orbit.json and orbit.csv into this directory")
    o.add_argument("--plot", help="write orbit.png (and continuation.png) into this directory")
    b = sub.add_parser("bench", help="error against run time: fem-dual beside RK45, DOP853, Radau")
    _add_problem_arguments(b, "slabs of the fem-dual runs, a list to sweep (default 1)")
    b.add_argument("--cells", default="2,4,8,16,32", help="cells per slab to sweep")
    b.add_argument("--degrees", default="2,3,4", help="degrees to sweep")
    b.add_argument("--repeats", default="3", help="timed repeats per configuration (median)")
    b.add_argument("--rtols", default="", help="tolerances of fem-dual --rtol rows (4 cells per "
                   "slab, each degree), the peers run at them too, e.g. 1e-6,1e-8")
    b.add_argument("--base", default="auto", help="base state of H (as for run)")
    b.add_argument("--coordinates", default="auto", help="linear scenes: modal, physical, auto "
                   "(as for run)")
    b.add_argument("--out", default=".", help="directory for bench.csv and bench.png")
    b.add_argument("--json", action="store_true", help='print {"rows": [...]} on stdout')
    f = sub.add_parser("flutter", help="critical follower load: eigenvalues and dual simulations")
    _add_problem_arguments(f, "slabs of each dual simulation (default 40)")
    f.set_defaults(slabs="40", T="40", x0=None, v0=None)
    f.add_argument("--cells", default="16", help="cells per slab (default 16)")
    f.add_argument("--degree", default="5", help="degree of the dual fields (default 5)")
    f.add_argument("--json", action="store_true", help="print {eigen, dual, eigen_s, dual_s, dual_tol}")
    st = sub.add_parser("stress", help="stiff and extreme cases against their references")
    st.add_argument("--case", action="append", default=[], metavar="NAME",
                    help="run only this case (repeatable; --list shows the names)")
    st.add_argument("--slow", action="store_true", help="also the slow cases (long horizons)")
    st.add_argument("--list", action="store_true", help="list the cases and what they expect")
    st.add_argument("--json", action="store_true", help='print {"rows": [...], "passed": ...}')
    sub.add_parser("scenes", help="list the scenes, their parameters and defaults")
    return parser


def _world(comm: "Optional[MPI.Comm]") -> "MPI.Comm":
    """`comm`, or MPI's world communicator (loaded only now)."""
    if comm is not None:
        return comm
    from mpi4py import MPI

    return MPI.COMM_WORLD


def _rank(comm) -> int:
    """This process's rank: the communicator's, or (before MPI is loaded) the launcher's."""
    if comm is not None:
        return comm.rank
    return int(os.environ.get("OMPI_COMM_WORLD_RANK", os.environ.get("PMI_RANK", "0")))


def _print0(comm, *args, file=None, **kwargs) -> None:
    """Print on rank 0 only."""
    if _rank(comm) == 0:
        print(*args, file=file if file is not None else sys.stdout, **kwargs)


def _one_line(text: str) -> str:
    """The message with control characters (a newline in a bad value) escaped."""
    return "".join(ch if ch.isprintable() else repr(ch)[1:-1] for ch in str(text))


def _join_negative_values(argv: Sequence[str]) -> List[str]:
    out: List[str] = []
    i = 0
    while i < len(argv):
        arg = argv[i]
        if arg in _VALUE_OPTIONS and i + 1 < len(argv) and argv[i + 1].startswith("-"):
            out.append(f"{arg}={argv[i + 1]}")
            i += 2
        else:
            out.append(arg)
            i += 1
    return out


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
        files["plot"] = check_output_dir_on_root(comm, args.plot, "--plot")
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


_JSON_STREAM = None  # where the JSON goes when stdout is kept for it alone


def _json_only_on_stdout() -> None:
    """For the rest of the process, everything but the JSON that is printed on stdout (PETSc's
    banner, -help, -log_view and -options_left at finalisation, monitors; petsc4py prints
    through sys.stdout, C code through descriptor 1) goes to stderr; the JSON alone keeps the
    real stdout."""
    global _JSON_STREAM
    sys.stdout.flush()
    saved = os.dup(1)
    os.dup2(2, 1)
    _JSON_STREAM = os.fdopen(saved, "w", encoding="utf-8")
    import atexit

    atexit.register(_JSON_STREAM.close)  # (left to the interpreter's shutdown, it can warn)


def _json_out():
    return _JSON_STREAM if _JSON_STREAM is not None else sys.stdout


@contextmanager
def _stdout_to_stderr(active: bool) -> Iterator[None]:
    """While active, what C libraries (PETSc monitors and views, -help) print on stdout goes
    to stderr, so that `--json` prints one JSON object on stdout and nothing else."""
    if not active:
        yield
        return
    import ctypes

    sys.stdout.flush()
    libc = ctypes.CDLL(None)
    saved = os.dup(1)
    os.dup2(2, 1)
    try:
        yield
    finally:
        libc.fflush(None)
        os.dup2(saved, 1)
        os.close(saved)


def _reference_line(e: Dict[str, Any]) -> str:
    if e["x_max"] is None:
        return "          reference: none (--reference none)"
    line = f"          reference x_max={e['x_max']:.3e}  v_max={e['v_max']:.3e}  "
    if e.get("reference_lost_at") is None:
        return line + f"final={e['final']:.3e}"
    return line + f"until t={e['reference_lost_at']:g}, where the reference overflowed"


def _summary(result: RunResult) -> str:
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
        lines.append(f"  slabs   {len(result.slab_lengths)} chosen for rtol={tol['rtol']:g} "
                     f"atol={tol['atol']:g} ({result.solver['rejected_slabs']} rejected)")
    elif result.solver.get("rejected_slabs"):
        lines.append(f"  slabs   {len(result.slab_lengths)} solved: "
                     f"{result.solver['rejected_slabs']} attempts were retried shorter")
    if fin["t"] is not None:
        est = result.estimate
        lines += [f"  final   t={fin['t']:g}  x={fmt(fin['x'])}  v={fmt(fin['v'])}",
                  f"  error   estimated x_max={est['x_max']:.3e}  v_max={est['v_max']:.3e}  "
                  f"(no reference needed)",
                  _reference_line(e),
                  f"  H_d     min={h['min']:.6g}  max={h['max']:.6g}  "
                  f"drift per slab={h['drift']:.3e}"]
    lines.append(f"  time    total {tm['total_s']:.3f} s (compile {tm['compile_s']:.3f} s, "
                 f"solve {tm['solve_s']:.3f} s, {result.solver['slab_solves']} slab solves)")
    if result.output_files:
        lines.append("  output  " + ", ".join(result.output_files))
    return "\n".join(lines)


def _list_scenes() -> str:
    from fem_dual.scenes import SCENES

    return "\n".join(cls.listing() for cls in SCENES.values())


def _int_list(name: str, text: str) -> List[int]:
    from fem_dual.config import _whole_number

    return [_whole_number(name, item) for item in text.split(",")]


def _bench(args, params, comm: MPI.Comm) -> int:
    from fem_dual.analysis import bench as bm
    from fem_dual.config import RunConfig
    from fem_dual.output import check_output_dir_on_root

    slabs = _int_list("slabs", args.slabs)
    base = RunConfig.create(args.scene, params, T=args.T, slabs=slabs[0], x0=args.x0,
                            v0=args.v0, base=args.base, coordinates=args.coordinates)
    degrees, cells = _int_list("degrees", args.degrees), _int_list("cells", args.cells)
    repeats = _int_list("repeats", args.repeats)
    if len(repeats) != 1 or repeats[0] > 100:
        raise InputError(f"repeats={args.repeats!r} must be one whole number from 1 to 100")
    repeats = repeats[0]
    for degree in degrees:  # every configuration is valid before anything runs
        for n in cells:
            for k in slabs:
                RunConfig.create(base.scene, T=base.T, cells=n, degree=degree, slabs=k)
    rtols = [RunConfig.create(base.scene, T=base.T, rtol=item).rtol
             for item in args.rtols.split(",") if args.rtols.strip()]
    out = check_output_dir_on_root(comm, args.out)
    skipped: List[str] = []
    rows = bm.bench(base, degrees, cells, repeats=repeats, comm=comm, slabs=slabs,
                    skipped=skipped, rtols=rtols)
    for line in skipped:
        _print0(comm, f"fem-dual bench: left out {line}", file=sys.stderr)
    if comm.rank == 0:
        bm.write_csv(rows, out / "bench.csv")
        bm.plot(rows, out / "bench.png", f"{args.scene}, T = {base.T:g}")
        if args.json:
            print(json.dumps({"rows": rows}, allow_nan=False), file=_json_out(), flush=True)
        else:
            print(bm.table(rows))
            peers = [m for m in ("DOP853", "DOP853-f", "Radau", "LSODA", "expm")
                     if any(r["method"] == m for r in rows)]
            for peer in peers:
                for target in (1e-4, 1e-6, 1e-8, 1e-10):  # (the speed issue's range: to 1e-10)
                    ratio = bm.ratio_at(rows, target, peer)
                    text = "not reached by both" if ratio is None else f"{ratio:.2f}"
                    print(f"wall-time ratio fem-dual / {peer} at max error <= {target:g}: "
                          f"{text}")
            for target in (1e-4, 1e-6, 1e-8, 1e-10):
                best = bm.ratio_same_times(rows, target)
                if best is not None:
                    what = (f"{best['slabs']} slabs" if best["method"] == "fem-dual"
                            else f"rtol {best['rtol']:g}")
                    print(f"wall-time ratio fem-dual / expm at the same output times, max error "
                          f"<= {target:g}: {best['ratio']:.2f} (p={best['degree']}, {what} x "
                          f"{best['cells']} cells, {best['samples']} times, "
                          f"{best['wall_s'] * 1e3:.3g} ms vs {best['expm_wall_s'] * 1e3:.3g} ms)")
            print(f"wrote {out / 'bench.csv'}, {out / 'bench.png'}")
    return 0


def _flutter(args, params, comm: MPI.Comm) -> int:
    from fem_dual.config import RunConfig
    from fem_dual.analysis.flutter import flutter
    from fem_dual.scenes import SCENES

    scene = SCENES.get(args.scene)
    x0 = args.x0 if args.x0 is not None else (None if scene is None or scene.n != 2
                                              else "0.1,-0.05")
    v0 = args.v0 if args.v0 is not None else (None if scene is None or scene.n != 2
                                              else "0.02,0.03")
    base = RunConfig.create(args.scene, params, T=args.T, cells=args.cells, degree=args.degree,
                            slabs=args.slabs, x0=x0, v0=v0)
    found = flutter(base, comm)
    if args.json:
        _print0(comm, json.dumps(found, allow_nan=False), file=_json_out(), flush=True)
    else:
        gap = abs(found["dual"] - found["eigen"]) / found["eigen"]
        _print0(comm, f"critical load of {args.scene}: eigenvalues {found['eigen']:.6f} "
                     f"({found['eigen_s']:.3f} s), dual simulations {found['dual']:.6f} "
                     f"({found['dual_s']:.2f} s); relative gap {gap:.2e}")
    return 0


def _orbit(args, params, comm) -> int:
    """`fem-dual orbit`: rank 0 solves (an orbit's time mesh is small), the others wait for its
    exit status. Exit 0 ok, 2 bad input, 3 no orbit (the JSON says what was reached)."""
    from fem_dual.config import RunConfig
    from fem_dual.analysis.orbit_input import Energy, parse_continuation, parse_mode

    if args.F is not None:
        if args.scene != "force":
            raise InputError(f"--F gives the force of scene force, not of {args.scene}")
        params["F"] = args.F
    mode, energy = parse_mode(args.mode)
    from fem_dual.scenes.base import parse_number

    from fem_dual.config import MIN_T

    period = parse_number("period", args.period)
    if not period > 0:
        raise InputError(f"period={args.period!r} must be positive")
    if period < MIN_T:
        raise InputError(f"period={args.period!r} is too small (at least {MIN_T:g})")
    from fem_dual.config import _whole_number

    if _whole_number("degree", args.degree) > 8:  # (before a run's limits, which name slabs)
        raise InputError(f"degree={args.degree} is too large for orbits (at most 8)")
    if _whole_number("cells", args.cells) > 4096:
        raise InputError(f"cells={args.cells} is too large for orbits (at most 4096)")
    config = RunConfig.create(args.scene, params, T=args.period, cells=args.cells,
                              degree=args.degree, x0=args.x0, v0=args.v0, check_petsc=False)
    from fem_dual.analysis.orbit_input import check_resolution

    check_resolution(config.scene, config.x0, config.v0, config.T, config.cells)
    continuation = (None if args.continuation is None
                    else parse_continuation(args.continuation, config.scene))
    if continuation is not None:  # every member's parameters, before any work
        from fem_dual.config import _scene

        for value in continuation[1]:
            member = _scene(config.scene.name, {**params, continuation[0]: value})
            member_has, why = Energy.find(member, config.x0) if mode == "energy" else (1, "")
            if member_has is None:
                raise InputError(f"mode energy: {config.scene.name} at {continuation[0]}="
                                 f"{value:.6g} has no energy: {why}")
    has, why = Energy.find(config.scene, config.x0) if mode == "energy" else (None, "")
    if mode == "energy" and has is None:
        raise InputError(f"mode energy needs a scene with an energy (linear with K symmetric "
                         f"and no damping, or a force with a potential); {config.scene.name} "
                         f"with these parameters has none: {why}")
    if has is not None and has.linear and not energy > 0:
        raise InputError(f"energy={energy:g} must be positive for {config.scene.name} (its "
                         "energy is 1/2 v.M v + 1/2 x.K x)")
    config.check_petsc()  # last: it imports PETSc
    comm = _world(comm)
    dirs = {}
    for option, value in (("out", args.out), ("plot", args.plot)):
        if value is not None:
            from fem_dual.output import check_output_dir_on_root

            dirs[option] = check_output_dir_on_root(comm, value, f"--{option}")
    status = 0
    if comm.rank == 0:
        try:
            status = _orbit_on_root(args, config, params, mode, energy, continuation, dirs)
        except InputError as exc:
            print(f"fem-dual: error: {_one_line(exc)}", file=sys.stderr)
            status = InputError.exit_status
        except Exception as exc:  # a bug: say so, and end the ranks that wait for rank 0
            if comm.size == 1:
                raise
            import traceback

            traceback.print_exc()
            print(f"fem-dual: internal error on rank 0: {_one_line(exc)}", file=sys.stderr)
            comm.Abort(1)
    return int(comm.bcast(status, root=0))


def _orbit_on_root(args, config, params, mode, energy, continuation, dirs):
    from fem_dual.compat import quiet_jit_logging
    from fem_dual.analysis.orbit import orbit_family, orbit_summary, write_orbit_files

    with _stdout_to_stderr(args.json), quiet_jit_logging():  # (expressions compile lazily)
        try:
            record = orbit_family(config.scene, params, config.x0, config.v0, config.T,
                                  config.degree, config.cells, mode, energy, continuation,
                                  with_estimate=not args.no_estimate,
                                  progress=lambda line: print(f"fem-dual: {line}",
                                                              file=sys.stderr, flush=True))
        except SolveError as exc:
            record = {"status": "interrupted" if isinstance(exc, faults.Interrupted) else
                      "failed", "message": str(exc), "scene": config.scene.name}
    problem = write_orbit_files(record, dirs) if record.get("period") is not None else None
    if problem:
        record["status"], record["message"] = "failed", problem
    if args.json:
        print(json.dumps(record, allow_nan=False), file=_json_out(), flush=True)
    else:
        print(orbit_summary(record))
    if record["status"] == "interrupted":
        print(f"fem-dual: stopped: {_one_line(record['message'])}", file=sys.stderr)
        return 128 + faults.requested()
    if record["status"] != "ok":
        what = "output failed" if problem else "no orbit"
        print(f"fem-dual: {what}: {_one_line(record['message'])}", file=sys.stderr)
        return SolveError.exit_status
    return 0


def _stress(args, comm: MPI.Comm) -> int:
    """Exit 0 when every case behaved as it must, 1 when one FAILed."""
    import dataclasses

    from fem_dual.analysis import stress as st

    if args.list:
        _print0(comm, "\n".join(f"{c.name}{' (slow)' if c.slow else ''}: {c.expected}"
                                for c in st.CASES))
        return 0
    rows = st.stress(args.case, slow=args.slow, comm=comm)
    passed = all(r.status != "FAIL" for r in rows)
    if args.json:
        _print0(comm, json.dumps({"rows": [dataclasses.asdict(r) for r in rows],
                                 "passed": passed}, allow_nan=False), file=_json_out(),
                flush=True)
    else:
        _print0(comm, st.table(rows))
        _print0(comm, f"{sum(r.status != 'FAIL' for r in rows)} of {len(rows)} cases behaved as "
                     "they must" + ("" if passed else "; FAIL marks the others"))
    return 0 if passed else 1


def _check_cache_home() -> None:
    """InputError where the cache folder for compiled code cannot be one: FFCx (its `fenics`
    folder) and fem_dual.native keep their libraries under $XDG_CACHE_HOME (default
    ~/.cache), and a file there, or above it, ended every run in a traceback from the JIT."""
    root = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    path = os.path.abspath(os.path.join(root, "fenics"))
    while not os.path.exists(path) and os.path.dirname(path) != path:
        path = os.path.dirname(path)  # the nearest part of it that exists
    if not os.path.isdir(path):
        raise InputError(f"{path} is not a directory, so the cache for compiled code "
                         f"({root}: XDG_CACHE_HOME, default ~/.cache) cannot be made there")


def main(argv: Optional[Sequence[str]] = None, comm: "Optional[MPI.Comm]" = None) -> int:
    """The command line; returns the exit status. SIGINT/SIGTERM stop a run after the slab at
    hand (fem_dual.faults) for as long as main runs, JSON printing included."""
    with faults.graceful_signals():
        return _main(argv, comm)


def _main(argv: Optional[Sequence[str]], comm: "Optional[MPI.Comm]") -> int:
    if argv is None and hasattr(signal, "SIGPIPE"):  # `fem-dual ... | head`: end quietly, as
        signal.signal(signal.SIGPIPE, signal.SIG_DFL)  # Unix tools do (not PETSc's handler)
    process = argv is None  # the command itself, not a call from Python
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        args = build_parser().parse_args(_join_negative_values(argv))
        if process and getattr(args, "json", False):
            _json_only_on_stdout()
        if args.command == "scenes":
            _print0(comm, _list_scenes())
            return 0
        if args.command in ("run", "orbit"):  # orbit: a continuation stops between orbits
            faults.arm()
        _check_cache_home()
        if getattr(args, "scene_file", None):
            from fem_dual.scenes import load_scene_file

            load_scene_file(args.scene_file)
        params = {}
        for item in getattr(args, "param", []):
            key, value = _key_value(item, "--param")
            if key in params:
                raise InputError(f"--param {key} is given twice ({params[key]!r} and {value!r})")
            params[key] = value
        if args.command == "orbit":
            return _orbit(args, params, comm)
        if args.command in ("bench", "flutter", "stress"):
            comm = _world(comm)
        if args.command == "bench":
            return _bench(args, params, comm)
        if args.command == "flutter":
            return _flutter(args, params, comm)
        if args.command == "stress":
            return _stress(args, comm)
        from fem_dual.config import RunConfig

        petsc = dict(_key_value(p, "--petsc-option") for p in args.petsc_option)
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
                                  t_eval=args.t_eval)
        if args.resume and args.out is None:
            raise InputError("--resume needs --out: the directory of the run to go on with")
        comm = _world(comm)  # after the values are checked: bad input answers before MPI loads
        from fem_dual.integrate.simulation import run

        files = _check_files(comm, args)  # after validation: bad input writes nothing
        with _stdout_to_stderr(args.json):
            result = run(config, comm, progress=not args.json and sys.stderr.isatty(),
                         resume=args.resume)
    except InputError as exc:
        _print0(comm, f"fem-dual: error: {_one_line(exc)}", file=sys.stderr)
        return InputError.exit_status
    except SolveError as exc:
        interrupted = isinstance(exc, faults.Interrupted)
        what = "stopped" if interrupted else "failed" if "writing the output" in str(exc) \
            else "solve failed"
        kept = _kept(exc.partial) if exc.partial is not None else ""
        _print0(comm, f"fem-dual: {what}: {_one_line(exc)}{kept}", file=sys.stderr)
        if exc.partial is not None and args.command == "run":
            problem = _write_files(comm, exc.partial, files)
            if problem:
                _print0(comm, f"fem-dual: error: {_one_line(problem)}", file=sys.stderr)
            if args.json and comm.rank == 0:
                exc.partial.write_json(_json_out())
        elif args.command == "flutter" and args.json:  # what the search could not decide
            _print0(comm, json.dumps({"status": "failed", "message": str(exc)}),
                    file=_json_out(), flush=True)
        return exc.exit_status
    except Exception as exc:  # a bug: say so, and end every rank (others may wait for this one)
        import traceback

        traceback.print_exc()
        print(f"fem-dual: internal error on rank {_rank(comm)}: {_one_line(exc)}",
              file=sys.stderr)
        if comm is not None and comm.size > 1:
            comm.Abort(1)
        return 1
    problem = _write_files(comm, result, files)
    if problem:  # the run is done; its output is not: a failure, not bad input
        _print0(comm, f"fem-dual: error: {_one_line(problem)}", file=sys.stderr)
        if args.json and comm.rank == 0:
            result.write_json(_json_out())
        return SolveError.exit_status
    if args.json:
        if comm.rank == 0:
            result.write_json(_json_out())
    else:
        _print0(comm, _summary(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
