"""Accuracy of the Ziegler column against the matrix exponential (reference, section 3.3)."""
import numpy as np
import pytest
import ufl
from dolfinx import fem
from dolfinx.fem import petsc as fem_petsc
from mpi4py import MPI

from fem_dual import RunConfig, run
from fem_dual.slab.problem import SlabProblem
from fem_dual.reference import IVPFlow
from fem_dual.scenes import get_scene
from helpers import observed_rates, ziegler_errors

# The coarsest level of each study is the coarsest whose error the acceptance rule (1e-3 of
# the motion's scale) lets through as it is; coarser runs are retried with shorter slabs.
CELLS = [80, 160, 320, 640]


@pytest.mark.mpi
@pytest.mark.parametrize("recovery, degree, rate, cells", [
    ("dtp", 2, 1.85, (320, 640, 1280)), ("dtp", 3, 2.85, CELLS[:3]),
    ("momentum", 2, 3.8, (40, 80, 160)), ("momentum", 3, 5.5, (8, 16, 32))])
def test_convergence_order(recovery, degree, rate, cells):
    """Vertex error: order p from the DtP map (x^ involves xi', of degree p - 1, one-sided at
    the vertices), order 2p from the momenta of the dual Lagrangian (superconvergent flux)."""
    results = ziegler_errors(degree, cells, T=5.0, recovery=recovery, staging="off")
    errors = [r.error["x_max"] for r in results]
    assert all(len(r.slab_lengths) == 1 for r in results)  # as asked: no slab was retried
    assert all(e < 1 for e in errors)
    assert np.all(observed_rates(errors) > rate), (errors, observed_rates(errors))
    v_errors = [r.error["v_max"] for r in results]
    assert np.all(observed_rates(v_errors) > rate - 0.1), v_errors


@pytest.mark.mpi
def test_initial_conditions_recovered():
    """x^(0) = x0 and v^(0) = v0 come back naturally: to discretisation accuracy through the DtP
    map, and to round-off through the momenta (the natural boundary condition at t = 0)."""
    x0, v0 = np.array([0.1, -0.05]), np.array([0.02, 0.03])
    gaps = {"dtp": [], "momentum": []}
    for recovery in gaps:
        for cells in (80, 160, 320):
            r = run(RunConfig.create("ziegler", cells=cells, degree=3, T=5.0, x0=x0, v0=v0,
                                     recovery=recovery, staging="off"))
            assert len(r.slab_lengths) == 1
            assert r.t[0] == 0.0 and r.recovery == recovery
            gaps[recovery].append(max(np.abs(r.x[0] - x0).max(), np.abs(r.v[0] - v0).max()))
    assert gaps["dtp"][-1] < 1e-5
    assert np.all(observed_rates(gaps["dtp"]) > 2.5), gaps
    assert max(gaps["momentum"]) < 1e-12, gaps


@pytest.mark.serial
def test_matrix_symmetric_positive_definite():
    scene = get_scene("ziegler").from_params({"P": "1.5"})
    problem = SlabProblem(scene, degree=2, cells=6, comm=MPI.COMM_SELF)
    problem.set_slab(np.array([0.1, 0.0]), np.zeros(2), 3.0)
    A = fem_petsc.assemble_matrix(fem.form(problem.jacobian), bcs=problem.bcs)
    A.assemble()
    dense = A.convert("dense").getDenseArray()
    assert np.abs(dense - dense.T).max() <= 1e-13 * np.abs(dense).max()
    assert np.linalg.eigvalsh(0.5 * (dense + dense.T)).min() > 0


@pytest.mark.serial
def test_action_is_the_closed_form_of_the_reference():
    """The action built from the pre-dual Lagrangian equals eq. (ZieglerDualAction), base state 0."""
    scene = get_scene("ziegler")()
    p = SlabProblem(scene, degree=2, cells=5, comm=MPI.COMM_SELF)
    x0, v0, dt = np.array([0.3, -0.2]), np.array([0.1, 0.4]), 2.5
    p.set_slab(x0, v0, dt)
    p.xbar.value, p.vbar.value = np.zeros(2), np.zeros(2)
    rng = np.random.default_rng(1)
    p.w.x.array[:] = rng.standard_normal(p.w.x.array.shape)
    c = {k: v.value.copy() for k, v in p.c.items()}
    M, K = ufl.as_matrix(c["M"].tolist()), ufl.as_matrix(c["K"].tolist())
    Ai, Bi = ufl.as_matrix(c["Ainv"].tolist()), ufl.as_matrix(c["Binv"].tolist())
    a = ufl.dot(K.T, p.eta) - p.dxi
    b = ufl.dot(M, p.deta) + p.xi
    L_d = 0.5 * ufl.dot(a, ufl.dot(Ai, a)) + 0.5 * ufl.dot(b, ufl.dot(Bi, b))
    dx = ufl.Measure("dx", domain=p.mesh.msh, metadata={"quadrature_degree": 4})
    closed = fem.assemble_scalar(fem.form(L_d * p.dt * dx))
    closed -= x0 @ p.w.eval([[0.0, 0, 0]], [0])[:2]
    closed -= (c["M"] @ v0) @ p.w.eval([[0.0, 0, 0]], [0])[2:]
    ours = fem.assemble_scalar(fem.form(p.action))
    assert ours == pytest.approx(closed, rel=1e-12)


