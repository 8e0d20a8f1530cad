"""Nonlinear curl forces (reference, sections 3.1 and 3.2), and the base for user-defined forces.

A `ForceScene` is a particle of mass m under a force F(x), with H = alpha/2 |x - xbar|^2 +
beta/2 |v - vbar|^2. Its float parameters become fem.Constants of the same names (plus M = m I and
Binv = I / beta); its reference is DOP853 at rtol = 1e-13 (atol = 1e-16) on `force_numpy`.
"""
from __future__ import annotations

import dataclasses
import functools
from typing import ClassVar, Dict, Optional, Tuple

import numpy as np

from fem_dual.errors import InputError
from fem_dual.scenes.base import (LazyForms, Scene, implicit_forms, matrix_field,
                                  require_positive, require_square)

__all__ = ["ForceScene", "Curl3D", "Curl2D", "Curl2DLifted", "Curl3DUFL", "Curl2DUFL"]


@dataclasses.dataclass(frozen=True)
class ForceScene(Scene):
    """A particle of mass m under F(x); subclasses give `forms` and `force_numpy`."""

    linear: ClassVar[bool] = False

    m: float = 1.0
    alpha: float = 1.0
    beta: float = 1.0

    def validate(self) -> None:
        require_positive(self, "m", "alpha", "beta")
        require_square(self, "alpha", "H's position weight and the dual action")
        require_square(self, "beta", "H's velocity weight, which is inverted")

    def mass_matrix(self) -> np.ndarray:
        return self.m * np.eye(self.n)

    def constants(self) -> Dict[str, np.ndarray]:
        values = {f.name: np.array(getattr(self, f.name), dtype=float)
                  for f in dataclasses.fields(self)}
        values["M"] = self.mass_matrix()
        values["Binv"] = np.eye(self.n) / self.beta
        return values

    def force_numpy(self, x: np.ndarray) -> np.ndarray:
        """F(x) for the reference. By default the scene's UFL force evaluated by UFL on numbers, so
        a user-defined force is written once; built-in scenes override it with hand-written numpy,
        which keeps their reference independent of the forms."""
        c = {k: (float(v) if np.ndim(v) == 0 else v) for k, v in self.constants().items()}
        F = self.forms.force(np.asarray(x, dtype=float), c)
        return np.array([F[i]((0.0,)) for i in range(self.n)])

    def force_jacobian_numpy(self, x: np.ndarray) -> Optional[np.ndarray]:
        """dF/dx at x exactly where the scene knows it (None: not known; callers difference)."""
        return None

    def reference(self, x0, v0):
        """DOP853 on x'' = M^-1 F(x) (a scene file may give a mass matrix other than m I)."""
        from fem_dual.reference import IVPFlow

        M = self.mass_matrix()
        if self.kinks(np.asarray(x0, dtype=float)[None]) is not None:  # (stop at each kink)
            kinks, minv = self.kinks, np.linalg.inv(M)
            return IVPFlow(lambda x: minv @ self.force_numpy(x), x0, v0, kinks=kinks,
                           branch=lambda signs: (lambda x, f=self.force_branch(signs):
                                                 minv @ f(x)))
        if np.array_equal(M, self.m * np.eye(self.n)):
            return IVPFlow(lambda x: self.force_numpy(x) / self.m, x0, v0)
        return IVPFlow(lambda x: np.linalg.solve(M, self.force_numpy(x)), x0, v0)

    def quadrature_degree(self, degree: int) -> int:
        # The reduced Lagrangian is not polynomial (A(eta)^-1, or the implicit map): quadrature
        # beyond the 2p of the quadratic part keeps its error below the discretisation error.
        return 2 * degree + 2


