"""What every scene is: a frozen parameter dataclass with defaults, parsing and validation, and the
declaration of what it needs (its forms module, linear or nonlinear solve, its reference).

Fields are floats unless their metadata says `kind="matrix"`: an n x n matrix given on the
command line as `NAME=a11,a12,...` (row-major) or `NAME=s` for s times the identity; "per_link":
one value or one per link; "choice": one of a few names.
"""
from __future__ import annotations

import abc
import dataclasses
import math
from types import ModuleType
from typing import ClassVar, Dict, Mapping, Optional, Tuple

import numpy as np

from fem_dual.errors import InputError

__all__ = ["Scene", "matrix_field", "per_link_field", "choice_field", "parse_number",
           "parse_vector", "require_spd", "require_positive", "is_spd"]


def matrix_field(doc: str):
    """A dataclass field holding an optional n x n matrix (None selects the scene's default)."""
    return dataclasses.field(default=None, metadata={"kind": "matrix", "doc": doc})


def parse_number(name: str, text: "str | float") -> float:
    """A finite float, or InputError naming `name` and the bad text."""
    if isinstance(text, bool):
        raise InputError(f"{name}={text!r} is not a number")
    try:
        value = float(text)
    except (TypeError, ValueError):
        raise InputError(f"{name}={text!r} is not a number") from None
    if not math.isfinite(value):
        raise InputError(f"{name}={text!r} is not finite")
    return value


def parse_vector(name: str, text: "str | tuple | list", n: int) -> np.ndarray:
    """A finite vector of exactly n entries, from 'a,b,..' or a sequence."""
    if isinstance(text, str):
        items = text.split(",")
    else:
        try:
            items = list(text)
        except TypeError:  # a scalar
            items = [text]
    if len(items) != n:
        raise InputError(f"{name}={_show(text)} has {len(items)} entries, expected {n}")
    return np.array([parse_number(name, item) for item in items])


def _show(text) -> str:
    if isinstance(text, str):
        return text
    try:
        return ",".join(str(t) for t in text)
    except TypeError:
        return str(text)


def _parse_matrix(name: str, text: "str | float | np.ndarray | tuple", n: int) -> np.ndarray:
    if isinstance(text, np.ndarray):
        items = list(text.ravel())
    elif isinstance(text, str):
        items = text.split(",")
    elif isinstance(text, (tuple, list)):
        items = list(np.ravel(np.asarray(text, dtype=object)))
    else:
        items = [text]
    values = [parse_number(name, item) for item in items]
    if len(values) == 1:
        return values[0] * np.eye(n)
    if len(values) != n * n:
        raise InputError(f"{name}={_show(text)} has {len(values)} entries, expected 1 or {n * n}")
    return np.array(values).reshape(n, n)


def per_link_field(default: float, doc: str):
    """A dataclass field holding one value, or one value per link ('a' or 'a1,a2,...')."""
    return dataclasses.field(default=default, metadata={"kind": "per_link", "doc": doc})


def choice_field(default: str, choices: Tuple[str, ...], doc: str):
    """A dataclass field holding one of `choices` (a name, not a number)."""
    return dataclasses.field(default=default, metadata={"kind": "choice", "choices": choices,
                                                        "doc": doc})


def _parse_choice(name: str, text, choices: Tuple[str, ...]) -> str:
    value = str(text).strip()
    if value not in choices:
        raise InputError(f"{name}={_show(text)} is not one of {', '.join(choices)}")
    return value


def _parse_per_link(name: str, text, n: int) -> list:
    items = text.split(",") if isinstance(text, str) else list(np.ravel([text]))
    values = [parse_number(name, item) for item in items]
    if len(values) not in (1, n):
        raise InputError(f"{name}={_show(text)} has {len(values)} entries, expected 1 or {n}")
    return values * n if len(values) == 1 else values


def _whole(name: str, value: float) -> int:
    if value != int(value):
        raise InputError(f"{name}={value!r} is not a whole number")
    return int(value)


def require_positive(scene: "Scene", *names: str) -> None:
    for name in names:
        value = getattr(scene, name)
        if not value > 0:
            raise InputError(f"{name}={value!r} must be positive")


def is_spd(matrix: np.ndarray) -> bool:
    scale = max(np.abs(matrix).max(), 1e-300)
    return (np.abs(matrix - matrix.T).max() <= 1e-12 * scale
            and np.linalg.eigvalsh(0.5 * (matrix + matrix.T)).min() > 0)


