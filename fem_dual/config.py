"""A run's configuration, validated in one place before anything is computed or written."""
from __future__ import annotations

import functools
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, Mapping, Optional, Sequence, Tuple, Union

import numpy as np

from fem_dual.choices import BASES, RECOVERIES
from fem_dual.errors import InputError
from fem_dual.inputs import (MIN_T, ROUNDOFF_REL, Number, choice, output_path, parse_times,
                             petsc_options, scene_of, tolerance_value, whole_number,
                             within_state_max)
from fem_dual.scenes import Scene
from fem_dual.scenes.base import DENSE_BUDGET, DENSE_WORDS, MAX_DOFS, parse_number, parse_vector
from fem_dual.slab.base_state import stiff_at_start

__all__ = ["RunConfig", "Tolerance", "REFUSE_RELATIVE", "ACCEPT_GLOBAL", "ROUNDOFF_REL",
           "MAX_VERTICES", "MAX_DEGREE", "STAGING_LIMIT", "MAX_DOFS", "DENSE_BUDGET", "DENSE_WORDS"]

# Fixed slabs (no --rtol): the acceptance rule. A run whose estimated error exceeds this fraction
# of the motion's scale is refused (exit 3), and a slab whose local error would make it so is
# retried shorter.
REFUSE_RELATIVE = 1e-3

# --rtol: the estimated global error may exceed the tolerance by at most this factor before the
# run is refused (the local errors are controlled; growth of the motion can still amplify them).
ACCEPT_GLOBAL = 10.0

# A continuum run given neither --rtol nor --slabs takes this --rtol (with --atol, if given): a
# mesh's modes spread over decades, and slabs of one length either follow the fastest the start
# state excites or fail at the first slab (beck by default: 1 slab of 100 cells, halved six
# times, refused at t = 0 with a local error 7 times its share). As any --rtol, the run is
# refused only where its estimate exceeds ACCEPT_GLOBAL times the tolerance.
CONTINUUM_RTOL = 1e-3



@dataclass(frozen=True)
class Tolerance:
    """What the run must reach: relative and absolute tolerances, and whether the user set them
    (adaptive slab lengths) or they are the acceptance rule of fixed slabs."""

    rtol: float
    atol: float
    adaptive: bool

    @classmethod
    def fixed(cls) -> "Tolerance":
        return cls(REFUSE_RELATIVE, 0.0, False)

    @property
    def label(self) -> str:
        """The tolerance as messages name it."""
        return (f"rtol={self.rtol:g}, atol={self.atol:g}" if self.adaptive
                else f"{self.rtol:g} of the motion's scale")

    @property
    def refuse_factor(self) -> float:
        """How far the weighted global estimate may exceed 1 before the run is refused."""
        return ACCEPT_GLOBAL if self.adaptive else 1.0


MAX_VERTICES = 20_000_000  # over the whole run: the vertex arrays of the JSON must fit in memory
SUPERPOSE = ("auto", "yes", "no")
MAX_DEGREE = 10  # equispaced Lagrange bases beyond this are too ill-conditioned to be useful
# The conditioning rule: the slab matrix's condition number grows like (cells * degree^2)^2 and
# amplifies the round-off of its assembly into the recovered state (measured in README, "Where
# to trust it"). With staging on, a slab with cells * degree^2 above this limit is solved as the
# fewest equal sub-slabs that satisfy it; the total number of time cells stays the same.
STAGING_LIMIT = 800
STAGING = ("auto", "off")
ASSEMBLY = ("auto", "forms", "kronecker", "pointwise", "spacetime")
# Auto assembly is pointwise up to this many dual unknowns per solved slab: its banded storage
# and index arrays grow with the slab (a 1.6-million-dof Ziegler slab would take gigabytes,
# which PETSc's sparse LU on the forms does not need).
POINTWISE_MAX_DOFS = 20_000


