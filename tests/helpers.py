"""Shared test helpers."""
import numpy as np

from fem_dual import RunConfig, run


def observed_rates(errors):
    e = np.asarray(errors)
    return np.log2(e[:-1] / e[1:])


def ziegler_errors(degree, cells_list, comm=None, **kw):
    from mpi4py import MPI
    comm = comm or MPI.COMM_WORLD
    results = [run(RunConfig.create("ziegler", cells=c, degree=degree, **kw), comm)
               for c in cells_list]
    return results
