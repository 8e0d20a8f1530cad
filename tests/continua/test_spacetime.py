"""The sparse, distributed space-time slab (fem_dual.continua.spacetime) is the dense Kronecker
path's slab (fem_dual.slab.kronecker, base state "start", energy weights): the same vertex
values x, v, on one rank and under ``mpirun -n 2 python -m pytest
tests/continua/test_spacetime.py``; and its preconditioner's CG iterations do not grow with
the mesh."""
import numpy as np
import pytest
from dolfinx import fem, mesh
from mpi4py import MPI

from fem_dual.continua.cauchy import CauchyElasticity, CauchyParameters, cauchy_forms
from fem_dual.continua.dofs import gather_rows
from fem_dual.continua.scenes import Cauchy2D
from fem_dual.continua.spacetime import SpaceTimeSlab
from fem_dual.continua.system import SpatialSystem
from fem_dual.scenes.linear import GeneralLinear
from fem_dual.slab.kronecker import KroneckerProblem, KroneckerSampler
from fem_dual.slab.kronecker_solver import KroneckerSolver

DEGREE, CELLS = 4, 8
U0 = ("0.01*sin(pi*x)*sin(pi*y)", "0.01*sin(pi*x)*sin(2*pi*y)")
V0 = ("0.05*sin(2*pi*x)*sin(pi*y)", "-0.03*x*(1-x)*y*(1-y)")
TIGHT = {"ksp_rtol": "1e-12"}


def dense_vertex_values(scene, x0, v0, dt, prefix):
    """x, v at the vertices (vertices, n) by the dense Kronecker path, on this rank alone."""
    problem = KroneckerProblem(scene, DEGREE, CELLS, MPI.COMM_SELF, base="start")
    solver = KroneckerSolver(problem, prefix)
    try:
        problem.set_slab(x0, v0, dt)
        solver.solve()
        linear = KroneckerSampler(problem).linear_part()
    finally:
        solver.close()
    n = scene.n
    return linear[:, :n], linear[:, n:2 * n]


def sparse_vertex_values(system, x0, v0, dt, **kwargs):
    """x, v at the vertices (vertices, n_local) by the sparse slab, and its CG iterations."""
    slab = SpaceTimeSlab.from_system(system, DEGREE, CELLS, **kwargs)
    try:
        slab.set_slab(x0, v0, dt)
        its = slab.solve()
        x, v = slab.vertex_values()
    finally:
        slab.close()
    return x, v, its


def by_dof(coordinates, field):
    """The permutation that sorts free dofs by (field, x, y)."""
    keys = np.round(coordinates, 12)
    return np.lexsort((keys[:, 1], keys[:, 0], field))


def relative(a, b):
    return np.abs(a - b).max() / np.abs(b).max()


@pytest.mark.mpi
@pytest.mark.parametrize("delta", [0.5, 0.0])
def test_cauchy_slab_equals_the_dense_kronecker_slab(delta):
    """Cauchy2D (non-symmetric K for delta != 0): the distributed sparse slab's vertex values
    are the dense path's (dofs matched by coordinates), to 1e-9 relative."""
    comm = MPI.COMM_WORLD
    dt = 0.3
    system = CauchyElasticity(CauchyParameters(delta=delta, elements=5), comm).system
    x0, v0 = system.interpolate(list(U0)), system.interpolate(list(V0))
    x, v, its = sparse_vertex_values(system, x0, v0, dt, options=TIGHT)
    assert its > 0
    layout = system.free_layout()
    x_all, v_all = gather_rows(comm, x.T.copy()), gather_rows(comm, v.T.copy())
    if comm.rank != 0:
        return
    scene = Cauchy2D(delta=delta, elements=5, weights="energy")
    serial = scene.spatial()[0]
    xs0, vs0 = scene.start_state(list(U0), list(V0))
    x_ref, v_ref = dense_vertex_values(scene, xs0, vs0, dt, "test_spacetime_dense_")
    mine, ref = by_dof(*layout), by_dof(serial.coordinates, serial.field)
    assert x_all.shape == (scene.n, CELLS + 1)
    assert relative(x_all[mine].T, x_ref[:, ref]) < 1e-9
    assert relative(v_all[mine].T, v_ref[:, ref]) < 1e-9


