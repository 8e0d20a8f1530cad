"""A run's configuration, validated in one place before anything is computed or written."""
from __future__ import annotations

import functools
import math
import numbers
import os
from collections.abc import Mapping as abc_Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, Mapping, Optional, Sequence, Union

import numpy as np

from fem_dual.slab.base_state import stiff_at_start
from fem_dual.errors import InputError
from fem_dual.choices import BASES, RECOVERIES
from fem_dual.scenes import Scene, get_scene
from fem_dual.scenes.base import (DENSE_BUDGET, DENSE_WORDS, MAX_DOFS, STATE_MAX, parse_number,
                                  parse_vector, show)

__all__ = ["RunConfig", "Tolerance", "REFUSE_RELATIVE", "ACCEPT_GLOBAL", "ROUNDOFF_REL",
           "MAX_VERTICES", "MAX_DEGREE", "STAGING_LIMIT", "MAX_DOFS", "DENSE_BUDGET", "DENSE_WORDS"]

# Fixed slabs (no --rtol): the acceptance rule. A run whose estimated error exceeds this fraction
# of the motion's scale is refused (exit 3), and a slab whose local error would make it so is
# retried shorter.
REFUSE_RELATIVE = 1e-3

# --rtol: the estimated global error may exceed the tolerance by at most this factor before the
# run is refused (the local errors are controlled; growth of the motion can still amplify them).
ACCEPT_GLOBAL = 10.0

# The estimate does not resolve errors below this fraction of the motion's scale (round-off of
# the assembled slab systems and of the recovery): it reports at least this much.
ROUNDOFF_REL = 1e-12


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
ASSEMBLY = ("auto", "forms", "kronecker", "pointwise")
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
MAX_TIMES = 1_000_000  # --t-eval: at most this many times
MODAL_MAX_DOFS = 2000  # auto: the O(n^3) modes of larger systems cost more than they save
# Every scene has at most MAX_DOFS = 1448 dofs (fem_dual.scenes.base, the memory rule: its dense
# n x n matrices, DENSE_WORDS of them at the peak of a run, within DENSE_BUDGET = 2 GiB),
# checked before anything sized by n is allocated.
KRONECKER_MIN_DOFS = 5  # auto: linear scenes from this many dofs take the Kronecker path

Number = Union[int, float, str]


def _quoted(value) -> str:
    """The repr of a value, on one short line (a string keeps its quotes, a list its brackets)."""
    return show(repr(value))


def _whole_number(name: str, value: Number, minimum: int = 1) -> int:
    if not isinstance(value, (str, numbers.Real)) or isinstance(value, (bool, np.bool_)):
        raise InputError(f"{name}={_quoted(value)} is not a whole number")
    text = str(value).strip()
    try:
        as_float = float(text)
    except ValueError:
        raise InputError(f"{name}={_quoted(text)} is not a whole number") from None
    if not math.isfinite(as_float) or as_float != int(as_float):
        raise InputError(f"{name}={_quoted(text)} is not a whole number")
    if int(as_float) < minimum:
        raise InputError(f"{name}={_quoted(text)} must be at least {minimum}")
    return int(as_float)


def _choice(name: str, value, choices: Sequence[str]) -> str:
    """`value` if it is one of `choices` (strings), else InputError naming `name`."""
    if not isinstance(value, str) or value not in choices:
        raise InputError(f"{name}={_quoted(value)} is not one of {', '.join(choices)}")
    return value


def _within_state_max(what: str, values: np.ndarray, advice: str) -> None:
    """InputError when an entry of `values` (the start state, the force there) exceeds
    STATE_MAX, where the dual action's squares overflow (it ended as a Newton failure with an
    infinite residual, exit 3)."""
    size = float(np.abs(values).max(initial=0.0))
    if size > STATE_MAX:
        raise InputError(f"{what}: an entry of size {size:.3g} is beyond {STATE_MAX:g}, where "
                         f"the dual action's squares overflow; {advice}")


