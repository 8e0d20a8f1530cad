"""Ending a run early without losing it: SIGINT/SIGTERM (SIGUSR1 under mpirun, which kills its
ranks on the other two) stop the slab loop after the slab at hand (the output is flushed and
the run's JSON says what was kept), and errors on one rank end every
rank (the slab loop shares them collectively; whatever escapes ends the job).
"""
from __future__ import annotations

import os
import signal
from contextlib import contextmanager
from typing import Iterator, Optional

from fem_dual.errors import SolveError

__all__ = ["Interrupted", "graceful_signals", "requested", "request", "clear", "arm",
           "signals_deferred"]

_requested: Optional[int] = None
_armed = False  # the handlers of graceful_signals stop runs only once armed (a `run` command)


def request(signum: int) -> None:
    """Ask the slab loop to stop after the slab at hand (what a SIGINT/SIGTERM does)."""
    global _requested
    _requested = signum


def requested() -> int:
    """The signal number that asked the run to stop, or 0."""
    return _requested or 0


def clear() -> None:
    global _requested
    _requested = None


def arm() -> None:
    """From now on (within graceful_signals) SIGINT/SIGTERM stop the run after a slab; before,
    they act as Python's defaults do (KeyboardInterrupt, termination)."""
    global _armed
    _armed = True


class Interrupted(SolveError):
    """The run was stopped by a signal; `partial` holds the slabs completed before. Exit status
    128 + the signal number (130 for SIGINT, 143 for SIGTERM), as shells report it."""

    def __init__(self, message: str, signum: int, slab: "int | None" = None):
        super().__init__(message, slab)
        self.signum = signum
        self.exit_status = 128 + signum


@contextmanager
def graceful_signals() -> Iterator[None]:
    """Once `arm()`ed, SIGINT and SIGTERM ask the slab loop to stop (fem_dual.faults.requested);
    a second one ends the process at once, as if unhandled. The previous handlers come back
    afterwards."""
    # mpirun (Open MPI) kills its ranks on SIGINT/SIGTERM but forwards SIGUSR1: under mpirun,
    # `kill -USR1 <mpirun>` is the graceful stop
    signals = [signal.SIGINT, signal.SIGTERM, signal.SIGUSR1]

    global _armed

    def handler(signum, frame) -> None:
        if not _armed and signum == signal.SIGINT:
            raise KeyboardInterrupt
        if requested() or not _armed:
            signal.signal(signum, signal.SIG_DFL)
            os.kill(os.getpid(), signum)
            return
        request(signum)

    previous = {s: signal.getsignal(s) for s in signals}
    clear()
    for s in signals:
        signal.signal(s, handler)
    try:
        yield
    finally:
        for s, old in previous.items():
            signal.signal(s, old)
        clear()
        _armed = False


@contextmanager
def signals_deferred() -> Iterator[None]:
    """SIGINT and SIGTERM wait until the block is done. For writes to a pipe: a signal that
    interrupts a blocked write of a long text makes Python drop the part not yet written
    (measured: a JSON object cut at 64 KiB), so results are written with them held back."""
    held = {signal.SIGINT, signal.SIGTERM, signal.SIGUSR1}
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, held)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)
