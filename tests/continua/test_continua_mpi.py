"""A distributed SpatialSystem is the serial one: run with
``mpirun -n 2 python3 -m pytest -m mpi tests/continua`` (in serial it compares a system with
itself, through the same dof matching)."""
import numpy as np
import pytest
from mpi4py import MPI

from fem_dual.continua.cauchy import CauchyElasticity, CauchyParameters


def by_dof(layout):
    """The permutation that sorts free dofs by (field, x, y), and the sorted keys."""
    coordinates, field = layout
    keys = np.round(coordinates, 12)
    order = np.lexsort((keys[:, 1], keys[:, 0], field))
    return order, np.column_stack([field[order], keys[order]])


@pytest.mark.mpi
@pytest.mark.parametrize("degree", [1, 2])
def test_distributed_cauchy_matrices_equal_the_serial_ones(degree):
    comm = MPI.COMM_WORLD
    params = CauchyParameters(delta=0.6, elements=16, degree=degree)
    distributed = CauchyElasticity(params, comm).system
    mats, layout = distributed.to_scipy(), distributed.free_layout()
    assert comm.allreduce(distributed.n_local) == distributed.n
    assert comm.size == 1 or 0 < distributed.n_local < distributed.n  # really distributed
    if comm.rank != 0:
        return
    serial = CauchyElasticity(params, MPI.COMM_SELF).system
    reference = serial.to_scipy()
    p, keys = by_dof(layout)
    q, reference_keys = by_dof(serial.free_layout())
    assert distributed.n == serial.n and np.array_equal(keys, reference_keys)
    for name in ("M", "K", "D"):
        A = mats[name].toarray()[np.ix_(p, p)]
        B = reference[name].toarray()[np.ix_(q, q)]
        assert np.abs(A - B).max() <= 1e-13 * max(np.abs(B).max(), 1.0), name
    assert mats["K"].nnz == reference["K"].nnz


@pytest.mark.mpi
def test_distributed_initial_field_and_function_round_trip():
    """interpolate gives the same global free vector on any number of ranks (matched by dof)."""
    comm = MPI.COMM_WORLD
    params = CauchyParameters(elements=16, degree=2)
    distributed = CauchyElasticity(params, comm).system
    exprs = ["sin(pi*x)*y*(1-y)", "x*(1-x)*exp(y)"]
    q = distributed.interpolate(exprs)
    assert np.array_equal(distributed.from_function(distributed.to_function(q)), q)
    g, layout = distributed.gather(q), distributed.free_layout()
    if comm.rank != 0:
        return
    serial = CauchyElasticity(params, MPI.COMM_SELF).system
    p, _ = by_dof(layout)
    r, _ = by_dof(serial.free_layout())
    assert np.allclose(g[p], serial.interpolate(exprs)[r], rtol=0, atol=1e-15)
