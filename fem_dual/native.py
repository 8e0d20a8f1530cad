"""Compiled loops around FFCx kernels: the inner loops that Python would run step by step.

UFL stays the single source: FFCx compiles the scene's force as a `fem.Expression` (its C
kernel is `tabulate_tensor_float64`), and a small C library, compiled here once per machine with
the compiler the FFCx JIT uses and kept in the user's cache (`$XDG_CACHE_HOME/fem-dual`, by
default `~/.cache/fem-dual`), calls that kernel inside its loops. Where no compiler is found,
`library()` returns None and the callers keep their numpy loops (`reason()` says why).

What it holds:
- `rk4`: classical Runge-Kutta in Nystrom form, the loop of
  fem_dual.base_state.FlowPredictor (the same stages and sums), with the force from its kernel.
- `band`: the Jacobian's band of fem_dual.local_action.LocalAction from the Hessian of the
  density at the quadrature points: the products of each Hessian group with its basis table and
  their scatter into the band, in one pass (numpy: a gather, a matrix product per group, a
  gather and a bincount).
"""
from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import tempfile
from pathlib import Path
from typing import Dict, Optional

import numpy as np

__all__ = ["library", "reason", "CompiledForce", "pointer"]

_SOURCE = r"""
#include <math.h>
#include <stdint.h>
#include <string.h>

typedef void (*kernel_t)(double *, const double *, const double *, const double *,
                         const int *, const uint8_t *);

static const double CELL[6] = {0.0, 0.0, 0.0, 1.0, 0.0, 0.0};

/* a = S F(x): S = scale I, or the matrix minv (n x n, row-major) where it is not NULL */
static void accel(kernel_t F, const double *c, int n, double scale, const double *minv,
                  const double *x, double *f, double *a)
{
    int i, j;
    const int local = 0;
    const uint8_t perm = 0;
    memset(f, 0, n * sizeof(double));
    F(f, x, c, CELL, &local, &perm);
    if (minv == NULL) {
        for (i = 0; i < n; ++i) a[i] = scale * f[i];
        return;
    }
    for (i = 0; i < n; ++i) {
        double s = 0.0;
        for (j = 0; j < n; ++j) s += minv[i * n + j] * f[j];
        a[i] = s;
    }
}

/* The band of LocalAction._band: for each Hessian group g (pairs lo[g] .. hi[g] - 1, basis
   table P_g (nd2, nq), given transposed: PT_g (nq, nd2) at PT + g nq nd2),
   B[start[g] + (ab cells + e) members + m - lo[g]] = sum_q P_g[ab, q] out[e, q, cols[m]]
   scale[e, m]; then band[flat[k]] += B[source[k]]. band (zeroed here) and B are the
   caller's. */
void fem_dual_band(int cells, int nq, int ncols, const double *out, int npairs,
                   const int64_t *cols, const double *scale, int ngroups, const int64_t *lo,
                   const int64_t *hi, const int64_t *start, const double *PT, int nd2,
                   int64_t entries, const int64_t *flat, const int64_t *source, double *B,
                   double *band, int64_t band_size)
{
    int g, e, m, q, ab;
    int64_t k;
    double acc[1024];
    for (g = 0; g < ngroups; ++g) {
        const double *Pg = PT + (int64_t)g * nd2 * nq;
        int members = (int)(hi[g] - lo[g]);
        for (e = 0; e < cells; ++e) {
            for (m = (int)lo[g]; m < hi[g]; ++m) {
                const double sc = scale[(int64_t)e * npairs + m];
                double *Bm = B + start[g] + (int64_t)e * members + (m - lo[g]);
                for (ab = 0; ab < nd2; ++ab) acc[ab] = 0.0;
                for (q = 0; q < nq; ++q) {
                    const double h = out[((int64_t)e * nq + q) * ncols + cols[m]] * sc;
                    const double *row = Pg + (int64_t)q * nd2;
                    for (ab = 0; ab < nd2; ++ab) acc[ab] += row[ab] * h;
                }
                for (ab = 0; ab < nd2; ++ab) Bm[(int64_t)ab * cells * members] = acc[ab];
            }
        }
    }
    memset(band, 0, band_size * sizeof(double));
    for (k = 0; k < entries; ++k) band[flat[k]] += B[source[k]];
}

/* Classical RK4 of x' = v, v' = a(x) in Nystrom form over `steps` steps of length h from z0 =
   (x, v): states and rates (steps + 1, 2n), rates = (v, a(x)). work: 7 n doubles. Returns 0, or
   1 where a value is not finite (the loop stops there). */
int fem_dual_rk4(uintptr_t kernel, const double *c, int n, int steps, double h, double scale,
                 const double *minv, const double *z0, double *states, double *rates,
                 double *work)
{
    kernel_t F = (kernel_t)kernel;
    double *k1 = work, *k2 = work + n, *k3 = work + 2 * n, *k4 = work + 3 * n;
    double *y = work + 4 * n, *ahead = work + 5 * n, *f = work + 6 * n;
    const double half = 0.5 * h, h2 = 0.25 * h * h, hh2 = 0.5 * h * h;
    const double hh6 = h * h / 6.0, h6 = h / 6.0;
    int s, i, m = 2 * n;
    double *x, *v;
    memcpy(states, z0, m * sizeof(double));
    accel(F, c, n, scale, minv, states, f, k1);
    memcpy(rates, states + n, n * sizeof(double));
    memcpy(rates + n, k1, n * sizeof(double));
    for (s = 0; s < steps; ++s) {
        x = states + s * m;
        v = x + n;
        for (i = 0; i < n; ++i) y[i] = x[i] + half * v[i];
        accel(F, c, n, scale, minv, y, f, k2);
        for (i = 0; i < n; ++i) y[i] += h2 * k1[i];
        accel(F, c, n, scale, minv, y, f, k3);
        for (i = 0; i < n; ++i) {
            ahead[i] = x[i] + h * v[i];
            y[i] = ahead[i] + hh2 * k2[i];
        }
        accel(F, c, n, scale, minv, y, f, k4);
        for (i = 0; i < n; ++i) {
            x[m + i] = ahead[i] + hh6 * (k1[i] + k2[i] + k3[i]);
            x[m + n + i] = v[i] + h6 * (k1[i] + 2.0 * (k2[i] + k3[i]) + k4[i]);
        }
        accel(F, c, n, scale, minv, x + m, f, k1);
        for (i = 0; i < n; ++i) {
            rates[(s + 1) * m + i] = x[m + n + i];
            rates[(s + 1) * m + n + i] = k1[i];
        }
        for (i = 0; i < m; ++i)
            if (!isfinite(x[m + i]) || !isfinite(rates[(s + 1) * m + i])) return 1;
    }
    return 0;
}
"""

