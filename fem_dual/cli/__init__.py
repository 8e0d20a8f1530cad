"""Command line: `fem-dual run | orbit | bench | flutter | stress | scenes`.

Exit status: 0 success, 2 bad input (one line on stderr naming the value), 3 a failed solve or a
failed write (the slabs completed before it are kept, in the output files and in the JSON with
status "failed"), or FFCx's cache of compiled forms failing (one line), 130/143 stopped by SIGINT/SIGTERM after a slab (kept alike, status
"interrupted"), 1 an internal error (under MPI it ends every rank); `stress` exits 1 when a case
did not behave as it must.

What answers without DOLFINx, PETSc or MPI (--help, --version, bad options): only the modules
imported here load at start; a command imports what it needs.
"""
from __future__ import annotations

import json
import os
import re
import stat
import signal
import sys
from typing import TYPE_CHECKING, Dict, Optional, Sequence

from fem_dual import faults
from fem_dual.cli.parser import build_parser, join_negative_values, key_value
from fem_dual.cli.streams import escaped, json_only_on_stdout, json_out, print0, rank, world
from fem_dual.errors import InputError, SolveError, one_line

if TYPE_CHECKING:  # annotations only
    from mpi4py import MPI

__all__ = ["main", "build_parser"]


def main(argv: Optional[Sequence[str]] = None, comm: "Optional[MPI.Comm]" = None) -> int:
    """The command line; returns the exit status. SIGINT/SIGTERM stop a run after the slab at
    hand (fem_dual.faults) for as long as main runs, JSON printing included."""
    with faults.graceful_signals():
        return _main(argv, comm)


def _main(argv: Optional[Sequence[str]], comm: "Optional[MPI.Comm]") -> int:
    if argv is None and hasattr(signal, "SIGPIPE"):  # `fem-dual ... | head`: end quietly, as
        signal.signal(signal.SIGPIPE, signal.SIG_DFL)  # Unix tools do (not PETSc's handler)
    process = argv is None  # the command itself, not a call from Python
    if process:
        _singleton_mpi_defaults()
    argv = list(sys.argv[1:] if argv is None else argv)
    args = None
    try:
        args = build_parser().parse_args(join_negative_values(argv))
        if process and getattr(args, "json", False):
            json_only_on_stdout()
        return _command(args, comm)
    except InputError as exc:
        print0(comm, f"fem-dual: error: {escaped(exc)}", file=sys.stderr)
        return InputError.exit_status
    except SolveError as exc:  # (run and orbit report their own)
        from fem_dual.cli.run import failure_line

        print0(comm, failure_line(exc), file=sys.stderr)
        if args is not None and args.command == "flutter" and args.json:  # undecided search
            print0(comm, json.dumps({"status": "failed", "message": str(exc)}),
                   file=json_out(), flush=True)
        return exc.exit_status
    except Exception as exc:  # a bug: say so, and end every rank (others may wait for this one)
        import traceback

        fault = _cache_fault(exc) or _compiler_fault(exc)
        if fault is None:
            traceback.print_exc()
        comm = comm if comm is not None else _loaded_world()
        status = 1 if fault is None else SolveError.exit_status
        print(f"fem-dual: error: {fault}" if fault is not None else
              f"fem-dual: internal error on rank {rank(comm)}: {escaped(exc)}", file=sys.stderr)
        if comm is not None and comm.size > 1:
            comm.Abort(status)
        return status


def _cache_fault(exc: Exception) -> Optional[str]:
    """One line for a failure of FFCx's cache of compiled forms (a compiled module missing or
    damaged, a compilation that never finished, a cache that cannot be written); None for any
    other exception."""
    jit = sys.modules.get("dolfinx.jit")
    if jit is None:
        return None
    cache = str(jit.get_parameters()["cache_dir"])
    text = str(exc)
    ffcx = ((isinstance(exc, ModuleNotFoundError) and "Unable to find JIT module" in text)
            or (isinstance(exc, TimeoutError) and "JIT compilation timed out" in text))
    files = isinstance(exc, (OSError, ImportError)) and (
        cache in text or str(getattr(exc, "filename", None) or "").startswith(cache))
    if not (ffcx or files):
        return None
    return (f"FFCx's cache of compiled forms ({cache}) failed: {one_line(exc).rstrip('.')}; "
            "remove that directory (fem-dual compiles its forms again) or point "
            "XDG_CACHE_HOME at a writable one, and run again")


