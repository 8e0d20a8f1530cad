"""A safe parser of force expressions typed on the command line, e.g. ``-k*x*y**2, -k*x**3``.

The text is parsed by :func:`ast.parse` (mode "eval") and checked against a whitelist; nothing is
ever ``eval``'d or ``exec``'d. The checked tree is compiled into a small tree of its own, which is
interpreted twice: into UFL (:meth:`ForceExpression.ufl`, for the forms) and into numpy float64
(:meth:`ForceExpression.numpy`, for the reference solver).

Grammar (the whitelist): components separated by top-level commas; each component is built from

* numbers: int and float literals (not bool, complex, str, bytes, None, ...), finite;
* names: the coordinates (:func:`coordinate_names`), ``pi``, the scene parameters ``m``, ``alpha``,
  ``beta`` and the parameters given with ``--param``;
* ``+ - * / **`` (binary), ``-`` and ``+`` (unary), parentheses;
* calls ``f(a)`` of the functions in :data:`FUNCTIONS`, exactly one positional argument.

Everything else (attributes, subscripts, lambdas, comprehensions, comparisons, keyword arguments,
``//``, ``%``, ``@``, bit operators, strings, parenthesised or nested tuples, ...) raises
:class:`InputError`, as do: a syntax error; an empty text or component; a character that is not
printable ASCII (tab allowed: it also rejects Unicode lookalikes such as a Cyrillic ``x``, which
Python would otherwise accept as identifiers, some even normalised to ``x``); an unknown name; a
non-finite literal; and, among the constant sub-expressions (those free of coordinates and
parameters), a zero divisor (``x/0``, ``x/-0.0``, ``x/(1-1)``), an exponent beyond
+-:data:`MAX_EXPONENT` (``x**1e6``, ``2**10**10``) or a value that is not finite (``10.0**400``,
``sqrt(-1)``, ``log(0)``).

Limits: :data:`MAX_LENGTH` characters (checked before parsing), :data:`MAX_DEPTH` levels of
syntax tree (each term of a chain ``a + b + ...`` is one level), :data:`MAX_NODES` tree nodes, 1 to
:data:`MAX_COMPONENTS` components. The parser evaluates no user code: literals become floats
(except integer literal exponents, kept ``int`` so that ``x**2`` stays a UFL power of an integer)
and the constant sub-expressions are checked by folding them in numpy float64, whose cost is
bounded by the size of the tree: no Python integer arithmetic (``10**10**10``) can run away.

Every error message is one line starting with "force expression: "; offending pieces are quoted
with ``repr`` (control characters escaped) and cut to about 60 characters; columns are 1-based.
The name ``e`` is not Euler's number (write ``exp(1)``); it may be a parameter.
"""
from __future__ import annotations

import abc
import ast
import dataclasses
import io
import keyword
import math
import operator
import re
import tokenize
from typing import Any, Callable, Iterable, Mapping, Optional, Tuple, Union

import numpy as np
import ufl

from fem_dual.errors import InputError

__all__ = ["RESERVED", "FUNCTIONS", "SCENE_PARAMETERS", "MAX_LENGTH", "MAX_DEPTH", "MAX_NODES",
           "MAX_COMPONENTS", "MAX_EXPONENT", "coordinate_names", "check_parameter_names",
           "ForceExpression", "parse_force"]

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

# UFL 2022.2 raises its own UFLException (division by zero while folding constants); later
# versions raise ValueError.
_UFL_ERRORS = (ArithmeticError, ValueError, getattr(getattr(ufl, "log", None), "UFLException",
                                                     ValueError))
_PREFIX = "force expression: "
_QUOTE_LIMIT = 60
_XYZ = ("x", "y", "z")
_OPENING, _CLOSING = frozenset("([{"), frozenset(")]}")
_INDEXED = re.compile(r"x[0-9]+")
_IDENTIFIER = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
_BINARY = {ast.Add: "+", ast.Sub: "-", ast.Mult: "*", ast.Div: "/", ast.Pow: "**"}
_OPERATORS = {"+": operator.add, "-": operator.sub, "*": operator.mul, "/": operator.truediv,
              "**": operator.pow}
