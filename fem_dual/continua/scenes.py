"""Continuum scenes: the method of lines on a DOLFINx spatial mesh, in time by the dual principle.

A `ContinuumScene` is a linear scene whose M, K, D are the free-dof matrices of UFL bilinear
forms on a DOLFINx mesh (fem_dual.continua.system), taken dense: the dense linear path (modal
coordinates, the zero base that drops the modes the slabs do not resolve, the eigen-decomposition
reference) runs on them as on any linear scene, within its memory rule (MAX_DOFS free dofs). Its
start state is given as fields: one expression per field component in the spatial coordinates
(`--u0`, `--v0`, the expression language of `--F`).

Built in:
- `beck`: Beck's column, a Timoshenko beam (w, theta) clamped at x = 0 under a tangential
  (follower) tip load P (fem_dual.continua.beck). Without rotary inertia theta is massless and
  follows w at every instant (theta = G w, fem_dual.continua.condense): the unknowns are the free
  w dofs; the start fields are projected in the elastic energy, and theta follows w0.
"""
from __future__ import annotations

import dataclasses
import functools
from typing import ClassVar, Dict, Optional, Sequence, Tuple

import numpy as np
from fem_dual.errors import InputError
from fem_dual.scenes import register
from fem_dual.scenes.base import require_positive, show
from fem_dual.scenes.linear import LinearScene

__all__ = ["ContinuumScene", "Beck", "split_fields"]


def split_fields(name: str, text, count: int) -> Tuple[str, ...]:
    """The `count` component expressions of `text` ("EXPR, EXPR"; commas inside parentheses
    belong to their expression); InputError naming `name` otherwise."""
    if not isinstance(text, str):
        if isinstance(text, (list, tuple)) and all(isinstance(t, str) for t in text):
            parts = [t.strip() for t in text]
        else:
            raise InputError(f"{name}={show(text)} must be {count} expressions of the spatial "
                             "coordinates, separated by commas")
    else:
        parts, depth, start = [], 0, 0
        for i, ch in enumerate(text):
            depth += (ch == "(") - (ch == ")")
            if ch == "," and depth == 0:
                parts.append(text[start:i].strip())
                start = i + 1
        parts.append(text[start:].strip())
    if len(parts) != count or not all(parts):
        raise InputError(f"{name}={show(text)} has {len(parts)} expressions, expected {count} "
                         "(one per field component)")
    return tuple(parts)


@dataclasses.dataclass(frozen=True)
class ContinuumScene(LinearScene):
    """A linear scene from a spatial discretisation. Subclasses give `field_names`, the default
    start fields, and `_discrete` (M, K, D and the interpolation of start fields)."""

    continuum: ClassVar[bool] = True
    field_names: ClassVar[Tuple[str, ...]] = ()
    default_u0: ClassVar[Tuple[str, ...]] = ()
    default_v0_fields: ClassVar[Tuple[str, ...]] = ()
    whole_fields: ClassVar[Tuple[str, ...]] = ("elements", "degree")

    def start_state(self, u0, v0) -> Tuple[np.ndarray, np.ndarray, Dict[str, object]]:
        """(x0, v0, notes) from the start fields' expressions (None: the defaults; u0 None:
        `default_start` where the scene has one)."""
        count = len(self.field_names)
        v = split_fields("v0", self.default_v0_fields if v0 is None else v0, count)
        v0_, _ = self.interpolate(v)
        if u0 is None and self.default_start() is not None:
            return self.default_start(), v0_, {"u0": "default", "v0": list(v)}
        u = split_fields("u0", self.default_u0 if u0 is None else u0, count)
        x0, notes = self.interpolate(u)
        return x0, v0_, {"u0": list(u), "v0": list(v), **notes}

    @classmethod
    def listing(cls) -> str:
        """What `fem-dual scenes` prints: the fields and their default start, not the dofs."""
        defaults = cls()
        params = ", ".join(f"{k}={v}" for k, v in defaults.parameters().items()
                           if k not in ("A", "B", "weights"))
        start = cls.default_start_text or ", ".join(cls.default_u0)  # (no mesh built)
        return (f"{cls.name}: {cls.summary}\n  fields ({', '.join(cls.field_names)}): n={defaults.n}"
                f" free dofs  T={cls.default_T:g}  --u0 default: {start}  --v0 default: "
                f"{', '.join(cls.default_v0_fields)}\n  parameters: {params}")

    default_start_text: ClassVar[str] = ""

    def default_start(self) -> Optional[np.ndarray]:
        """The free dofs of the default start field computed in the discrete space (None:
        `default_u0`'s expressions)."""
        return None

    def interpolate(self, texts: Sequence[str]) -> Tuple[np.ndarray, Dict[str, object]]:
        """(the state vector of the fields `texts`, notes for the JSON)."""
        raise NotImplementedError

    @property
    def default_x0(self):  # type: ignore[override]
        return tuple(self.start_state(None, None)[0])

    @property
    def default_v0(self):  # type: ignore[override]
        return tuple(self.start_state(None, None)[1])


