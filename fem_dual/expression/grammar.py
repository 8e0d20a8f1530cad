"""The vocabulary and limits of the force-expression language (its whitelist of names and
functions, its sizes) and its one-line error messages."""
from __future__ import annotations

import keyword
import re
from typing import Iterable, Optional, Tuple

from fem_dual.errors import InputError

__all__ = ["RESERVED", "FUNCTIONS", "SCENE_PARAMETERS", "MAX_LENGTH", "MAX_DEPTH", "MAX_NODES",
           "MAX_COMPONENTS", "MAX_EXPONENT", "coordinate_names", "check_parameter_names",
           "_QUOTE_LIMIT", "_quote", "_error", "_coordinate_index", "_is_reserved",
           "_describe_coordinates", "_check_count"]

FUNCTIONS = ("sin", "cos", "tan", "exp", "log", "sqrt", "sinh", "cosh", "tanh", "atan", "abs")
SCENE_PARAMETERS = ("m", "alpha", "beta")
#: Names that can never be parameters; every name ``x<digits>`` (x1, x2, ...) is reserved too,
#: whatever the number of components, so that a parameter never turns into a coordinate.
RESERVED = ("x", "y", "z", "pi") + FUNCTIONS

MAX_LENGTH = 10_000
MAX_DEPTH = 100
MAX_NODES = 10_000
MAX_COMPONENTS = 1000
MAX_EXPONENT = 1000

_PREFIX = "force expression: "
_QUOTE_LIMIT = 60
_XYZ = ("x", "y", "z")
_INDEXED = re.compile(r"x[0-9]+")
_IDENTIFIER = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


# --- messages -----------------------------------------------------------------------------------

def _quote(piece: str) -> str:
    """repr of `piece`, cut to about 60 characters (cut before quoting: escapes stay whole)."""
    if len(piece) > _QUOTE_LIMIT:
        piece = piece[:_QUOTE_LIMIT - 3] + "..."
    return repr(piece)


def _one_line(message: str) -> str:
    return "".join(ch if ch.isprintable() else ascii(ch)[1:-1] for ch in message)


def _error(message: str) -> InputError:
    return InputError(_one_line(_PREFIX + message))


# --- names --------------------------------------------------------------------------------------

def coordinate_names(n: int) -> Tuple[str, ...]:
    """('x','y','z')[:n] for n <= 3 and also ('x1',...,'xn') for any n: BOTH spellings are
    accepted for n <= 3 (x == x1, y == x2, z == x3); for n > 3 only x1..xn."""
    if not isinstance(n, int) or n < 1:
        raise ValueError(f"coordinate_names: n must be a positive int, got {n!r}")
    indexed = tuple(f"x{i}" for i in range(1, n + 1))
    return (_XYZ[:n] if n <= 3 else ()) + indexed


def _coordinate_index(name: str, n: int) -> Optional[int]:
    """0-based index of coordinate `name` for n components, or None."""
    if n <= 3 and name in _XYZ[:n]:
        return _XYZ.index(name)
    digits = name[1:]
    if (_INDEXED.fullmatch(name) and digits[0] != "0" and len(digits) <= len(str(n))
            and int(digits) <= n):  # the length first: int() of 5000 digits raises
        return int(digits) - 1
    return None


def _is_reserved(name: str) -> bool:
    return name in RESERVED or _INDEXED.fullmatch(name) is not None


def _describe_coordinates(n: int) -> str:
    xyz = ", ".join(_XYZ[:n]) + ", " if n <= 3 else ""
    return xyz + ("x1" if n == 1 else f"x1..x{n}")


def check_parameter_names(names: Iterable[str], n: Optional[int] = None) -> Tuple[str, ...]:
    """The names of --param, checked: ASCII identifiers, not keywords, not reserved (a coordinate
    x, y, z or x<digits>, a function, or pi). Returns them sorted and without repeats. `n` is
    only range-checked: reservation does not depend on the number of components."""
    if n is not None:
        _check_count(n)
    if isinstance(names, str):
        names = (names,)
    checked = set()
    for name in names:
        if not isinstance(name, str) or not _IDENTIFIER.fullmatch(name) or keyword.iskeyword(name):
            raise _error(f"parameter name {_quote(str(name))} is not a plain ASCII identifier")
        if _is_reserved(name):
            kind = "function" if name in FUNCTIONS else "constant" if name == "pi" else "coordinate"
            raise _error(f"parameter name {_quote(name)} clashes with the {kind} of that name")
        checked.add(name)
    return tuple(sorted(checked))


def _check_count(n: int) -> None:
    if not 1 <= n <= MAX_COMPONENTS:
        raise _error(f"{n} components; between 1 and {MAX_COMPONENTS} are allowed")