_REJECTED_OPERATORS = {ast.MatMult: "@", ast.FloorDiv: "//", ast.Mod: "%", ast.LShift: "<<",
                       ast.RShift: ">>", ast.BitOr: "|", ast.BitXor: "^", ast.BitAnd: "&",
                       ast.Not: "not", ast.Invert: "~"}
_CONSTRUCTS = {
    ast.Attribute: "attribute access", ast.Subscript: "subscript", ast.Lambda: "lambda",
    ast.ListComp: "list comprehension", ast.SetComp: "set comprehension",
    ast.DictComp: "dict comprehension", ast.GeneratorExp: "generator expression",
    ast.IfExp: "conditional expression", ast.Compare: "comparison", ast.BoolOp: "boolean operator",
    ast.Starred: "starred expression", ast.JoinedStr: "f-string", ast.FormattedValue: "f-string",
    ast.Set: "set display", ast.List: "list display", ast.Dict: "dict display",
    ast.NamedExpr: "assignment expression", ast.Await: "await", ast.Yield: "yield",
    ast.YieldFrom: "yield", ast.Slice: "slice", ast.Tuple: "nested tuple",
}


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


# --- the compiled tree --------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class _Num:
    value: Union[int, float]
    source: str


@dataclasses.dataclass(frozen=True)
class _Coord:
    index: int
    source: str


@dataclasses.dataclass(frozen=True)
class _Param:
    name: str
    source: str


@dataclasses.dataclass(frozen=True)
class _Neg:
    operand: "_Node"
    source: str


@dataclasses.dataclass(frozen=True)
class _Bin:
    op: str
    left: "_Node"
    right: "_Node"
    source: str


@dataclasses.dataclass(frozen=True)
class _Call:
    function: str
    argument: "_Node"
    source: str


_Node = Union[_Num, _Coord, _Param, _Neg, _Bin, _Call]


class _Backend(abc.ABC):
    """One target of the compiled tree (numpy, UFL, the constant check): how leaves are made
    and how an operation (an operator or one of `functions`) is applied."""

    functions: Mapping[str, Callable] = {}

    @abc.abstractmethod
    def number(self, value: Union[int, float]) -> Any:
        """The leaf of a number."""

    @abc.abstractmethod
    def coordinate(self, index: int) -> Any:
        """The leaf of a coordinate."""

    @abc.abstractmethod
    def parameter(self, name: str) -> Any:
        """The leaf of a parameter."""

    def apply(self, operation: Callable, operands: tuple, node: _Node) -> Any:
        return operation(*operands)


def _evaluate(node: _Node, backend: _Backend) -> Any:
    """Interpret the compiled tree (depth <= MAX_DEPTH, so recursion is safe)."""
    if isinstance(node, _Num):
        return backend.number(node.value)
    if isinstance(node, _Coord):
        return backend.coordinate(node.index)
    if isinstance(node, _Param):
        return backend.parameter(node.name)
    if isinstance(node, _Neg):
        operation, children = operator.neg, (node.operand,)
    elif isinstance(node, _Bin):
        operation, children = _OPERATORS[node.op], (node.left, node.right)
    else:
        operation, children = backend.functions[node.function], (node.argument,)
    operands = tuple(_evaluate(child, backend) for child in children)
    return backend.apply(operation, operands, node)


_NUMPY_FUNCTIONS = {"sin": np.sin, "cos": np.cos, "tan": np.tan, "exp": np.exp, "log": np.log,
                    "sqrt": np.sqrt, "sinh": np.sinh, "cosh": np.cosh, "tanh": np.tanh,
                    "atan": np.arctan, "abs": np.abs}