def damped_system(comm, elements=4):
    """The clamped Cauchy square with a non-symmetric damping form 0.3 m + 0.05 k."""
    body = CauchyElasticity(CauchyParameters(delta=0.5, elements=elements), comm)
    m, k = cauchy_forms(body.V, body.C, body.rho)
    tdim = body.msh.topology.dim
    body.msh.topology.create_connectivity(tdim - 1, tdim)
    facets = mesh.exterior_facet_indices(body.msh.topology)
    clamp = fem.dirichletbc(np.zeros(2), fem.locate_dofs_topological(body.V, tdim - 1, facets),
                            body.V)
    d = 0.3 * m + 0.05 * k
    system = SpatialSystem(body.V, [clamp], m, k, d)
    system.body = body  # (keeps the constants of the forms alive)
    return system


@pytest.mark.mpi
def test_damped_slab_equals_the_dense_kronecker_slab():
    """With a damping matrix D (here not symmetric): the D terms of the Hessian, the right-hand
    side and the recovery are the dense path's (a GeneralLinear scene of the same matrices, in
    the distributed free-dof order)."""
    comm = MPI.COMM_WORLD
    dt = 0.4
    system = damped_system(comm)
    assert system.has_damping
    x0, v0 = system.interpolate(list(U0)), system.interpolate(list(V0))
    x, v, _ = sparse_vertex_values(system, x0, v0, dt, options=TIGHT)
    M, K, D = system.dense()
    x_all, v_all = gather_rows(comm, x.T.copy()), gather_rows(comm, v.T.copy())
    x0_all, v0_all = system.gather(x0), system.gather(v0)
    if comm.rank != 0:
        return
    scene = GeneralLinear(dofs=system.n, M=tuple(map(tuple, M)), K=tuple(map(tuple, K)),
                          D=tuple(map(tuple, D)), weights="energy")
    x_ref, v_ref = dense_vertex_values(scene, x0_all, v0_all, dt, "test_spacetime_damped_")
    assert relative(x_all.T, x_ref) < 1e-9
    assert relative(v_all.T, v_ref) < 1e-9


@pytest.mark.mpi
def test_preconditioner_iterations_do_not_grow_with_the_mesh():
    """CG iterations (time-mode preconditioner, AMG) on 6 and on 12 elements a side, dt = 0.5
    (the time-resolution resonances already within both meshes' spectra): at most 1.5 times."""
    comm = MPI.COMM_WORLD
    counts = []
    for elements in (6, 12):
        system = CauchyElasticity(CauchyParameters(delta=0.5, elements=elements), comm).system
        x0 = system.interpolate(list(U0))
        counts.append(sparse_vertex_values(system, x0, 0 * x0, 0.5,
                                           options={"ksp_rtol": "1e-10"})[2])
    assert counts[1] <= 1.5 * counts[0], counts


def test_the_preconditioned_model_is_bounded_over_every_spatial_frequency():
    """The symmetric model with exact spatial solves (P_4, 8 cells): its condition number grows
    with the radians tau the mesh's fastest mode turns per slab until the worst time-resolution
    resonance (tau = 29.6) and stays there (272 for sgs): CG counts stop growing with the
    mesh; the Gauss-Seidel sweep over the coupling gains 4x on dropping it."""
    from fem_dual.continua.spacetime_pc import model_condition
    sgs = model_condition(4, 8, [3.4, 13.6, 27.2, 32.0, 400.0])
    assert np.all(np.diff(sgs) >= 0) and sgs[0] < 10 and 50 < sgs[1] < sgs[2]
    assert sgs[3] == pytest.approx(sgs[4], rel=1e-9) and 250 < sgs[4] < 300
    jacobi = model_condition(4, 8, [400.0], coupling="jacobi")
    assert jacobi[0] > 3.5 * sgs[4]
    with pytest.raises(ValueError, match="coupling"):
        model_condition(4, 8, [1.0], coupling="exact")


