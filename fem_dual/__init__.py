"""fem-dual: particle dynamics under curl forces through a dual variational principle, solved as a
space-time finite element problem on a 1D time mesh with FEniCSx (DOLFINx 0.5.2)."""
from fem_dual.config import RunConfig
from fem_dual.driver import RunResult, run
from fem_dual.errors import InputError, SolveError
from fem_dual.scenes import SCENES, get_scene

__all__ = ["RunConfig", "RunResult", "run", "InputError", "SolveError", "SCENES", "get_scene"]
__version__ = "0.1.0"
