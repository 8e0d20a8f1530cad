"""Linear second-order systems M q'' + D q' + K q = 0 (reference, section 3.3 and its closing
remark): the base of every linear scene. A subclass gives M, K and D from its parameters; H is
1/2 q.A q + 1/2 v.B v with SPD `A` and `B`.

The weights (the conditioning rule, measured in the README, "Where to trust it"): the dual
Euler-Lagrange system is balanced when A / B scales like K M, so that its zero- and first-order
parts differ by the squared frequencies in both the xi and the eta block. Two choices satisfy it:
"identity" (A = I, B = M^2: the principal part is the identity) for problems of one time scale,
and "energy" (A = sym K, or the springs of a column, B = M: H is the energy of the deviation from
the base state), which keeps every mode balanced when fast and slow modes coexist. "auto" picks
energy when the frequencies of M^-1 K spread by more than STIFF_SPREAD and that stiffness is
positive definite.
"""
from __future__ import annotations

import abc
import dataclasses
import functools
from typing import ClassVar, Dict, Optional, Tuple

import numpy as np

from fem_dual.errors import InputError
from fem_dual.reference import FirstOrderModes, first_order_matrix
from fem_dual.scenes.base import (LazyForms, Scene, choice_field, is_spd, matrix_field, require_spd,
                                  show)

__all__ = ["LinearScene", "GeneralLinear", "STIFF_SPREAD"]

STIFF_SPREAD = 5.0  # omega_max / omega_min beyond which auto weights are "energy"
SPREAD_FROM_MODES = 64  # dofs from which frequency_spread reads the pencil's modes


def _same(a, b) -> bool:
    try:
        return bool(np.array_equal(np.asarray(a, dtype=object), np.asarray(b, dtype=object)))
    except (TypeError, ValueError):
        return a is b