@pytest.mark.mpi
def test_slab_api_and_failure():
    """num_dofs counts the CG unknowns; set_slab checks the start state's shape; a CG that
    cannot converge in its iteration limit is a SolveError."""
    from fem_dual.errors import SolveError

    comm = MPI.COMM_WORLD
    system = CauchyElasticity(CauchyParameters(delta=0.5, elements=4), comm).system
    slab = SpaceTimeSlab.from_system(system, DEGREE, CELLS, options={"ksp_max_it": "2"})
    try:
        assert slab.num_dofs == DEGREE * CELLS * 2 * system.n
        with pytest.raises(ValueError):
            slab.set_slab(np.zeros(system.n_local + 1), np.zeros(system.n_local), 0.1)
        x0 = system.interpolate(list(U0))
        slab.set_slab(x0, 0 * x0, 0.1)
        with pytest.raises(SolveError):
            slab.solve()
    finally:
        slab.close()


def test_time_interpolation_is_exact_for_the_coarser_degree():
    """TimeMatrices.interpolation carries a P_p function of the slab's cells into P_(p+1)
    exactly (their values agree at the richer space's nodes)."""
    from fem_dual.slab.time_space import TimeMatrices

    coarse, fine = TimeMatrices(DEGREE, CELLS), TimeMatrices(DEGREE + 1, CELLS)
    f = lambda s: 1 + s - 3 * s ** 2 + 2 * s ** DEGREE  # noqa: E731 (degree p: in P_p)
    s_coarse = (np.arange(CELLS)[:, None] + coarse.nodes()[None]) / CELLS
    s_fine = (np.arange(CELLS)[:, None] + fine.nodes()[None]) / CELLS
    values = np.zeros(coarse.size)
    values[coarse.cell_dofs] = f(s_coarse)
    out = fine.interpolation(coarse) @ values
    assert np.abs(out[fine.cell_dofs] - f(s_fine)).max() < 1e-13
    with pytest.raises(ValueError):
        coarse.interpolation(fine)


@pytest.mark.mpi
def test_companion_started_from_the_answer_converges_to_the_same_slab_sooner():
    """The degree p + 1 slab started from the degree p answer's dual fields reaches the slab it
    reaches from zero (to the CG tolerance) in fewer iterations; a guess for another start state
    is not used."""
    comm = MPI.COMM_WORLD
    system = CauchyElasticity(CauchyParameters(delta=0.5, elements=8), comm).system
    x0 = system.interpolate(list(U0))
    v0 = system.interpolate(list(V0))
    answer = SpaceTimeSlab.from_system(system, DEGREE, CELLS, options=TIGHT)
    cold = SpaceTimeSlab.from_system(system, DEGREE + 1, CELLS, options=TIGHT)
    warm = SpaceTimeSlab.from_system(system, DEGREE + 1, CELLS, options=TIGHT)
    try:
        for slab in (answer, cold, warm):
            slab.set_slab(x0, v0, 0.05)
        answer.solve()
        cold_its, warm_its = cold.solve(), warm.solve(answer)
        assert warm_its < cold_its, (warm_its, cold_its)
        for a, b in zip(warm.vertex_values(), cold.vertex_values()):
            scale = comm.allreduce(np.abs(b).max(), op=MPI.MAX)
            assert comm.allreduce(np.abs(a - b).max(), op=MPI.MAX) < 1e-9 * scale
        warm.set_slab(2 * x0, v0, 0.05)  # another start: solved from zero
        warm.solve(answer)
        assert not warm.ksp.getInitialGuessNonzero()
    finally:
        for slab in (answer, cold, warm):
            slab.close()
