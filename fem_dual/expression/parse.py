"""From text to a checked, compiled force: the text's checks, Python's parser under the
whitelist, and the translation of its syntax tree into the compiled tree."""
from __future__ import annotations

import ast
import io
import math
import tokenize
from typing import Iterable, Optional, Tuple, Union

import numpy as np

from fem_dual.errors import InputError
from fem_dual.expression.backends import _ConstantChecker
from fem_dual.expression.force import ForceExpression
from fem_dual.expression.grammar import (FUNCTIONS, MAX_DEPTH, MAX_LENGTH, MAX_NODES,
                                         SCENE_PARAMETERS, _QUOTE_LIMIT, _check_count,
                                         _coordinate_index, _describe_coordinates, _error,
                                         _is_reserved, _quote, check_parameter_names)
from fem_dual.expression.tree import _Bin, _Call, _Coord, _Neg, _Node, _Num, _Param, _evaluate

__all__ = ["parse_force"]

_OPENING, _CLOSING = frozenset("([{"), frozenset(")]}")
_BINARY = {ast.Add: "+", ast.Sub: "-", ast.Mult: "*", ast.Div: "/", ast.Pow: "**"}
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
