"""The N-link follower-load column: M, K, D assembled in code for any number of links."""
from __future__ import annotations

import dataclasses
from typing import ClassVar, Tuple

import numpy as np

from fem_dual.errors import InputError
from fem_dual.scenes.base import (LazyForms, per_link_field, require_positive, require_square,
                                  show)
from fem_dual.scenes.linear import LinearScene

__all__ = ["Column", "scaled_column_params", "scaled_column", "lowest_mode"]


@dataclasses.dataclass(frozen=True)
class Column(LinearScene):
    """N = `links` rigid links with joint masses m, springs c, dampers d (one value, or one per
    link), length l, tip follower load P. links=2, m=2,1 reproduces `ziegler`."""

    name: ClassVar[str] = "column"
    forms: ClassVar = LazyForms("fem_dual.forms.column")
    default_T: ClassVar[float] = 20.0
    summary: ClassVar[str] = "N-link follower-load column (Ziegler for N = 2, Beck for large N)"
    size_field: ClassVar[str] = "links"  # from 2 to MAX_DOFS (the memory rule of scenes.base)
    min_dofs: ClassVar[int] = 2

    links: int = 2
    m: tuple = per_link_field(1.0, "joint and tip masses")
    c: tuple = per_link_field(1.0, "rotational springs (base first)")
    d: tuple = per_link_field(0.0, "joint dampers (base first)")
    l: float = 1.0
    P: float = 1.0

    @property
    def n(self) -> int:  # type: ignore[override]
        return int(self.links)

    @property
    def default_x0(self) -> Tuple[float, ...]:  # type: ignore[override]
        return (0.1,) + (0.0,) * (self.n - 1)

    @property
    def default_v0(self) -> Tuple[float, ...]:  # type: ignore[override]
        return (0.0,) * self.n

    def _per_link(self, name: str) -> np.ndarray:
        value = getattr(self, name)
        return np.full(self.n, float(value)) if np.ndim(value) == 0 else np.asarray(value, float)

    def validate(self) -> None:
        require_positive(self, "l")
        require_square(self, "l", "the mass matrix M = l^2 (sums of m)")
        if not (self._per_link("m") > 0).all():
            raise InputError(f"m={show(self.m)} must be positive")
        super().validate()

    def mass_matrix(self) -> np.ndarray:
        return self.forms.mass_matrix(self._per_link("m"), self.l)

    def stiffness_matrix(self) -> np.ndarray:
        return (self.forms.joint_matrix(self._per_link("c"))
                - self.forms.follower_matrix(self.n, self.l, self.P))

    def energy_stiffness(self) -> np.ndarray:
        """The springs alone: positive definite under any load (sym K is not, for long columns
        under a follower load)."""
        return self.forms.joint_matrix(self._per_link("c"))

    def damping_matrix(self) -> np.ndarray:
        return self.forms.joint_matrix(self._per_link("d"))


def scaled_column_params(links: int, P: float = 0.0) -> dict:
    """Parameters of N links scaled like a continuous column (L = 1, EI = 1, mu = 1: l = 1/N,
    c = N, m = 1/N), whose lowest frequency and flutter load approach Beck's column."""
    return {"links": str(links), "l": repr(1.0 / links), "c": repr(float(links)),
            "m": repr(1.0 / links), "P": repr(P)}


def scaled_column(links: int, P: float = 0.0) -> Column:
    """The scaled column of scaled_column_params, validated."""
    return Column.from_params(scaled_column_params(links, P))


def lowest_mode(scene: LinearScene, amplitude: float = 0.1) -> np.ndarray:
    """The real eigenvector of M^-1 K with the smallest |eigenvalue|, scaled to max |x| =
    amplitude: a start state that keeps the motion in the resolved part of the spectrum."""
    lam, U = np.linalg.eig(np.linalg.solve(scene.mass_matrix(), scene.stiffness_matrix()))
    x0 = np.real(U[:, int(np.argmin(np.abs(lam)))])
    return amplitude * x0 / np.abs(x0).max()