def auto_pointwise(scene, cells: int, degree: int, petsc: Optional[Mapping[str, str]],
                   kronecker: bool) -> bool:
    """Whether auto assembly takes the pointwise path: not in Kronecker form, a slab of at most
    POINTWISE_MAX_DOFS dual unknowns (`cells` cells of degree `degree`, 2n dual fields), and no
    PETSc options for the slab solver (--petsc-option, or under its prefix in PETSC_OPTIONS),
    which need the PETSc KSP or SNES on the forms."""
    if kronecker or (cells * degree + 1) * 2 * scene.n > POINTWISE_MAX_DOFS:
        return False
    from fem_dual.petsc_check import solver_prefix, user_options

    return not user_options(solver_prefix(scene.name), petsc)
COORDINATES = ("auto", "physical", "modal")
REFERENCES = ("auto", "none")
MODAL_MAX_DOFS = 2000  # auto: the O(n^3) modes of larger systems cost more than they save
# Every scene has at most MAX_DOFS = 1448 dofs (fem_dual.scenes.base, the memory rule: its dense
# n x n matrices, DENSE_WORDS of them at the peak of a run, within DENSE_BUDGET = 2 GiB),
# checked before anything sized by n is allocated.
KRONECKER_MIN_DOFS = 5  # auto: linear scenes from this many dofs take the Kronecker path

























