"""numpy's floating-point warnings off where a value that overflows is judged instead (numpy
only: the driver's estimates and the Newton's tests use it without DOLFINx)."""
from __future__ import annotations

import functools
from contextlib import contextmanager
from typing import Iterator

import numpy as np

__all__ = ["quiet_numpy"]

_QUIET = [0]  # how many quiet blocks are running (one np.errstate is enough)


@contextmanager
def quiet_numpy() -> Iterator[None]:
    """numpy's floating-point warnings off: a state that overflows gives inf or NaN, which the
    Newton and the driver judge (a warning would be a second message). Inside another such
    block the warnings are off already, and no np.errstate is entered again (5 us a call: a run
    of the slab loop enters one for all its pointwise calls, fem_dual.driver.Simulation.run)."""
    if _QUIET[0]:
        yield
        return
    _QUIET[0] += 1
    try:
        with np.errstate(all="ignore"):
            yield
    finally:
        _QUIET[0] -= 1


def _quiet(method):
    """Run `method` within quiet_numpy."""
    @functools.wraps(method)
    def wrapped(*args, **kwargs):
        if _QUIET[0]:
            return method(*args, **kwargs)
        with quiet_numpy():
            return method(*args, **kwargs)
    return wrapped