class _NumpyBackend(_Backend):
    """float64 scalars throughout (no Python float arithmetic: 1/0 is inf, not an exception);
    run it under np.errstate(all="ignore")."""

    functions = _NUMPY_FUNCTIONS

    def __init__(self, x: np.ndarray, values: Mapping[str, float]):
        self.x, self.values = x, values

    def number(self, value):
        return np.float64(value)

    def coordinate(self, index):
        return self.x[index]

    def parameter(self, name):
        return np.float64(self.values[name])


class _Dual:
    """A value with its gradient in the coordinates (forward-mode differentiation): the force's
    Jacobian exactly, for the independent check of an orbit's multipliers, where differences
    would share their truncation error with fem-dual's own."""

    __array_ufunc__ = None  # numpy scalars defer to the operators below

    def __init__(self, value, grad):
        self.value, self.grad = np.float64(value), grad

    @staticmethod
    def parts(a):
        return (a.value, a.grad) if isinstance(a, _Dual) else (np.float64(a), 0.0)

    def __add__(self, other):
        b, db = _Dual.parts(other)
        return _Dual(self.value + b, self.grad + db)

    __radd__ = __add__

    def __sub__(self, other):
        b, db = _Dual.parts(other)
        return _Dual(self.value - b, self.grad - db)

    def __rsub__(self, other):
        b, db = _Dual.parts(other)
        return _Dual(b - self.value, db - self.grad)

    def __mul__(self, other):
        b, db = _Dual.parts(other)
        return _Dual(self.value * b, self.grad * b + self.value * db)

    __rmul__ = __mul__

    def __truediv__(self, other):
        b, db = _Dual.parts(other)
        return _Dual(self.value / b, (self.grad * b - self.value * db) / (b * b))

    def __rtruediv__(self, other):
        b, db = _Dual.parts(other)
        return _Dual(b / self.value, (db * self.value - b * self.grad) / (self.value ** 2))

    def __pow__(self, other):
        b, db = _Dual.parts(other)
        value = self.value ** b
        grad = b * self.value ** (b - 1) * self.grad if b != 0 else 0.0 * self.grad
        if isinstance(other, _Dual):  # a ** b = exp(b log a)
            grad = grad + value * np.log(self.value) * db
        return _Dual(value, grad)

    def __rpow__(self, other):
        a = np.float64(other)
        value = a ** self.value
        return _Dual(value, value * np.log(a) * self.grad)

    def __neg__(self):
        return _Dual(-self.value, -self.grad)

    def __pos__(self):
        return self


def _chain(function, derivative):
    """f on a _Dual by the chain rule, plain f on a number."""
    def apply(a):
        if not isinstance(a, _Dual):
            return function(a)
        return _Dual(function(a.value), derivative(a.value) * a.grad)
    return apply


_DUAL_FUNCTIONS = {
    "sin": _chain(np.sin, np.cos), "cos": _chain(np.cos, lambda u: -np.sin(u)),
    "tan": _chain(np.tan, lambda u: 1.0 / np.cos(u) ** 2), "exp": _chain(np.exp, np.exp),
    "log": _chain(np.log, lambda u: 1.0 / u), "sqrt": _chain(np.sqrt, lambda u: 0.5 / np.sqrt(u)),
    "sinh": _chain(np.sinh, np.cosh), "cosh": _chain(np.cosh, np.sinh),
    "tanh": _chain(np.tanh, lambda u: 1.0 / np.cosh(u) ** 2),
    "atan": _chain(np.arctan, lambda u: 1.0 / (1.0 + u * u)), "abs": _chain(np.abs, np.sign)}


class _DualBackend(_NumpyBackend):
    """Coordinates carry their unit gradients: every component comes with its row of the
    Jacobian."""

    functions = _DUAL_FUNCTIONS

    def coordinate(self, index):
        grad = np.zeros(len(self.x))
        grad[index] = 1.0
        return _Dual(self.x[index], grad)


