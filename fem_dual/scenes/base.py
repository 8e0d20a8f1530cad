"""What every scene is: a frozen parameter dataclass with defaults, parsing and validation, and the
declaration of what it needs (its forms module, linear or nonlinear solve, its reference).

Fields are floats unless their metadata says `kind="matrix"`: an n x n matrix given on the
command line as `NAME=a11,a12,...` (row-major) or `NAME=s` for s times the identity; "per_link":
one value or one per link; "choice": one of a few names.

Every scene, built from parameters (`from_params`) or handed over as an object (`checked`), is
validated before anything sized by its number of dofs n is allocated: n within the dense-matrix
budget (MAX_DOFS), then every number finite and normal (zero, or at least the smallest normal
float64: a subnormal mass or length has no finite reciprocal), then the scene's own `validate`.
"""
from __future__ import annotations

import abc
from collections.abc import Mapping as abc_Mapping
import dataclasses
import importlib
import math
import numbers
import re
from types import ModuleType
from typing import Callable, ClassVar, Dict, Mapping, Optional, Tuple

import numpy as np

from fem_dual.errors import InputError

__all__ = ["Scene", "matrix_field", "per_link_field", "choice_field", "parse_number",
           "parse_vector", "require_spd", "require_positive", "require_normal", "require_square",
           "is_spd", "show", "dense_bytes", "DENSE_BUDGET", "DENSE_WORDS", "MAX_DOFS", "TINY"]

TINY = float(np.finfo(float).tiny)  # the smallest normal float64: below it, 1/x overflows
# The memory rule: a linear scene of n dofs holds dense n x n float64 matrices, and the dense
# parts of its run add more: M, K, D, H's weights A, B and their inverses (7), the 2n x 2n
# first-order matrix (4) and its complex eigenvectors, cached (8), the QZ of the first-order
# pencil for the reference (16 with its workspace) and of (K, M) for the modes, the modal
# basis (5), the reference's matrix exponentials (4 each, several at once). Measured with
# tracemalloc: 70 n^2 float64 at the peak of a 400-dof linear run, 126 n^2 for a 400-link column
# whose reference falls back to expm; DENSE_WORDS rounds that up. A scene whose n would need
# more than DENSE_BUDGET is refused before anything is allocated: MAX_DOFS = 1448.
DENSE_BUDGET = 2 * 1024 ** 3  # bytes
DENSE_WORDS = 128  # n x n float64 matrices a linear run holds at its peak (see above)

STATE_MAX = 1e150  # |x0|, |v0| a dual action can hold (it squares them)


class LazyForms:
    """A scene's forms module (UFL), imported when first used: listing the scenes and checking
    their parameters import no UFL (`fem-dual scenes` answers in a quarter of a second).
    `build(module)` makes the forms from the module (a user-defined force's implicit map)."""

    def __init__(self, module: str, build: Optional[Callable] = None):
        self.module, self.build = module, build
        self._value = None

    def __get__(self, obj, owner):
        if obj is None:  # dataclasses look at every annotated class attribute: not an import
            return self
        if self._value is None:
            module = importlib.import_module(self.module)
            self._value = module if self.build is None else self.build(module)
        return self._value


def implicit_forms(module):
    """forms.implicit's map from a module's force and auxiliary potential."""
    from fem_dual.forms import implicit

    return implicit.make(module.force, module.aux_potential)


def dense_bytes(n: float) -> float:
    """Bytes of the dense matrices of a scene of n dofs under the memory rule."""
    try:
        n = float(n)
    except OverflowError:  # a whole number beyond float64
        return math.inf
    return DENSE_WORDS * 8.0 * n * n  # inf, not OverflowError, for absurd n