@dataclasses.dataclass(frozen=True)
class LinearScene(Scene):
    """M q'' + D q' + K q = 0 with the explicit DtP map of forms.linear; one KSP solve per slab."""

    linear: ClassVar[bool] = True
    forms: ClassVar = LazyForms("fem_dual.forms.linear")

    A: Optional[tuple] = matrix_field("H's position matrix (SPD); default from `weights`")
    B: Optional[tuple] = matrix_field("H's velocity matrix (SPD); default from `weights`")
    weights: str = choice_field("auto", ("auto", "identity", "energy"),
                                "default A, B: identity (I, M^2), energy (sym K, M), auto")

    @abc.abstractmethod
    def stiffness_matrix(self) -> np.ndarray:
        """K, any n x n (non-symmetric for a curl force)."""

    def damping_matrix(self) -> np.ndarray:
        return np.zeros((self.n, self.n))

    def frequency_spread(self) -> float:
        """omega_max / omega_min over the eigenvalues of M^-1 K (inf if one is zero); of a
        large undamped scene from the pencil's modes, which its spectrum computes anyway (a
        small one's eigenvalues cost less than importing scipy before its input is checked)."""
        modes = self._pencil_modes if self.n >= SPREAD_FROM_MODES else None
        if modes is not None:
            lam = np.abs(modes.lam) ** 2  # lambda = +-sqrt(-mu): |lambda|^2 = |mu|
        else:
            lam = np.abs(np.linalg.eigvals(np.linalg.solve(self.mass_matrix(),
                                                           self.stiffness_matrix())))
        return float(np.sqrt(lam.max() / lam.min())) if lam.min() > 0 else float("inf")

    def energy(self, x, v) -> float:
        """1/2 v^T M v + 1/2 x^T K x: conserved by the motion when K is symmetric and there is
        no damping (with a non-symmetric K, what the non-conservative part changes)."""
        x, v = np.asarray(x, float), np.asarray(v, float)
        return float(0.5 * v @ self.mass_matrix() @ v + 0.5 * x @ self.stiffness_matrix() @ x)

    def energy_stiffness(self) -> np.ndarray:
        """The stiffness of H's energy weights: sym K here; a scene with a conservative
        elastic part (the column's springs) may give that instead."""
        K = self.stiffness_matrix()
        return 0.5 * (K + K.T)

    def weighting(self) -> str:
        """The weights in use: `weights`, with auto resolved by the conditioning rule."""
        return self.weights if self.weights != "auto" else self._auto_weighting

    @functools.cached_property
    def _auto_weighting(self) -> str:  # once per scene: A, B, constants and records ask again
        energy = self.frequency_spread() > STIFF_SPREAD and is_spd(self.energy_stiffness())
        return "energy" if energy else "identity"

    def A_matrix(self) -> np.ndarray:
        if self.weighting() == "energy":
            return self.matrix("A", self.energy_stiffness())
        return self.matrix("A", np.eye(self.n))

    def B_matrix(self) -> np.ndarray:
        M = self.mass_matrix()
        return self.matrix("B", M if self.weighting() == "energy" else M @ M)

    def _finite_matrix(self, name: str, build) -> np.ndarray:
        """build() (a matrix of the scene), or InputError when it overflows float64: then the
        parameters given (those that differ from the defaults) are named."""
        try:
            with np.errstate(all="ignore"):
                matrix = np.asarray(build(), dtype=float)
            if np.isfinite(matrix).all():
                return matrix
        except (OverflowError, FloatingPointError, ZeroDivisionError):
            pass
        raise InputError(f"{name} of scene {self.name} is not finite in float64 with "
                         f"{self._given()}")

    def _given(self) -> str:
        try:
            defaults = type(self)()
        except Exception:  # a scene without defaults for every field: name them all
            defaults = None
        given = [f"{f.name}={show(getattr(self, f.name), 24)}" for f in dataclasses.fields(self)
                 if defaults is None or not _same(getattr(self, f.name), getattr(defaults, f.name))]
        return ", ".join(given) if given else "its defaults"

    def validate(self) -> None:
        M = self._finite_matrix("M", self.mass_matrix)
        require_spd("M", M, inverted=True)
        self._finite_matrix("K", self.stiffness_matrix)
        self._finite_matrix("D", self.damping_matrix)
        self._finite_matrix("the first-order matrix (M^-1 K, M^-1 D)", self.first_order_matrix)
        if self.weights == "energy" and self.A is None and not is_spd(self.energy_stiffness()):
            raise InputError("weights=energy needs a positive definite energy stiffness (sym K, "
                             "the springs of a column); use weights=identity or give A")
        require_spd("A", self._finite_matrix("A", self.A_matrix), inverted=True)
        B = self._finite_matrix("B", self.B_matrix)
        if B is M or np.array_equal(B, M):  # (the energy weight: M, checked above)
            return
        default = "M" if self.weighting() == "energy" else "M^2"
        require_spd("B", B, inverted=True, label=None if self.B is not None else (
            f"B = {default} = {show(B)} (H's velocity weight for weights={self.weighting()}, "
            f"M={show(M)})"))

    def constants(self) -> Dict[str, np.ndarray]:
        A, B = self.A_matrix(), self.B_matrix()
        return {"M": self.mass_matrix(), "K": self.stiffness_matrix(), "D": self.damping_matrix(),
                "A": A, "B": B, "Ainv": _inverse(A), "Binv": _inverse(B)}

    def acceleration(self, x0: np.ndarray, v0: np.ndarray) -> np.ndarray:
        """v' at the state (x0, v0): -M^-1 (K x0 + D v0)."""
        return self.accelerations(np.asarray(x0, float)[None], np.asarray(v0, float)[None])[0]

    def accelerations(self, x: np.ndarray, v: np.ndarray) -> np.ndarray:
        """-M^-1 (K x + D v) for each row of x and v (rows, n)."""
        K, D = self.stiffness_matrix(), self.damping_matrix()
        return -(x @ K.T + v @ D.T) @ self.mass_inverse.T

    @functools.cached_property
    def mass_inverse(self) -> np.ndarray:
        """M^-1, computed once per scene (read-only: the accelerations, the modal maps and the
        data floor share it)."""
        Minv = np.linalg.inv(self.mass_matrix())
        Minv.flags.writeable = False
        return Minv

    def first_order_matrix(self) -> np.ndarray:
        """A of z' = A z (a copy: the caller may change it)."""
        return self._first_order.copy()

    @functools.cached_property
    def _first_order(self) -> np.ndarray:
        # once per scene: the validation, the slab-map checks and the base state each need it
        # (two n x n solves: 25 ms for 450 dofs)
        return first_order_matrix(self.mass_matrix(), self.stiffness_matrix(),
                                  self.damping_matrix())

    @functools.cached_property
    def spectrum(self) -> Tuple[np.ndarray, np.ndarray]:
        """Eigenvalues and eigenvectors (unit columns) of the first-order system, computed once
        per scene (the resolution guard, the growth bound and the slab-map check all need
        them). Undamped: from the n x n pencil K w = mu M w, lambda = +-sqrt(-mu) with the
        vectors (w, lambda w) from the real modes the modal coordinates use (the rates of a
        450-dof square in 2.3 s, where the 2n x 2n eig and its least squares take 13 s)."""
        modes = self._pencil_modes
        if modes is None:
            return np.linalg.eig(self.first_order_matrix())
        return modes.lam, modes.V

    @functools.cached_property
    def _pencil_modes(self) -> Optional[FirstOrderModes]:
        """The first-order modes of an undamped scene from K W = M W diag(mu) where they are a
        basis (FirstOrderModes.of) and W is well conditioned; else None. W from the pencil's
        real modes (fem_dual.modes, shared with the modal coordinates): each block's
        eigenvectors in its columns."""
        if np.any(self.damping_matrix()):
            return None
        from fem_dual.modes import block_slices, condition_1, finite_real_modes

        M = self.mass_matrix()
        modes = finite_real_modes(M, self.stiffness_matrix())
        if modes is None:
            return None
        U, Kr = modes[:2]
        mu, W = np.zeros(len(M), complex), np.zeros(M.shape, complex)
        slices = block_slices(Kr)
        single = np.array([b.start for b in slices if b.stop - b.start == 1], dtype=int)
        mu[single], W[:, single] = Kr[single, single], U[:, single]  # (a one-mode block's eig)
        for b in (b for b in slices if b.stop - b.start > 1):
            mu[b], Y = np.linalg.eig(Kr[b, b])
            W[:, b] = U[:, b] @ Y
        modes = FirstOrderModes.of(mu, W)
        return modes if modes is not None and condition_1(W) <= 1e10 else None

    def modal_coefficients(self, x0: np.ndarray, v0: np.ndarray) -> np.ndarray:
        """c with V c = (x0, v0) for the eigenvectors V of `spectrum`."""
        modes = self._pencil_modes
        if modes is None:
            return np.linalg.lstsq(self.spectrum[1], np.concatenate([x0, v0]), rcond=None)[0]
        return modes.coefficients(x0, v0)

    def fastest_rate(self, x0=None, v0=None, relative: float = 1e-6,
                     scales: Optional[Tuple[float, float]] = None) -> float:
        """max |lambda| over the eigenvalues of the first-order system (radians per unit time,
        growth and decay included); given a start state, over the modes it excites (modal
        amplitude above `relative` of the state). With `scales` (of x and of v): over the
        modes that are left once the fastest ones, together, carry at most `relative` x the
        scales in x and in v (|x| and |v| per component, summed over the modes left out): the
        modes a zero base may drop within that tolerance."""
        lam, U = self.spectrum
        if x0 is None:
            return float(np.abs(lam).max())
        z0 = np.concatenate([x0, v0])
        coefficients = self.modal_coefficients(x0, v0)
        if scales is None:
            amplitude = np.abs(coefficients) * np.linalg.norm(U, axis=0)
            excited = amplitude > relative * max(np.linalg.norm(z0), 1e-300)
            return float(np.abs(lam[excited]).max()) if excited.any() else 0.0
        n = self.n
        parts = np.abs(U * coefficients)  # (2n, modes): each mode's |x| and |v| per component
        order = np.argsort(-np.abs(lam), kind="stable")  # fastest first
        tail_x = np.cumsum(parts[:n, order], axis=1).max(axis=0)
        tail_v = np.cumsum(parts[n:, order], axis=1).max(axis=0)
        dropped = (tail_x <= relative * scales[0]) & (tail_v <= relative * scales[1])
        kept = order[np.argmin(dropped):] if not dropped.all() else order[:0]
        return float(np.abs(lam[kept]).max()) if len(kept) else 0.0

    def reference(self, x0, v0):
        from fem_dual.reference import linear_flow

        return linear_flow(self.mass_matrix(), self.stiffness_matrix(), self.damping_matrix(),
                           x0, v0)