@dataclasses.dataclass(frozen=True)
class Curl3D(ForceScene):
    """F(x) = -(yz, 2xz, xy); explicit DtP map through A(eta)^-1 (section 3.2)."""

    name: ClassVar[str] = "curl3d"
    n: ClassVar[int] = 3
    forms: ClassVar = LazyForms("fem_dual.forms.curl3d")
    default_T: ClassVar[float] = 2.0
    default_x0: ClassVar[Tuple[float, ...]] = (0.3, 0.2, 0.1)
    default_v0: ClassVar[Tuple[float, ...]] = (0.0, 0.0, 0.0)
    summary: ClassVar[str] = ("3D curl force -(yz, 2xz, xy) [- K x], explicit DtP map "
                              "(section 3.2)")

    K: Optional[tuple] = matrix_field("a linear spring under the curl force, F = -K x - "
                                      "(yz, 2xz, xy); default zero")

    def spring(self) -> np.ndarray:
        return self.matrix("K", np.zeros((3, 3)))

    def position_weight(self) -> np.ndarray:
        """H's position matrix A = alpha I + sym K: alpha I in the reference; with a stiff
        spring, its energy, which keeps the weights balanced for the fast direction (the
        conditioning rule of linear scenes)."""
        K = self.spring()
        return self.alpha * np.eye(3) + 0.5 * (K + K.T)

    def validate(self) -> None:
        super().validate()
        if np.linalg.eigvalsh(self.position_weight()).min() <= 0:
            raise InputError(f"K={list(self.spring().ravel())} makes H's weight alpha I + sym K "
                             "indefinite; raise alpha")

    def constants(self) -> Dict[str, np.ndarray]:
        values = super().constants()
        values.pop("K", None)
        values["K"], values["A"] = self.spring(), self.position_weight()
        return values

    def force_numpy(self, x):
        a, b, c = np.asarray(x, dtype=float).tolist()  # (floats: the rk4 base calls it often)
        curl = np.array([-b * c, -2.0 * a * c, -a * b])
        return curl if self.K is None else curl - self._spring @ x

    @functools.cached_property
    def _spring(self) -> np.ndarray:
        return self.spring()  # (the rk4 base evaluates the force 4 times a step)

    def force_jacobian_numpy(self, x):
        return -self.spring() - np.array([[0.0, x[2], x[1]], [2 * x[2], 0.0, 2 * x[0]],
                                          [x[1], x[0], 0.0]])


@dataclasses.dataclass(frozen=True)
class Curl2D(ForceScene):
    """F(x) = -k (x y^2, x^3); implicit DtP map, hand-derived G (section 3.1)."""

    name: ClassVar[str] = "curl2d"
    n: ClassVar[int] = 2
    forms: ClassVar = LazyForms("fem_dual.forms.curl2d")
    default_T: ClassVar[float] = 2.0
    default_x0: ClassVar[Tuple[float, ...]] = (1.0, 1.0)
    default_v0: ClassVar[Tuple[float, ...]] = (0.0, 0.0)
    summary: ClassVar[str] = "2D curl force -k (x y^2, x^3), implicit DtP map (section 3.1)"

    k: float = 1.0

    def force_numpy(self, x):
        a, b = np.asarray(x, dtype=float).tolist()  # (floats: the rk4 base calls it often)
        return np.array([-self.k * a * b * b, -self.k * a ** 3])

    def force_jacobian_numpy(self, x):
        return -self.k * np.array([[x[1] ** 2, 2 * x[0] * x[1]], [3 * x[0] ** 2, 0.0]])


# User-defined forces: only F and H are written; G and DF come from UFL (forms.implicit).
@dataclasses.dataclass(frozen=True)
class Curl3DUFL(Curl3D):
    """curl3d declared as a user-defined force: implicit DtP path, G derived by UFL."""

    name: ClassVar[str] = "curl3d-ufl"
    forms: ClassVar = LazyForms("fem_dual.forms.curl3d", implicit_forms)
    summary: ClassVar[str] = "curl3d as a user-defined force (G derived by UFL)"


@dataclasses.dataclass(frozen=True)
class Curl2DUFL(Curl2D):
    """curl2d declared as a user-defined force: G derived by UFL."""

    name: ClassVar[str] = "curl2d-ufl"
    forms: ClassVar = LazyForms("fem_dual.forms.curl2d", implicit_forms)
    summary: ClassVar[str] = "curl2d as a user-defined force (G derived by UFL)"


@dataclasses.dataclass(frozen=True)
class Curl2DLifted(Curl2D):
    """curl2d by quadratic lifting: explicit augmented DtP map, multipliers lambda, mu."""

    name: ClassVar[str] = "curl2d-lifted"
    forms: ClassVar = LazyForms("fem_dual.forms.curl2d_lifted")
    summary: ClassVar[str] = "curl2d by quadratic lifting r = y^2, s = x^2 (remark of section 3.1)"