def _scene(scene, params) -> Scene:
    """The validated scene of `scene`: a name (with `params`), a Scene class (with `params`) or a
    Scene object (without), which is validated like one built from its name."""
    if isinstance(scene, str):
        return get_scene(scene).from_params(params)
    if isinstance(scene, type) and issubclass(scene, Scene):
        return scene.from_params(params)
    if isinstance(scene, Scene):
        if params is not None and (not isinstance(params, abc_Mapping) or len(params)):
            raise InputError("give parameters with the scene name, not with a Scene object")
        return scene.checked()
    raise InputError(f"scene must be a scene name or a Scene object, not {_what(scene)}")


def _what(value) -> str:
    """A value named by what it is: None, or its type and short repr."""
    return "None" if value is None else f"{type(value).__name__} {_quoted(value)}"


def _out(out) -> Optional[Path]:
    if out is None:
        return None
    if (not isinstance(out, (str, os.PathLike)) or isinstance(out, bytes)
            or isinstance(os.fspath(out), bytes)):
        raise InputError(f"out must be a path, not {_what(out)}")
    text = os.fspath(out)
    if not text.strip() or "\0" in text:
        raise InputError(f"out must be a path, not {_quoted(text)}")
    return Path(text)


def _petsc(petsc) -> Dict[str, str]:
    """PETSc options as NAME -> text; values strings, or numbers and booleans spelt for PETSc."""
    if petsc is None:
        return {}
    if not isinstance(petsc, abc_Mapping):
        raise InputError(f"petsc must be a mapping of option names to values, not "
                         f"{type(petsc).__name__}")
    options = {}
    for key, value in petsc.items():
        if not isinstance(key, str):
            raise InputError(f"petsc: option name {_quoted(key)} is not a string")
        key = key.lstrip("-")
        if not key or any(ch.isspace() for ch in key):
            raise InputError(f"PETSc option {key!r} is not an option name")
        if isinstance(value, (bool, np.bool_)):
            value = "true" if value else "false"
        elif isinstance(value, (int, np.integer)):
            value = str(int(value))
        elif isinstance(value, (float, np.floating)):
            if not math.isfinite(value):
                raise InputError(f"petsc: option {key}={value!r} is not finite")
            value = repr(float(value))
        elif not isinstance(value, str):
            raise InputError(f"petsc: option {key} has the value {_what(value)}; give a "
                             "string ('' for a flag), a number or a boolean")
        options[key] = value
    return options


def _tolerance(name: str, value: Number) -> float:
    """A tolerance: finite, positive and below 1; a relative one no finer than the error
    estimate resolves (ROUNDOFF_REL of the motion's scale)."""
    tol = parse_number(name, value)
    if not 0.0 < tol < 1.0:
        raise InputError(f"{name}={value!r} must lie between 0 and 1 (exclusive)")
    if name == "rtol" and tol < ROUNDOFF_REL:
        raise InputError(f"rtol={value!r} is below what the error estimate resolves "
                         f"({ROUNDOFF_REL:g} of the motion's scale)")
    return tol


def parse_times(text: "str | Sequence[float]", T: float) -> np.ndarray:
    """Times in [0, T] from "t1,t2,..." or "START:STOP:COUNT" (COUNT equispaced, both ends
    included), or a sequence of numbers; InputError naming the bad piece."""
    if isinstance(text, str) and ":" in text:
        parts = text.split(":")
        if len(parts) != 3:
            raise InputError(f"t-eval={text!r} is not START:STOP:COUNT")
        start, stop = parse_number("t-eval start", parts[0]), parse_number("t-eval stop", parts[1])
        count = _whole_number("t-eval count", parts[2])
        if count > MAX_TIMES:
            raise InputError(f"t-eval count={count} is too large (at most {MAX_TIMES})")
        times = np.linspace(start, stop, count)
    else:
        if isinstance(text, (abc_Mapping, set, frozenset, bytes, bool, np.bool_)):
            raise InputError(f"t-eval={_quoted(text)} is not a list of times")
        items = (text.split(",") if isinstance(text, str)
                 else list(np.ravel(np.asarray(text, dtype=object))))
        if not items:
            raise InputError("t-eval has no times")
        if len(items) > MAX_TIMES:
            raise InputError(f"t-eval has {len(items)} times (at most {MAX_TIMES})")
        times = np.array([parse_number("t-eval", item) for item in items])
    bad = times[(times < 0) | (times > T)]
    if len(bad):
        raise InputError(f"t-eval time {bad[0]!r} lies outside [0, T={T:g}]")
    return times


