"""Fields of a free vector for output: each field of V as its own ``fem.Function``, and that
function interpolated into vertex (P1) values, which is what ``XDMFFile.write_function`` stores
in DOLFINx 0.5.2 (it writes vertex values of whatever it gets; P2 data must be interpolated
first, here explicitly).

A *field* is a sub-space of a mixed space (Beck: w and theta), or the whole space when V is
scalar or blocked (a displacement vector stays one vector field).
"""
from __future__ import annotations

from typing import List, Sequence

import ufl
from dolfinx import fem

__all__ = ["split_fields", "vertex_functions"]


def split_fields(u: fem.Function) -> List[fem.Function]:
    """The fields of u, each a Function on its own (collapsed) space, values copied."""
    V = u.function_space
    if V.num_sub_spaces == 0 or V.dofmap.index_map_bs > 1:
        return [u]
    return [u.sub(i).collapse() for i in range(V.num_sub_spaces)]


def vertex_functions(u: fem.Function, names: Sequence[str]) -> List[fem.Function]:
    """Each field of u interpolated into continuous P1 of its shape and named, ready for
    ``XDMFFile.write_function(f, t)``."""
    parts = split_fields(u)
    if len(names) != len(parts):
        raise ValueError(f"vertex_functions: {len(names)} names for {len(parts)} fields")
    out = []
    for part, name in zip(parts, names):
        msh = part.function_space.mesh
        shape = part.ufl_shape
        if shape:
            element = ufl.VectorElement("Lagrange", msh.ufl_cell(), 1, dim=shape[0])
        else:
            element = ufl.FiniteElement("Lagrange", msh.ufl_cell(), 1)
        f = fem.Function(fem.FunctionSpace(msh, element), name=name)
        f.interpolate(part)
        out.append(f)
    return out
