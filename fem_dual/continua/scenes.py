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

import abc
import dataclasses
import functools
from typing import ClassVar, Dict, Optional, Sequence, Tuple

import numpy as np
from fem_dual.errors import InputError
from fem_dual.scenes import register
from fem_dual.scenes.base import MAX_DOFS, require_positive, show
from fem_dual.scenes.linear import LinearScene

__all__ = ["ContinuumScene", "Beck", "Cauchy2D", "split_fields"]


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
    if len(parts) != count:
        raise InputError(f"{name}={show(text)} has {len(parts)} expressions, expected {count} "
                         "(one per field component)")
    if not all(parts):
        raise InputError(f"{name}={show(text)}: expression {parts.index('') + 1} of {count} is "
                         "empty")
    return tuple(parts)


SPARSE_REFERENCE_BUDGET = 1.5e7  # dofs x radians of the fastest mode: about 10 s of reference


@dataclasses.dataclass(frozen=True)
class ContinuumScene(LinearScene):
    """A linear scene from a spatial discretisation. Subclasses give `field_names`,
    `vertex_layout`, the default start fields, M and K, and the abstract methods below (the
    start fields' vector, the dofs' coordinates, the spatial system)."""

    continuum: ClassVar[bool] = True
    field_names: ClassVar[Tuple[str, ...]] = ()
    default_u0: ClassVar[Tuple[str, ...]] = ()
    default_v0_fields: ClassVar[Tuple[str, ...]] = ()
    whole_fields: ClassVar[Tuple[str, ...]] = ("elements", "degree")

    def _free_dofs(self, n: int, degrees: range) -> int:
        """n, the free dofs of `elements` cells of `degree`; InputError naming elements or
        degree where the dense path cannot hold them."""
        if not isinstance(self.degree, (int, np.integer)) or self.degree not in degrees:
            raise InputError(f"degree={show(self.degree)} must be from {degrees.start} to "
                             f"{degrees.stop - 1}")
        limit = self.sparse_max_dofs or self.dense_limit
        if isinstance(self.elements, (int, np.integer)) and self.elements < 1:
            raise InputError(f"elements={show(self.elements)} must be at least 1")
        if isinstance(self.elements, (int, np.integer)) and n < 1:
            raise InputError(f"elements={show(self.elements)} with degree {self.degree} leaves "
                             "no free dof")
        if isinstance(self.elements, (int, np.integer)) and n > limit:
            path = "sparse" if self.sparse_max_dofs else "dense"
            raise InputError(f"elements={show(self.elements)} is too large: with degree "
                             f"{self.degree} it gives {n} free dofs, more than the {limit} of the "
                             f"{path} path of scene {self.name}")
        return n

    # -- the sparse path (scenes with sparse_max_dofs): beyond the dense limit ----------------
    sparse_max_dofs: ClassVar[int] = 0  # 0: the dense path only

    @property
    def dense_limit(self) -> int:
        return min(self.max_dofs, MAX_DOFS)

    @property
    def sparse(self) -> bool:
        """Whether the scene is beyond its dense limit: solved by the space-time backend
        (fem_dual.continua.spacetime_backend), without any dense n x n matrix."""
        return self.n > self.dense_limit

    @classmethod
    def check_size(cls, n) -> int:
        if cls.sparse_max_dofs and isinstance(n, (int, np.integer)) and n > cls.max_dofs:
            return int(n)  # (_free_dofs checked it against sparse_max_dofs)
        return super().check_size(n)

    def distributed_system(self, comm):
        """The scene's SpatialSystem assembled over `comm` (the sparse path)."""
        raise InputError(f"scene {self.name} has no sparse path")

    def serial_system(self):
        """The scene's SpatialSystem on this rank alone (the state's order)."""
        return self.spatial()[0]

    @functools.cached_property
    def _csr(self):
        """{"M", "K", "D"} of the serial system as scipy CSR matrices (gathered once)."""
        return self.serial_system().to_scipy()

    def weighting(self) -> str:
        """Energy weights on the sparse path (the space-time backend's A = Ke, B = M)."""
        return "energy" if self.sparse else super().weighting()

    def accelerations(self, x: np.ndarray, v: np.ndarray) -> np.ndarray:
        """-M^-1 (K x + D v) for each row of x and v; on the sparse path with one sparse LU of
        M (the rates of the dense output between vertices, fem_dual.integrate.dense)."""
        if not self.sparse:
            return super().accelerations(x, v)
        mats = self._csr
        rhs = np.asarray(mats["K"] @ np.asarray(x, float).T + mats["D"] @ np.asarray(v, float).T)
        return -self._mass_lu.solve(np.ascontiguousarray(rhs)).T

    @functools.cached_property
    def _mass_lu(self):
        from scipy.sparse.linalg import splu

        return splu(self._csr["M"].tocsc())

    def fastest_rate(self, x0=None, v0=None, relative: float = 1e-6, scales=None) -> float:
        """On the sparse path: the largest |lambda| of the pencil (K, M) (ARPACK), sqrt'd: the
        fastest mode of the mesh, whatever the start state excites (no modal amplitudes)."""
        if not self.sparse:
            return super().fastest_rate(x0, v0, relative, scales)
        return self._mesh_rate

    @functools.cached_property
    def _mesh_rate(self) -> float:
        from scipy.sparse.linalg import eigs

        mats = self._csr
        lam = eigs(mats["K"].tocsc(), k=1, M=mats["M"].tocsc(), which="LM",
                   return_eigenvectors=False, tol=1e-3)
        return float(np.sqrt(np.abs(lam).max()))

    def reference_affordable(self, T: float) -> bool:
        """Whether the sparse reference (fem_dual.reference.SparseFlow) over [0, T] fits its
        budget: its work grows like n times the radians the fastest mode turns (3e-7 to 7e-7 s
        each: 1 s for 3,042 dofs turning 169 radians, 22 s for 722 dofs turning 41,600), plus
        a norm estimate per call (per batch of slabs). The dense path's always does."""
        if not self.sparse:
            return True
        return self.n * self._mesh_rate * T <= SPARSE_REFERENCE_BUDGET

    def reference(self, x0, v0):
        """The exact motion of the semi-discrete system: the eigen-decomposition on the dense
        path, expm_multiply of the sparse first-order operator on the sparse one."""
        if not self.sparse:
            return super().reference(x0, v0)
        from fem_dual.reference import SparseFlow

        mats = self._csr
        return SparseFlow(mats["M"], mats["K"], mats["D"], np.asarray(x0, float),
                          np.asarray(v0, float), self._mesh_rate)

    def _dense_only(self, what: str) -> None:
        if self.sparse:
            raise InputError(f"{what} of scene {self.name} needs its dense matrices: "
                             f"{self.n} free dofs are beyond its dense limit of "
                             f"{self.dense_limit}")

    def start_state(self, u0, v0) -> Tuple[np.ndarray, np.ndarray]:
        """(x0, v0) from the start fields' expressions (None: the defaults; u0 None:
        `default_start` where the scene has one)."""
        count = len(self.field_names)
        v = split_fields("v0", self.default_v0_fields if v0 is None else v0, count)
        fields = [("v0", v, self.interpolate(v))]
        x0 = self.default_start() if u0 is None else None
        if x0 is None:
            u = split_fields("u0", self.default_u0 if u0 is None else u0, count)
            x0 = self.interpolate(u)
            fields.append(("u0", u, x0))
        for name, texts, values in fields:
            if not np.isfinite(values).all():
                raise InputError(f"{name}={', '.join(texts)!r} is not finite on the mesh")
        return x0, fields[0][2]

    def field_parameters(self) -> Dict[str, float]:
        """The scene's numbers the start fields' expressions may use by name."""
        return {k: float(v) for k, v in self.parameters().items()
                if isinstance(v, (int, float, np.integer, np.floating))
                and not isinstance(v, bool)}

    @classmethod
    def listing(cls) -> str:
        """What `fem-dual scenes` prints: the fields and their default start, not the dofs."""
        defaults = cls()
        params = ", ".join(f"{k}={v}" for k, v in defaults.parameters().items()
                           if k not in ("A", "B", "weights"))
        start = cls.default_start_text or ", ".join(cls.default_u0)  # (no mesh built)
        return (f"{cls.name}: {cls.summary}\n  fields ({', '.join(cls.field_names)}): "
                f"n={defaults.n} free dofs  T={cls.default_T:g}  --u0 default: {start}  --v0 default: "
                f"{', '.join(cls.default_v0_fields)}\n  parameters: {params}")

    default_start_text: ClassVar[str] = ""

    def system_arrays(self, x0: np.ndarray, v0: np.ndarray) -> Dict[str, np.ndarray]:
        """The semi-discrete system M x'' + D x' + K x = 0 of the free dofs, in the order of the
        JSON's x and v, with the start vectors u0, v0 (what `<scene>_system.npz` holds): dense
        M, K, D, or beyond the dense limit their CSR parts (M_data, M_indices, M_indptr,
        M_shape, ...)."""
        arrays = {"u0": np.asarray(x0, float), "v0": np.asarray(v0, float),
                  "dof_coordinates": self.dof_coordinates()}
        if not self.sparse:
            arrays.update(M=self.mass_matrix(), K=self.stiffness_matrix(),
                          D=self.damping_matrix())
            return arrays
        for name, matrix in self._csr.items():  # CSR parts
            arrays.update({f"{name}_data": matrix.data, f"{name}_indices": matrix.indices,
                           f"{name}_indptr": matrix.indptr,
                           f"{name}_shape": np.array(matrix.shape)})
        return arrays

    @abc.abstractmethod
    def dof_coordinates(self) -> np.ndarray:
        """(n, dim): where each free dof sits in space."""

    # (name, scalar components) of each field written to XDMF: Beck's w and theta, a vector
    vertex_layout: ClassVar[Tuple[Tuple[str, Tuple[int, ...]], ...]] = ()

    @abc.abstractmethod
    def spatial(self):
        """(SpatialSystem, mesh, (system.n, n) map from the state to the system's free
        vector) on this rank alone."""

    def vertex_mesh(self) -> Tuple[np.ndarray, Optional[np.ndarray]]:
        """(vertex coordinates (vertices, gdim), cells (cells, 3) of a triangle mesh, or None
        for a line whose vertices are in order along it)."""
        return self._vertex_map[0], self._vertex_map[1]

    def vertex_fields(self, x: np.ndarray, v: np.ndarray) -> Dict[str, np.ndarray]:
        """{field name: (times, vertices[, components])} of the states x, v (times, n): each
        field and its velocity (`<name>_dot`) at the mesh's vertices (what XDMF stores)."""
        out = {}
        points = len(self._vertex_map[0])
        for (name, components), rows in zip(self.vertex_layout, self._vertex_map[2]):
            for key, state in ((name, x), (f"{name}_dot", v)):
                values = np.asarray(rows @ np.asarray(state).T).T  # (times, vertices x comps)
                values = values.reshape(len(values), points, len(components))
                out[key] = values[..., 0] if len(components) == 1 else values
        return out

    @functools.cached_property
    def _vertex_map(self):
        """(points, cells or None, per field a sparse (vertices x components, n) map from the
        state to its values at the vertices; a constrained vertex has the value 0)."""
        import scipy.sparse as sps

        from fem_dual.continua.dofs import dof_keys

        system, msh, full = self.spatial()
        gdim = msh.geometry.dim
        points = msh.geometry.x[:, :gdim]
        cells = None
        if msh.topology.dim == 1:
            points = points[np.argsort(points[:, 0])]
        else:
            cells = msh.geometry.dofmap.array.reshape(-1, 3).astype(np.int64)
        scale = float(np.abs(points).max(initial=1.0))
        where = {}  # dof key (coordinates, component) -> free dof of the system
        for dof, key in enumerate(dof_keys(system.coordinates[:, :gdim], system.field, scale)):
            where.setdefault(key, dof)
        full = sps.identity(self.n, format="csr") if full is None else sps.csr_matrix(full)
        maps = []
        for _, components in self.vertex_layout:
            rows, dofs = [], []
            for c, component in enumerate(components):
                keys = dof_keys(points, np.full(len(points), component), scale)
                for i, key in enumerate(keys):
                    dof = where.get(key)
                    if dof is not None:
                        rows.append(i * len(components) + c)
                        dofs.append(dof)
            pick = sps.csr_matrix((np.ones(len(rows)), (rows, dofs)),
                                  shape=(len(points) * len(components), system.n))
            maps.append((pick @ full).tocsr())
        return points, cells, maps

    def default_start(self) -> Optional[np.ndarray]:
        """The free dofs of the default start field computed in the discrete space (None:
        `default_u0`'s expressions)."""
        return None

    @abc.abstractmethod
    def interpolate(self, texts: Sequence[str]) -> np.ndarray:
        """The state vector of the fields `texts` (one expression per component)."""

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
    vertex_layout: ClassVar[Tuple[Tuple[str, Tuple[int, ...]], ...]] = (("w", (0,)),
                                                                        ("theta", (1,)))
    default_v0_fields: ClassVar[Tuple[str, ...]] = ("0", "0")
    default_start_text: ClassVar[str] = ("the static deflection under a uniform load, "
                                         "tip 0.01 L")
    # `fem-dual flutter beck` without --param elements: the eigenvalue load at 100 P2 elements
    # is 20.050926 (2.8e-5 below Beck's 20.0509536; 50 elements: 20.05116, 2.1e-4 above)
    flutter_params: ClassVar[Dict[str, str]] = {"elements": "100"}

    EI: float = 1.0
    rhoA: float = 1.0
    kGA: float = 1.0e7
    L: float = 1.0
    P: float = 10.0
    elements: int = 50
    degree: int = 2

    @property
    def n(self) -> int:  # type: ignore[override]
        return self._free_dofs(int(self.elements) * int(self.degree), range(1, 5))

    def validate(self) -> None:
        for name in ("EI", "rhoA", "kGA", "L"):
            require_positive(self, name)  # (elements and degree: `n`, checked first)
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
        try:
            return column, condense_rotation(column)
        except np.linalg.LinAlgError:
            raise InputError(f"EI={show(self.EI)}, kGA={show(self.kGA)}, L={show(self.L)}: the "
                             "beam's stiffness is not positive definite in float64 (scales "
                             "too far apart)") from None

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

    def interpolate(self, texts: Sequence[str]) -> np.ndarray:
        """The deflection's part of the elastic-energy projection of the fields (w, theta) onto
        the discrete space, K_el u = k_el(u_field, .), so that the modes the mesh resolves
        poorly carry what the field's energy puts in them, not the interpolation's residue
        (interpolating the static deflection left 1e-4 of the state in the highest mode,
        omega = 1.2e6; the projection 3e-6). Theta follows w."""
        column, condensed = self._column
        return _energy_projection(column, list(texts), self.field_parameters())[
            condensed.w_index]

    def default_start(self) -> Optional[np.ndarray]:
        """The discrete static deflection under a uniform transverse load (K_el w = the load's
        vector), scaled to a tip deflection of 0.01 L: the modes carry what a load puts in
        them, decaying with frequency, down to round-off in the fastest ones (the energy
        projection of the continuum's deflection left 1.6e-13 in each of the fastest modes,
        a velocity of 2e-7 at omega = 1.2e6)."""
        condensed = self.condensed
        w = np.linalg.solve(condensed.K_el, condensed.M @ np.ones(self.n))
        return 0.01 * self.L * w / np.abs(w).max()

    def dof_coordinates(self) -> np.ndarray:
        """(n, 1): x of each free w dof."""
        column, condensed = self._column
        return np.asarray(column.system.coordinates[condensed.w_index][:, :1], float)

    def spatial(self):
        column, condensed = self._column
        full = np.zeros((column.system.n, self.n))  # (w, theta = G w) from w
        full[condensed.w_index] = np.eye(self.n)
        full[condensed.theta_index] = condensed.theta_map
        return column.system, column.msh, full


