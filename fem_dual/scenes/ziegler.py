"""The linearised Ziegler column (reference, section 3.3)."""
from __future__ import annotations

import dataclasses
from typing import ClassVar, Dict, Optional, Tuple

import numpy as np

import forms.ziegler as ziegler_forms
from fem_dual.reference import LinearFlow, first_order_matrix
from fem_dual.scenes.base import Scene, matrix_field, require_positive, require_spd

__all__ = ["Ziegler"]


@dataclasses.dataclass(frozen=True)
class Ziegler(Scene):
    """Ziegler column: masses m1, m2, springs c1, c2, link length l, follower load P; H given by
    the SPD matrices A (default I) and B (default M^2)."""

    name: ClassVar[str] = "ziegler"
    n: ClassVar[int] = 2
    linear: ClassVar[bool] = True
    forms: ClassVar = ziegler_forms
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
    A: Optional[tuple] = matrix_field("H's position matrix (SPD); default identity")
    B: Optional[tuple] = matrix_field("H's velocity matrix (SPD); default M^2")

    def validate(self) -> None:
        require_positive(self, "m1", "m2", "l")
        require_spd("A", self.A_matrix())
        require_spd("B", self.B_matrix())

    def mass_matrix(self) -> np.ndarray:
        return ziegler_forms.mass_matrix(self.m1, self.m2, self.l)

    def stiffness_matrix(self) -> np.ndarray:
        return ziegler_forms.stiffness_matrix(self.c1, self.c2, self.l, self.P)

    def A_matrix(self) -> np.ndarray:
        return self.matrix("A", np.eye(self.n))

    def B_matrix(self) -> np.ndarray:
        M = self.mass_matrix()
        return self.matrix("B", M @ M)

    def constants(self) -> Dict[str, np.ndarray]:
        A, B = self.A_matrix(), self.B_matrix()
        return {"M": self.mass_matrix(), "K": self.stiffness_matrix(), "A": A, "B": B,
                "Ainv": np.linalg.inv(A), "Binv": np.linalg.inv(B)}

    def reference(self, x0, v0) -> LinearFlow:
        A = first_order_matrix(self.mass_matrix(), self.stiffness_matrix())
        return LinearFlow(A, x0, v0)