MIN_T = 1e-150  # shorter final times overflow 1/dt^2 in the forms (and subnormals lose digits)


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

    @functools.cached_property
    def base_state(self) -> str:  # cached: stiff_at_start differentiates the force
        """The base state in use: `base`, with auto resolved. Linear scenes with energy weights
        (stiff ones): zero, residual-free, damps what the slabs do not resolve. Nonlinear scenes
        stiff at the start: the predictor (fem_dual.slab.base_state). Otherwise the start state,
        the reference's time staging, as accurate and cheaper there."""
        if self.base != "auto":
            return self.base
        if self.scene.linear:
            return "zero" if self._stiff_linear else "start"
        return "predictor" if stiff_at_start(self.scene, self.x0, self.v0) else "start"

    @property
    def _stiff_linear(self) -> bool:
        """A linear scene with energy weights (its frequencies spread: the auto weights of the
        conditioning rule, or asked for), where the zero base state is stable for every mode."""
        return self.scene.linear and self.scene.weighting() == "energy"

    @functools.cached_property
    def modal(self) -> bool:
        """Whether the slabs are solved in modal coordinates (fem_dual.slab.modal): asked for, or
        auto for a stiff linear scene on the zero base whose modes allow it."""
        if self.coordinates != "auto":
            return self.coordinates == "modal"
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
        if self.assembly != "auto":
            return self.assembly == "pointwise"
        return auto_pointwise(self.scene, self.slab_cells, self.degree, self.petsc,
                              self.kronecker)

    @property
    def kronecker(self) -> bool:
        """Whether the slabs are solved in Kronecker form (matrix-free CG)."""
        if self.assembly != "auto":
            return self.assembly == "kronecker"
        return (self.scene.linear and self.scene.n >= KRONECKER_MIN_DOFS
                and self.recovery == "momentum" and self.base != "predictor")

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
               T: Optional[Number] = None, cells: Number = 100, degree: Number = 2,
               slabs: Number = 1, x0: Optional[Union[str, Sequence[float]]] = None,
               v0: Optional[Union[str, Sequence[float]]] = None,
               out: Optional[Union[str, Path]] = None,
               petsc: Optional[Mapping[str, str]] = None,
               max_halvings: Number = 6, superpose: str = "auto", staging: str = "auto",
               recovery: str = "momentum", assembly: str = "auto",
               rtol: Optional[Number] = None, atol: Optional[Number] = None,
               base: str = "auto", coordinates: str = "auto", reference: str = "auto",
               t_eval: Optional[Union[str, Sequence[float]]] = None,
               check_petsc: bool = True) -> "RunConfig":
        """Validate every input; raises InputError naming the first bad value.

        With `rtol` (and optionally `atol`) the slab lengths are chosen by the error estimate
        so that the estimated error stays within atol + rtol * scale (see fem_dual.integrate.estimate);
        `slabs` is then only the first guess's upper bound and must be left at 1."""
        scene = _scene(scene, params)
        T_value = scene.default_T if T is None else parse_number("T", T)
        if not T_value > 0:
            raise InputError(f"T={T!r} must be positive")
        if T_value < MIN_T:  # the forms divide by the slab length and by its square
            raise InputError(f"T={T!r} is too small (at least {MIN_T:g}: 1/T^2 must not "
                             "overflow)")
        cells_ = _whole_number("cells", cells)
        degree_ = _whole_number("degree", degree)
        slabs_ = _whole_number("slabs", slabs)
        if degree_ > MAX_DEGREE:
            raise InputError(f"degree={degree_} is too large (at most {MAX_DEGREE})")
        if cells_ * slabs_ > MAX_VERTICES:
            raise InputError(f"cells={cells_} x slabs={slabs_} = {cells_ * slabs_} time cells is "
                             f"too large (at most {MAX_VERTICES})")
        n = scene.n
        x0_ = parse_vector("x0", scene.default_x0 if x0 is None else x0, n)
        v0_ = parse_vector("v0", scene.default_v0 if v0 is None else v0, n)
        for name, value in (("x0", x0_), ("v0", v0_)):
            _within_state_max(f"{name}={','.join(map(repr, map(float, value)))}", value,
                              "rescale the coordinates")
        out_ = _out(out)
        petsc_ = _petsc(petsc)
        halvings = _whole_number("max-halvings", max_halvings, minimum=0)
        if halvings > 30:
            raise InputError(f"max-halvings={max_halvings!r} is too large (at most 30)")
        _choice("superpose", superpose, SUPERPOSE)
        if superpose == "yes" and not scene.linear:
            raise InputError(f"superpose=yes needs a linear scene ({scene.name} is nonlinear)")
        _choice("staging", staging, STAGING)
        _choice("recovery", recovery, RECOVERIES)
        _choice("assembly", assembly, ASSEMBLY)
        if assembly == "kronecker" and not scene.linear:
            raise InputError(f"assembly=kronecker needs a linear scene ({scene.name} is "
                             "nonlinear)")
        if assembly == "pointwise" and petsc_:
            raise InputError("assembly=pointwise uses no PETSc solver: the PETSc options ("
                             + ", ".join(f"{k}={v}" for k, v in petsc_.items())
                             + ") need assembly=forms")
        if assembly == "kronecker" and recovery != "momentum":
            raise InputError("assembly=kronecker recovers the motion from the momenta only "
                             f"(recovery={recovery!r})")
        _choice("base", base, ("auto",) + BASES)
        if assembly == "kronecker" and base == "predictor":
            raise InputError("base=predictor needs assembly=forms (the Kronecker form holds the "
                             "start or zero base only)")
        if base == "rk4" and scene.linear:
            raise InputError(f"base=rk4 is for nonlinear scenes ({scene.name} is linear: its "
                             "slabs are solved by superposition from the start or zero base)")
        _choice("coordinates", coordinates, COORDINATES)
        if coordinates == "modal":
            if not scene.linear:
                raise InputError(f"coordinates=modal needs a linear scene ({scene.name} is "
                                 "nonlinear)")
            from fem_dual.slab.modal import modal_obstacle

            obstacle = modal_obstacle(scene)
            if obstacle:
                raise InputError(f"coordinates=modal: {obstacle}")
        _choice("reference", reference, REFERENCES)
        times = None if t_eval is None else parse_times(t_eval, T_value)
        if not scene.linear:  # the force must be finite where the motion starts
            with np.errstate(all="ignore"):
                f0 = np.asarray(scene.force_numpy(x0_), dtype=float)
            if f0.shape != (n,) or not np.isfinite(f0).all():
                raise InputError(f"the force is not finite at x0={','.join(map(repr, x0_))} "
                                 f"(F = {','.join(map(str, np.ravel(f0)))})")
            _within_state_max(f"the force at x0={','.join(map(repr, map(float, x0_)))}", f0,
                              "rescale the force or the coordinates")
        rtol_ = None if rtol is None else _tolerance("rtol", rtol)
        if atol is not None and rtol is None:
            raise InputError(f"atol={atol!r} needs rtol (atol alone sets no tolerance)")
        atol_ = 0.0 if atol is None else _tolerance("atol", atol)
        if rtol_ is not None and slabs_ != 1:
            raise InputError(f"slabs={slabs!r} and rtol={rtol!r} contradict each other: rtol "
                             "chooses the slab lengths")
        config = cls(scene, T_value, cells_, degree_, slabs_, x0_, v0_, out_, petsc_, halvings,
                     superpose, staging, recovery, assembly, rtol_, atol_, base, coordinates,
                     reference, times)
        if check_petsc:
            config.check_petsc()
        return config

    def identity(self) -> Dict[str, Any]:
        """The options that decide a run's slabs and values: a resumed run must repeat them."""
        from fem_dual import __version__

        # rtol before slabs: a run with --rtol has slabs=1, so rtol names the difference
        return {"scene": self.scene.name, "parameters": self.scene.parameters(), "T": self.T,
                "cells": self.cells, "degree": self.degree, "rtol": self.rtol,
                "atol": self.atol, "slabs": self.slabs,
                "x0": self.x0.tolist(), "v0": self.v0.tolist(),
                "base": self.base, "coordinates": self.coordinates,
                "recovery": self.recovery, "assembly": self.assembly,
                "staging": self.staging, "superpose": self.superpose,
                "max_halvings": self.max_halvings, "petsc": dict(sorted(self.petsc.items())),
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
