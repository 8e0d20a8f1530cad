"""Cauchy elasticity without major symmetry: the structure of K, the work of a closed strain
cycle, convergence of the symmetric frequencies, and the reality of the spectrum."""
import numpy as np
import pytest
import scipy.sparse.linalg as spla
import ufl
from dolfinx import fem, mesh
from mpi4py import MPI

from fem_dual.continua import SpatialSystem
from fem_dual.continua.cauchy import (ANTISYMMETRIC, CauchyElasticity, CauchyParameters,
                                      cauchy_forms, elasticity_matrix, real_spectrum_guaranteed,
                                      spectrum_check, symmetrizing_scale)
from fem_dual.continua.dofs import gather_csr
from fem_dual.errors import InputError


def dense_stiffness(problem, C):
    A = problem.stiffness(C)
    out = gather_csr(A)
    A.destroy()
    return None if out is None else out.toarray()


@pytest.mark.mpi
def test_stiffness_is_symmetric_part_plus_delta_times_antisymmetric_part():
    lam, mu, delta = 1.0, 1.0, 0.6
    problem = CauchyElasticity(CauchyParameters(lam=lam, mu=mu, delta=delta, elements=6))
    K = dense_stiffness(problem, elasticity_matrix(lam, mu, delta))
    K0 = dense_stiffness(problem, elasticity_matrix(lam, mu, 0.0))
    Ka = dense_stiffness(problem, ANTISYMMETRIC)
    if MPI.COMM_WORLD.rank == 0:
        scale = np.abs(K).max()
        assert np.abs(K0 - K0.T).max() <= 1e-14 * scale
        assert np.array_equal(Ka, -Ka.T)
        assert np.abs(K - (K0 + delta * Ka)).max() <= 1e-14 * scale
        assert np.abs((K - K.T) - 2 * delta * Ka).max() <= 1e-14 * scale


@pytest.mark.serial
@pytest.mark.parametrize("degree", [1, 2])
def test_work_of_a_closed_strain_cycle_is_minus_two_delta_times_its_area(degree):
    """One triangle, free (no clamping), homogeneous strains eps11 = a, eps22 = b (exact in
    P1): the work k(u, du) around the rectangle 0 -> (a, 0) -> (a, b) -> (0, b) -> 0 in the
    (eps11, eps22) plane is -2 delta a b times the triangle's area. Along a straight segment
    the integral of du^T K u is (u_1 - u_0)^T K (u_0 + u_1) / 2 exactly."""
    domain = ufl.Mesh(ufl.VectorElement("Lagrange", ufl.triangle, 1))
    points = np.array([[0.0, 0.0], [1.0, 0.2], [0.3, 0.8]])
    msh = mesh.create_mesh(MPI.COMM_SELF, np.array([[0, 1, 2]], dtype=np.int64), points, domain)
    V = fem.FunctionSpace(msh, ufl.VectorElement("Lagrange", msh.ufl_cell(), degree))
    lam, mu, delta = 1.3, 0.7, 0.45
    C = fem.Constant(msh, elasticity_matrix(lam, mu, delta))
    system = SpatialSystem(V, [], *cauchy_forms(V, C, fem.Constant(msh, 1.0)))
    _, K, _ = system.dense()
    U1, U2 = system.interpolate(["x", "0"]), system.interpolate(["0", "y"])
    a, b = 0.02, 0.03
    corners = [(0, 0), (a, 0), (a, b), (0, b), (0, 0)]
    states = [e11 * U1 + e22 * U2 for e11, e22 in corners]
    work = sum((u1 - u0) @ K @ (u0 + u1) / 2 for u0, u1 in zip(states[:-1], states[1:]))
    area = 0.5 * abs(np.cross(points[1] - points[0], points[2] - points[0]))
    assert work == pytest.approx(-2 * delta * a * b * area, rel=1e-12)


@pytest.mark.serial
@pytest.mark.parametrize("degree, cells, rate", [(1, [4, 8, 16, 32], 1.8),
                                                 (2, [4, 8, 16, 32], 3.0)])