@pytest.mark.mpi
def test_slabs_agree_with_one_slab():
    one = run(RunConfig.create("ziegler", cells=160, degree=3, T=10.0, slabs=1))
    many = run(RunConfig.create("ziegler", cells=40, degree=3, T=10.0, slabs=4))
    assert len(many.t) == 4 * 40 + 1  # each junction once
    assert np.allclose(one.t, many.t)
    gap = np.abs(one.x - many.x).max()
    assert gap <= one.error["x_max"] + many.error["x_max"]
    assert max(one.error["x_max"], many.error["x_max"]) < 1e-4
    assert many.slab_lengths == [2.5] * 4


@pytest.mark.mpi
def test_hamiltonian_conserved_per_slab():
    drifts = [run(RunConfig.create("ziegler", cells=c, degree=3, T=10.0, slabs=5))
              .hamiltonian["drift"] for c in (10, 20, 40)]
    assert drifts[-1] < 1e-4
    assert np.all(observed_rates(drifts) > 2.5), drifts


@pytest.mark.mpi
def test_parallel_matches_serial():
    """The distributed time mesh gives the serial numbers (run on COMM_SELF on every rank)."""
    cfg = RunConfig.create("ziegler", cells=30, degree=3, T=6.0, slabs=3)
    par, ser = run(cfg, MPI.COMM_WORLD), run(cfg, MPI.COMM_SELF)
    assert np.array_equal(par.t, ser.t)
    scale = np.abs(ser.x).max()
    assert np.abs(par.x - ser.x).max() <= 1e-10 * scale
    assert np.abs(par.v - ser.v).max() <= 1e-10 * np.abs(ser.v).max()
    assert par.error["x_max"] == pytest.approx(ser.error["x_max"], rel=1e-8)


@pytest.mark.serial
def test_reference_matches_an_ode_solver():
    """The matrix-exponential reference against DOP853 on the same problem."""
    scene = get_scene("ziegler").from_params({"P": "1.8"})
    x0, v0 = np.array([0.1, 0.0]), np.array([0.0, 0.2])
    t = np.linspace(0.0, 15.0, 301)
    x, v = scene.reference(x0, v0)(t)
    M, K = scene.mass_matrix(), scene.stiffness_matrix()
    xs, vs = IVPFlow(lambda q: -np.linalg.solve(M, K @ q), x0, v0)(t)
    assert np.abs(x - xs).max() < 1e-10 and np.abs(v - vs).max() < 1e-10


@pytest.mark.mpi
def test_cg_with_preconditioner_by_options_matches_lu():
    """The SPD slab system can be solved by CG, selected under the solver's prefix."""
    lu = run(RunConfig.create("ziegler", cells=40, degree=3, T=6.0, slabs=3))
    cg = run(RunConfig.create("ziegler", cells=40, degree=3, T=6.0, slabs=3,
                              petsc={"ksp_type": "cg", "pc_type": "jacobi", "ksp_rtol": "1e-14",
                                     "ksp_max_it": "5000"}))
    assert min(cg.solver["ksp_iterations"]) > 1  # really iterative
    assert np.abs(cg.x - lu.x).max() < 1e-9 * np.abs(lu.x).max()


@pytest.mark.mpi
def test_factorisation_reuse_equals_reassembly():
    """Equal slabs reuse one assembled, factored matrix; a fresh solver per slab agrees."""
    from fem_dual.slab.petsc_solvers import LinearSlabSolver

    scene = get_scene("ziegler")()
    problem = SlabProblem(scene, degree=3, cells=12)
    reused = LinearSlabSolver(problem, "test_reuse_")
    rng = np.random.default_rng(0)
    for _ in range(3):
        x0, v0 = rng.standard_normal(2), rng.standard_normal(2)
        problem.set_slab(x0, v0, 1.5)
        reused.solve()
        first = problem.w.x.array.copy()
        LinearSlabSolver(problem, "test_fresh_").solve()
        assert np.allclose(problem.w.x.array, first, rtol=1e-12, atol=1e-14)
    assert reused.assemblies == 1
