"""What `fem-dual orbit` computed for one orbit (its JSON object), and how two degrees' orbits
differ."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional

import numpy as np

__all__ = ["OrbitResult", "_differences"]


@dataclass
class OrbitResult:
    """What `fem-dual orbit` computed (its JSON object)."""

    scene: str
    parameters: Dict[str, Any]
    mode: str
    period: float
    mu: float
    t: List[float]
    x: List[List[float]]
    v: List[List[float]]
    multipliers: List[List[float]]
    nontrivial_multipliers: List[List[float]]  # without the pair at 1 (flow and family)
    closure: float
    closure_relative: float
    newton: Dict[str, Any]
    timings: Dict[str, float]
    degree: int
    cells: int
    guess: Dict[str, Any]
    status: str = "ok"
    message: str = ""
    energy: Optional[float] = None  # at the orbit's start (V(0) = 0)
    energy_target: Optional[float] = None  # mode energy: the E asked for
    estimate: Dict[str, Any] = field(default_factory=dict)
    # the independent check by DOP853 (the multipliers of its monodromy, and their largest
    # distance to fem-dual's, relative to 1 + |multiplier|)
    check: Dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> Dict[str, Any]:
        from dataclasses import asdict

        return asdict(self)


def _differences(result: OrbitResult, other: OrbitResult) -> Dict[str, float]:
    """The differences in period, vertex states and energy (where both have one) of the same
    orbit at two degrees."""
    out = {"period": abs(other.period - result.period),
           "state": float(np.abs(np.hstack([np.array(other.x) - np.array(result.x),
                                            np.array(other.v) - np.array(result.v)])).max())}
    if result.energy is not None and other.energy is not None:
        out["energy"] = abs(other.energy - result.energy)
    return out
