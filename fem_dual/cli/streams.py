"""Where the command line prints: rank 0 only, one line per message, and with `--json` one JSON
object alone on stdout (what C libraries print there goes to stderr)."""
from __future__ import annotations

import os
import sys
from contextlib import contextmanager
from typing import TYPE_CHECKING, Iterator, Optional

if TYPE_CHECKING:  # annotations only: --help and bad options answer without MPI
    from mpi4py import MPI

__all__ = ["world", "rank", "print0", "escaped", "json_only_on_stdout", "json_out",
           "stdout_to_stderr"]


def world(comm: "Optional[MPI.Comm]") -> "MPI.Comm":
    """`comm`, or MPI's world communicator (loaded only now)."""
    if comm is not None:
        return comm
    from mpi4py import MPI

    return MPI.COMM_WORLD


def rank(comm) -> int:
    """This process's rank: the communicator's, or (before MPI is loaded) the launcher's."""
    if comm is not None:
        return comm.rank
    return int(os.environ.get("OMPI_COMM_WORLD_RANK", os.environ.get("PMI_RANK", "0")))


def print0(comm, *args, file=None, **kwargs) -> None:
    """Print on rank 0 only."""
    if rank(comm) == 0:
        print(*args, file=file if file is not None else sys.stdout, **kwargs)


def escaped(text: str) -> str:
    """The message with control characters (a newline in a bad value) escaped: one line."""
    return "".join(ch if ch.isprintable() else repr(ch)[1:-1] for ch in str(text))


_JSON_STREAM = None  # where the JSON goes when stdout is kept for it alone


def json_only_on_stdout() -> None:
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


def json_out():
    """The stream the JSON object goes to."""
    return _JSON_STREAM if _JSON_STREAM is not None else sys.stdout


@contextmanager
def stdout_to_stderr(active: bool) -> Iterator[None]:
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
