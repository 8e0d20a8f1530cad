"""fem-dual: particle dynamics under curl forces through a dual variational principle, solved as a
space-time finite element problem on a 1D time mesh with FEniCSx (DOLFINx 0.5.2).

The names below load on first use (PEP 562), so that `fem-dual --help`, `--version` and
`scenes` answer without importing DOLFINx and PETSc."""
import importlib
import os

# Under mpirun every rank is one process on one core: threaded BLAS would oversubscribe the
# cores (two ranks x two threads on two cores made the 200-link column 1.4x slower). Only a
# default, before numpy loads its BLAS; a user's own setting wins.
_size = os.environ.get("OMPI_COMM_WORLD_SIZE", os.environ.get("PMI_SIZE", "1")).strip()
if _size.isascii() and _size.isdigit() and int(_size) > 1:  # (not a number: no launcher)
    for _name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(_name, "1")
# An empty XDG_CACHE_HOME means the default, ~/.cache (the XDG base directory specification);
# DOLFINx would put FFCx's cache into the working directory instead.
if os.environ.get("XDG_CACHE_HOME", None) == "":
    del os.environ["XDG_CACHE_HOME"]

from fem_dual.errors import InputError, SolveError  # noqa: E402 -- after the BLAS default

__all__ = ["RunConfig", "RunResult", "run", "InputError", "SolveError", "SCENES", "get_scene"]
__version__ = "0.1.0"

_LAZY = {"RunConfig": "fem_dual.config", "RunResult": "fem_dual.integrate.result",
         "run": "fem_dual.integrate.api",
         "SCENES": "fem_dual.scenes", "get_scene": "fem_dual.scenes"}


def __getattr__(name: str):
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'fem_dual' has no attribute {name!r}")


def __dir__():
    return sorted(list(globals()) + list(_LAZY))