def _energy_projection(column, texts: Sequence[str],
                       parameters: Dict[str, float]) -> np.ndarray:
    """The free vector u with K_el u = k_el(field, .), field given by its expressions."""
    import ufl
    from dolfinx.fem import petsc as fem_petsc

    from fem_dual.continua.dofs import gather_csr
    from fem_dual.continua.initial import field_expression, jit_input
    from fem_dual.continua.system import compile_form

    parts = [field_expression(t, column.msh, parameters) for t in texts]
    if all(isinstance(p, float) for p in parts):  # constants: interpolated exactly
        return column.system.interpolate(texts, parameters)
    field = ufl.as_vector(parts)
    # (the form's own trial function: one made anew on column.W need not compare equal to it,
    # and a replace that finds nothing left a bilinear form, whose element matrices
    # assemble_vector wrote past the vector's element buffers)
    trial = next(a for a in ufl.algorithms.extract_arguments(column.forms["k_el"])
                 if a.number() == 1)
    rhs = ufl.replace(column.forms["k_el"], {trial: field})
    if len(ufl.algorithms.extract_arguments(rhs)) != 1:
        raise RuntimeError("the energy projection's right-hand side is not a linear form")
    b = fem_petsc.assemble_vector(jit_input(f"u0={', '.join(texts)!r}",
                                            lambda: compile_form(rhs)))
    values = b.array[column.system.free].copy()
    b.destroy()
    K = column.system.assemble(column.forms["k_el"])
    dense = gather_csr(K).toarray()
    K.destroy()
    return np.linalg.solve(dense, values)


