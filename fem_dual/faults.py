"""Ending a run early without losing it: SIGINT/SIGTERM stop the slab loop after the slab at hand
(the output is flushed and the run's JSON says what was kept), and errors on one rank end every
rank (the slab loop shares them collectively; whatever escapes ends the job).
"""
from __future__ import annotations

import os
import signal
from contextlib import contextmanager
from typing import Iterator, Optional

from fem_dual.errors import SolveError

__all__ = ["Interrupted", "graceful_signals", "requested", "request", "clear"]

_requested: Optional[int] = None


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


class Interrupted(SolveError):
    """The run was stopped by a signal; `partial` holds the slabs completed before. Exit status
    128 + the signal number (130 for SIGINT, 143 for SIGTERM), as shells report it."""

    def __init__(self, message: str, signum: int, slab: "int | None" = None):
        super().__init__(message, slab)
        self.signum = signum
        self.exit_status = 128 + signum


@contextmanager
def graceful_signals() -> Iterator[None]:
    """SIGINT and SIGTERM ask the slab loop to stop (fem_dual.faults.requested); a second one
    ends the process at once, as if unhandled. The previous handlers come back afterwards."""
    signals = [signal.SIGINT, signal.SIGTERM]

    def handler(signum, frame) -> None:
        if requested():
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
