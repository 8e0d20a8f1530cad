"""Modal coordinates for linear scenes: the slabs are solved for r with q = U r, where U holds
the modes of the pencil (K, M) (real 2 x 2 blocks for complex pairs, above flutter, and one
block for modes about to coalesce).

In these coordinates M q'' + D q' + K q = 0 reads r'' + Dr r' + Kr r = 0 with Kr = U^-1 M^-1 K U
(block) diagonal and Dr = U^-1 M^-1 D U (full unless the damping is modal). With energy weights
(A = sym Kr, B = I) and a zero base state the dual problem of an undamped system decouples mode
by mode: every mode the cells resolve keeps the order 2p, every mode they do not is damped,
whatever the non-normality of K. In physical coordinates a follower load (K not symmetric)
couples the resolved modes to the unresolved ones through the weights, and the slow motion of
a stiff column is only accurate to 1e-3 .. 1e-4 (README, "Stiff systems").

The dense eigen-decomposition costs O(n^3), once per run (0.2 s for n = 200, 2 s for n = 1000):
fine for columns of hundreds of links, not for a continuum.
"""
from __future__ import annotations

import dataclasses
import functools
from typing import ClassVar, Optional, Tuple

import numpy as np

from fem_dual.errors import InputError
from fem_dual.modes import finite_real_modes, modes_hold
from fem_dual.slab.values import VertexValues, times_last
from fem_dual.scenes.base import is_spd
from fem_dual.scenes.linear import LinearScene

__all__ = ["ModalScene", "ModalBasis", "MAX_CONDITION", "modal_obstacle", "modal_decomposition",
           "modes_inverse"]

RESOLVED_TURN = 0.25  # under a tolerance the zero base drops a mode turning more than this x
# degree radians per cell: between it and degree radians the slab follows the mode with an
# error that does not shrink like dt^(2p+1) (judged per unit of time it drove the slabs of a
# beam to 1e-6 of its period), beyond it the mode is damped anyway
MAX_CONDITION = 1e8  # cond(U) beyond this: modes too close to coalescing (near flutter)


@dataclasses.dataclass(frozen=True)
class ModalScene(LinearScene):
    """r'' + Dr r' + Kr r = 0: a linear scene in the modal coordinates of another one."""

    name: ClassVar[str] = "modal"
    default_T: ClassVar[float] = 1.0
    summary: ClassVar[str] = "a linear scene in modal coordinates (built by fem_dual.slab.modal)"

    Kr: tuple = ()
    Dr: tuple = ()

    @property
    def n(self) -> int:  # type: ignore[override]
        return len(self.Kr)

    def mass_matrix(self) -> np.ndarray:
        return np.eye(self.n)

    def stiffness_matrix(self) -> np.ndarray:
        return np.array(self.Kr, dtype=float)

    def damping_matrix(self) -> np.ndarray:
        return np.array(self.Dr, dtype=float)


@functools.lru_cache(maxsize=4)
def _decomposition(scene: LinearScene) -> tuple:
    """((U, Kr, Ar, omega), None) of the scene's modes (see fem_dual.modes.real_modes), or
    (None, why they cannot be used). Once per scene: the check of `coordinates` and the
    ModalBasis of a run and of its companion share it (a QZ of the pencil costs 0.2 s for 200
    links)."""
    if scene.A is not None or scene.B is not None:
        return None, "H's weights A, B were given in physical coordinates"
    modes = finite_real_modes(scene.mass_matrix(), scene.stiffness_matrix())
    if modes is None:
        return None, "the modes of (K, M) cannot be computed"
    U, Ar = modes[0], modes[2]
    cond = np.linalg.cond(U)
    if not cond < MAX_CONDITION:
        return None, (f"the modes of (K, M) are nearly dependent (condition number "
                      f"{cond:.3g}, near flutter or a repeated frequency)")
    hold, error = modes_hold(scene.mass_matrix(), scene.stiffness_matrix())
    if not hold:
        return None, (f"the modes of (K, M) do not hold: their backward error is {error:.3g} "
                      "(a repeated frequency whose modes are defective, or nearly so)")
    if not is_spd(Ar):
        lam = np.linalg.eigvals(modes[1])
        if (lam.imag[lam.real <= 0] != 0).any():
            return None, ("a pair of modes of (K, M) grows as it oscillates (complex "
                          "eigenvalues with real part <= 0: far past the flutter load)")
        return None, "a mode of (K, M) does not oscillate (zero or negative stiffness)"
    return modes, None


@functools.lru_cache(maxsize=4)
def modes_inverse(scene: LinearScene) -> np.ndarray:
    """U^-1 of the scene's modes (modal_decomposition: not None), once per scene (read-only:
    the modal maps and the data floor share it)."""
    Uinv = np.linalg.inv(modal_decomposition(scene)[0])
    Uinv.flags.writeable = False
    return Uinv


def modal_decomposition(scene: LinearScene) -> Optional[tuple]:
    """(U, Kr, Ar, omega) of the scene's modes (fem_dual.modes.real_modes), or None where they
    cannot be used (modal_obstacle says why)."""
    return _decomposition(scene)[0]