@dataclass(frozen=True)
class RunConfig:
    """Everything a run needs. Build it with `RunConfig.create`, which validates."""

    scene: Scene
    T: float
    cells: int
    degree: int
    slabs: int
    x0: np.ndarray
    v0: np.ndarray
    out: Optional[Path] = None
    petsc: Dict[str, str] = field(default_factory=dict)
    max_halvings: int = 6
    superpose: str = "auto"  # linear scenes: slabs by superposition (auto: when slabs > 2n)
    staging: str = "auto"  # auto: split slabs whose cells * degree^2 > STAGING_LIMIT
    recovery: str = "momentum"  # primal state from the momenta of L_d, or "dtp" (the DtP map)
    assembly: str = "auto"  # linear scenes: UFL forms + LU, or Kronecker sums + CG
    rtol: Optional[float] = None  # tolerance-driven slab lengths (None: fixed slabs)
    atol: float = 0.0
    base: str = "auto"  # H's base state per slab: start, zero, auto (see base_state)
    coordinates: str = "auto"  # linear scenes: physical, modal, auto (see modal)
    reference: str = "auto"  # auto: the scene's reference; none: skip it (error is null)
    t_eval: Optional[np.ndarray] = None  # extra output times (dense output, fem_dual.integrate.dense)
    # --rtol: a run predicted to take more slabs stops (exit 3); None: the default budget
    # (fem_dual.integrate.budget: 5000 slabs, or time for linear slabs taken in chunks)
    max_slabs: Optional[int] = None
    rtol_given: bool = True  # False: rtol is the default of the scene kind (CONTINUUM_RTOL)
    # what `create` took (timings.setup_s; a copy by dataclasses.replace keeps it)
    setup_s: float = field(default=0.0, compare=False)

    @functools.cached_property
    def base_state(self) -> str:  # cached: stiff_at_start differentiates the force
        """The base state in use: `base`, with auto resolved (`base_choice`). Linear scenes with
        energy weights (stiff ones): zero, residual-free, damps what the slabs do not resolve;
        other linear scenes: the start state (the reference's time staging). Nonlinear scenes
        stiff at the start: the predictor (fem_dual.slab.base_state); others: with --rtol rk4,
        near the motion, so that Newton converges on long slabs and the dual correction is
        small; on fixed slabs the start state."""
        return self.base_choice[0]

    @functools.cached_property
    def base_choice(self) -> Tuple[str, str]:
        """(the base state in use, why): `base`, or auto resolved from the problem."""
        if self.base != "auto":
            return self.base, "asked for (--base)"
        if self.scene.linear:
            if self._stiff_linear:
                return "zero", ("auto: a stiff linear scene (energy weights): the zero base "
                                "damps the modes the slabs do not resolve")
            return "start", "auto: a linear scene that is not stiff"
        if stiff_at_start(self.scene, self.x0, self.v0):
            return "predictor", ("auto: stiff at the start (a fast mode of the linearised "
                                 "force beyond the motion's own rate): the predictor damps it")
        if self.rtol is None:
            return "start", ("auto: fixed slabs of a motion not stiff at the start: the start "
                             "state, whose error the degree p + 1 companion sees in full")
        return "rk4", ("auto: --rtol on a motion not stiff at the start: classical Runge-Kutta "
                       "from each slab's start, which the dual correction refines, so that the "
                       "controller's slabs are long")

    @property
    def _stiff_linear(self) -> bool:
        """A linear scene with energy weights (its frequencies spread: the auto weights of the
        conditioning rule, or asked for), where the zero base state is stable for every mode."""
        return (self.scene.linear and not self.scene.sparse
                and self.scene.weighting() == "energy")

    @functools.cached_property
    def modal(self) -> bool:
        """Whether the slabs are solved in modal coordinates (fem_dual.slab.modal): asked for, or
        auto for a stiff linear scene on the zero base whose modes allow it."""
        if self.coordinates != "auto":
            return self.coordinates == "modal"
        if self.spacetime:
            return False
        from fem_dual.slab.modal import modal_obstacle

        return (self._stiff_linear and self.base_state == "zero"
                and self.scene.n <= MODAL_MAX_DOFS and modal_obstacle(self.scene) is None)

    @property
    def tolerance(self) -> Tolerance:
        """The run's tolerance: the user's --rtol/--atol (adaptive slab lengths), or the
        acceptance rule of fixed slabs."""
        if self.rtol is None:
            return Tolerance.fixed()
        return Tolerance(self.rtol, self.atol, True)

    @functools.cached_property
    def pointwise(self) -> bool:
        """Whether the slabs are assembled pointwise and solved by banded LU (linear scenes) or
        the dense Newton (nonlinear ones) of fem_dual.slab.pointwise_newton: asked for, or auto
        (`auto_pointwise`)."""
        if self.assembly != "auto" or self.spacetime:
            return self.assembly == "pointwise"
        return auto_pointwise(self.scene, self.slab_cells, self.degree, self.petsc,
                              self.kronecker)

    @property
    def kronecker(self) -> bool:
        """Whether the slabs are solved in Kronecker form (matrix-free CG)."""
        if self.assembly != "auto" or self.spacetime:
            return self.assembly == "kronecker"
        return (self.scene.linear and self.scene.n >= KRONECKER_MIN_DOFS
                and self.recovery == "momentum" and self.base != "predictor")

    @property
    def spacetime(self) -> bool:
        """Whether the slabs are solved by the sparse, distributed space-time backend
        (fem_dual.continua.spacetime_backend): asked for, or auto for a continuum beyond its
        dense limit."""
        return self.assembly == "spacetime" or (self.assembly == "auto" and self.scene.sparse)

    @property
    def uses_reference(self) -> bool:
        """Whether the run is compared with its reference: not with --reference none, nor on
        the sparse path beyond its reference's budget (fem_dual.continua.scenes)."""
        if self.reference == "none":
            return False
        return not self.scene.sparse or self.scene.reference_affordable(self.T)

    @property
    def stages(self) -> int:
        """Sub-slabs per requested slab under the conditioning rule (1 with staging off)."""
        if self.staging == "off":
            return 1
        return max(1, math.ceil(self.cells * self.degree ** 2 / STAGING_LIMIT))

    @property
    def slab_cells(self) -> int:
        """Time cells per solved slab."""
        return math.ceil(self.cells / self.stages)

    @property
    def slab_count(self) -> int:
        """Number of solved slabs (requested slabs times stages)."""
        return self.slabs * self.stages

    @classmethod
    def create(cls, scene: Union[str, Scene], params: Optional[Mapping[str, object]] = None, *,
               T: Optional[Number] = None, cells: Optional[Number] = None,
               degree: Optional[Number] = None,
               slabs: Optional[Number] = None, x0: Optional[Union[str, Sequence[float]]] = None,
               v0: Optional[Union[str, Sequence[float]]] = None,
               out: Optional[Union[str, Path]] = None,
               petsc: Optional[Mapping[str, str]] = None,
               max_halvings: Number = 6, superpose: str = "auto", staging: str = "auto",
               recovery: str = "momentum", assembly: str = "auto",
               rtol: Optional[Number] = None, atol: Optional[Number] = None,
               base: str = "auto", coordinates: str = "auto", reference: str = "auto",
               t_eval: Optional[Union[str, Sequence[float]]] = None,
               max_slabs: Optional[Number] = None, u0: Optional[Union[str, Sequence[str]]] = None,
               check_petsc: bool = True) -> "RunConfig":
        """Validate every input; raises InputError naming the first bad value.

        With `rtol` (and optionally `atol`) the slab lengths are chosen by the error estimate
        so that the estimated error stays within atol + rtol * scale (see
        fem_dual.integrate.estimate); `slabs` must then be left out or 1. A continuum scene
        given neither takes rtol = CONTINUUM_RTOL; others take one slab. `cells` and `degree`
        left out are the defaults of the run's kind (`default_discretisation`)."""
        tic = time.perf_counter()
        scene = scene_of(scene, params)
        T_value = _horizon(scene, T)
        rtol_value = None if rtol is None else tolerance_value("rtol", rtol)
        rtol_given = not (rtol is None and slabs is None and scene.continuum)
        if not rtol_given:
            rtol_value = CONTINUUM_RTOL
        slabs = 1 if slabs is None else slabs
        cells, degree = default_discretisation(rtol_value, cells, degree)
        cells_, degree_, slabs_ = _discretisation(cells, degree, slabs)
        x0_, v0_ = _start_state(scene, x0, v0, u0)
        out_, petsc_ = output_path(out), petsc_options(petsc)
        halvings = whole_number("max-halvings", max_halvings, minimum=0)
        if halvings > 30:
            raise InputError(f"max-halvings={max_halvings!r} is too large (at most 30)")
        budget = None if max_slabs is None else whole_number("max-slabs", max_slabs, minimum=1)
        _check_choices(scene, petsc_, superpose, staging, recovery, assembly, base, coordinates,
                       reference)
        times = None if t_eval is None else parse_times(t_eval, T_value)
        if not scene.linear:
            _force_at_start(scene, x0_)
        rtol_, atol_ = _tolerances(rtol_value, atol, slabs, slabs_)
        config = cls(scene, T_value, cells_, degree_, slabs_, x0_, v0_, out_, petsc_, halvings,
                     superpose, staging, recovery, assembly, rtol_, atol_, base, coordinates,
                     reference, times, budget, rtol_given)
        if check_petsc:
            config.check_petsc()
        object.__setattr__(config, "setup_s", time.perf_counter() - tic)  # (frozen)
        return config

    def identity(self) -> Dict[str, Any]:
        """The options that decide a run's slabs and values: a resumed run must repeat them
        (not --max-slabs: a run stopped by its budget resumes with a larger one)."""
        from fem_dual import __version__

        # rtol before slabs: a run with --rtol has slabs=1, so rtol names the difference
        return {"scene": self.scene.name, "parameters": self.scene.parameters(), "T": self.T,
                "cells": self.cells, "degree": self.degree, "rtol": self.rtol,
                "atol": self.atol, "slabs": self.slabs,
                "x0": self.x0.tolist(), "v0": self.v0.tolist(),
                "base": self.base, "coordinates": self.coordinates,
                "recovery": self.recovery, "assembly": self.assembly,
                "staging": self.staging, "superpose": self.superpose,
                "max_halvings": self.max_halvings,
                "petsc": dict(sorted(self.petsc.items())),
                "version": __version__}

    def check_petsc(self) -> None:
        """The PETSc options (--petsc-option, PETSC_OPTIONS) are input too: InputError naming a
        bad one. Imports PETSc (create does it last; `check_petsc=False` leaves it to the
        caller, whose own checks then answer without PETSc)."""
        from fem_dual.petsc_check import check_user_options, solver_prefix, user_options

        scene = self.scene
        path = ("kronecker" if self.kronecker else "forms") if scene.linear else "snes"
        prefix = solver_prefix(scene.name)
        given = user_options(prefix, self.petsc) if self.assembly == "pointwise" else None
        if given:
            given = ", ".join(f"-{prefix}{k}" for k in given)
            raise InputError(f"assembly=pointwise uses no PETSc solver: the PETSc options "
                             f"({given}, from PETSC_OPTIONS) need assembly=forms")
        check_user_options(prefix, self.petsc, path)


