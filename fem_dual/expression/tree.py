"""The compiled tree of a force expression, its backends' interface, and its interpreter."""
from __future__ import annotations

import abc
import dataclasses
import operator
from typing import Any, Callable, Mapping, Union

__all__ = ["_Num", "_Coord", "_Param", "_Neg", "_Bin", "_Call", "_Node", "_Backend", "_evaluate"]

_OPERATORS = {"+": operator.add, "-": operator.sub, "*": operator.mul, "/": operator.truediv,
              "**": operator.pow}


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