class _ConstantChecker(_Backend):
    """The parse-time check of the sub-expressions free of coordinates and parameters, folded
    in float64 (bounded work; never Python ints): each must be finite, no divisor may be zero
    and no exponent beyond +-MAX_EXPONENT. Non-constant values are None."""

    functions = _NUMPY_FUNCTIONS

    def number(self, value):
        return np.float64(value)

    def coordinate(self, index):
        return None

    def parameter(self, name):
        return None

    def apply(self, operation, operands, node):
        if isinstance(node, _Bin):
            self._check_right(node, operands[1])
        if any(operand is None for operand in operands):
            return None
        value = operation(*operands)
        if not np.isfinite(value):
            raise _error(f"constant {_quote(node.source)} evaluates to {float(value)!r}")
        return value

    @staticmethod
    def _check_right(node: _Bin, right) -> None:
        if right is None:
            return
        if node.op == "/" and right == 0:
            raise _error(f"division by zero: {_quote(node.source)}")
        if node.op == "**" and abs(right) > MAX_EXPONENT:
            raise _error(f"exponent of {_quote(node.source)} is beyond +-{MAX_EXPONENT}")


class _UFLBackend(_Backend):
    """UFL operators on UFL leaves; numbers in `x` or `c` become UFL constants."""

    functions = {"sin": ufl.sin, "cos": ufl.cos, "tan": ufl.tan, "exp": ufl.exp, "log": ufl.ln,
                 "sqrt": ufl.sqrt, "sinh": ufl.sinh, "cosh": ufl.cosh, "tanh": ufl.tanh,
                 "atan": ufl.atan, "abs": abs}  # abs(expr) is ufl.algebra.Abs

    def __init__(self, x, c: Mapping[str, Any]):
        self.x, self.c = x, c

    @staticmethod
    def _leaf(value):
        if isinstance(value, ufl.core.expr.Expr):
            return value
        if np.ndim(value) == 0:
            return ufl.as_ufl(float(value))
        return ufl.as_ufl(value)  # not a scalar: UFL says why

    def number(self, value):
        return ufl.as_ufl(value)

    def coordinate(self, index):
        return self._leaf(self.x[index])

    def parameter(self, name):
        return self._leaf(self.c[name])

    def apply(self, operation, operands, node):
        """UFL folds constant operands with Python floats (x or c given as numbers): refuse
        what is not real and finite there (in UFL sqrt(-1) is 1j and 1e300*1e300 is inf)."""
        value = ufl.as_ufl(operation(*operands))  # functions of constants fold to floats
        if isinstance(value, ufl.constantvalue.ScalarValue):
            number = value.value()
            if isinstance(number, complex) or not math.isfinite(number):
                raise _error(f"{_quote(node.source)} evaluates to {number!r}, not a finite real")
        return value


# --- parsing ------------------------------------------------------------------------------------

def _check_text(text: str) -> str:
    """Type, length, characters, emptiness: all before ast.parse."""
    if not isinstance(text, str):
        raise _error(f"expected a string, got {type(text).__name__}")
    if len(text) > MAX_LENGTH:
        raise _error(f"text of {len(text)} characters is longer than {MAX_LENGTH}")
    for column, ch in enumerate(text, start=1):
        if not (" " <= ch <= "~" or ch == "\t") or ch == "#":
            raise _error(f"character {ch!r} (U+{ord(ch):04X}) at column {column} is not allowed; "
                         "expressions are printable ASCII without comments")
    if not text.strip():
        raise _error("empty expression")
    return text


def _top_level_commas(source: str) -> list:
    """0-based positions of the commas outside any bracket, from Python's own tokenizer (so
    brackets inside string literals do not count); stops quietly where tokenizing fails."""
    depth, commas = 0, []
    try:
        for token in tokenize.generate_tokens(io.StringIO(source).readline):
            if token.type != tokenize.OP:
                continue
            if token.string in _OPENING:
                depth += 1
            elif token.string in _CLOSING:
                depth -= 1
            elif token.string == "," and depth == 0:
                commas.append(token.start[1])
    except (tokenize.TokenError, SyntaxError):
        pass
    return commas