FIXED_CELLS, FIXED_DEGREE = 100, 2  # fixed slabs: cells per slab and degree by default
ADAPTIVE_CELLS = 4  # --rtol: cells per slab by default (the controller chooses the lengths)


def adaptive_degree(rtol: float) -> int:
    """The degree --rtol takes by default: the order 2p of the vertex values grows with the
    digits asked, p = round(-log10(rtol) / 2) + 1 within [2, 6] (3 at 1e-4, 4 at 1e-6, 5 at
    1e-8, 6 at 1e-10): a slab then spans about as much of the motion at every tolerance, and
    the cost follows the tolerance (docs/performance.md has the measurements)."""
    return int(min(6, max(2, round(-math.log10(rtol) / 2) + 1)))


def default_discretisation(rtol: Optional[float], cells, degree) -> Tuple[Number, Number]:
    """(cells, degree) with what was left out (None) filled in: for fixed slabs FIXED_CELLS
    and FIXED_DEGREE, with --rtol ADAPTIVE_CELLS and `adaptive_degree(rtol)`."""
    if rtol is None:
        return (FIXED_CELLS if cells is None else cells,
                FIXED_DEGREE if degree is None else degree)
    return (ADAPTIVE_CELLS if cells is None else cells,
            adaptive_degree(rtol) if degree is None else degree)


