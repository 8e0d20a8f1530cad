"""`run`: a configuration in, a RunResult out (the library's entry point)."""
from __future__ import annotations

import gc
import time
from typing import Callable, Optional

from mpi4py import MPI

from fem_dual.config import RunConfig
from fem_dual.errors import InputError, SolveError
from fem_dual.integrate.result import RunResult
from fem_dual.integrate.simulation import Simulation
from fem_dual.output import check_output_dir_on_root

__all__ = ["run", "RunResult", "Simulation"]


def run(config: RunConfig, comm: MPI.Comm = MPI.COMM_WORLD, progress: bool = False,
        resume: bool = False, before: Optional[Callable[[], None]] = None) -> RunResult:
    """Solve the dual problem slab by slab, recover the primal motion, compare with the reference.

    With `resume`, go on from the last slab an earlier run of the same options wrote into
    `config.out` (the end state equals an uninterrupted run's).

    Nonlinear scenes retry a slab whose Newton (or DtP map) fails with half its length, up to
    `config.max_halvings` times; `progress` shows a bar over the slabs on stderr (rank 0).

    Nothing is written before every input is checked: the PETSc options are checked as the
    solver is set up, `config.out` is checked, `before()` (the caller's own checks, e.g. the
    command line's --csv and --plot) runs, and only then is `config.out` made.

    Raises:
        SolveError: a slab failed, or writing the output did; `partial` holds the result of the
            slabs completed before, whose output files (if any) are readable.
        fem_dual.faults.Interrupted: SIGINT/SIGTERM (with fem_dual.faults.graceful_signals)
            stopped the run after a slab; `partial` as for SolveError.
    """
    if not isinstance(config, RunConfig):
        raise InputError(f"config must be a RunConfig (RunConfig.create(...)), not "
                         f"{type(config).__name__}")
    tic = time.perf_counter()
    config.scene.checked()  # a RunConfig built without create() is validated all the same
    if resume and config.out is None:
        raise InputError("resume needs the output directory of the run to go on with (--out)")
    sim = Simulation.for_config(config, comm)  # (bad or unused PETSc options raise InputError)
    # the set-up no other timing holds: building and checking the inputs (RunConfig.create),
    # and what the simulation needs beyond its own build (compile_s), e.g. the modal coordinates
    setup_s = config.setup_s + max(time.perf_counter() - tic - sim.setup_s, 0.0)
    failure = None
    try:
        if config.out is not None:  # a bad --out is bad input, on every rank
            check_output_dir_on_root(comm, config.out, create=False)
        if before is not None:
            before()
        if config.out is not None:
            check_output_dir_on_root(comm, config.out)
        result = sim.run(config, progress, resume, setup_s)
    except (SolveError, InputError) as exc:  # raised on every rank alike: close collectively
        failure = exc
    # (any other exception may be one rank's own: a collective close could hang, so its
    # objects are left to petsc4py's garbage)
    sim.close()
    # The simulation's objects (UFL expressions, compiled kernels, the slab problem) hold each
    # other in reference cycles, which Python frees when its cycle collector next runs: a
    # young-generation collection (about a millisecond) frees them now, so that repeated runs
    # keep a flat footprint (tests/test_memory.py)
    del sim
    gc.collect(1)
    if failure is not None:
        raise failure
    return result
