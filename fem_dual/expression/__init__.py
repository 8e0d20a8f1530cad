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
from fem_dual.expression.force import ForceExpression
from fem_dual.expression.grammar import (FUNCTIONS, MAX_COMPONENTS, MAX_DEPTH, MAX_EXPONENT,
                                         MAX_LENGTH, MAX_NODES, RESERVED, SCENE_PARAMETERS,
                                         check_parameter_names, coordinate_names)
from fem_dual.expression.parse import parse_force

__all__ = ["RESERVED", "FUNCTIONS", "SCENE_PARAMETERS", "MAX_LENGTH", "MAX_DEPTH", "MAX_NODES",
           "MAX_COMPONENTS", "MAX_EXPONENT", "coordinate_names", "check_parameter_names",
           "ForceExpression", "parse_force"]
