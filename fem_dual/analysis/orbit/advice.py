"""A slab solver's or a run's advice, turned into what to do for an orbit instead."""
from __future__ import annotations

__all__ = ["ORBIT_ADVICE", "_orbit_advice"]

# a run's advice (options `fem-dual orbit` does not have) and what to do for an orbit instead
_RUN_ADVICE = ("use smaller slabs or larger alpha", "use smaller slabs (more --slabs)",
               "loosen --rtol, or raise --cells or --degree",
               "use more slabs or cells per slab, a higher degree, or --rtol to choose the slab "
               "lengths")
ORBIT_ADVICE = "give a better guess (--period, --x0, --v0), or raise --cells or --degree"


def _orbit_advice(message: str) -> str:
    """A slab solver's or a run's advice, turned into an orbit's."""
    for advice in _RUN_ADVICE:
        message = message.replace(advice, ORBIT_ADVICE)
    return message