MAX_DOFS = math.isqrt(DENSE_BUDGET // (8 * DENSE_WORDS))  # the largest n within DENSE_BUDGET


def matrix_field(doc: str):
    """A dataclass field holding an optional n x n matrix (None selects the scene's default)."""
    return dataclasses.field(default=None, metadata={"kind": "matrix", "doc": doc})


# A number as text: a plain decimal, optionally with an exponent ("1", "-0.5", "2.", ".5",
# "1e-8", "1E+3"); not Python's wider float() syntax ("1_0", "0x10", "infinity").
DECIMAL = re.compile(r"\s*[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?\s*")


def parse_number(name: str, text: "str | float") -> float:
    """A finite float, or InputError naming `name` and the bad text. Text must be a plain
    decimal number (digits, one point, an exponent)."""
    if isinstance(text, (bool, np.bool_, complex, np.complexfloating)):
        raise InputError(f"{name}={_quoted(text)} is not a number")
    if isinstance(text, str) and not DECIMAL.fullmatch(text):
        if text.strip().lower().lstrip("+-") in ("inf", "infinity", "nan"):
            raise InputError(f"{name}={_quoted(text)} is not finite")
        raise InputError(f"{name}={_quoted(text)} is not a number")
    try:
        value = float(text)
    except (TypeError, ValueError, OverflowError):
        raise InputError(f"{name}={_quoted(text)} is not a number") from None
    if not math.isfinite(value):
        raise InputError(f"{name}={_quoted(text)} is not finite")
    return value


def parse_vector(name: str, text: "str | tuple | list", n: int) -> np.ndarray:
    """A finite vector of exactly n entries, from 'a,b,..' or a sequence."""
    if isinstance(text, str):
        items = text.split(",")
    elif isinstance(text, (abc_Mapping, set, frozenset, bytes)):
        raise InputError(f"{name}={show(text)} is not a vector: give 'a,b,...' or a sequence of "
                         "numbers")
    else:
        try:
            items = list(text)
        except TypeError:  # a scalar
            items = [text]
    if len(items) != n:
        raise InputError(f"{name}={show(text)} has {len(items)} entries, expected {n}")
    return np.array([parse_number(name, item) for item in items])


def _quoted(text) -> str:
    """The repr of a value, on one short line (a string keeps its quotes, a list its brackets)."""
    return show(repr(text))


def show(text, limit: int = 60) -> str:
    """A value as it may appear in a one-line message: strings as given, sequences joined by
    commas, anything else by its repr; newlines flattened, long text cut at `limit` chars."""
    if isinstance(text, str):
        out = text
    elif isinstance(text, np.ndarray):
        out = ",".join(str(t) for t in text.ravel()[:limit])
    elif isinstance(text, (list, tuple)):
        out = ",".join(show(t, limit) for t in text[:limit])
    else:
        out = repr(text)
    out = " ".join(out.split()) if ("\n" in out or "\r" in out) else out
    return out if len(out) <= limit else out[:limit - 3] + "..."



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
        raise InputError(f"{name}={show(text)} has {len(values)} entries, expected 1 or {n * n}")
    return np.array(values).reshape(n, n)


def per_link_field(default: float, doc: str):
    """A dataclass field holding one value, or one value per link ('a' or 'a1,a2,...')."""
    return dataclasses.field(default=default, metadata={"kind": "per_link", "doc": doc})


def choice_field(default: str, choices: Tuple[str, ...], doc: str):
    """A dataclass field holding one of `choices` (a name, not a number)."""
    return dataclasses.field(default=default, metadata={"kind": "choice", "choices": choices,
                                                        "doc": doc})


def _parse_choice(name: str, text, choices: Tuple[str, ...]) -> str:
    if not isinstance(text, str):
        raise InputError(f"{name}={show(text)} is not one of {', '.join(choices)}")
    value = text.strip()
    if value not in choices:
        raise InputError(f"{name}={show(text)} is not one of {', '.join(choices)}")
    return value


def _parse_per_link(name: str, text, n: int) -> list:
    if isinstance(text, (abc_Mapping, set, frozenset, bytes)):
        raise InputError(f"{name}={show(text)} is not a number or a list of numbers")
    items = (text.split(",") if isinstance(text, str)
             else list(np.ravel(np.asarray(text, dtype=object))))
    values = [parse_number(name, item) for item in items]
    if len(values) not in (1, n):
        raise InputError(f"{name}={show(text)} has {len(values)} entries, expected 1 or {n}")
    return values * n if len(values) == 1 else values


def _whole(name: str, value: float) -> int:
    if value != int(value):
        raise InputError(f"{name}={value!r} is not a whole number")
    return int(value)


def _count(n: int) -> str:
    """A whole number for a message: in full below 1e15, else as a power of ten."""
    if abs(n) < 10 ** 15:
        return str(n)
    try:
        return f"{float(n):.3g}"
    except OverflowError:
        return f"{'-' if n < 0 else ''}10^{len(str(abs(n))) - 1}"


def _whole_value(value) -> bool:
    """Whether `value` is a whole number (an integer, or a float without a fraction; no bool)."""
    if isinstance(value, (bool, np.bool_)):
        return False
    if isinstance(value, numbers.Integral):
        return True
    return (isinstance(value, numbers.Real) and math.isfinite(value)
            and float(value) == int(value))


def require_normal(name: str, value) -> float:
    """A real number, finite, and zero or normal (|value| >= TINY): a subnormal value has no
    finite reciprocal and carries only a few bits. InputError naming `name` otherwise."""
    if (isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real)):
        raise InputError(f"{name}={_quoted(value)} is not a number")
    value = float(value)
    if not math.isfinite(value):
        raise InputError(f"{name}={value!r} is not finite")
    if value != 0.0 and abs(value) < TINY:
        raise InputError(f"{name}={value!r} is subnormal (nonzero but below {TINY:.4g}, the "
                         "smallest normal float64): its reciprocal is not finite")
    return value


