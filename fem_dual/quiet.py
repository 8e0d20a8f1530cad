"""numpy's floating-point warnings off where a value that overflows is judged instead (numpy
only: the driver's estimates and the Newton's tests use it without DOLFINx)."""
from __future__ import annotations

import functools
from typing import Optional

import numpy as np

__all__ = ["quiet_numpy"]

_QUIET = [0]  # how many quiet blocks are running (one np.errstate is enough)


class quiet_numpy:  # noqa: N801 -- used as a function: `with quiet_numpy():`
    """numpy's floating-point warnings off: a state that overflows gives inf or NaN, which the
    Newton and the driver judge (a warning would be a second message). Inside another such
    block the warnings are off already, and no np.errstate is entered again (5 us a call: a run
    of the slab loop enters one for all its pointwise calls, fem_dual.integrate.simulation.Simulation.run).
    A class, not a generator context manager: the nested blocks of a run cost a tenth."""

    __slots__ = ("_state",)

    def __enter__(self) -> None:
        self._state: Optional[np.errstate] = None
        if not _QUIET[0]:
            state = np.errstate(all="ignore")
            state.__enter__()
            self._state = state
            _QUIET[0] += 1

    def __exit__(self, *exc) -> bool:
        if self._state is not None:
            _QUIET[0] -= 1
            self._state.__exit__(*exc)
        return False


def _quiet(method):
    """Run `method` within quiet_numpy."""
    @functools.wraps(method)
    def wrapped(*args, **kwargs):
        if _QUIET[0]:
            return method(*args, **kwargs)
        with quiet_numpy():
            return method(*args, **kwargs)
    return wrapped
