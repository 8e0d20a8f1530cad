"""The parsed force: its components and their translations into UFL, numpy and the Jacobian."""
from __future__ import annotations

import dataclasses
import functools
from typing import Any, Mapping, Tuple

import numpy as np
import ufl

from fem_dual.errors import InputError
from fem_dual.expression.backends import (_UFL_ERRORS, _BranchBackend, _Dual, _DualBackend,
                                          _NumpyBackend, _UFLBackend)
from fem_dual.expression.grammar import _error, _quote
from fem_dual.expression.tree import _Call, _evaluate, _Node

__all__ = ["ForceExpression"]


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

    def branch(self, x, values: Mapping[str, float], signs) -> np.ndarray:
        """F(x) as `numpy`, on the branch of the kinks where their arguments have the `signs`
        (one +1 or -1 per kink, in `kinks` order): abs(u) is sign * u there."""
        point = np.asarray(x, dtype=np.float64)
        chosen = {node.source: float(s) for node, s in zip(self.kinks, signs)}
        backend = _BranchBackend(point, values, chosen)
        with np.errstate(all="ignore"):
            return np.array([_evaluate(node, backend) for node in self._components],
                            dtype=np.float64)

    @functools.cached_property
    def kinks(self) -> Tuple[_Node, ...]:
        """The arguments of its non-smooth functions (abs): where one changes sign, the force's
        derivative jumps. (Found once: every event check of the reference asks.)"""
        found, stack = [], list(self._components)
        while stack:
            node = stack.pop()
            if isinstance(node, _Call) and node.function == "abs":
                found.append(node.argument)
            stack += [getattr(node, name) for name in ("operand", "left", "right", "argument")
                      if hasattr(node, name)]
        unique = {node.source: node for node in found}  # (the same text is the same kink)
        return tuple(unique[key] for key in sorted(unique))

    def kink_values(self, x: np.ndarray, values: Mapping[str, float]) -> np.ndarray:
        """(points, kinks): the kinks' arguments at the points `x` (points, n)."""
        points = np.asarray(x, dtype=np.float64).reshape(-1, self.n)
        backend = _NumpyBackend(points.T, values)
        with np.errstate(all="ignore"):
            columns = [np.broadcast_to(_evaluate(node, backend), (len(points),))
                       for node in self.kinks]
        return np.column_stack(columns) if columns else np.zeros((len(points), 0))

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
