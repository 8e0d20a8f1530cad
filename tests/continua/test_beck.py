"""Beck's column: cantilever frequencies, the condensation of theta, Euler buckling under the dead
load, Beck's flutter load under the follower load, and their convergence under refinement."""
import math

import numpy as np
import pytest
from dolfinx import io
from mpi4py import MPI
from scipy.optimize import brentq

from fem_dual.continua.beck import BeckColumn, BeckParameters
from fem_dual.continua.condense import condense_rotation, schur_complement
from fem_dual.continua.dofs import gather_csr
from fem_dual.continua.fields import vertex_functions
from fem_dual.continua.flutter import (beck_eigenvalues, buckling_load, flutter_load, frequencies,
                                       lowest_eigenvalues, pencil_eigenvalues)
from fem_dual.errors import InputError

BECK = 20.0509536190  # Beck's flutter load, EI/L^2
OMEGA2 = 121.3425  # flutter frequency squared at it, EI/(rhoA L^4)
EULER_LIMIT = 1e12  # kGA for the Euler-Bernoulli limit in the convergence studies


def cantilever_omegas(count=2):
    """omega_k = beta_k^2 with 1 + cos(beta) cosh(beta) = 0 (Euler-Bernoulli, EI = rhoA = L = 1)."""
    starts = [1.0, 4.0, 7.0][:count]
    return np.array([brentq(lambda b: 1 + math.cos(b) * math.cosh(b), a, a + 1.5)
                     for a in starts]) ** 2


def observed_rates(errors):
    e = np.abs(np.asarray(errors))
    return np.log2(e[:-1] / e[1:])


def condensed(**kw):
    return condense_rotation(BeckColumn(BeckParameters(**kw)))


def beck_flutter(beck, step=2.0):
    return flutter_load(lambda P: beck_eigenvalues(beck, P), step=step, P_max=40.0)


@pytest.mark.mpi
def test_frequencies_at_the_default_discretisation():
    omega = frequencies(condensed(), 2)
    assert np.allclose(omega, [3.5160153, 22.0344916], rtol=1e-5, atol=0)
    assert np.allclose(omega, cantilever_omegas(), rtol=1e-5, atol=0)


@pytest.mark.serial
@pytest.mark.parametrize("degree, cells, rate", [(1, [4, 8, 16, 32], 1.9),
                                                 (2, [2, 4, 8, 16], 3.8)])
def test_frequencies_converge_at_order_2_degree_minus_2(degree, cells, rate):
    """omega_1, omega_2 in the Euler-Bernoulli limit: errors O(h^(2 degree - 2))... for P1
    O(h^2), for P2 O(h^4) (measured: 4.00 / 4.00 / 4.00 and 3.97 / 3.95 / 3.99)."""
    exact = cantilever_omegas()
    errors = np.array([frequencies(condensed(elements=n, degree=degree, kGA=EULER_LIMIT), 2)
                       / exact - 1 for n in cells])
    assert np.all(observed_rates(errors[:, 0]) > rate)
    assert np.all(observed_rates(errors[:, 1]) > rate)


@pytest.mark.mpi
@pytest.mark.parametrize("kGA", [1e3, 1e7])
def test_condensation_is_the_schur_complement_of_the_assembled_stiffness(kGA):
    column = BeckColumn(BeckParameters(elements=10, kGA=kGA))
    beck = condense_rotation(column)
    parts = column.parts()
    K = gather_csr(parts["K_el"])
    field = column.system.free_layout()
    if MPI.COMM_WORLD.rank == 0:
        K, field = K.toarray(), field[1]
        direct = schur_complement(K, field)
        assert np.allclose(beck.K_el, direct, rtol=0, atol=1e-9 * np.abs(direct).max())
        # a backward-stable inverse: within round-off times the condition number (1e8 at
        # kGA = 1e7), whatever the BLAS
        atol = 10 * np.finfo(float).eps * np.linalg.cond(beck.K_el)
        assert np.allclose(beck.F_el @ beck.K_el, np.eye(beck.n), atol=atol)
        # theta = G w is the static response: K_tw w + K_tt G w = 0
        iw, it = beck.w_index, beck.theta_index
        residual = K[np.ix_(it, iw)] + K[np.ix_(it, it)] @ beck.theta_map
        assert np.abs(residual).max() < 1e-9 * np.abs(K[np.ix_(it, iw)]).max()


@pytest.mark.mpi
def test_flutter_load_and_frequency_at_the_default_discretisation():
    result = beck_flutter(condensed())
    assert result.kind == "flutter"
    assert result.bracket[1] - result.bracket[0] <= 1e-9
    assert abs(result.load - BECK) < 1e-4
    assert abs(result.omega2 - OMEGA2) < 5e-4
    # the coalescing pair: the two lowest eigenvalues, complex conjugates past the load
    pair = result.eigenvalues[:2]
    assert np.all(pair.imag != 0) and np.isclose(pair[0], np.conj(pair[1]))


@pytest.mark.mpi
def test_dead_load_buckles_at_pi_squared_over_4():
    beck = condensed(load="dead")
    assert abs(buckling_load(beck) / (math.pi**2 / 4) - 1) < 1e-6
    result = flutter_load(lambda P: beck_eigenvalues(beck, P), step=1.0, P_max=10.0)
    assert result.kind == "divergence"
    assert abs(result.load / (math.pi**2 / 4) - 1) < 1e-6


