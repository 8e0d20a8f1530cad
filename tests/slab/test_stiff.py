"""Stiff systems: the zero base state damps what the slabs do not resolve, modal coordinates keep
the order of the resolved modes under a follower load."""
from __future__ import annotations

import numpy as np
import pytest
from mpi4py import MPI

from fem_dual import RunConfig
from fem_dual.integrate.api import Simulation, run
from fem_dual.errors import InputError, SolveError
from fem_dual.scenes import get_scene

OMEGAS = np.logspace(-2, 4, 13)  # radians per slab
DEGREES = (2, 3, 4, 5, 6)
CELLS = (1, 2, 4, 8, 16)


def _oscillator(k: float = 1.0, weights: str = "energy"):
    return get_scene("linear").from_params({"dofs": "1", "K": repr(k), "weights": weights})


def slab_map(scene, degree: int, cells: int, dt: float, base: str, kronecker: bool,
             modal: bool = False) -> np.ndarray:
    """The 2n x 2n map from a slab's start state to its end state, through the driver's own
    slab solve (the same on every rank)."""
    sim = Simulation(scene, degree, cells, MPI.COMM_WORLD, kronecker=kronecker,
                     with_dual=False, base=base, modal=modal)
    sim.begin(RunConfig.create(scene, T=dt, cells=cells, degree=degree, base=base,
                               coordinates="modal" if modal else "physical",
                               assembly="kronecker" if kronecker else "forms"))
    columns = []
    for z in np.eye(2 * scene.n):
        vals = sim.solve_slab(z, 0.0, dt)
        if MPI.COMM_WORLD.rank == 0:
            columns.append(np.concatenate([vals.x[-1], vals.v[-1]]))
    return MPI.COMM_WORLD.bcast(np.array(columns).T if columns else None)


def spectral_radius(matrix: np.ndarray) -> float:
    return float(np.abs(np.linalg.eigvals(matrix)).max())


@pytest.mark.mpi
def test_the_zero_base_slab_map_never_amplifies():
    """rho <= 1 + 1e-10 for every Omega up to 1e4 radians per slab, p = 2..6, c = 1..16; the
    unresolved limit is 1/T_c(p+1) (Chebyshev), an L-stable damping."""
    scene = _oscillator()
    worst = 0.0
    for p in DEGREES:
        for c in CELLS:
            rho = [spectral_radius(slab_map(scene, p, c, om, "zero", kronecker=True))
                   for om in OMEGAS]
            worst = max(worst, max(rho))
            chebyshev = 1.0 / np.cosh(c * np.arccosh(p + 1.0))  # 1 / T_c(p + 1)
            assert rho[-1] <= max(2.0 * chebyshev, 1e-12), (p, c, rho[-1], chebyshev)
    assert worst <= 1.0 + 1e-10, worst


def test_the_start_base_amplifies_unresolved_modes():
    """The start base state (the slab's start, held constant): rho grows like
    (Omega/c)/(p+1)^2, the mechanism the zero base removes (this is why --base start keeps the
    resolution guard)."""
    scene = _oscillator()
    rho = spectral_radius(slab_map(scene, 4, 1, 1e3, "start", kronecker=True))
    assert 20 < rho < 80, rho  # 40 here


@pytest.mark.parametrize("p,c", [(2, 1), (4, 4)])
def test_both_assembly_paths_give_the_same_slab_map(p, c):
    scene = _oscillator()
    for om in (0.5, 50.0, 5e3):
        forms = slab_map(scene, p, c, om, "zero", kronecker=False)
        kron = slab_map(scene, p, c, om, "zero", kronecker=True)
        assert np.abs(forms - kron).max() <= 1e-9 * max(1.0, np.abs(forms).max()), om


def test_identity_weights_far_from_energy_balance_are_why_zero_needs_energy_weights():
    """omega = 10 with A = I, B = M^2: the zero base amplifies in the middle range; auto
    therefore picks the zero base only with energy weights."""
    scene = _oscillator(100.0, "identity")
    rho = spectral_radius(slab_map(scene, 2, 1, 1.0, "zero", kronecker=True))  # Omega = 10
    assert rho > 1.2, rho  # 1.58
    assert RunConfig.create(scene).base_state == "start"
    assert RunConfig.create(_oscillator(100.0, "energy")).base_state == "zero"