@dataclasses.dataclass(frozen=True)
class GeneralLinear(LinearScene):
    """Any M q'' + D q' + K q = 0: `dofs` = n, M SPD, K and D any n x n (row-major lists)."""

    name: ClassVar[str] = "linear"
    default_T: ClassVar[float] = 10.0
    summary: ClassVar[str] = "any M q'' + D q' + K q = 0 (M SPD; K, D any), remark of section 3.3"

    size_field: ClassVar[str] = "dofs"
    max_dofs: ClassVar[int] = 1000  # M, K, D are typed as n^2 numbers each

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

    def mass_matrix(self) -> np.ndarray:
        return self.matrix("M", np.eye(self.n))

    def stiffness_matrix(self) -> np.ndarray:
        return self.matrix("K", np.eye(self.n))

    def damping_matrix(self) -> np.ndarray:
        return self.matrix("D", np.zeros((self.n, self.n)))


def _inverse(matrix: np.ndarray) -> np.ndarray:
    """matrix^-1; of a diagonal one (modal coordinates' weights) elementwise: LAPACK's inverse
    of the 450 x 450 diagonal weights of a square's modal scene took 20 ms each."""
    d = np.diag(matrix)
    if np.count_nonzero(d) == len(d) == np.count_nonzero(matrix):  # (a zero pivot: as inv)
        return np.diag(1.0 / d)
    return np.linalg.inv(matrix)
