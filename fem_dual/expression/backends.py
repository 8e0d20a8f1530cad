"""The targets of the compiled tree: numpy float64, dual numbers (the exact Jacobian), the
parse-time check of constant sub-expressions, and UFL."""
from __future__ import annotations

import math
from typing import Any, Mapping

import numpy as np
import ufl

from fem_dual.expression.grammar import MAX_EXPONENT, _error, _quote
from fem_dual.expression.tree import _Backend, _Bin

__all__ = ["_UFL_ERRORS", "_NumpyBackend", "_BranchBackend", "_Dual", "_DualBackend",
           "_ConstantChecker", "_UFLBackend"]

# UFL 2022.2 raises its own UFLException (division by zero while folding constants); later
# versions raise ValueError.
_UFL_ERRORS = (ArithmeticError, ValueError, getattr(getattr(ufl, "log", None), "UFLException",
                                                     ValueError))


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


class _BranchBackend(_NumpyBackend):
    """numpy on one branch of the force's kinks: abs(u) is s u with the sign s given for each
    kink (by its argument's text), so the force is smooth across the kink (the continuation of
    the branch the motion is on: what an integrator that stops at the kink needs)."""

    def __init__(self, x: np.ndarray, values: Mapping[str, float], signs: Mapping[str, float]):
        super().__init__(x, values)
        self.signs = signs

    def apply(self, operation, operands, node):
        if getattr(node, "function", None) == "abs" and node.argument.source in self.signs:
            return self.signs[node.argument.source] * operands[0]
        return operation(*operands)


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
