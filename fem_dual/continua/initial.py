"""Initial fields from text: one expression of fem-dual's expression language per scalar
component of a function space, in the spatial coordinates (``x`` on an interval, ``x, y`` in 2D,
``x, y, z`` in 3D; also ``x1, x2, ...``), e.g. ``["sin(pi*x/2)", "0"]`` for Beck's (w, theta) or
``["x*(1-x)*y*(1-y)", "0"]`` for a 2D displacement.

The text is parsed by :func:`fem_dual.expression.parse_force` (whitelisted, never evaluated as
Python) with as many coordinates as the mesh has dimensions, translated into UFL over
``ufl.SpatialCoordinate`` and interpolated into each scalar sub-space (a ``fem.Expression`` at
the element's interpolation points: the Lagrange nodes).
"""
from __future__ import annotations

from typing import Mapping, Optional, Sequence

import numpy as np
import ufl
from dolfinx import fem

from fem_dual.compat import (constant, equispaced_coordinates, quiet_jit_logging,
                             with_portable_fallback)
from fem_dual.errors import InputError
from fem_dual.expression import parse_force
from fem_dual.continua.dofs import leaf_spaces

__all__ = ["field_expression", "interpolate_fields", "jit_input"]


def field_expression(text: str, msh, parameters: Mapping[str, float]):
    """One scalar field of the coordinates of `msh` as UFL (or a float if it is a constant).

    The expression language takes as many coordinates as components; the text is parsed as the
    first of gdim components (the others ``0``), so that ``y`` exists exactly when the mesh
    has a second dimension. Parameters enter as ``fem.Constant``.
    """
    gdim = msh.geometry.dim
    if not isinstance(text, str):
        raise InputError(f"initial field: expected a string, got {type(text).__name__}")
    try:
        parsed = parse_force(", ".join([text] + ["0"] * (gdim - 1)), tuple(parameters))
    except InputError as exc:  # the language's messages speak of a force
        raise InputError(f"initial field {text[:60]!r}: "
                         f"{str(exc).removeprefix('force expression: ')}") from None
    if parsed.n != gdim:
        raise InputError(f"initial field: {text!r} has {parsed.n - gdim + 1} components; give "
                         "one expression per field component")
    missing = [name for name in parsed.parameters if name not in parameters]
    if missing:
        raise InputError(f"initial field: parameter {missing[0]!r} in {text!r} has no value")
    values = {name: constant(msh, parameters[name]) for name in parsed.parameters}
    value = parsed.ufl(ufl.SpatialCoordinate(msh), values)[0]
    if isinstance(value, ufl.constantvalue.ConstantValue):
        return float(value)
    _finite_at_points(text, parsed, msh, {k: float(v) for k, v in parameters.items()})
    return value


FINITE_SAMPLE = 512  # mesh points at which an initial field is evaluated before it is compiled


def _finite_at_points(text: str, parsed, msh, values: Mapping[str, float]) -> None:
    """InputError where the field is not finite at some of (about FINITE_SAMPLE of) the
    mesh's cell midpoints, evaluated in float64 before FFCx compiles it: numbers beyond float64
    (``1e308*x*10``) would become a constant inf in C that no compiler takes."""
    gdim = msh.geometry.dim
    # (the cells' midpoints: a field may be singular where no node or quadrature point lies)
    points = msh.geometry.x[msh.geometry.dofmap.array.reshape(
        msh.geometry.dofmap.num_nodes, -1), :gdim].mean(axis=1)
    points = points[::max(1, len(points) // FINITE_SAMPLE)]
    for point in points:
        if not np.isfinite(parsed.numpy(point, values)[0]):
            where = ", ".join(f"{c:g}" for c in point)
            raise InputError(f"initial field {text[:60]!r} is not finite at ({where})")


def jit_input(what: str, build):
    """build(): the JIT compilation of code made from the user's input (quietly); its failure
    (FFCx's or the C compiler's: a constant of inf in the code) an InputError naming `what`."""
    try:
        with quiet_jit_logging():
            return build()
    except Exception as exc:  # noqa: BLE001 -- whatever FFCx, cffi or gcc raise
        raise InputError(f"{what} cannot be compiled ({type(exc).__name__}; a constant beyond "
                         "float64?)") from None


def interpolate_fields(V: fem.FunctionSpace, texts: Sequence[str],
                       parameters: Optional[Mapping[str, float]] = None) -> np.ndarray:
    """The values of every local dof of V (``Function.x.array`` layout, ghosts included) of the
    field whose k-th scalar component is ``texts[k]`` (order of
    :func:`fem_dual.continua.dofs.leaf_spaces`)."""
    leaves = leaf_spaces(V)
    if isinstance(texts, str) or len(texts) != len(leaves):
        count = 1 if isinstance(texts, str) else len(texts)
        raise InputError(f"initial field: {count} expression(s) for {len(leaves)} field "
                         "components; give one per component")
    parameters = dict(parameters or {})
    equispaced_coordinates(V.mesh)  # (the expressions' signatures: fem_dual.compat)
    u = fem.Function(V)
    for leaf, text in zip(leaves, texts):
        value = field_expression(text, V.mesh, parameters)
        collapsed, parent = (V, np.arange(u.x.array.size)) if leaf is V else leaf.collapse()
        part = fem.Function(collapsed)
        if isinstance(value, float):
            part.x.array[:] = value
        else:
            expr = jit_input(f"initial field {text[:60]!r}", lambda: with_portable_fallback(
                lambda params: fem.Expression(value, collapsed.element.interpolation_points(),
                                              jit_params=params)))
            part.interpolate(expr)
        u.x.array[parent] = part.x.array
    u.x.scatter_forward()
    return u.x.array.copy()