def _require_entries(name: str, given, values: np.ndarray) -> None:
    """Every entry of `values` (converted from `given`) a number, finite and zero or normal."""
    flat = np.ravel(np.asarray(given, dtype=object))
    if any(isinstance(v, (bool, np.bool_, str, bytes)) for v in flat):
        raise InputError(f"{name}={show(given)} holds something that is not a number")
    if not np.isfinite(values).all():
        raise InputError(f"{name}={show(given)} is not finite")
    small = values[(values != 0) & (np.abs(values) < TINY)]
    if small.size:
        raise InputError(f"{name} has the subnormal entry {small[0]!r} (nonzero but below "
                         f"{TINY:.4g}, the smallest normal float64)")


def require_positive(scene: "Scene", *names: str) -> None:
    for name in names:
        value = require_normal(name, getattr(scene, name))
        if not value > 0:
            raise InputError(f"{name}={value!r} must be positive")


def require_square(scene: "Scene", name: str, enters: str) -> None:
    """InputError unless the square of the length `name` is finite and normal (it scales
    `enters`, which is inverted)."""
    value = float(getattr(scene, name))
    square = value * value
    if not TINY <= square <= np.finfo(float).max:
        raise InputError(f"{name}={value!r} is out of range: {name}^2 = {square!r} (it scales "
                         f"{enters}) must be finite and at least {TINY:.4g}")


# From this size a symmetric matrix is first tried by Cholesky with LAPACK's condition estimate
# (a sixth of eigvalsh's time: 4 ms against 22 ms at 450 dofs); below it, scipy is not loaded
# to check an input. A factor whose reciprocal condition is at least CLEARLY_DEFINITE shows
# a positive definite matrix (the factorisation's backward error, some n eps, lies far below
# its smallest eigenvalue); anything else is decided by the eigenvalues, as for small ones.
CHOLESKY_FROM = 64
CLEARLY_DEFINITE = 1e-10


def _clearly_definite(matrix: np.ndarray) -> bool:
    """Whether a symmetric `matrix` of CHOLESKY_FROM rows or more is certainly positive
    definite with a normal smallest eigenvalue (False: the eigenvalues decide)."""
    if len(matrix) < CHOLESKY_FROM:
        return False
    from scipy.linalg import lapack

    factor, info = lapack.dpotrf(matrix, lower=False, clean=False)
    if info != 0:
        return False
    norm = float(np.abs(matrix).sum(axis=0).max())
    rcond, info = lapack.dpocon(factor, norm)
    # (the smallest eigenvalue is at least about rcond |A|_1: normal with a margin of 1e18)
    return info == 0 and rcond >= CLEARLY_DEFINITE and rcond * norm >= 1e18 * TINY


def is_spd(matrix: np.ndarray) -> bool:
    scale = max(np.abs(matrix).max(), 1e-300)
    if not np.abs(matrix - matrix.T).max() <= 1e-12 * scale:
        return False
    symmetric = 0.5 * (matrix + matrix.T)
    return _clearly_definite(symmetric) or np.linalg.eigvalsh(symmetric).min() > 0