def _empty_component(text: str) -> Optional[int]:
    """1-based index of the first blank component between top-level commas, or None."""
    commas = _top_level_commas(text)
    if not commas:
        return None
    bounds = [-1] + commas + [len(text)]
    for k in range(len(bounds) - 1):
        if not text[bounds[k] + 1:bounds[k + 1]].strip():
            return k + 1
    return None


def _excerpt(text: str, column: int) -> str:
    """About 60 characters of `text` around the 1-based `column`."""
    start = max(0, column - 1 - _QUOTE_LIMIT // 2)
    piece = text[start:start + _QUOTE_LIMIT]
    return ("..." if start else "") + piece


def _parse(text: str, source: str, lead: int) -> ast.Expression:
    """`source` is `text` stripped (leading blanks are an IndentationError), `lead` blanks on the
    left: columns in messages count in `text`."""
    try:
        return ast.parse(source, mode="eval")
    except SyntaxError as exc:
        empty = _empty_component(source)
        if empty is not None:
            raise _error(f"component {empty} of {_quote(source)} is empty") from None
        column = lead + max(exc.offset or 1, 1)
        raise _error(f"syntax error at column {column}: {exc.msg}: "
                     f"{_quote(_excerpt(text, column))}") from None
    except (RecursionError, MemoryError, ValueError, OverflowError):
        raise _error(f"too deeply nested for the parser: {_quote(source)}") from None


def _check_size(tree: ast.AST, source: str) -> None:
    """Node count and depth, iteratively (the parser accepts trees far deeper than recursion)."""
    stack, count = [(tree, 1)], 0
    while stack:
        node, depth = stack.pop()
        count += 1
        if count > MAX_NODES:
            raise _error(f"more than {MAX_NODES} syntax nodes: {_quote(source)}")
        if depth > MAX_DEPTH:
            raise _error(f"nested deeper than {MAX_DEPTH} levels (each term of a chain a + b + "
                         f"... is one level): {_quote(source)}")
        stack.extend((child, depth + 1) for child in ast.iter_child_nodes(node))


def _components(body: ast.expr, source: str) -> list:
    """The component nodes: those of a top-level tuple written without parentheses and without
    a trailing comma, or the single expression."""
    if not isinstance(body, ast.Tuple):
        return [body]
    for element in body.elts:
        if isinstance(element, ast.Tuple):
            raise _error(f"nested tuple is not allowed: {_quote(_segment(source, element))}")
    commas = _top_level_commas(source)
    if not commas:
        raise _error(f"parenthesised tuple is not allowed, separate the components by commas "
                     f"at the top level: {_quote(source)}")
    if not source[commas[-1] + 1:].strip():
        raise _error(f"component {len(commas) + 1} of {_quote(source)} is empty "
                     "(trailing comma)")
    return list(body.elts)


def _segment(source: str, node: ast.AST) -> str:
    """The source of `node`: the text is one line of ASCII, so columns index characters (and
    ast.get_source_segment would split the whole text again for every node)."""
    start, end = getattr(node, "col_offset", None), getattr(node, "end_col_offset", None)
    return source[start:end] if start is not None and end is not None else source


def _signed_literal(node: ast.expr) -> Optional[Union[int, float]]:
    """The value of a numeric literal under unary signs (-2, +-0.5), or None."""
    sign = 1
    while isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.USub, ast.UAdd)):
        sign = -sign if isinstance(node.op, ast.USub) else sign
        node = node.operand
    if isinstance(node, ast.Constant) and type(node.value) in (int, float):
        return sign * node.value
    return None


