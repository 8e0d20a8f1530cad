"""MPI helpers: rank-0 printing, one allreduce helper, gathers and broadcasts."""
from __future__ import annotations

import sys
from typing import Any

import numpy as np
from mpi4py import MPI

__all__ = ["allreduce", "gather_rows", "bcast", "print0", "is_root", "input_on_root",
           "root_first", "on_root"]


def is_root(comm: MPI.Comm) -> bool:
    return comm.rank == 0


def print0(comm: MPI.Comm, *args: Any, file=None, **kwargs: Any) -> None:
    """Print on rank 0 only."""
    if comm.rank == 0:
        print(*args, file=file if file is not None else sys.stdout, **kwargs)


def allreduce(comm: MPI.Comm, value: Any, op: str = "sum") -> Any:
    """The one helper through which global numbers are reduced (sum, max, min, land, lor)."""
    if comm.size == 1:  # (mpi4py would pickle a copy: microseconds, per Newton step)
        return value
    ops = {"sum": MPI.SUM, "max": MPI.MAX, "min": MPI.MIN, "land": MPI.LAND, "lor": MPI.LOR}
    return comm.allreduce(value, op=ops[op])


def gather_rows(comm: MPI.Comm, rows: np.ndarray) -> "np.ndarray | None":
    """Concatenate the 2D arrays of all ranks on rank 0 (None elsewhere)."""
    if comm.size == 1:  # (mpi4py would pickle a copy)
        return rows
    parts = comm.gather(np.ascontiguousarray(rows), root=0)
    if comm.rank != 0:
        return None
    parts = [p for p in parts if p.size]
    return np.concatenate(parts, axis=0) if parts else np.zeros((0, rows.shape[1]))


def bcast(comm: MPI.Comm, obj: Any) -> Any:
    """Broadcast from rank 0 (on one rank the object itself: mpi4py would pickle a copy, which
    for the result of a long run is its whole vertex arrays once more)."""
    if comm.size == 1:
        return obj
    return comm.bcast(obj, root=0)


def input_on_root(comm: MPI.Comm, build: Any) -> Any:
    """build() on rank 0 (None elsewhere); its InputError (or OSError, a path that cannot be
    used) an InputError on every rank, so no rank goes on into collective work alone."""
    from fem_dual.errors import InputError

    value, problem = None, None
    if comm.rank == 0:
        try:
            value = build()
        except InputError as exc:
            problem = str(exc)
        except OSError as exc:
            problem = f"--out: {exc.filename or ''} {exc.strerror or exc}".replace("  ", " ")
    problem = bcast(comm, problem)
    if problem:
        raise InputError(problem)
    return value


def root_first(comm: MPI.Comm, action: Any) -> None:
    """action() on rank 0, then on the other ranks (what rank 0 leaves behind, a JIT cache,
    they reuse). An exception on rank 0 is raised there and, as the same kind of error with the
    same message, on every other rank (none of them runs action then). Collective."""
    from fem_dual.errors import InputError, SolveError

    if comm.size == 1:
        action()
        return
    failure = None
    if comm.rank == 0:
        try:
            action()
        except Exception as exc:  # noqa: BLE001 -- shared, then raised on every rank
            failure = exc
    what = comm.bcast(None if failure is None else (type(failure).__name__, str(failure)),
                      root=0)
    if failure is not None:
        raise failure
    if what is not None:
        kinds = {"InputError": InputError, "SolveError": SolveError}
        raise kinds.get(what[0], RuntimeError)(what[1])
    if comm.rank != 0:
        action()


def on_root(comm: MPI.Comm, action: Any) -> "tuple[Any, str | None]":
    """action() on rank 0: (its value, why it failed in one line or None); (None, None)
    elsewhere. Not collective: the caller shares the outcome with its next broadcast, so an
    error on rank 0 (a full disk, a bug) ends the run on every rank instead of leaving them
    waiting in the next collective."""
    from fem_dual.errors import one_line

    if comm.rank != 0:
        return None, None
    try:
        return action(), None
    except Exception as exc:  # noqa: BLE001 -- shared, then raised on every rank
        return None, one_line(exc)