def _horizon(scene: Scene, T: Optional[Number]) -> float:
    """The final time: the scene's default, or a positive number whose 1/T^2 is finite."""
    T_value = scene.default_T if T is None else parse_number("T", T)
    if not T_value > 0:
        raise InputError(f"T={T!r} must be positive")
    if T_value < MIN_T:  # the forms divide by the slab length and by its square
        raise InputError(f"T={T!r} is too small (at least {MIN_T:g}: 1/T^2 must not "
                         "overflow)")
    return T_value


def _discretisation(cells: Number, degree: Number, slabs: Number) -> Tuple[int, int, int]:
    """(cells, degree, slabs) as whole numbers within their limits."""
    cells_ = whole_number("cells", cells)
    degree_ = whole_number("degree", degree)
    slabs_ = whole_number("slabs", slabs)
    if degree_ > MAX_DEGREE:
        raise InputError(f"degree={degree_} is too large (at most {MAX_DEGREE})")
    if cells_ * slabs_ > MAX_VERTICES:
        raise InputError(f"cells={cells_} x slabs={slabs_} = {cells_ * slabs_} time cells is "
                         f"too large (at most {MAX_VERTICES})")
    return cells_, degree_, slabs_


def _start_state(scene: Scene, x0, v0, u0=None) -> Tuple[np.ndarray, np.ndarray]:
    """(x0, v0): the scene's defaults or the given vectors, within STATE_MAX; for a continuum
    scene from its start fields u0, v0 (expressions of the spatial coordinates)."""
    n = scene.n
    if scene.continuum and x0 is None:  # (x0 given: the free dofs' vector, as final.x)
        x0_, v0_ = scene.start_state(u0, v0)
    elif u0 is not None and x0 is not None:
        raise InputError("the start is given twice: u0 (fields) and x0 (the dofs' vector)")
    elif u0 is not None:
        raise InputError(f"u0 gives the start fields of a continuum scene ({scene.name} is "
                         "not one): give x0")
    else:
        x0_ = parse_vector("x0", scene.default_x0 if x0 is None else x0, n)
        v0_ = parse_vector("v0", scene.default_v0 if v0 is None else v0, n)
    for name, value in (("x0", x0_), ("v0", v0_)):
        within_state_max(f"{name}={','.join(map(repr, map(float, value)))}", value,
                         "rescale the coordinates")
    return x0_, v0_