def modal_obstacle(scene: LinearScene) -> Optional[str]:
    """Why the scene cannot be solved in modal coordinates, or None."""
    return _decomposition(scene)[1]


class ModalBasis:
    """q = U r for a linear scene: its modal scene and the maps between the coordinates.

    Raises:
        InputError: the scene has no usable modal coordinates (see modal_obstacle).
    """

    def __init__(self, scene: LinearScene):
        modes, obstacle = _decomposition(scene)
        if obstacle:
            raise InputError(f"coordinates=modal: {obstacle}")
        U, Kr, Ar, self.omega = modes  # omega: each coordinate's frequency
        M, D = scene.mass_matrix(), scene.damping_matrix()
        Uinv = modes_inverse(scene)
        # (undamped: no n x n solve and products for a zero Dr, 45 ms at 450 dofs)
        Dr = Uinv @ np.linalg.solve(M, D @ U) if D.any() else np.zeros_like(U)
        self.physical = scene
        self.U, self.Uinv, self.M = U, Uinv, M
        self.eta_map = Uinv.T @ scene.mass_inverse  # eta_q = M^-1 U^-T eta_r (rows: @ its T)
        # the transposes the maps multiply rows with, contiguous (BLAS is 2x slower on a
        # transposed view)
        self._Ut, self._Uinv_t = np.ascontiguousarray(U.T), np.ascontiguousarray(Uinv.T)
        self._eta_t = np.ascontiguousarray(self.eta_map.T)
        self.scene = ModalScene(Kr=_rows(Kr), Dr=_rows(Dr), A=_rows(Ar), weights="energy")
        self.scene.validate()

    def unresolved(self, z: np.ndarray, dt: float, cells: int, degree: int,
                   turn: float = 1.0) -> np.ndarray:
        """(2n,): how much of the state z (physical) lies in modes that turn more than
        `turn` x `degree` radians per cell of a slab of length dt, as |x| and |v| per component
        (summed over those modes); of many states (slabs, 2n) at once. The zero base damps
        them within a slab (or `drop` takes them away): this is what the answer loses, which
        the companion of degree p + 1, damping them too, cannot show."""
        r = self.forward(z)
        n = r.shape[-1] // 2
        fast = self.fast(dt, cells, degree, turn)
        if not fast.any():
            return np.zeros(r.shape)
        w = self.omega[fast]
        amplitude = np.hypot(r[..., :n][..., fast], r[..., n:][..., fast] / w)  # per mode
        size = np.abs(self.U[:, fast])
        return np.concatenate([amplitude @ size.T, (w * amplitude) @ size.T], axis=-1)

    def fast(self, dt: float, cells: int, degree: int, turn: float = 1.0) -> np.ndarray:
        """(n,) bool: the modes that turn more than `turn` x `degree` radians per cell of a
        slab of length dt with `cells` cells."""
        return self.omega * dt / cells > turn * degree

    def drop(self, r: np.ndarray, dt: float, cells: int, degree: int,
             turn: float) -> np.ndarray:
        """The modal state(s) r without the modes `fast` names (the zero base's damping made
        exact: what it takes away is `unresolved`, judged once)."""
        fast = self.fast(dt, cells, degree, turn)
        if not fast.any():
            return r
        n = r.shape[-1] // 2
        r = np.array(r, dtype=float)
        r[..., :n][..., fast] = 0.0
        r[..., n:][..., fast] = 0.0
        return r

    def forward(self, z: np.ndarray) -> np.ndarray:
        """(x, v) -> (r, r'), of one state (2n,) or many (slabs, 2n)."""
        n = z.shape[-1] // 2
        return np.concatenate([times_last(z[..., :n], self._Uinv_t),
                               times_last(z[..., n:], self._Uinv_t)], axis=-1)

    def forward_units(self, rows: slice) -> np.ndarray:
        """forward(I[rows]) of the identity's rows (unit states) without a product: their
        modal states are the rows of blockdiag(U^-T, U^-T) (a 450-dof slab map's 900 unit
        states took two 900 x 450 x 450 products per slab length and simulation)."""
        n = len(self.U)
        units = np.arange(2 * n)[rows]
        out = np.zeros((len(units), 2 * n))
        x = units < n  # (x's units, then v's)
        out[x, :n] = self._Uinv_t[units[x]]
        out[~x, n:] = self._Uinv_t[units[~x] - n]
        return out

    def back(self, values: Optional[VertexValues]) -> Optional[VertexValues]:
        """Vertex values in physical coordinates (dual fields by their pairing: xi_q = U^-T
        xi_r, eta_q = M^-1 U^-T eta_r; H_d is a scalar), of one slab or many."""
        if values is None:
            return None
        out = VertexValues(s=values.s, x=times_last(values.x, self._Ut),
                           v=times_last(values.v, self._Ut), hamiltonian=values.hamiltonian)
        if values.xi is not None:
            out.xi = times_last(values.xi, self.Uinv)
            out.eta = times_last(values.eta, self._eta_t)
        return out


def _rows(matrix: np.ndarray) -> Tuple[tuple, ...]:
    return tuple(map(tuple, np.asarray(matrix, dtype=float)))