class _Compiler:
    """Whitelist check and translation of one component, with its names resolved."""

    def __init__(self, source: str, n: int, parameters: Tuple[str, ...]):
        self.source, self.n, self.parameters = source, n, parameters
        self.used: set = set()

    def fail(self, what: str, node: ast.AST) -> InputError:
        return _error(f"{what} is not allowed: {_quote(_segment(self.source, node))}")

    def build(self, node: ast.expr) -> _Node:
        source = _segment(self.source, node)
        if isinstance(node, ast.Constant):
            return _Num(self.literal(node), source)
        if isinstance(node, ast.Name):
            return self.name(node, source)
        if isinstance(node, ast.UnaryOp):
            return self.unary(node, source)
        if isinstance(node, ast.BinOp):
            return self.binary(node, source)
        if isinstance(node, ast.Call):
            return self.call(node, source)
        raise self.fail(_CONSTRUCTS.get(type(node), type(node).__name__), node)

    def literal(self, node: ast.Constant) -> float:
        value = node.value
        if type(value) not in (int, float):
            what = {bool: "boolean literal", complex: "complex literal", str: "string literal",
                    bytes: "bytes literal"}.get(type(value), f"literal {value!r}")
            raise self.fail(what, node)
        try:
            number = float(value)
        except OverflowError:
            number = math.inf
        if not math.isfinite(number):
            raise _error(f"literal {_quote(_segment(self.source, node))} is not finite")
        return number

    def name(self, node: ast.Name, source: str) -> _Node:
        name = node.id
        index = _coordinate_index(name, self.n)
        if index is not None:
            return _Coord(index, source)
        if name == "pi":
            return _Num(math.pi, source)
        if name in self.parameters:
            self.used.add(name)
            return _Param(name, source)
        raise self.unknown(name)

    def unknown(self, name: str) -> InputError:
        if name in FUNCTIONS:
            return _error(f"function {_quote(name)} must be called, as in {name}(x)")
        if _is_reserved(name):
            return _error(f"coordinate {_quote(name)} does not exist with n = {self.n} "
                          f"components (coordinates: {_describe_coordinates(self.n)})")
        params = ", ".join(self.parameters)
        if len(params) > _QUOTE_LIMIT:
            params = params[:_QUOTE_LIMIT - 3] + "..."
        hint = "; for Euler's number write exp(1)" if name == "e" else ""
        return _error(f"unknown name {_quote(name)} (allowed: {_describe_coordinates(self.n)}, "
                      f"pi, {params}; functions: {', '.join(FUNCTIONS)}; more parameters with "
                      f"--param){hint}")

    def unary(self, node: ast.UnaryOp, source: str) -> _Node:
        if not isinstance(node.op, (ast.USub, ast.UAdd)):
            raise self.fail(f"operator {_REJECTED_OPERATORS.get(type(node.op), '?')!r}", node)
        operand = self.build(node.operand)
        if isinstance(node.op, ast.UAdd):
            return operand
        if isinstance(operand, _Num):
            return _Num(-operand.value, source)
        return _Neg(operand, source)

    def binary(self, node: ast.BinOp, source: str) -> _Node:
        op = _BINARY.get(type(node.op))
        if op is None:
            raise self.fail(f"operator {_REJECTED_OPERATORS.get(type(node.op), '?')!r}", node)
        left, right = self.build(node.left), self.build(node.right)
        exponent = _signed_literal(node.right) if op == "**" else None
        if type(exponent) is int:
            right = _Num(exponent, right.source)  # x**2 stays a power of an integer in UFL
        return _Bin(op, left, right, source)

    def call(self, node: ast.Call, source: str) -> _Node:
        func = node.func
        if not isinstance(func, ast.Name) or func.id not in FUNCTIONS:
            what = f"call of {_quote(_segment(self.source, func))}"
            raise _error(f"{what} is not allowed (functions: {', '.join(FUNCTIONS)}): "
                         f"{_quote(source)}")
        if node.keywords:
            raise self.fail("keyword argument", node)
        if len(node.args) != 1 or isinstance(node.args[0], ast.Starred):
            raise _error(f"{func.id} takes exactly one argument: {_quote(source)}")
        return _Call(func.id, self.build(node.args[0]), source)


