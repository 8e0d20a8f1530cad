"""Linear second-order systems M q'' + D q' + K q = 0 (reference, section 3.3 and its closing
remark): the base of every linear scene. A subclass gives M, K and D from its parameters; H is
1/2 q.A q + 1/2 v.B v with SPD `A` (default I) and `B` (default M^2, which makes the principal
part of the dual Euler-Lagrange system the identity)."""
from __future__ import annotations

import abc
import dataclasses
from typing import ClassVar, Dict, Optional

import numpy as np

import forms.linear as linear_forms
from fem_dual.reference import LinearFlow, first_order_matrix
from fem_dual.errors import InputError
from fem_dual.scenes.base import Scene, matrix_field, require_spd

__all__ = ["LinearScene", "GeneralLinear"]


@dataclasses.dataclass(frozen=True)
class LinearScene(Scene):
    """M q'' + D q' + K q = 0 with the explicit DtP map of forms.linear; one KSP solve per slab."""

    linear: ClassVar[bool] = True
    forms: ClassVar = linear_forms

    A: Optional[tuple] = matrix_field("H's position matrix (SPD); default identity")
    B: Optional[tuple] = matrix_field("H's velocity matrix (SPD); default M^2")

    @abc.abstractmethod
    def stiffness_matrix(self) -> np.ndarray:
        """K, any n x n (non-symmetric for a curl force)."""

    def damping_matrix(self) -> np.ndarray:
        return np.zeros((self.n, self.n))

    def A_matrix(self) -> np.ndarray:
        return self.matrix("A", np.eye(self.n))

    def B_matrix(self) -> np.ndarray:
        M = self.mass_matrix()
        return self.matrix("B", M @ M)

    def validate(self) -> None:
        require_spd("M", self.mass_matrix())
        require_spd("A", self.A_matrix())
        require_spd("B", self.B_matrix())

    def constants(self) -> Dict[str, np.ndarray]:
        A, B = self.A_matrix(), self.B_matrix()
        return {"M": self.mass_matrix(), "K": self.stiffness_matrix(), "D": self.damping_matrix(),
                "A": A, "B": B, "Ainv": np.linalg.inv(A), "Binv": np.linalg.inv(B)}

    def first_order_matrix(self) -> np.ndarray:
        return first_order_matrix(self.mass_matrix(), self.stiffness_matrix(),
                                  self.damping_matrix())

    def reference(self, x0, v0) -> LinearFlow:
        return LinearFlow(self.first_order_matrix(), x0, v0)


@dataclasses.dataclass(frozen=True)
class GeneralLinear(LinearScene):
    """Any M q'' + D q' + K q = 0: `dofs` = n, M SPD, K and D any n x n (row-major lists)."""

    name: ClassVar[str] = "linear"
    default_T: ClassVar[float] = 10.0
    summary: ClassVar[str] = "any M q'' + D q' + K q = 0 (M SPD; K, D any), remark of section 3.3"

    dofs: int = 2
    M: Optional[tuple] = matrix_field("mass matrix (SPD); default identity")
    K: Optional[tuple] = matrix_field("stiffness (any, non-symmetric allowed); default identity")
    D: Optional[tuple] = matrix_field("damping (any); default zero")

    @property
    def n(self) -> int:  # type: ignore[override]
        return int(self.dofs)

    @property
    def default_x0(self):  # type: ignore[override]
        return (0.1,) + (0.0,) * (self.n - 1)

    @property
    def default_v0(self):  # type: ignore[override]
        return (0.0,) * self.n

    def validate(self) -> None:
        if not 1 <= self.dofs <= 1000:
            raise InputError(f"dofs={self.dofs!r} must be between 1 and 1000")
        super().validate()

    def mass_matrix(self) -> np.ndarray:
        return self.matrix("M", np.eye(self.n))

    def stiffness_matrix(self) -> np.ndarray:
        return self.matrix("K", np.eye(self.n))

    def damping_matrix(self) -> np.ndarray:
        return self.matrix("D", np.zeros((self.n, self.n)))