@dataclasses.dataclass(frozen=True)
class Beck(ContinuumScene):
    """Beck's column: EI, rhoA, kGA, L, tip follower load P, `elements` cells of Lagrange
    `degree` (w and theta)."""

    name: ClassVar[str] = "beck"
    default_T: ClassVar[float] = 2.0
    summary: ClassVar[str] = ("Beck's column: a Timoshenko beam on a DOLFINx interval mesh under "
                              "a tip follower load (flutter at P = 20.05 EI/L^2)")
    size_field: ClassVar[str] = "elements"
    field_names: ClassVar[Tuple[str, ...]] = ("w", "theta")
    default_v0_fields: ClassVar[Tuple[str, ...]] = ("0", "0")
    default_start_text: ClassVar[str] = ("the static deflection under a uniform load, "
                                         "tip 0.01 L")

    EI: float = 1.0
    rhoA: float = 1.0
    kGA: float = 1.0e7
    L: float = 1.0
    P: float = 10.0
    elements: int = 50
    degree: int = 2

    @property
    def n(self) -> int:  # type: ignore[override]
        return int(self.elements) * int(self.degree)

    def validate(self) -> None:
        for name in ("EI", "rhoA", "kGA", "L"):
            require_positive(self, name)
        if not 1 <= self.degree <= 4:
            raise InputError(f"degree={show(self.degree)} must be from 1 to 4")
        super().validate()

    @functools.cached_property
    def _column(self):
        """(BeckColumn, CondensedBeck) on this rank alone (the beam is one-dimensional)."""
        from mpi4py import MPI

        from fem_dual.continua.beck import BeckColumn, BeckParameters
        from fem_dual.continua.condense import condense_rotation

        params = BeckParameters(EI=self.EI, rhoA=self.rhoA, kGA=self.kGA, L=self.L, P=self.P,
                                elements=int(self.elements), degree=int(self.degree))
        column = BeckColumn(params, MPI.COMM_SELF)  # (one-dimensional: dense on every rank)
        return column, condense_rotation(column)

    @property
    def condensed(self):
        return self._column[1]

    def mass_matrix(self) -> np.ndarray:
        return self.condensed.M

    def stiffness_matrix(self) -> np.ndarray:
        return self.condensed.stiffness(self.P)

    def energy_stiffness(self) -> np.ndarray:
        """The elastic stiffness K_c: positive definite under any load."""
        return self.condensed.K_el

    def interpolate(self, texts: Sequence[str]) -> Tuple[np.ndarray, Dict[str, object]]:
        """The elastic-energy projection of the fields (w, theta) onto the discrete space:
        K_el u = k_el(u_field, .), so that the modes the mesh resolves poorly carry what the
        field's energy puts in them, not the interpolation's residue (interpolating the static
        deflection left 1e-4 of the state in the highest mode, omega = 1.2e6; the projection
        3e-6)."""
        column, condensed = self._column
        full = _energy_projection(column, list(texts), {"L": self.L})
        w = full[condensed.w_index]
        theta = full[condensed.theta_index]
        follows = condensed.theta_map @ w
        gap = float(np.abs(theta - follows).max() / max(np.abs(follows).max(), 1e-300))
        return w, {"theta0_gap": gap if np.abs(follows).max() > 0 else
                   float(np.abs(theta).max())}

    def default_start(self) -> Optional[np.ndarray]:
        """The discrete static deflection under a uniform transverse load (K_el w = the load's
        vector), scaled to a tip deflection of 0.01 L: the modes carry what a load puts in
        them, decaying with frequency, down to round-off in the fastest ones (the energy
        projection of the continuum's deflection left 1.6e-13 in each of the fastest modes,
        a velocity of 2e-7 at omega = 1.2e6)."""
        condensed = self.condensed
        w = np.linalg.solve(condensed.K_el, condensed.M @ np.ones(self.n))
        return 0.01 * self.L * w / np.abs(w).max()

    def theta(self, w: np.ndarray) -> np.ndarray:
        """The rotation's free dofs that follow the deflection's w."""
        return self.condensed.theta_map @ w


def _energy_projection(column, texts: Sequence[str],
                       parameters: Dict[str, float]) -> np.ndarray:
    """The free vector u with K_el u = k_el(field, .), field given by its expressions."""
    import ufl
    from dolfinx.fem import petsc as fem_petsc

    from fem_dual.continua.dofs import gather_csr
    from fem_dual.continua.initial import field_expression
    from fem_dual.continua.system import compile_form

    parts = [field_expression(t, column.msh, parameters) for t in texts]
    if all(isinstance(p, float) for p in parts):  # constants: interpolated exactly
        return column.system.interpolate(texts, parameters)
    field = ufl.as_vector(parts)
    trial = ufl.TrialFunction(column.W)
    rhs = ufl.replace(column.forms["k_el"], {trial: field})
    b = fem_petsc.assemble_vector(compile_form(rhs))
    values = b.array[column.system.free].copy()
    b.destroy()
    K = column.system.assemble(column.forms["k_el"])
    dense = gather_csr(K).toarray()
    K.destroy()
    return np.linalg.solve(dense, values)


for _cls in (Beck,):
    register(_cls)