def _compiler_fault(exc: Exception) -> Optional[str]:
    """One line for a C compiler that fails on FFCx's generated code (with DOLFINx's own flags
    too, or with a user's: fem_dual.compat.with_portable_fallback); None for any other
    exception."""
    compat = sys.modules.get("fem_dual.compat")  # (not loaded: nothing was compiled)
    if compat is None or not compat.compiler_failed(exc):
        return None
    return (f"the C compiler ({os.environ.get('CC', 'cc')}) failed on the code FFCx generated: "
            f"{one_line(exc).rstrip('.')}; check the compiler (CC) and any "
            "cffi_extra_compile_args in dolfinx_jit_parameters.json")


# Set by a launcher (mpirun, srun, a PMI server) in every process it starts
_LAUNCHED = ("OMPI_COMM_WORLD_SIZE", "PMIX_RANK", "PMI_RANK", "PMI_SIZE", "SLURM_PROCID")
# Open MPI's parameter files: the system's (Debian's path), the user's, and any named by
# OMPI_MCA_mca_base_param_files
_MCA_FILES = ("/etc/openmpi/openmpi-mca-params.conf", "~/.openmpi/mca-params.conf")
MCA_FILE_BYTES = 1 << 20  # read of a parameter file, at most


def _singleton_mpi_defaults() -> None:
    """A process started without a launcher is one rank on its own: Open MPI opens and probes
    every transport of its pml framework at MPI_Init (here the cm one's, about 0.2 s of the
    start-up) though one rank has no peer to reach. Such a process takes the ob1 pml, unless
    OMPI_MCA_pml or a parameter file chooses a pml or excludes ob1; under a launcher the ranks
    keep Open MPI's own choice."""
    if any(name in os.environ for name in _LAUNCHED) or "OMPI_MCA_pml" in os.environ:
        return
    named = os.environ.get("OMPI_MCA_mca_base_param_files")
    # Open MPI reads the files it is given (a comma-separated list) instead of its defaults;
    # a ':' is split too: reading one file more can only leave Open MPI's choice in place
    files = _MCA_FILES if named is None else re.split("[,:]", named)
    for value in (_mca_value(name.strip(), "pml") for name in files if name.strip()):
        if value is not None and (not value.startswith("^")
                                  or "ob1" in value[1:].replace(" ", "").split(",")):
            return
    os.environ["OMPI_MCA_pml"] = "ob1"


def _mca_value(path: str, key: str) -> Optional[str]:
    """The value an Open MPI parameter file gives `key` ("key = value" lines, # comments);
    None where the file or the key is not there. Only a regular file is read, its first
    MCA_FILE_BYTES (a FIFO or a device is not waited on)."""
    path = os.path.expanduser(path)
    try:
        if not stat.S_ISREG(os.stat(path).st_mode):
            return None
        with open(path, encoding="utf-8", errors="replace") as text:
            lines = text.read(MCA_FILE_BYTES).splitlines()
    except OSError:
        return None
    value = None
    for line in lines:
        name, sep, rest = line.split("#", 1)[0].partition("=")
        if sep and name.strip() == key:
            value = rest.strip()
    return value


def _command(args, comm: "Optional[MPI.Comm]") -> int:
    """Run the parsed command; its exit status."""
    if args.command == "scenes":
        import fem_dual.continua.scenes  # noqa: F401 (registers beck)
        from fem_dual.scenes import SCENES

        print0(comm, "\n".join(cls.listing() for cls in SCENES.values()))
        return 0
    if args.command in ("run", "orbit"):  # orbit: a continuation stops between orbits
        faults.arm()
    _check_cache_home()
    if getattr(args, "scene_file", None):
        from fem_dual.scenes import load_scene_file

        load_scene_file(args.scene_file)
    params = _params(args)
    if args.command == "run":
        from fem_dual.cli.run import run

        return run(args, params, comm)
    if args.command == "orbit":
        from fem_dual.cli.orbit import orbit

        return orbit(args, params, comm)
    from fem_dual.cli import analysis

    comm = world(comm)
    if args.command == "stress":
        return analysis.stress(args, comm)
    return getattr(analysis, args.command)(args, params, comm)  # bench, flutter


def _params(args) -> Dict[str, str]:
    """--param NAME=VALUE, each name once."""
    params: Dict[str, str] = {}
    for item in getattr(args, "param", []):
        key, value = key_value(item, "--param")
        if key in params:
            raise InputError(f"--param {key} is given twice ({params[key]!r} and {value!r})")
        params[key] = value
    return params


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


def _loaded_world():
    """MPI's world communicator if MPI is loaded (a failure before it needs no Abort)."""
    mpi = sys.modules.get("mpi4py.MPI")
    return None if mpi is None else mpi.COMM_WORLD