def test_symmetric_frequencies_converge(degree, cells, rate):
    """delta = 0: lambda_1 and lambda_3 of the clamped square, orders from successive
    differences (P1: 1.94 / 1.97 / 1.98; P2: 3.49 / 3.44 and 3.57 / 3.84, below 4 because the
    clamped corners limit the eigenfunctions' smoothness)."""
    lams = []
    for n in cells:
        mats = CauchyElasticity(CauchyParameters(elements=n, degree=degree)).system.to_scipy()
        lam = spla.eigsh(mats["K"].tocsc(), k=3, M=mats["M"].tocsc(), sigma=0,
                         return_eigenvectors=False)
        lams.append(np.sort(lam)[[0, 2]])
    d = np.abs(np.diff(np.array(lams), axis=0))
    rates = np.log2(d[:-1] / d[1:])
    assert np.all(rates > rate), rates


@pytest.mark.mpi
@pytest.mark.parametrize("degree, cells", [(1, 4), (1, 8), (2, 2), (2, 4)])
@pytest.mark.parametrize("fraction", [0.3, 0.6, 0.9])
def test_spectrum_is_real_for_delta_within_lam_plus_mu(degree, cells, fraction):
    lam, mu = 1.0, 1.0
    delta = fraction * (lam + mu)
    problem = CauchyElasticity(CauchyParameters(lam=lam, mu=mu, delta=delta, elements=cells,
                                                degree=degree))
    result = spectrum_check(problem.system)
    assert result.method == "dense" and result.checked == problem.system.n
    assert result.stable and result.max_imag == 0.0
    assert real_spectrum_guaranteed(lam, mu, delta)


@pytest.mark.serial
@pytest.mark.parametrize("fraction", [1.1, 1.5])
def test_spectrum_is_complex_beyond_lam_plus_mu(fraction):
    problem = CauchyElasticity(CauchyParameters(delta=fraction * 2.0, elements=4, degree=2))
    result = spectrum_check(problem.system)
    assert not result.real and result.positive and result.complex_count > 0
    assert not real_spectrum_guaranteed(1.0, 1.0, fraction * 2.0)


@pytest.mark.mpi
@pytest.mark.parametrize("degree", [1, 2])
def test_scaling_of_the_second_component_symmetrises_K(degree):
    """The proof of the real spectrum: diag(I, s I)^-1 K diag(I, s I) is symmetric."""
    lam, mu, delta = 1.0, 2.0, 2.5
    problem = CauchyElasticity(CauchyParameters(lam=lam, mu=mu, delta=delta, elements=5,
                                                degree=degree))
    M, K, _ = problem.system.dense()
    layout = problem.system.free_layout()
    field = MPI.COMM_WORLD.bcast(None if layout is None else layout[1], root=0)
    S = np.where(field == 0, 1.0, symmetrizing_scale(lam, mu, delta))
    Ks = K * S[None, :] / S[:, None]
    assert np.abs(Ks - Ks.T).max() <= 1e-13 * np.abs(K).max()
    assert np.all(np.linalg.eigvalsh(0.5 * (Ks + Ks.T)) > 0)


@pytest.mark.mpi
def test_slepc_check_of_the_lowest_eigenvalues_matches_the_dense_one():
    problem = CauchyElasticity(CauchyParameters(delta=0.6, elements=8))
    dense = spectrum_check(problem.system)
    lowest = spectrum_check(problem.system, dense_limit=0, nev=6)
    assert lowest.method == "slepc" and lowest.checked >= 6 and lowest.stable
    assert np.allclose(np.sort(lowest.lowest.real)[:6], np.sort(dense.lowest.real)[:6],
                       rtol=1e-9)


@pytest.mark.parametrize("kw", [{"mu": 0.0}, {"lam": -2.0}, {"rho": -1.0}, {"elements": 0},
                                {"degree": 1.5}, {"delta": float("nan")}])
def test_parameters_are_checked(kw):
    with pytest.raises(InputError, match="cauchy"):
        CauchyParameters(**kw)