@pytest.mark.serial
def test_follower_load_never_diverges():
    """det K(P) != 0: the lowest real part stays positive up to past the flutter load."""
    beck = condensed(elements=20)
    for P in np.linspace(0.0, 30.0, 16):
        lam = lowest_eigenvalues(beck_eigenvalues(beck, P), 4)
        assert lam.real.min() > 1.0


@pytest.mark.serial
def test_flutter_load_convergence_table(capsys):
    """25 / 50 / 100 / 200 P2 cells. At the default kGA = 1e7 the loads converge at order 3
    to the Timoshenko value (a few 1e-5 below Beck's); in the Euler-Bernoulli limit to Beck's
    value itself, also at order 3."""
    cells = [25, 50, 100, 200]
    rows = {}
    for kGA in (1e7, EULER_LIMIT):
        loads = [beck_flutter(condensed(elements=cells[0], kGA=kGA)).load]
        for n in cells[1:]:  # each mesh's search starts just below the coarser one's load
            found = flutter_load(lambda P, b=condensed(elements=n, kGA=kGA): beck_eigenvalues(
                b, P), step=2e-3 * loads[-1], P_max=40.0, start=0.999 * loads[-1])
            loads.append(found.load)
        rows[kGA] = np.array(loads)
    timoshenko, euler = rows[1e7], rows[EULER_LIMIT]
    with capsys.disabled():
        print("\ncells  P_cr(kGA=1e7)    P_cr(kGA=1e12)   error vs Beck (1e12)")
        for n, a, b in zip(cells, timoshenko, euler):
            print(f"{n:5d}  {a:.10f}  {b:.10f}  {b - BECK:+.3e}")
        print("orders (differences, 1e7):", np.round(observed_rates(np.diff(timoshenko)), 2),
              " orders (errors, 1e12):", np.round(observed_rates(euler - BECK), 2))
    assert np.all(observed_rates(np.diff(timoshenko)) > 2.8)
    assert np.all(observed_rates(euler - BECK) > 2.8)
    assert abs(timoshenko[2] - BECK) < 1e-4 and abs(euler[-1] - BECK) < 1e-5


@pytest.mark.serial
def test_stiffness_is_the_elastic_minus_geometric_plus_follower_part():
    column = BeckColumn(BeckParameters(elements=6, P=3.0))
    parts = {name: gather_csr(A).toarray() for name, A in column.parts().items()}
    P = 7.5
    K = gather_csr(column.stiffness(P)).toarray()
    assert np.allclose(K, parts["K_el"] - P * parts["K_g"] + P * parts["K_f"], rtol=0, atol=1e-6)
    assert np.count_nonzero(np.linalg.svd(parts["K_f"], compute_uv=False) > 1e-12) == 1
    K3 = gather_csr(column.system.K).toarray()  # the system's K is K(params.P)
    assert np.allclose(K3, parts["K_el"] - 3.0 * (parts["K_g"] - parts["K_f"]), atol=1e-6)


@pytest.mark.serial
def test_rotary_inertia_keeps_theta_and_lowers_the_frequency():
    params = dict(elements=10, kGA=1e4)
    with pytest.raises(ValueError, match="rotary inertia"):
        condensed(rhoI=1e-4, **params)
    M, K, _ = BeckColumn(BeckParameters(rhoI=1e-4, **params)).system.dense()
    full = np.sqrt(lowest_eigenvalues(pencil_eigenvalues(K, M), 1).real)
    rigid = frequencies(condensed(**params), 1)
    assert full[0] < rigid[0] and abs(full[0] / rigid[0] - 1) < 1e-3


@pytest.mark.parametrize("kw, name", [({"elements": 0}, "elements"), ({"EI": -1.0}, "EI"),
                                      ({"kGA": math.inf}, "kGA"), ({"load": "pull"}, "load"),
                                      ({"degree": 2.0}, "degree"), ({"rhoI": -1.0}, "rhoI")])
def test_parameters_are_checked(kw, name):
    with pytest.raises(InputError, match=name):
        BeckParameters(**kw)


@pytest.mark.mpi
def test_condensed_state_gives_w_and_theta_fields(tmp_path):
    """w = x^2 (exact in P2) expands to theta = G w, w' = 2x up to the shear strain
    (w' - theta = EI theta''/kGA with theta'(L) = 0: a boundary layer of width sqrt(EI/kGA)
    at the tip that 8 cells smear), and both fields go to XDMF as vertex functions."""
    column = BeckColumn(BeckParameters(elements=8))
    beck = condense_rotation(column)
    system = column.system
    full = system.gather(system.interpolate(["x**2", "0"]))
    w = None if full is None else full[beck.w_index]
    w = w if MPI.COMM_WORLD.size == 1 else MPI.COMM_WORLD.bcast(w, root=0)
    u = system.to_function(system.scatter(beck.expand(w)))
    w1, theta1 = vertex_functions(u, ["w", "theta"])
    x = w1.function_space.tabulate_dof_coordinates()[:, 0]
    assert np.allclose(w1.x.array, x**2, atol=1e-12)
    assert np.allclose(theta1.x.array, 2 * x, rtol=1e-3, atol=1e-12)
    path = MPI.COMM_WORLD.bcast(str(tmp_path / "beck.xdmf"), root=0)
    with io.XDMFFile(MPI.COMM_WORLD, path, "w") as xdmf:
        xdmf.write_mesh(column.msh)
        xdmf.write_function(w1, 0.0)
        xdmf.write_function(theta1, 0.0)
