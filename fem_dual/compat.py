"""Everything that depends on DOLFINx 0.5.2 specifics lives here, and nowhere else."""
from __future__ import annotations

import logging
from contextlib import contextmanager
from typing import Iterator

import numpy as np
import ufl
from dolfinx import fem

__all__ = ["quiet_jit_logging", "CellPointEvaluator", "vector_space", "vector_space_dg1",
           "constant", "destroy_petsc", "release_function_vector"]


def _drop_info(record: logging.LogRecord) -> bool:
    return record.levelno >= logging.WARNING


_JIT_LOGGERS = ("ffcx", "UFL", "dolfinx", "distutils", "setuptools")


@contextmanager
def quiet_jit_logging() -> Iterator[None]:
    """Compile forms quietly and leave the host's logging as it was. The JIT of 0.5.2 builds
    through setuptools, which resets the root logger to INFO and logs every compiler call, and
    FFCx sets its logger's level from its options: within the block a filter on the root logger
    (it survives that reset) drops what is below WARNING; afterwards the root logger and the JIT's
    loggers get back their levels, handlers and filters."""
    root = logging.getLogger()
    saved = [(log, log.level, list(log.handlers), list(log.filters))
             for log in [root] + [logging.getLogger(name) for name in _JIT_LOGGERS]]
    root.addFilter(_drop_info)
    try:
        yield
    finally:
        for log, level, handlers, filters in saved:
            log.setLevel(level)
            log.handlers[:] = handlers
            log.filters[:] = filters


def vector_space(msh, degree: int, dim: int, family: str = "Lagrange") -> fem.FunctionSpace:
    """One blocked Lagrange (or "DG") space of `dim` components (0.5.2: ufl.VectorElement).
    On an interval, the first two dofs of a cell sit at its reference points 0 and 1."""
    return fem.FunctionSpace(msh, ufl.VectorElement(family, msh.ufl_cell(), degree, dim=dim))


def vector_space_dg1(msh, dim: int) -> fem.FunctionSpace:
    """Discontinuous P1 with `dim` components; its cell dofs sit at reference points 0 and 1."""
    return vector_space(msh, 1, dim, "DG")


def destroy_petsc(*objects) -> None:
    """Destroy PETSc objects now (collective). petsc4py 3.18 does not destroy an object whose
    Python wrapper is dropped: it stashes it on its communicator's garbage list until a
    collective PETSc.garbage_cleanup(comm), which nothing calls (and cannot reach the
    communicators DOLFINx duplicates per mesh), so every dropped KSP, SNES, matrix and vector
    of a slab solver stayed allocated. None entries are skipped; destroying twice is
    harmless."""
    for obj in objects:
        if obj is not None:
            obj.destroy()


def release_function_vector(function: fem.Function) -> None:
    """Destroy the PETSc Vec that 0.5.2's `Function.vector` wraps around the dofs (made on first
    access, kept in `_petsc_x`); a later `.vector` makes a new one."""
    vec = getattr(function, "_petsc_x", None)
    if vec is not None:
        vec.destroy()
        function._petsc_x = None


def constant(msh, value) -> fem.Constant:
    """A fem.Constant of float64 whatever the input's dtype (0.5.2 rejects integer arrays)."""
    return fem.Constant(msh, np.asarray(value, dtype=np.float64))


class CellPointEvaluator:
    """Evaluates a UFL expression at fixed reference points of given cells.

    0.5.2's `fem.Expression.eval(cells)` returns a flat (cells, points * value_size) array; this
    reshapes it to (cells, points, value_size).

    0.5.2's `fem.Expression` packs the constants of the expression as given, while FFCx's
    kernel reads those left after it expands the derivatives: a constant that a derivative
    removes (the parameter of a force F = a in dG/dx) shifted every later constant into the
    wrong slot (`force --F a --param a=-2` read H's weight from a, and the DtP map was refused
    as singular). The derivatives are expanded here first, so both see the same constants, and
    a kernel that reads another number of constants stops at set-up.
    """

    def __init__(self, expr: ufl.core.expr.Expr, ref_points: np.ndarray):
        from ufl.algorithms import expand_derivatives
        from ufl.algorithms.analysis import extract_constants

        self._points = np.asarray(ref_points, dtype=np.float64).reshape(-1, 1)
        expanded = expand_derivatives(expr)
        self._expr = fem.Expression(expanded, self._points)
        packed = len(extract_constants(expanded))
        if packed != self._expr.ufcx_expression.num_constants:
            raise RuntimeError(f"the compiled expression reads "
                               f"{self._expr.ufcx_expression.num_constants} constants where "
                               f"{packed} are packed")
        self.value_size = self._expr.value_size
        self.expression = expr
        space = self._expr.argument_function_space
        # (with a test function, each point's values run over the value and the basis)
        self._width = self.value_size * (1 if space is None else space.element.space_dimension)

    def __call__(self, cells: np.ndarray) -> np.ndarray:
        """(cells, points, values) in a new array (the C++ eval, without 0.5.2's Python
        checks: see `into`)."""
        cells = np.asarray(cells, dtype=np.int32)
        points = self._points.shape[0]
        values = self.into(cells, np.zeros((len(cells), points * self._width)))
        return values.reshape(len(cells), points, self._width)

    @property
    def compiled(self) -> fem.Expression:
        """The compiled expression (its kernel and coefficients: fem_dual.native)."""
        return self._expr

    def into(self, cells: np.ndarray, out: np.ndarray) -> np.ndarray:
        """Evaluate into `out` (int32 `cells`; float64 (cells, points * value_size), zeroed by
        the caller where the expression has an argument): 0.5.2's `eval` checks the shapes and
        allocates in Python on every call, which costs as much as the evaluation of a small
        expression; the C++ object does neither."""
        self._expr._cpp_object.eval(cells, out)
        return out
