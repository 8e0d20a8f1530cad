"""The Floquet multipliers of an orbit found: those of fem-dual's slab maps along it (SlabFlow), on
slabs refined until the degree p + 1 companion's agree, and how far they are from the companion's,
from DOP853's and from round-off."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np

from fem_dual.analysis.floquet import (FLOW_MAX_CELLS, FLOW_TARGET, MULTIPLIER_TOL, SlabFlow,
                                       floquet_multipliers, multiplier_distance, vector_field)
from fem_dual.analysis.orbit.result import OrbitResult

__all__ = ["FlowMultipliers", "MultiplierErrors", "refine_multipliers", "multiplier_errors",
           "sorted_multipliers", "_off_one"]


@dataclass
class FlowMultipliers:
    """An orbit's multipliers by fem-dual's slab maps: of the monodromy `Phi` on `cells` cells,
    the pair at 1 (`trivial`) and the others (`nontrivial`), and the others of the degree p + 1
    companion (`companion`); `field` is the vector field, `direction` its value at the orbit's
    start."""

    Phi: np.ndarray
    cells: int
    field: Callable
    direction: np.ndarray
    trivial: np.ndarray
    nontrivial: np.ndarray
    companion: np.ndarray


@dataclass
class MultiplierErrors:
    """How far an orbit's nontrivial multipliers may be off: from the companion's (`error`), from
    DOP853's (`check`; its multipliers, all, in `dop853`), by round-off (`roundoff`), and the
    pair's distance from 1 (`trivial`), all relative to 1 + |multiplier|."""

    error: float
    check: float
    roundoff: float
    trivial: float
    dop853: np.ndarray


def refine_multipliers(flow: SlabFlow, scene, z0: np.ndarray, T: float, flow_cells: int,
                       other: Optional[OrbitResult], extent: float, Phi_check: np.ndarray,
                       check: bool) -> FlowMultipliers:
    """The multipliers of the orbit from z0 over T by `flow`, from `flow_cells` cells on, doubled
    until the companion's (along `other`, the degree p + 1 orbit, where given) agree to
    FLOW_TARGET and the pair at 1 has settled, or FLOW_MAX_CELLS is reached; without `check`,
    those of `Phi_check`."""
    Phi = Phi_c = Phi_check
    # the companion flow (degree p + 1) runs along the degree p + 1 orbit: the multipliers'
    # estimate sees the error of the orbit's start as well as the flow's
    other_z0, other_T = ((np.concatenate([other.x[0], other.v[0]]), other.period)
                         if other is not None else (z0, T))
    field = vector_field(scene)
    direction, other_direction = field(z0), field(other_z0)
    # multipliers: the pair at 1 (the flow's direction and the family's), the nontrivial
    trivial, lam_n = trivial_c, lam_c_n = floquet_multipliers(Phi, direction)
    off_before = np.inf
    while check:  # finer slabs until the multipliers' estimate meets FLOW_TARGET
        _, Phi, Phi_c = flow(scene, z0, T, flow_cells, other_z0, other_T, extent)
        trivial, lam_n = floquet_multipliers(Phi, direction)
        trivial_c, lam_c_n = floquet_multipliers(Phi_c, other_direction)
        error = multiplier_distance(lam_n, lam_c_n)
        # the pair at 1 is held to MULTIPLIER_TOL only, and only while finer slabs bring it
        # nearer: it carries the orbit's own error too (4e-11 where the nontrivial agree to
        # 1e-12), and round-off far from the origin (3e-4 at 1e4, 5e6 times the extent)
        off = max(_off_one(trivial), _off_one(trivial_c))
        settled = off <= MULTIPLIER_TOL or off > 0.5 * off_before
        if (error <= FLOW_TARGET and settled) or 2 * flow_cells > FLOW_MAX_CELLS:
            break
        flow_cells, off_before = 2 * flow_cells, off
    return FlowMultipliers(Phi, flow_cells, field, direction, trivial, lam_n, lam_c_n)


def multiplier_errors(flow: FlowMultipliers, Phi_check: np.ndarray,
                      check: bool) -> MultiplierErrors:
    """The errors of `flow`'s multipliers, among them the distance to those of DOP853's
    monodromy `Phi_check`; without `check`, no round-off and no distance of the pair from 1."""
    trivial_check, lam_check_n = floquet_multipliers(Phi_check, flow.direction)
    multipliers_error = multiplier_distance(flow.nontrivial, flow.companion)
    multipliers_check = multiplier_distance(flow.nontrivial, lam_check_n)
    # the pair's distance from 1: its error, known exactly (estimate.trivial_multipliers);
    # the nontrivial ones are vouched for by degree p + 1 and DOP853, not by it (far from
    # the origin the pair is off by round-off in tangents that the others do not need)
    trivial_error = _off_one(flow.trivial) if check else 0.0
    # eigenvalues carry round-off of about eps |Phi| each: a multiplier far below the
    # largest (its inverse, in a reversible system) is known no better than that
    Phi = flow.Phi
    roundoff = float(len(Phi) * np.finfo(float).eps * np.linalg.norm(Phi, 2)) if check else 0.0
    return MultiplierErrors(multipliers_error, multipliers_check, roundoff, trivial_error,
                            sorted_multipliers(trivial_check, lam_check_n))


def sorted_multipliers(trivial: np.ndarray, nontrivial: np.ndarray) -> np.ndarray:
    """All multipliers, the largest in modulus first (then by imaginary part)."""
    lam = np.concatenate([trivial, nontrivial])
    return lam[np.lexsort((lam.imag, -np.abs(lam)))]


def _off_one(trivial: np.ndarray) -> float:
    """The trivial pair's largest distance from 1, relative to 1 + |1| as the others'."""
    return float(np.abs(trivial - 1).max() / 2)
