"""The command line's grammar: `fem-dual run | orbit | bench | flutter | stress | scenes`.

Options and their help texts are the contract other tools read: keep them stable, add freely.
"""
from __future__ import annotations

import argparse
from typing import List, Sequence

from fem_dual.errors import InputError

__all__ = ["build_parser", "key_value", "join_negative_values"]

# Options whose value may start with "-" (negative numbers): "--x0 -1,2" is joined to "--x0=-1,2".
_VALUE_OPTIONS = ("--T", "--x0", "--v0", "--u0", "--param", "--cells", "--degree", "--slabs",
                  "--max-halvings", "--rtol", "--atol", "--F", "--t-eval", "--period",
                  "--mode", "--continue")


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, exit 2 (by the caller), no usage dump
        raise InputError(message)


def key_value(text: str, what: str) -> tuple:
    """(NAME, VALUE) of "NAME=VALUE"; InputError naming `what` otherwise."""
    key, sep, value = text.partition("=")
    if not sep or not key.strip():
        raise InputError(f"{what} {text!r} is not of the form NAME=VALUE")
    return key.strip(), value.strip()


def join_negative_values(argv: Sequence[str]) -> List[str]:
    """argv with a negative value joined to its option ("--x0", "-1,2" -> "--x0=-1,2")."""
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


def build_parser() -> argparse.ArgumentParser:
    """The parser of every command."""
    parser = _Parser(prog="fem-dual", description="Particle dynamics under curl forces through a "
                     "dual variational principle, solved in space-time with FEniCSx.")
    from fem_dual import __version__

    parser.add_argument("--version", action="version", version=f"fem-dual {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True
    for add in (_run, _orbit, _bench, _flutter, _stress):
        add(sub)
    sub.add_parser("scenes", help="list the scenes, their parameters and defaults")
    return parser


def _add_problem_arguments(p: argparse.ArgumentParser, slabs_help: str) -> None:
    """The problem definition shared by `run` and `bench`: scene, horizon, parameters, state."""
    p.add_argument("scene", metavar="SCENE", help="a scene name (`fem-dual scenes` lists them)")
    p.add_argument("--T", help="final time (default: the scene's)")
    p.add_argument("--slabs", default=None, help=slabs_help)
    p.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                   help="scene parameter (repeatable); matrices as a11,a12,... or a scalar")
    p.add_argument("--x0", help="initial position a,b,...")
    p.add_argument("--v0", help="initial velocity a,b,...; continuum scenes (beck): "
                   "the velocity field, one expression per field component")
    p.add_argument("--u0", help="continuum scenes: the start field, one expression per field "
                   "component in the spatial coordinates (x; x, y), e.g. \"0.01*x**2, 0.02*x\"")


def _run(sub) -> None:
    """`run`: solve one scene."""
    r = sub.add_parser("run", help="solve one scene and compare it with its reference")
    _add_problem_arguments(r, "number of equal time slabs (default 1; a continuum given "
                           "neither --slabs nor --rtol takes --rtol 1e-3)")
    r.add_argument("--cells", help="time cells per slab (default 100; with --rtol 4)")
    r.add_argument("--degree", help="polynomial degree of the dual fields (default 2; with --rtol "
                   "from the tolerance: 3 at 1e-4, 4 at 1e-6, 5 at 1e-8, 6 at 1e-10)")
    r.add_argument("--max-slabs", default=None, help="with --rtol: a run predicted to need "
                   "more slabs than this (from the lengths of the last slabs) stops with the "
                   "figure, exit 3 (default 5000; a linear scene whose slabs run in chunks: "
                   "beyond 5000 while they fit in 60 s and 1 GB at its pace)")
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
                   "(default) = zero for stiff linear scenes, start for other linear ones, "
                   "predictor for nonlinear ones stiff at the start, otherwise rk4 with --rtol "
                   "and start on fixed slabs (the JSON's solver.base and solver.base_reason say "
                   "which and why)")
    r.add_argument("--coordinates", default="auto", help="linear scenes: modal (solve in the "
                   "modes of (K, M): resolved modes keep order 2p under a follower load, "
                   "unresolved ones are damped), physical, auto (default) = modal on the zero "
                   "base when the modes are well conditioned")
    r.add_argument("--F", help='scene force: the force, one expression per component, e.g. '
                   '"-k*x*y**2, -k*x**3" (x, y, z or x1..xn; + - * / **; sin cos tan exp log '
                   "sqrt sinh cosh tanh atan abs; pi; parameters by --param)")
    r.add_argument("--scene-file", help="a Python file declaring your own scene (a ForceScene "
                   "subclass with forms, see docs/scenes.md); SCENE names it")
    r.add_argument("--reference", default="auto", help="auto (default): compare with the "
                   "scene's reference (matrix exponential or DOP853 at 1e-13); none: skip it "
                   "(the error estimate remains)")
    r.add_argument("--t-eval", help="also the state at these times: t1,t2,... or "
                   "START:STOP:COUNT (JSON t_eval; Hermite interpolation between the vertices, "
                   "with the equation of motion)")
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


def _orbit(sub) -> None:
    """`orbit`: a periodic orbit and its continuation."""
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


def _bench(sub) -> None:
    """`bench`: error against run time beside scipy's integrators."""
    b = sub.add_parser("bench", help="error against run time: fem-dual beside RK45, DOP853, Radau")
    _add_problem_arguments(b, "slabs of the fem-dual runs, a list to sweep (default 1)")
    b.set_defaults(slabs="1")
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


def _flutter(sub) -> None:
    """`flutter`: the critical follower load."""
    f = sub.add_parser("flutter", help="critical follower load: eigenvalues and dual simulations")
    _add_problem_arguments(f, "slabs of each dual simulation (default 40)")
    f.set_defaults(slabs="40", T="40", x0=None, v0=None)
    f.add_argument("--cells", default="16", help="cells per slab (default 16)")
    f.add_argument("--degree", default="5", help="degree of the dual fields (default 5)")
    f.add_argument("--out", help="continuum scenes (beck): write the two slowest mode shapes "
                   "(<scene>_modes.xdmf) and the flutter motion (the dual simulation just above "
                   "the load found, with its usual files) into this directory")
    f.add_argument("--json", action="store_true", help="print {eigen, dual, eigen_s, dual_s, "
                   "dual_tol}; continuum scenes add omega2, dual_bracket, runs, elements, files")


def _stress(sub) -> None:
    """`stress`: stiff and extreme cases against their references."""
    st = sub.add_parser("stress", help="stiff and extreme cases against their references")
    st.add_argument("--case", action="append", default=[], metavar="NAME",
                    help="run only this case (repeatable; --list shows the names)")
    st.add_argument("--slow", action="store_true", help="also the slow cases (long horizons)")
    st.add_argument("--list", action="store_true", help="list the cases and what they expect")
    st.add_argument("--json", action="store_true", help='print {"rows": [...], "passed": ...}')