@dataclasses.dataclass(frozen=True)
class Cauchy2D(ContinuumScene):
    """Plane-strain Cauchy elasticity on the unit square, clamped on its boundary: Lame lam, mu,
    the non-symmetric modulus delta, density rho; `elements` per side of Lagrange `degree`."""

    name: ClassVar[str] = "cauchy2d"
    default_T: ClassVar[float] = 1.0
    summary: ClassVar[str] = ("Cauchy elasticity without major symmetry (no strain energy) on "
                              "the clamped unit square, plane strain, DOLFINx triangles")
    size_field: ClassVar[str] = "elements"
    max_dofs: ClassVar[int] = 512  # dense: 450 free dofs (16 P1 elements a side) took 45 s
    sparse_max_dofs: ClassVar[int] = 4_000_000  # beyond max_dofs: the space-time backend
    field_names: ClassVar[Tuple[str, ...]] = ("u1", "u2")
    vertex_layout: ClassVar[Tuple[Tuple[str, Tuple[int, ...]], ...]] = (("u", (0, 1)),)
    default_u0: ClassVar[Tuple[str, ...]] = ("0.01*sin(pi*x)*sin(pi*y)",
                                             "0.01*sin(pi*x)*sin(2*pi*y)")
    default_v0_fields: ClassVar[Tuple[str, ...]] = ("0", "0")

    lam: float = 1.0
    mu: float = 1.0
    delta: float = 0.5
    rho: float = 1.0
    elements: int = 8
    degree: int = 1

    @property
    def n(self) -> int:  # type: ignore[override]
        k = int(self.elements) * int(self.degree)
        # the interior Lagrange nodes, two components
        return self._free_dofs(2 * max(k - 1, 0) ** 2, range(1, 4))

    def validate(self) -> None:
        for name in ("mu", "rho"):
            require_positive(self, name)
        if not self.lam + self.mu > 0:
            raise InputError(f"lam={show(self.lam)} must exceed -mu={show(-self.mu)} (a "
                             "positive symmetric part of C)")
        if not abs(self.delta) <= self.lam + self.mu:
            raise InputError(f"delta={show(self.delta)}: beyond |delta| <= lam + mu = "
                             f"{show(self.lam + self.mu)} the spectrum of the clamped square is "
                             "not real (it flutters): not a motion to follow in time here")
        if not self.sparse:  # (the sparse path holds no dense matrix to check)
            super().validate()

    def _body_parameters(self):
        from fem_dual.continua.cauchy import CauchyParameters

        return CauchyParameters(lam=self.lam, mu=self.mu, delta=self.delta, rho=self.rho,
                                elements=int(self.elements), degree=int(self.degree))

    @functools.cached_property
    def _body(self):
        """The body on this rank alone (every rank holds it whole: the state's order, the start
        fields, the output)."""
        from mpi4py import MPI

        from fem_dual.continua.cauchy import CauchyElasticity

        return CauchyElasticity(self._body_parameters(), MPI.COMM_SELF)

    @functools.cached_property
    def _dense(self):
        self._dense_only("the dense path")
        return self._body.system.dense(limit=self.max_dofs)

    def distributed_system(self, comm):
        from fem_dual.continua.cauchy import CauchyElasticity

        body = CauchyElasticity(self._body_parameters(), comm)
        body.system.body = body  # (keeps the mesh and the constants of its forms)
        return body.system

    def mass_matrix(self) -> np.ndarray:
        return self._dense[0]

    def stiffness_matrix(self) -> np.ndarray:
        return self._dense[1]

    def energy_stiffness(self) -> np.ndarray:
        """The symmetric part of K (C_s): positive definite."""
        K = self.stiffness_matrix()
        return 0.5 * (K + K.T)

    def interpolate(self, texts: Sequence[str]) -> np.ndarray:
        """The fields interpolated at the Lagrange nodes (clamped: 0 on the boundary)."""
        return self._body.system.interpolate(list(texts), self.field_parameters())

    def spatial(self):
        body = self._body
        return body.system, body.msh, None  # (the state is the system's free vector)

    def dof_coordinates(self) -> np.ndarray:
        return np.asarray(self._body.system.coordinates[:, :2], float)


for _cls in (Beck, Cauchy2D):
    register(_cls)