def require_spd(name: str, matrix: np.ndarray) -> None:
    """InputError unless `matrix` is symmetric positive definite."""
    scale = max(np.abs(matrix).max(), 1e-300)
    if np.abs(matrix - matrix.T).max() > 1e-12 * scale:
        raise InputError(f"{name}={_show(list(matrix.ravel()))} is not symmetric")
    if np.linalg.eigvalsh(matrix).min() <= 0:
        raise InputError(f"{name}={_show(list(matrix.ravel()))} is not positive definite")


@dataclasses.dataclass(frozen=True)
class Scene(abc.ABC):
    """Base of all scenes. Subclasses are frozen dataclasses of their parameters."""

    name: ClassVar[str]
    n: ClassVar[int]  # number of primal degrees of freedom
    linear: ClassVar[bool]  # quadratic action: one KSP solve per slab, no Newton
    forms: ClassVar[ModuleType]  # force, aux_potential, dtp_map, constant_names
    default_T: ClassVar[float]
    default_x0: ClassVar[Tuple[float, ...]]
    default_v0: ClassVar[Tuple[float, ...]]
    summary: ClassVar[str] = ""
    solver_defaults: ClassVar[Dict[str, str]] = {}  # PETSc options this scene needs by default

    # -- construction -------------------------------------------------------------------------
    @classmethod
    def parameter_names(cls) -> Tuple[str, ...]:
        return tuple(f.name for f in dataclasses.fields(cls))

    @classmethod
    def from_params(cls, params: Optional[Mapping[str, object]] = None) -> "Scene":
        """Build and validate a scene from NAME -> value (strings from the command line, or numbers).

        Raises:
            InputError: an unknown name, a value that is not a finite number, or a value the scene
                rejects in `validate`.
        """
        params = dict(params or {})
        known = {f.name: f for f in dataclasses.fields(cls)}
        for key in params:
            if key not in known:
                raise InputError(f"unknown parameter {key!r} for scene {cls.name} "
                                 f"(known: {', '.join(known)})")
        kind = {key: known[key].metadata.get("kind", "float") for key in params}
        values: Dict[str, object] = {key: parse_number(key, text) for key, text in params.items()
                                     if kind[key] == "float"}
        for size in ("links", "dofs"):  # sizes: everything sized by n depends on them
            if size in values:
                values[size] = _whole(size, values[size])
        n = cls(**values).n  # scalar fields first: n may depend on them (a column's links)
        for key, text in params.items():
            if kind[key] == "matrix":
                values[key] = tuple(map(tuple, _parse_matrix(key, text, n)))
            elif kind[key] == "per_link":
                values[key] = tuple(_parse_per_link(key, text, n))
            elif kind[key] == "choice":
                values[key] = _parse_choice(key, text, known[key].metadata["choices"])
        scene = cls(**values)
        scene.validate()
        return scene

    @classmethod
    def listing(cls) -> str:
        """What `fem-dual scenes` prints: summary, size, defaults and parameters."""
        defaults = cls()
        params = ", ".join(f"{k}={v}" for k, v in defaults.parameters().items())
        return (f"{cls.name}: {cls.summary}\n  n={defaults.n}  T={cls.default_T:g}  "
                f"x0={defaults.default_x0}  v0={defaults.default_v0}\n  parameters: {params}")

    def matrix(self, name: str, default: np.ndarray) -> np.ndarray:
        """The matrix parameter `name`, or `default` where the user gave none."""
        value = getattr(self, name)
        return np.array(default if value is None else value, dtype=float)

    # -- what a scene provides ----------------------------------------------------------------
    def validate(self) -> None:
        """Raise InputError for parameters the scene cannot use."""

    @abc.abstractmethod
    def mass_matrix(self) -> np.ndarray:
        """M, symmetric positive definite."""

    @abc.abstractmethod
    def constants(self) -> Dict[str, np.ndarray]:
        """Values of the fem.Constants its forms module uses, by name."""

    @abc.abstractmethod
    def reference(self, x0: np.ndarray, v0: np.ndarray):
        """The independent reference flow: called with increasing chunks of times t, it returns
        (x, v) at those times (see fem_dual.reference)."""

    def quadrature_degree(self, degree: int) -> int:
        """Quadrature degree of the action for dual fields of polynomial degree `degree`."""
        return 2 * degree

    def parameters(self) -> Dict[str, object]:
        """The parameter values (matrices as nested lists), for the JSON record."""
        out: Dict[str, object] = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, tuple):
                value = [list(v) if isinstance(v, tuple) else v for v in value]
            out[f.name] = value
        return out
