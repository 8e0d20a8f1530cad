"""A scene's force and a compiled expression as FFCx kernels with their packed coefficients,
for the compiled loops that call those kernels themselves (fem_dual.native)."""
from __future__ import annotations

from typing import Optional

import numpy as np

from fem_dual.native import library, pointer

__all__ = ["CompiledForce", "PackedExpression"]


class CompiledForce:
    """A scene's UFL force F(x) compiled by FFCx (a `fem.Expression` of x, a DG0 vector on a
    mesh of one cell), for the compiled loops: `kernel` is its tabulate_tensor_float64's
    address, `pack(scene)` the constants it reads, in its order, for the scene's values.

    Args:
        scene: a nonlinear scene (its forms give `force(x, c)`).

    Raises:
        ValueError: the force is a number (no expression to compile: `of` gives None).
    """

    @classmethod
    def of(cls, scene) -> Optional["CompiledForce"]:
        """The compiled force of `scene`; None for a force that is a number (F = 1)."""
        try:
            return cls(scene)
        except ValueError:
            return None

    def __init__(self, scene):
        import ufl
        from dolfinx import fem, mesh
        from mpi4py import MPI

        from fem_dual.compat import (CellPointEvaluator, constant, equispaced_coordinates,
                                     quiet_jit_logging, vector_space)

        n = scene.n
        msh = mesh.create_unit_interval(MPI.COMM_SELF, 1)
        equispaced_coordinates(msh)  # (stable signatures: fem_dual.compat)
        self.x = fem.Function(vector_space(msh, 0, n, "DG"))
        self.c = {k: constant(msh, v) for k, v in scene.constants().items()}
        force = ufl.as_vector([scene.forms.force(self.x, self.c)[i] for i in range(n)])
        if force.ufl_domain() is None:  # depends on neither x nor a constant
            raise ValueError("the force is a number")
        with quiet_jit_logging():
            expr = CellPointEvaluator(force, np.zeros(1)).compiled
        self._packed = PackedExpression(expr, np.zeros(1, dtype=np.int32))
        self.kernel = self._packed.kernel
        self.n = n

    def pack(self, scene) -> np.ndarray:
        """The kernel's constants for `scene`'s parameter values."""
        for key, value in scene.constants().items():
            self.c[key].value = value
        return self._packed.constants()


class PackedExpression:
    """A compiled `fem.Expression` with its coefficients packed as DOLFINx packs them for its
    kernel (a row per cell: each coefficient's cell values, dof by dof and component by
    component, in the kernel's order), for the compiled loops that call the kernel themselves.
    Elements on an interval need no dof transformation (Lagrange, DG, Quadrature).

    Args:
        expr: the compiled expression (fem_dual.compat.CompiledExpression).
        cells: the cells (int32) whose rows are packed.
    """

    def __init__(self, expr, cells: np.ndarray):
        import cffi
        from dolfinx import cpp

        ufcx = expr.ufcx_expression
        self.coefficients = list(expr.coefficients)  # (in the kernel's order)
        self.cells = np.asarray(cells, dtype=np.int32)
        columns, self._slots = [], {}
        offset = 0
        for f in self.coefficients:
            V = f.function_space
            bs = V.dofmap.index_map_bs
            dofs = V.dofmap.list.array.reshape(len(V.dofmap.list.offsets) - 1, -1)[self.cells]
            index = (dofs[:, :, None] * bs + np.arange(bs)).reshape(len(self.cells), -1)
            columns.append((f, f.x.array, index))  # (a view of f's vector: stays valid)
            self._slots[id(f)] = offset + np.arange(index.shape[1])
            offset += index.shape[1]
        self._columns = columns
        self.packed = np.zeros((len(self.cells), max(offset, 1)))
        self._compiled = self._compiled_pack()
        msh = expr.mesh
        geometry = msh.geometry.dofmap.array.reshape(-1, 2)[self.cells]
        self.coords = np.ascontiguousarray(msh.geometry.x[geometry].reshape(len(self.cells), 6))
        self._constants = lambda: cpp.fem.pack_constants(expr._cpp_object)
        self.kernel = int(cffi.FFI().cast("uintptr_t", ufcx.tabulate_tensor_float64))

    def _compiled_pack(self) -> Optional[tuple]:
        """(the `pack` function, its arguments) of the compiled gather where the library is
        available (the coefficients' value arrays are views of their vectors: they stay
        valid), else None."""
        built = library()
        if built is None or not self._columns:
            return None
        ffi, lib = built
        kept = [np.ascontiguousarray(index, dtype=np.int64) for _, _, index in self._columns]
        views = [ffi.from_buffer("double[]", values) for _, values, _ in self._columns]
        views += [ffi.from_buffer("int64_t[]", index) for index in kept]
        address = (lambda view: int(ffi.cast("uintptr_t", view)))
        count = len(kept)
        width = np.array([index.shape[1] for index in kept], dtype=np.int64)
        offset = np.concatenate([[0], np.cumsum(width)[:-1]]).astype(np.int64)
        values = ffi.new("uintptr_t[]", [address(v) for v in views[:count]])
        index = ffi.new("uintptr_t[]", [address(v) for v in views[count:]])
        args = (len(self.cells), count, self.packed.shape[1], pointer(ffi, width),
                pointer(ffi, offset), values, index, pointer(ffi, self.packed))
        self._keep_alive = (kept, views, width, offset)
        return lib.fem_dual_pack, args

    def pack(self) -> np.ndarray:
        """The rows of the coefficients' current values."""
        if self._compiled is not None:
            self._compiled[0](*self._compiled[1])
            return self.packed
        start = 0
        for _, values, index in self._columns:
            self.packed[:, start:start + index.shape[1]] = values[index]
            start += index.shape[1]
        return self.packed

    def index(self, f) -> np.ndarray:
        """(cells, columns): where in `f.x.array` each of its columns of a row is packed from."""
        return next(index for g, _, index in self._columns if g is f)

    def slot(self, f) -> np.ndarray:
        """The columns of a row that hold the coefficient `f`'s cell values."""
        return self._slots[id(f)]

    def constants(self) -> np.ndarray:
        """The kernel's constants at their current values."""
        return np.ascontiguousarray(self._constants(), dtype=np.float64)
