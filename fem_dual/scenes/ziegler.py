"""The linearised Ziegler column (reference, section 3.3), with optional joint damping."""
from __future__ import annotations

import dataclasses
from typing import ClassVar, Tuple

import numpy as np

from fem_dual.scenes.base import LazyForms, require_positive, require_square
from fem_dual.scenes.linear import LinearScene

__all__ = ["Ziegler"]


@dataclasses.dataclass(frozen=True)
class Ziegler(LinearScene):
    """Ziegler column: masses m1, m2, springs c1, c2, link length l, follower load P, joint
    dampers d1, d2 (D = [[d1 + d2, -d2], [-d2, d2]])."""

    name: ClassVar[str] = "ziegler"
    n: ClassVar[int] = 2
    forms: ClassVar = LazyForms("fem_dual.forms.ziegler")
    default_T: ClassVar[float] = 20.0
    default_x0: ClassVar[Tuple[float, ...]] = (0.1, 0.0)
    default_v0: ClassVar[Tuple[float, ...]] = (0.0, 0.0)
    summary: ClassVar[str] = "linearised Ziegler column with a follower load (section 3.3)"

    m1: float = 2.0
    m2: float = 1.0
    c1: float = 1.0
    c2: float = 1.0
    l: float = 1.0
    P: float = 1.0
    d1: float = 0.0
    d2: float = 0.0

    def validate(self) -> None:
        require_positive(self, "m1", "m2", "l")
        require_square(self, "l", "the mass matrix M = l^2 [[m1 + m2, m2], [m2, m2]]")
        super().validate()

    def mass_matrix(self) -> np.ndarray:
        return self.forms.mass_matrix(self.m1, self.m2, self.l)

    def stiffness_matrix(self) -> np.ndarray:
        return self.forms.stiffness_matrix(self.c1, self.c2, self.l, self.P)

    def damping_matrix(self) -> np.ndarray:
        return np.array([[self.d1 + self.d2, -self.d2], [-self.d2, self.d2]], dtype=float)
