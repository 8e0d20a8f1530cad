"""The step-size controller: how long the next slab is.

Hairer-Norsett-Wanner, as in scipy's `_ivp/rk.py` and SUNDIALS: from the weighted local error per
unit of time `err` of an accepted or rejected slab (`fem_dual.integrate.estimate`), the next
length is the slab's times `step_factor(err)` (about err^(-1/(2p)), kept within
[MIN_SHRINK, MAX_GROWTH]); `SlabSchedule` rounds it to a power of two of its unit, remembers
rejected lengths, and meets the end of [0, T] without an odd last slab.
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING, Optional, Tuple

import numpy as np

if TYPE_CHECKING:
    from fem_dual.config import RunConfig

__all__ = ["SlabSchedule", "step_factor", "step_factors", "initial_fraction", "schedule_for",
           "ADAPTIVE_LEVELS", "FIRST_PATIENCE", "MAX_PATIENCE"]

SAFETY = 0.9
MAX_GROWTH = 4.0
MIN_SHRINK = 0.125
ADAPTIVE_LEVELS = 40  # --rtol: the shortest slab is T / 2^40


def step_factor(err: Optional[float], order: int) -> float:
    """Hairer's factor for the next slab length from the weighted error per unit of time
    (err ~ dt^order); a solve that failed (err None) or a non-finite error halves."""
    if err is None or not math.isfinite(err):
        return 0.5 if err is None else MIN_SHRINK
    if not err > 0.0:
        return MAX_GROWTH
    return min(max(SAFETY * err ** (-1.0 / order), MIN_SHRINK), MAX_GROWTH)


def step_factors(err: np.ndarray, order: int) -> np.ndarray:
    """`step_factor` of finite errors, at once."""
    with np.errstate(divide="ignore"):
        grown = SAFETY * np.where(err > 0.0, err, 1.0) ** (-1.0 / order)
    return np.where(err > 0.0, np.clip(grown, MIN_SHRINK, MAX_GROWTH), MAX_GROWTH)


def initial_fraction(rate: float, T: float, cells: int) -> float:
    """The first adaptive slab's length as a fraction of T: about one radian of the motion per
    cell, from the rate |z'| / |z| at the start (the controller corrects it within a few
    slabs)."""
    if not (rate > 0 and math.isfinite(rate)):
        return 1.0
    return min(1.0, cells / (rate * T))


def schedule_for(config: RunConfig, cells: int, rate: float) -> SlabSchedule:
    """Fixed slabs (cut at most max_halvings times), or adaptive lengths from a first guess of
    about one radian per cell (`rate`: the fastest mode of a linear scene, the start's rate of
    a nonlinear one)."""
    if config.rtol is None:
        return SlabSchedule(config.T, config.slab_count, config.max_halvings, shrinks=False)
    return SlabSchedule(config.T, 1, ADAPTIVE_LEVELS,
                        first=initial_fraction(rate, config.T, cells))


CUT_RESOLUTION = 1e-9  # a cut slab ends this fraction of its length before the cut, at most
KINK_AT_START = 1e-6  # a kink this close to a slab's start (fraction of its length) is not cut:
# it is the one the previous slab was cut at, located again a little later
MAX_UNITS = 2 ** 52  # positions stay exact in float64 (t0 = pos T / total): refinement stops
FIRST_PATIENCE = 4  # slabs a rejected length is not tried again, after its first rejection
MAX_PATIENCE = 256  # ... doubled after each repeated rejection up to this


class SlabSchedule:
    """Slabs of [0, T]: nominally `slabs` equal ones, each cut at most `max_halvings` times
    (minimum length T / (slabs 2^max_halvings)). Lengths are powers of two of that minimum, so
    equal lengths recur (linear scenes reuse their slab maps); a slab grows back after a success
    by the factor its caller allows, never beyond the nominal length, and only to a length its
    start position is a multiple of (so the end of [0, T] is met without an odd last slab).

    A rejected length is remembered (`ceiling`): the slabs grow back to it only after `wait`
    accepted slabs, a wait that doubles each time the same length is rejected again (up to
    MAX_PATIENCE) and halves when it passes. Without it an error just above the tolerance at
    one length and well below it at half that length made every other attempt a rejection.

    Positions are kept as integers in units of the minimum length, so start times carry no
    accumulated round-off and equal slabs start exactly at k T / slabs.

    A slab may be cut to end at a given time (`cut`: a kink of the force inside it); from then
    on lengths are still powers of two, but no longer aligned to their multiples (the last slab
    is short where it meets T).

    Args:
        T: horizon.
        slabs: number of nominal slabs.
        max_halvings: how often a nominal slab may be halved.
        first: the first slab's length as a fraction of the nominal one (rounded down to a
            power of two).
        shrinks: whether an accepted slab's factor below 1 shortens the next one (lengths
            chosen by a tolerance); fixed slabs keep their length until one is rejected (a slab
            accepted close to the tolerance made two half slabs every few dozen slabs).
    """

    STATE_SIZE = 7  # len(state)

    def __init__(self, T: float, slabs: int, max_halvings: int = 0, first: float = 1.0,
                 shrinks: bool = True):
        self.T, self.shrinks = T, shrinks
        self.nominal = 2**max_halvings
        self.total = slabs * self.nominal
        self.pos = 0
        self.length = self._power_of_two_at_most(self.nominal * min(max(first, 0.0), 1.0))
        self.ceiling = 0  # units; 0: no rejected length to keep below
        self.wait = 0  # accepted slabs before the ceiling may be tried again
        self.patience = 0  # the wait after the next rejection at the ceiling (halved)
        self.aligned = 1  # 0 after a cut: lengths no longer divide their start positions
        self.resume = 0  # after a cut: the length the cut slab had, taken up again after it

    @property
    def state(self) -> Tuple[int, ...]:
        """Everything `accept` and `halve` depend on (a resumed run restores it)."""
        return (self.pos, self.length, self.ceiling, self.wait, self.patience, self.aligned,
                self.resume)

    @state.setter
    def state(self, value) -> None:
        (self.pos, self.length, self.ceiling, self.wait, self.patience, self.aligned,
         self.resume) = (int(a) for a in value)

    def _power_of_two_at_most(self, units: float) -> int:
        units = min(max(units, 1.0), float(self.nominal))
        return 1 << int(math.floor(math.log2(units)))

    def done(self) -> bool:
        return self.pos >= self.total

    def current(self) -> Tuple[float, float]:
        """(t0, dt) of the slab to solve next."""
        length = min(self.length, self.total - self.pos)
        return self.pos * self.T / self.total, length * self.T / self.total

    def accept(self, factor: float = 2.0) -> None:
        """Advance past the current slab; the next one is at most `factor` times as long."""
        self.pos += min(self.length, self.total - self.pos)
        length = self._power_of_two_at_most(self.length * (factor if self.shrinks
                                                          else max(factor, 1.0)))
        if self.ceiling and self.length >= self.ceiling:  # the rejected length passed now
            self.ceiling, self.patience = 0, self.patience // 2
        elif self.ceiling:
            self.wait = max(self.wait - 1, 0)
            if self.wait:
                length = min(length, self.ceiling // 2)
        if self.resume:  # the slab was cut at a kink: no verdict on the length it had
            length, self.resume = max(length, self.resume), 0
        while self.aligned and length > 1 and self.pos % length:
            length //= 2
        self.length = length

    def cut(self, t: float) -> bool:
        """End the current slab within CUT_RESOLUTION of its length before the time t (inside
        it); False where t lies within KINK_AT_START of its start. Where the unit is coarser
        than CUT_RESOLUTION, every length and position is refined by a power of two first
        (exactly: the slab times stay the same floats). A cut is no verdict on the length: the
        ceiling of rejected lengths is kept, and the slab after the cut one takes up the length
        the cut slab had (`resume`)."""
        t0, dt = self.current()
        if not t0 + KINK_AT_START * dt <= t < t0 + dt:  # (closer: the kink at its start)
            return False
        unit = self.T / self.total
        refine = 0
        while (unit / 2 ** refine > CUT_RESOLUTION * dt
               and self.total << (refine + 1) <= MAX_UNITS):
            refine += 1
        if refine:
            self.pos, self.length, self.total, self.nominal, self.ceiling, self.resume = (
                value << refine for value in (self.pos, self.length, self.total, self.nominal,
                                              self.ceiling, self.resume))
        units = int(math.floor((t - t0) * self.total / self.T))
        if not 1 <= units < min(self.length, self.total - self.pos):
            return False
        self.resume = max(self.resume, self.length)
        self.length, self.aligned = units, 0
        return True

    def accept_each(self, factors) -> np.ndarray:
        """`accept_run` slab by slab (its states; what the vectorised path must equal)."""
        states = []
        for factor in factors:
            length = self.length
            self.accept(float(factor))
            states.append(self.state)
            if self.length != length:
                break
        return np.array(states, dtype=np.int64).reshape(-1, self.STATE_SIZE)

    def accept_run(self, factors) -> np.ndarray:
        """`accept` slab after slab with the step factors `factors`, stopping after the first
        slab whose factor changes the length; returns the state after each accepted slab
        ((slabs, STATE_SIZE) integers).
        Vectorised (a chunk of hundreds of equal slabs of a linear scene took a millisecond
        slab by slab, 2.5 ms of a 10 ms run); the same states as `accept`."""
        factors = np.asarray(factors, dtype=float)
        if not self.aligned or not len(factors):
            return self.accept_each(factors)
        if self.ceiling and self.length >= self.ceiling:  # the first slab clears the ceiling
            length = self.length
            first = self.accept_each(factors[:1])
            if self.length != length or len(factors) == 1:
                return first
            return np.vstack([first, self.accept_run(factors[1:])])
        k = np.arange(1, len(factors) + 1)
        length = self.length
        wait = np.maximum(self.wait - k, 0) if self.ceiling else np.full(len(k), self.wait)
        pos = np.minimum(self.pos + k * length, self.total)  # (the last slab may be short)
        scaled = length * (factors if self.shrinks else np.maximum(factors, 1.0))
        with np.errstate(divide="ignore", invalid="ignore"):
            units = np.clip(np.nan_to_num(scaled, nan=1.0), 1.0, float(self.nominal))
            candidate = np.left_shift(1, np.floor(np.log2(units)).astype(np.int64))
        if self.ceiling:  # below a rejected length while the wait lasts
            candidate = np.where(wait > 0, np.minimum(candidate, self.ceiling // 2), candidate)
        lowest = pos & -pos  # the largest power of two dividing pos (pos > 0)
        candidate = np.maximum(np.minimum(candidate, np.where(pos > 0, lowest, candidate)), 1)
        changed = np.flatnonzero(candidate != length)
        count = int(changed[0]) + 1 if len(changed) else len(factors)
        self.pos, self.length = int(pos[count - 1]), int(candidate[count - 1])
        self.wait = int(wait[count - 1])
        states = np.empty((count, self.STATE_SIZE), dtype=np.int64)
        states[:, 0], states[:, 1], states[:, 3] = pos[:count], candidate[:count], wait[:count]
        states[:, 2], states[:, 4], states[:, 5] = self.ceiling, self.patience, self.aligned
        states[:, 6] = self.resume
        return states

    def halve(self, factor: float = 0.5) -> bool:
        """Shorten the current slab to at most `factor` (at most 1/2) of its length; False when
        it is already at the minimum length."""
        if self.length == 1:
            return False
        if self.length == self.ceiling:  # rejected again after the wait: wait longer
            self.patience = min(2 * self.patience, MAX_PATIENCE)
        else:
            self.patience = max(self.patience, FIRST_PATIENCE)
        self.ceiling, self.wait = self.length, self.patience
        self.length = self._power_of_two_at_most(self.length * min(factor, 0.5))
        return True
