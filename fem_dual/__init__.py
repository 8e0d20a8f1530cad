"""fem-dual: particle dynamics under curl forces through a dual variational principle, solved as a
space-time finite element problem on a 1D time mesh with FEniCSx (DOLFINx 0.5.2)."""
import os

# Under mpirun every rank is one process on one core: threaded BLAS would oversubscribe the
# cores (two ranks x two threads on two cores made the 200-link column 1.4x slower). Only a
# default, before numpy loads its BLAS; a user's own setting wins.
if int(os.environ.get("OMPI_COMM_WORLD_SIZE", os.environ.get("PMI_SIZE", "1"))) > 1:
    for _name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(_name, "1")

from fem_dual.config import RunConfig
from fem_dual.driver import RunResult, run
from fem_dual.errors import InputError, SolveError
from fem_dual.scenes import SCENES, get_scene

__all__ = ["RunConfig", "RunResult", "run", "InputError", "SolveError", "SCENES", "get_scene"]
__version__ = "0.1.0"