def require_spd(name: str, matrix: np.ndarray, inverted: bool = False,
                label: Optional[str] = None) -> None:
    """InputError unless `matrix` is finite and symmetric positive definite; `inverted` (the
    run divides by it): its smallest eigenvalue must also be normal, so that its inverse is
    finite. The message shows `label` (default NAME=entries)."""
    shown = label or f"{name}={show(matrix)}"
    if not np.isfinite(matrix).all():
        raise InputError(f"{shown} is not finite")
    scale = max(np.abs(matrix).max(), 1e-300)
    if np.abs(matrix - matrix.T).max() > 1e-12 * scale:
        raise InputError(f"{shown} is not symmetric")
    if _clearly_definite(matrix):
        return
    smallest = np.linalg.eigvalsh(matrix).min()
    if smallest <= 0:
        raise InputError(f"{shown} is not positive definite")
    if inverted and smallest < TINY:
        raise InputError(f"{shown} has the eigenvalue {smallest:.4g}, below the "
                         f"smallest normal float64 ({TINY:.4g}): its inverse is not finite")


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
    size_field: ClassVar[Optional[str]] = None  # the parameter that sets n (a column's links)
    min_dofs: ClassVar[int] = 1
    max_dofs: ClassVar[int] = MAX_DOFS  # a scene may lower it; MAX_DOFS bounds every scene
    whole_fields: ClassVar[Tuple[str, ...]] = ()  # parameters that are whole numbers
    continuum: ClassVar[bool] = False  # a spatial discretisation: start state from fields
    sparse: ClassVar[bool] = False  # no dense matrices: a continuum beyond its dense limit

    # -- construction -------------------------------------------------------------------------
    @classmethod
    def parameter_names(cls) -> Tuple[str, ...]:
        return tuple(f.name for f in dataclasses.fields(cls))

    @classmethod
    def from_params(cls, params: Optional[Mapping[str, object]] = None) -> "Scene":
        """Build and validate a scene from NAME -> value (strings from the command line, or numbers).

        The number of dofs is checked (MAX_DOFS) before any parameter sized by it is parsed.

        Raises:
            InputError: an unknown name, a value that is not a finite number, or a value the scene
                rejects in `validate`.
        """
        params = cls._params_dict(params)
        known = {f.name: f for f in dataclasses.fields(cls)}
        for key in params:
            if key not in known:
                raise InputError(f"unknown parameter {show(repr(key))} for scene {cls.name} "
                                 f"(known: {', '.join(known)})")
        kind = {key: known[key].metadata.get("kind", "float") for key in params}
        values: Dict[str, object] = {key: parse_number(key, text) for key, text in params.items()
                                     if kind[key] == "float"}
        sizes = {"links", "dofs", cls.size_field, *cls.whole_fields} - {None}
        for size in sizes:  # whole numbers (sizes: n depends on them)
            if size in values:
                values[size] = _whole(size, values[size])
        n = cls.check_size(cls(**values).n)  # scalar fields first: n may depend on them
        for key, text in params.items():
            if kind[key] == "matrix":
                values[key] = tuple(map(tuple, _parse_matrix(key, text, n)))
            elif kind[key] == "per_link":
                values[key] = tuple(_parse_per_link(key, text, n))
            elif kind[key] == "choice":
                values[key] = _parse_choice(key, text, known[key].metadata["choices"])
        return cls(**values).checked()

    @staticmethod
    def _params_dict(params) -> Dict[str, object]:
        """`params` as a dict of NAME -> value; InputError unless a mapping with string keys."""
        if params is None:
            return {}
        if not isinstance(params, abc_Mapping):
            raise InputError(f"params must be a mapping of parameter names to values, not "
                             f"{type(params).__name__}")
        for key in params:
            if not isinstance(key, str):
                raise InputError(f"params: parameter name {show(key)} is not a string")
        return dict(params)

    @classmethod
    def check_size(cls, n) -> int:
        """n as the number of dofs of this scene: a whole number from `min_dofs` to `max_dofs`
        and within the memory rule (MAX_DOFS); InputError naming the size parameter."""
        name = cls.size_field or "n"
        if not _whole_value(n):
            raise InputError(f"{name}={_quoted(n)} is not a whole number")
        n = int(n)
        shown = _count(n)
        if n < cls.min_dofs:
            raise InputError(f"{name}={shown} must be at least {cls.min_dofs}")
        if dense_bytes(n) > DENSE_BUDGET:
            need = dense_bytes(n) / 2 ** 30
            need = f"about {need:.4g}" if math.isfinite(need) else "more than 1e300"
            raise InputError(
                f"{name}={shown} is too large: {shown} dofs need {need} GiB of dense "
                f"matrices ({DENSE_WORDS} n x n float64: M, K, D, H's weights, the 2n x 2n "
                f"first-order matrix, its eigenvectors, the reference's), above the budget of "
                f"{DENSE_BUDGET / 2 ** 30:g} GiB: at most {MAX_DOFS}")
        if n > cls.max_dofs:
            raise InputError(f"{name}={shown} is too large (at most {cls.max_dofs} for scene "
                             f"{cls.name})")
        return n

    def kinks(self, x: np.ndarray) -> Optional[np.ndarray]:
        """(points, kinks): where the force is not smooth: values whose sign changes mark a jump
        of its derivative (fem_dual.integrate.kinks ends slabs there); None for a smooth force."""
        return None

    def checked(self) -> "Scene":
        """This scene, validated, for a scene built by `from_params` and one handed over as an
        object alike: the plain numbers (finite, normal), the number of dofs (before anything
        sized by it), the parameters sized by it, then `validate`. InputError names the first
        bad value. Once per object (a scene is frozen)."""
        if not self.__dict__.get("_checked", False):
            self.check_values()
            n = self.check_size(self.n)
            self.check_sized_values(n)
            self.validate()
            self.__dict__["_checked"] = True  # frozen: its fields cannot change afterwards
        return self

    def _fields(self, *kinds: str):
        """(name, value) of the fields of these kinds: "matrix", "per_link", "choice", or by
        type "float", "int", "str" (fields of other types are the scene's own to check)."""
        for f in dataclasses.fields(self):
            kind = f.metadata.get("kind")
            if kind is None:
                kind = f.type if isinstance(f.type, str) else getattr(f.type, "__name__", "")
            if kind in kinds:
                yield f.name, getattr(self, f.name)

    def check_values(self) -> None:
        """InputError for a plain field of the wrong type or value: float fields finite and
        normal (require_normal), whole numbers whole, choices among their choices."""
        for name, value in self._fields("float"):
            require_normal(name, value)
        for name, value in self._fields("int"):
            if name == self.size_field:
                self.check_size(value)  # before n is computed from it
            elif not _whole_value(value):
                raise InputError(f"{name}={_quoted(value)} is not a whole number")
        for f in dataclasses.fields(self):
            if f.metadata.get("kind") == "choice":
                value = getattr(self, f.name)
                if not isinstance(value, str) or value not in f.metadata["choices"]:
                    raise InputError(f"{f.name}={_quoted(value)} is not one of "
                                     f"{', '.join(f.metadata['choices'])}")

    def check_sized_values(self, n: int) -> None:
        """InputError for a matrix field that is not None or n x n, or a per-link field that is
        not one number or n of them; every entry finite and normal (require_normal)."""
        for name, value in self._fields("matrix"):
            if value is None:
                continue
            try:
                matrix = np.asarray(value, dtype=float)
            except (TypeError, ValueError, OverflowError):
                raise InputError(f"{name}={_quoted(value)} is not a matrix of numbers") from None
            if matrix.shape != (n, n):
                raise InputError(f"{name} has shape {matrix.shape}, expected ({n}, {n})")
            _require_entries(name, value, matrix)
        for name, value in self._fields("per_link"):
            if np.ndim(value) == 0:
                require_normal(name, value)
                continue
            try:
                values = np.asarray(value, dtype=float)
            except (TypeError, ValueError, OverflowError):
                raise InputError(f"{name}={_quoted(value)} is not a list of numbers") from None
            if values.shape != (n,):
                raise InputError(f"{name}={show(value)} has {values.size} entries, expected "
                                 f"one number or {n}")
            _require_entries(name, value, values)

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

    def mass_diagonal(self) -> Optional[np.ndarray]:
        """M's diagonal when M is diagonal (the usual m I: a division instead of LAPACK), else
        None; once per object (a scene is frozen)."""
        if "_mass_diagonal" not in self.__dict__:
            M = self.mass_matrix()
            d = M.diagonal().copy()
            self.__dict__["_mass_diagonal"] = None if np.count_nonzero(M - np.diag(d)) else d
        return self.__dict__["_mass_diagonal"]

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
        """The parameter values (matrices as nested lists), for the JSON record: new lists on
        every call, from the fields read once per object (a scene is frozen)."""
        if "_parameters" not in self.__dict__:
            self.__dict__["_parameters"] = tuple(
                (f.name, getattr(self, f.name)) for f in dataclasses.fields(self))
        out: Dict[str, object] = {}
        for name, value in self.__dict__["_parameters"]:
            if isinstance(value, tuple):
                value = [list(v) if isinstance(v, tuple) else v for v in value]
            out[name] = value
        return out
