"""Compiled loops around FFCx kernels: the inner loops that Python would run step by step.

UFL stays the single source: FFCx compiles the scene's force as a `fem.Expression` (its C
kernel is `tabulate_tensor_float64`), and a small C library (the sources in `src/`, built at
install time by fem_dual.native.build) calls that kernel inside its loops. `library()` loads
it; where it cannot be built or loaded, it returns None and the callers keep their numpy loops,
the compiled loops' twins (`reason()` says why). The numerical modules call the loops through
typed bindings, one module per C source:

- `rk4` (rk4.c): classical Runge-Kutta in Nystrom form, the loop of
  fem_dual.slab.base_state.FlowPredictor (the same stages and sums), with the force from its
  kernel, and its cubic Hermite read at the slab's nodes.
- `band` (band.c): the Jacobian's band of fem_dual.slab.local_action.LocalAction from the
  Hessian of the density at the quadrature points (numpy: a gather, a matrix product per
  group, a gather and a bincount).
- `dtp` (dtp.c): the Newton iteration of fem_dual.slab.pointwise_dtp.PointwiseDtP (an implicit
  DtP map solved at every point), the same steps and stopping rule, with G and G_x from the
  kernel of its expression (`force.PackedExpression` packs that kernel's coefficients as
  DOLFINx does).
- `newton` (newton.c): a slab's Newton of fem_dual.slab.pointwise_newton (the residual and band
  of fem_dual.slab.local_action from the kernel of the density's gradient and Hessian, the
  implicit DtP map solved inside each evaluation, the step by the banded Cholesky below), while
  every full step is taken; the numpy iteration decides the rest (line search, failures), so
  those rules live in one place (fem_dual.slab.native_newton drives it).
- `cholesky` (cholesky.c): the banded Cholesky factorisation in LAPACK's storage (dpbtrf's with
  uplo = 'U') and its solves, for every banded Jacobian (fem_dual.slab.banded.BandedLU): twice
  the reference LAPACK's speed on these bands.
- `tangents` (tangents.c): the exact tangents of a solved slab after their banded solve
  (LocalAction._tangent_matrix): the solved unknowns through the density's Hessian to the
  momenta at the cell ends (numpy: a dozen batched products).
- `estimate` (estimate.c): a slab's error estimate from the answer's and the companion's
  vertex values (fem_dual.integrate.simulation._estimates), and what the run's accumulator
  keeps of accepted slabs (fem_dual.integrate.sinks.Accumulator; numpy: some twenty array
  operations each).
- `force` (pack.c): the compiled force of a scene and the gather of a compiled expression's
  coefficients into its kernel's rows (`PackedExpression.pack`; numpy: a gather and a copy per
  coefficient).
"""
from __future__ import annotations

from pathlib import Path
from typing import Dict, Optional

import numpy as np

__all__ = ["library", "require", "reason", "path", "pointer"]

_loaded: Dict[str, object] = {}
_C_ARRAYS = {np.dtype(np.float64): "double[]", np.dtype(np.int64): "int64_t[]"}


def _locate() -> Path:
    """The library built from the present sources: the package's (`make install`) where it is
    intact and current, else the user cache's, compiled there first where it is not."""
    from fem_dual.native import build

    if build.current(build.PACKAGED):
        return build.PACKAGED
    target = build.cached()
    if not build.current(target):
        build.compile_library(target)
    return target


def library():
    """(ffi, lib) of the compiled loops, loaded on first use; None where they cannot be built
    or loaded (`reason()` says why)."""
    if "lib" in _loaded:
        return _loaded["lib"]
    result = None
    try:
        import cffi

        from fem_dual.native import build

        target = _locate()
        ffi = cffi.FFI()
        ffi.cdef(build.declarations())
        lib = ffi.dlopen(str(target))
        for name in dir(lib):  # every declared function (AttributeError where one is missing)
            getattr(lib, name)
        result = (ffi, lib)
        _loaded["path"] = target
    except (ImportError, OSError, AttributeError) as exc:
        _loaded["reason"] = f"{type(exc).__name__}: {exc}"
    _loaded["lib"] = result
    return result


def require():
    """(ffi, lib) of the compiled loops, for the bindings (their callers check `library()`
    first).

    Raises:
        RuntimeError: they are not available.
    """
    built = library()
    if built is None:
        raise RuntimeError(f"the compiled loops are not available: {reason()}")
    return built


def reason() -> Optional[str]:
    """Why the compiled loops are not in use (None: they are, or were not asked for yet)."""
    return _loaded.get("reason")  # type: ignore[return-value]


def path() -> Optional[Path]:
    """The library in use (None: none, or not asked for yet)."""
    return _loaded.get("path")  # type: ignore[return-value]


def pointer(ffi, array: Optional[np.ndarray], kind: Optional[str] = None):
    """A C pointer to a C-contiguous array (NULL for None): `double *` for float64 values,
    `int64_t *` for int64 ones, else `kind`. The pointer keeps the array alive while it lives
    (a temporary array passed to a call stays valid through the call).

    Raises:
        TypeError: an array of another type, without `kind`.
    """
    if array is None:
        return ffi.NULL
    if kind is not None:
        return ffi.from_buffer(kind.replace("*", "[]"), array)
    if array.dtype not in _C_ARRAYS:
        raise TypeError(f"no C array type for {array.dtype} values")
    return ffi.from_buffer(_C_ARRAYS[array.dtype], array)