def _check_choices(scene: Scene, petsc: Dict[str, str], superpose: str, staging: str,
                   recovery: str, assembly: str, base: str, coordinates: str,
                   reference: str) -> None:
    """Each choice is one of its values, and the choices fit the scene and each other."""
    choice("superpose", superpose, SUPERPOSE)
    if superpose == "yes" and not scene.linear:
        raise InputError(f"superpose=yes needs a linear scene ({scene.name} is nonlinear)")
    choice("staging", staging, STAGING)
    choice("recovery", recovery, RECOVERIES)
    choice("assembly", assembly, ASSEMBLY)
    if assembly == "spacetime" and not getattr(scene, "sparse_max_dofs", 0):
        raise InputError(f"assembly=spacetime needs a continuum scene with a sparse path "
                         f"({scene.name} has none)")
    if assembly == "kronecker" and not scene.linear:
        raise InputError(f"assembly=kronecker needs a linear scene ({scene.name} is "
                         "nonlinear)")
    if assembly == "pointwise" and petsc:
        raise InputError("assembly=pointwise uses no PETSc solver: the PETSc options ("
                         + ", ".join(f"{k}={v}" for k, v in petsc.items())
                         + ") need assembly=forms")
    if assembly == "kronecker" and recovery != "momentum":
        raise InputError("assembly=kronecker recovers the motion from the momenta only "
                         f"(recovery={recovery!r})")
    choice("base", base, ("auto",) + BASES)
    if assembly == "kronecker" and base == "predictor":
        raise InputError("base=predictor needs assembly=forms (the Kronecker form holds the "
                         "start or zero base only)")
    if base == "rk4" and scene.linear:
        raise InputError(f"base=rk4 is for nonlinear scenes ({scene.name} is linear: its "
                         "slabs are solved by superposition from the start or zero base)")
    choice("coordinates", coordinates, COORDINATES)
    if coordinates == "modal":
        if not scene.linear:
            raise InputError(f"coordinates=modal needs a linear scene ({scene.name} is "
                             "nonlinear)")
        from fem_dual.slab.modal import modal_obstacle

        obstacle = modal_obstacle(scene)
        if obstacle:
            raise InputError(f"coordinates=modal: {obstacle}")
    choice("reference", reference, REFERENCES)


def _force_at_start(scene: Scene, x0: np.ndarray) -> None:
    """A nonlinear scene's force must be finite, and within STATE_MAX, where the motion
    starts."""
    with np.errstate(all="ignore"):
        f0 = np.asarray(scene.force_numpy(x0), dtype=float)
    if f0.shape != (scene.n,) or not np.isfinite(f0).all():
        raise InputError(f"the force is not finite at x0={','.join(map(repr, x0))} "
                         f"(F = {','.join(map(str, np.ravel(f0)))})")
    within_state_max(f"the force at x0={','.join(map(repr, map(float, x0)))}", f0,
                     "rescale the force or the coordinates")


def _tolerances(rtol: Optional[float], atol: Optional[Number], slabs: Number,
                slab_count: int) -> Tuple[Optional[float], float]:
    """(rtol, atol): rtol (checked already) sets the tolerance (atol only beside it) and
    chooses the lengths (slabs left at 1)."""
    if atol is not None and rtol is None:
        raise InputError(f"atol={atol!r} needs rtol (atol alone sets no tolerance)")
    atol_ = 0.0 if atol is None else tolerance_value("atol", atol)
    if rtol is not None and slab_count != 1:
        raise InputError(f"slabs={slabs!r} and rtol={rtol!r} contradict each other: rtol "
                         "chooses the slab lengths")
    return rtol, atol_
