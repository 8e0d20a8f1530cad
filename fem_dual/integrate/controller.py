"""The step-size controller: how long the next slab is.

Hairer-Norsett-Wanner, as in scipy's `_ivp/rk.py` and SUNDIALS: from the weighted local error per
unit of time `err` of an accepted or rejected slab (`fem_dual.integrate.estimate`), the next
length is the slab's times `step_factor(err)` (about err^(-1/(2p)), kept within
[MIN_SHRINK, MAX_GROWTH]); `SlabSchedule` rounds it down to a length of its grid (four lengths
an octave under a tolerance, powers of two for fixed slabs) and remembers rejected lengths.
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
# --rtol: lengths an octave (SlabSchedule). A linear scene pays a superposition basis for each
# length it meets twice: column links=6 at --rtol 1e-4 / 1e-8 took 0.14 / 0.54 s on powers of
# two (error 3e-3 / 1.4e-3 x rtol x scale), 0.29 / 0.73 s on two an octave (1.0e-2 / 5.4e-3),
# 0.38 / 1.15 s on four (1.4e-2 / 9.5e-3)
NONLINEAR_PER_OCTAVE = 4
LINEAR_PER_OCTAVE = 2


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
    per_octave = LINEAR_PER_OCTAVE if config.scene.linear else NONLINEAR_PER_OCTAVE
    return SlabSchedule(config.T, 1, ADAPTIVE_LEVELS,
                        first=initial_fraction(rate, config.T, cells), per_octave=per_octave)


CUT_RESOLUTION = 1e-9  # a cut slab ends this fraction of its length before the cut, at most
KINK_AT_START = 1e-6  # a kink this close to a slab's start (fraction of its length) is not cut:
# it is the one the previous slab was cut at, located again a little later
MAX_UNITS = 2 ** 52  # positions stay exact in float64 (t0 = pos T / total): refinement stops
FIRST_PATIENCE = 4  # slabs a rejected length is not tried again, after its first rejection
MAX_PATIENCE = 256  # ... doubled after each repeated rejection up to this
FINE_SHRINK = 0.8  # a rejected slab of a fine grid is at most this long next (1/2 for powers
# of two)


def grid_floor(units: np.ndarray, per_octave: int = 1) -> np.ndarray:
    """The longest length of the grid at most `units` (>= 1, floats): the lengths m 2^k with m
    in [q, 2q) for q = `per_octave` (a power of two: 1 gives the powers of two, 4 the lengths
    4, 5, 6, 7 times 2^k, steps of 1.14-1.25), and the integers below q. Vectorised; int64."""
    units = np.asarray(units, dtype=float)
    shift = int(per_octave).bit_length() - 1
    k = np.maximum(np.floor(np.log2(units)).astype(np.int64) - shift, 0)
    m = np.floor(units / np.left_shift(np.int64(1), k).astype(float)).astype(np.int64)
    return np.left_shift(m, k)


def _reaching(t0: float, T: float) -> float:
    """The dt with t0 + dt == T in floats (t0 < T)."""
    dt = T - t0
    while t0 + dt < T:
        dt = math.nextafter(dt, math.inf)
    while t0 + dt > T:
        dt = math.nextafter(dt, -math.inf)
    return dt


class SlabSchedule:
    """Slabs of [0, T]: nominally `slabs` equal ones, each cut at most `max_halvings` times
    (minimum length T / (slabs 2^max_halvings)). A slab grows back after a success by the
    factor its caller allows, never beyond the nominal length. Lengths lie on a grid of that
    minimum unit, so equal lengths recur (linear scenes reuse their slab maps):

    - powers of two, and only lengths their start position is a multiple of (`aligned`: the
      end of [0, T] is met without an odd last slab): fixed slabs;
    - a finer grid (`per_octave` > 1, `grid_floor`), not aligned: the last slab is short where
      it meets T. Lengths chosen by a tolerance. With powers of two the local
      error, about dt^(2p+1), jumps by 2^(2p+1) between neighbouring lengths (512 at p = 4), so
      the accepted errors lay up to that far below the tolerance; a step of 1.25 is 7.5.

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
        first: the first slab's length as a fraction of the nominal one (rounded down to the
            grid).
        shrinks: whether an accepted slab's factor below 1 shortens the next one (lengths
            chosen by a tolerance); fixed slabs keep their length until one is rejected (a slab
            accepted close to the tolerance made two half slabs every few dozen slabs).
        per_octave: lengths an octave of the grid (`grid_floor`; 1: powers of two).
    """

    STATE_SIZE = 7  # len(state)

    def __init__(self, T: float, slabs: int, max_halvings: int = 0, first: float = 1.0,
                 shrinks: bool = True, per_octave: int = 1):
        self.T, self.shrinks = T, shrinks
        self.per_octave = per_octave  # the grid of lengths (grid_floor)
        self.fine = per_octave > 1
        self.nominal = 2**max_halvings
        self.total = slabs * self.nominal
        self.pos = 0
        self.length = self._grid_at_most(self.nominal * min(max(first, 0.0), 1.0))
        self.ceiling = 0  # units; 0: no rejected length to keep below
        self.wait = 0  # accepted slabs before the ceiling may be tried again
        self.patience = 0  # the wait after the next rejection at the ceiling (halved)
        # 0 on the fine grid and after a cut: lengths no longer divide their start positions
        self.aligned = 0 if self.fine else 1
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

    def _grid_at_most(self, units: float) -> int:
        return int(grid_floor(min(max(units, 1.0), float(self.nominal)), self.per_octave))

    def _kept(self, factor: np.ndarray) -> np.ndarray:
        """The factors an accepted slab's successor is scaled by: below 1 only where the slab
        shrinks (`shrinks`), and then only below SAFETY (a slab accepted within the tolerance
        keeps its length: rounded down to the grid, a factor of 0.95 shortened it by a step of
        20 % or a half, and the lengths alternated between two, each with its own slab map)."""
        if not self.shrinks:
            return np.maximum(factor, 1.0)
        return np.where(factor >= SAFETY, np.maximum(factor, 1.0), factor)

    def _below(self, units: int) -> int:
        """The longest length of the grid shorter than `units` (> 1)."""
        return units // 2 if not self.fine else self._grid_at_most(units - 1)

    def done(self) -> bool:
        return self.pos >= self.total

    def current(self) -> Tuple[float, float]:
        """(t0, dt) of the slab to solve next. Where lengths are not aligned (the fine grid, a
        cut) the last slab's dt is the one whose t0 + dt is T in floats (an end at T less an
        ulp left T outside the motion)."""
        length = min(self.length, self.total - self.pos)
        t0 = self.pos * self.T / self.total
        if not self.aligned and self.pos + length >= self.total:
            return t0, _reaching(t0, self.T)
        return t0, length * self.T / self.total

    def accept(self, factor: float = 2.0) -> None:
        """Advance past the current slab; the next one is at most `factor` times as long."""
        self.pos += min(self.length, self.total - self.pos)
        length = self._grid_at_most(self.length * float(self._kept(np.float64(factor))))
        if self.ceiling and self.length >= self.ceiling:  # the rejected length passed now
            self.ceiling, self.patience = 0, self.patience // 2
        elif self.ceiling:
            self.wait = max(self.wait - 1, 0)
            if self.wait:
                length = min(length, self._below(self.ceiling))
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
        if not len(factors):
            return self.accept_each(factors)
        if self.resume or (self.ceiling and self.length >= self.ceiling):
            # the first slab takes up a cut slab's length or clears the ceiling
            length = self.length
            first = self.accept_each(factors[:1])
            if self.length != length or len(factors) == 1:
                return first
            return np.vstack([first, self.accept_run(factors[1:])])
        k = np.arange(1, len(factors) + 1)
        length = self.length
        wait = np.maximum(self.wait - k, 0) if self.ceiling else np.full(len(k), self.wait)
        pos = np.minimum(self.pos + k * length, self.total)  # (the last slab may be short)
        scaled = length * self._kept(factors)
        with np.errstate(divide="ignore", invalid="ignore"):
            units = np.clip(np.nan_to_num(scaled, nan=1.0), 1.0, float(self.nominal))
            candidate = grid_floor(units, self.per_octave)
        if self.ceiling:  # below a rejected length while the wait lasts
            candidate = np.where(wait > 0, np.minimum(candidate, self._below(self.ceiling)),
                                 candidate)
        if self.aligned:
            lowest = pos & -pos  # the largest power of two dividing pos (pos > 0)
            candidate = np.minimum(candidate, np.where(pos > 0, lowest, candidate))
        candidate = np.maximum(candidate, 1)
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
        """Shorten the current slab to at most `factor` of its length (at most 1/2 on powers of
        two, FINE_SHRINK on the fine grid); False when it is already at the minimum length."""
        self.length = min(self.length, self.total - self.pos)  # (a short last slab: its own)
        if self.length == 1:
            return False
        if self.ceiling and self.length >= self.ceiling:
            # the rejected length (or a longer one) tried again after the wait: wait longer,
            # below the shortest length rejected
            self.patience = min(2 * self.patience, MAX_PATIENCE)
        else:
            self.patience = max(self.patience, FIRST_PATIENCE)
            self.ceiling = self.length
        self.wait = self.patience
        shrink = FINE_SHRINK if self.fine else 0.5
        self.length = min(self._grid_at_most(self.length * min(factor, shrink)),
                          self._below(min(self.length, self.ceiling)))
        return True