_CDEF = """
void fem_dual_band(int cells, int nq, int ncols, const double *out, int npairs,
                   const int64_t *cols, const double *scale, int ngroups, const int64_t *lo,
                   const int64_t *hi, const int64_t *start, const double *PT, int nd2,
                   int64_t entries, const int64_t *flat, const int64_t *source, double *B,
                   double *band, int64_t band_size);
int fem_dual_rk4(uintptr_t kernel, const double *c, int n, int steps, double h, double scale,
                 const double *minv, const double *z0, double *states, double *rates,
                 double *work);
"""

_FLAGS = ("-O3", "-fPIC", "-shared")  # no -march=native: the same code on every machine
_loaded: Dict[str, object] = {}


def _cache_dir() -> Path:
    root = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(root) / "fem-dual"


def _compile(target: Path) -> None:
    """Compile the library into `target` (written under another name, then renamed: processes
    that compile at once each leave a whole file)."""
    import sysconfig

    compiler = (sysconfig.get_config_var("CC") or "cc").split()[0]
    if shutil.which(compiler) is None:
        compiler = shutil.which("cc") or shutil.which("gcc") or ""
        if not compiler:
            raise OSError("no C compiler (cc, gcc) on PATH")
    target.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=target.parent) as tmp:
        source = Path(tmp) / "fem_dual_native.c"
        source.write_text(_SOURCE)
        built = Path(tmp) / target.name
        subprocess.run([compiler, "-O3", "-fPIC", "-shared", "-o", str(built), str(source),
                        "-lm"], check=True, capture_output=True, timeout=120)
        os.replace(built, target)


def library():
    """(ffi, lib) of the compiled loops, compiled on first use and kept; None where it cannot
    be built or loaded (`reason()` says why)."""
    if "lib" in _loaded:
        return _loaded["lib"]
    result = None
    try:
        import cffi

        digest = hashlib.sha256((_SOURCE + _CDEF + " ".join(_FLAGS)).encode()).hexdigest()[:16]
        target = _cache_dir() / f"native-{digest}.so"
        if not target.exists():
            _compile(target)
        ffi = cffi.FFI()
        ffi.cdef(_CDEF)
        try:
            lib = ffi.dlopen(str(target))
        except OSError:  # a damaged file (a compile killed before the rename cannot leave one)
            _compile(target)
            lib = ffi.dlopen(str(target))
        result = (ffi, lib)
    except (ImportError, OSError, subprocess.SubprocessError) as exc:
        _loaded["reason"] = f"{type(exc).__name__}: {exc}"
    _loaded["lib"] = result
    return result


def reason() -> Optional[str]:
    """Why the compiled loops are not in use (None: they are, or were not asked for yet)."""
    return _loaded.get("reason")  # type: ignore[return-value]


def pointer(ffi, array: Optional[np.ndarray], kind: str = "double *"):
    """A C pointer to a C-contiguous float64 array (NULL for None), valid while it lives."""
    if array is None:
        return ffi.NULL
    return ffi.cast(kind, array.ctypes.data)


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
        import cffi
        import ufl
        from dolfinx import cpp, fem, mesh
        from mpi4py import MPI

        from fem_dual.compat import constant, quiet_jit_logging, vector_space

        n = scene.n
        msh = mesh.create_unit_interval(MPI.COMM_SELF, 1)
        self.x = fem.Function(vector_space(msh, 0, n, "DG"))
        self.c = {k: constant(msh, v) for k, v in scene.constants().items()}
        force = ufl.as_vector([scene.forms.force(self.x, self.c)[i] for i in range(n)])
        if force.ufl_domain() is None:  # depends on neither x nor a constant
            raise ValueError("the force is a number")
        with quiet_jit_logging():
            self._expr = fem.Expression(force, np.zeros((1, 1)))
        self._pack = lambda: cpp.fem.pack_constants(self._expr._cpp_object)
        self.kernel = int(cffi.FFI().cast("uintptr_t",
                                          self._expr.ufcx_expression.tabulate_tensor_float64))
        self.n = n

    def pack(self, scene) -> np.ndarray:
        """The kernel's constants for `scene`'s parameter values."""
        for key, value in scene.constants().items():
            self.c[key].value = value
        return np.ascontiguousarray(self._pack(), dtype=np.float64)