def _two_modes(fast: float = 1e3):
    """M q'' + K q = 0 with modes omega = 1 and `fast`, coupled by the shear q = S r,
    S = [[1, 1], [0, 1]]: M = S^-T S^-1, K = S^-T diag(1, fast^2) S^-1, integers, so the data
    are exact in binary and the slow mode q = (cos t, 0) is the exact solution from (1, 0)."""
    w2 = fast ** 2
    params = {"dofs": "2", "M": "1,-1,-1,2", "K": f"1,-1,-1,{1 + w2!r}"}
    return get_scene("linear").from_params(params)


def _slow_error(r) -> float:
    """Max error against the exact slow motion x = (cos t, 0), v = (-sin t, 0)."""
    t = np.asarray(r.t)
    exact_x = np.stack([np.cos(t), np.zeros_like(t)], axis=1)
    exact_v = np.stack([-np.sin(t), np.zeros_like(t)], axis=1)
    return float(max(np.abs(r.x - exact_x).max(), np.abs(r.v - exact_v).max()))


@pytest.mark.mpi
@pytest.mark.parametrize("coordinates", ["physical", "modal"])
def test_two_modes_cost_what_the_slow_one_needs(coordinates):
    """omega = 1 and 1e3, T = 10, 20 slabs of one P4 cell (2 radians of the slow mode per slab,
    1000 of the fast one): the start base errs by 6e13 here; the zero base is right to the
    order of the slow mode, the fast mode stays at round-off, and the estimate vouches."""
    scene = _two_modes()
    assert scene.frequency_spread() == pytest.approx(1e3)
    r = run(RunConfig.create(scene, T=10, slabs=20, cells=1, degree=4, x0="1,0", v0="0,0",
                             coordinates=coordinates, assembly="forms"))
    assert r.status == "ok" and r.solver["rejected_slabs"] == 0
    error = _slow_error(r)
    assert error < 1e-7, error  # 5e-9 here
    assert error <= r.error_estimate <= 20 * error, (error, r.error_estimate)
    fast = np.abs(r.x[:, 1]).max()  # the fast mode's share of the position
    assert fast < 1e-10, fast


def test_two_modes_on_the_start_base_are_refused_not_wrong():
    scene = _two_modes()
    with pytest.raises(SolveError, match="under-resolved|estimated|amplifies"):
        run(RunConfig.create(scene, T=10, slabs=20, cells=1, degree=4, x0="1,0", v0="0,0",
                             base="start", max_halvings=2, assembly="forms"))


@pytest.mark.parametrize("coordinates", ["physical", "modal"])
def test_resolved_modes_keep_order_2p_on_the_zero_base(coordinates):
    scene = _two_modes()
    errors = []
    slabs = (20, 40, 80)
    for k in slabs:
        r = run(RunConfig.create(scene, T=10, slabs=k, cells=1, degree=3, x0="1,0",
                                 v0="0,0", coordinates=coordinates, assembly="forms"))
        errors.append(_slow_error(r))
    orders = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    assert (orders > 2 * 3 - 0.7).all(), (errors, orders)


def test_an_excited_fast_mode_is_damped_and_the_estimate_says_so():
    """Start with the fast mode excited: its motion cannot be followed by 20 slabs; the answer
    is refused (exit 3), never reported as ok."""
    scene = _two_modes()
    with pytest.raises(SolveError, match="estimated"):
        run(RunConfig.create(scene, T=10, slabs=20, cells=1, degree=4, x0="1,1", v0="0,0",
                             max_halvings=2, assembly="forms"))


def test_modal_coordinates_need_a_linear_scene_with_oscillating_modes():
    with pytest.raises(InputError, match="coordinates=modal needs a linear scene"):
        RunConfig.create("curl3d", coordinates="modal")
    with pytest.raises(InputError, match="coordinates"):
        RunConfig.create("ziegler", coordinates="spectral")
    with pytest.raises(InputError, match="base"):
        RunConfig.create("ziegler", base="middle")
    with pytest.raises(InputError, match="does not oscillate"):  # beyond the divergence load
        RunConfig.create("linear", {"dofs": "2", "K": "1,0,0,-1"}, coordinates="modal")
    # far past a flutter load: a growing oscillation, not a missing stiffness
    with pytest.raises(InputError, match="grows as it oscillates"):
        RunConfig.create("column", {"links": "10", "P": "0.5"}, coordinates="modal")