# --- the result ---------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class ForceExpression:
    """A parsed force F(x): n components over the coordinates, the parameters it uses, and its
    two translations. Build it with :func:`parse_force`."""

    text: str
    n: int
    parameters: Tuple[str, ...]
    _components: Tuple[_Node, ...] = dataclasses.field(repr=False, compare=False, default=())

    def ufl(self, x, c: Mapping[str, Any]) -> ufl.core.expr.Expr:
        """F(x) as ``ufl.as_vector``: `x` indexable by 0..n-1 (a UFL vector or ufl.variable, or
        numbers); `c` maps every name in `parameters` to a UFL object (fem.Constant) or a float.
        Raises InputError if a constant sub-expression, folded by UFL, is not a finite real."""
        backend = _UFLBackend(x, c)
        values = [self._ufl_component(k, backend) for k in range(self.n)]
        return ufl.as_vector(values)

    def _ufl_component(self, k: int, backend: _UFLBackend):
        node = self._components[k]
        try:
            value = _evaluate(node, backend)
        except InputError:
            raise
        except _UFL_ERRORS as exc:
            reason = str(exc.args[-1]) if exc.args else type(exc).__name__
            raise _error(f"{_quote(node.source)} cannot be built: {reason}") from None
        if value.ufl_shape != ():
            raise _error(f"component {k + 1} {_quote(node.source)} is not a scalar "
                         f"(shape {value.ufl_shape}): is a parameter not a number?")
        return value

    def numpy(self, x, values: Mapping[str, float]) -> np.ndarray:
        """F(x) in float64, shape (n,), for a point `x` of n numbers; `values` maps every name in
        `parameters` to a float. inf and nan are returned as they come (no warnings)."""
        point = np.asarray(x, dtype=np.float64)
        if point.shape != (self.n,):
            raise ValueError(f"x has shape {point.shape}, expected ({self.n},)")
        backend = _NumpyBackend(point, values)
        with np.errstate(all="ignore"):
            return np.array([_evaluate(node, backend) for node in self._components],
                            dtype=np.float64)

    def jacobian(self, x, values: Mapping[str, float]) -> np.ndarray:
        """dF/dx at a point `x` (n, n), exactly (forward-mode differentiation of the tree;
        abs has the derivative sign). inf and nan are returned as they come."""
        point = np.asarray(x, dtype=np.float64)
        if point.shape != (self.n,):
            raise ValueError(f"x has shape {point.shape}, expected ({self.n},)")
        backend = _DualBackend(point, values)
        with np.errstate(all="ignore"):
            return np.array([_jacobian_row(_evaluate(node, backend), self.n)
                             for node in self._components])


def _jacobian_row(value, n: int) -> np.ndarray:
    if isinstance(value, _Dual):
        return np.broadcast_to(np.asarray(value.grad, dtype=np.float64), (n,)).copy()
    return np.zeros(n)  # a component free of the coordinates


def parse_force(text: str, known_parameters: Iterable[str] = ()) -> ForceExpression:
    """Components separated by top-level commas. n = number of components. known_parameters:
    names given with --param (plus m, alpha, beta, always allowed). Any other identifier that is
    not a coordinate, function, or pi -> InputError naming it (and listing the allowed names
    briefly). Known parameters that clash with reserved names are refused too."""
    _check_text(text)
    lead = len(text) - len(text.lstrip())
    source = text.strip()
    tree = _parse(text, source, lead)
    _check_size(tree, source)
    nodes = _components(tree.body, source)
    n = len(nodes)
    _check_count(n)
    allowed = tuple(sorted(set(check_parameter_names(known_parameters)) | set(SCENE_PARAMETERS)))
    compiler = _Compiler(source, n, allowed)
    components = tuple(compiler.build(node) for node in nodes)
    with np.errstate(all="ignore"):
        for component in components:
            _evaluate(component, _ConstantChecker())
    return ForceExpression(text, n, tuple(sorted(compiler.used)), components)
