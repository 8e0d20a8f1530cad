"""The Kronecker (time x space) path of linear scenes: matrix-free CG with the
fast-diagonalisation preconditioner, for columns of many links."""
import re

import numpy as np
import pytest
from mpi4py import MPI

from fem_dual import RunConfig, SolveError, run
from fem_dual.cli import main
from fem_dual.scenes.column import lowest_mode, scaled_column

SMALL = dict(T=4.0, slabs=2, cells=6, degree=3)


def _both(scene, params, **kw):
    forms = run(RunConfig.create(scene, params, assembly="forms", **kw))
    kron = run(RunConfig.create(scene, params, assembly="kronecker", **kw))
    assert kron.solver["assembly"] == "kronecker" and forms.solver["assembly"] == "forms"
    return forms, kron


def _rel(a, b):
    return np.abs(a - b).max() / np.abs(b).max()


@pytest.mark.mpi
def test_symmetric_column_equals_the_forms_path_and_cg_needs_one_or_two_steps():
    """Springs only, energy weights: the preconditioner is the exact inverse."""
    forms, kron = _both("column", {"links": "3", "c": "3,2,1", "P": "0", "weights": "energy"},
                        superpose="no", **SMALL)
    assert _rel(kron.x, forms.x) < 1e-12 and _rel(kron.v, forms.v) < 1e-12
    assert max(kron.solver["ksp_iterations"]) <= 2


@pytest.mark.mpi
@pytest.mark.parametrize("scene, params", [
    ("column", {"links": "3", "m": "1,2,1", "d": "0.05", "P": "0.8"}),
    ("ziegler", {"P": "1.3", "d1": "0.1", "d2": "0.05"}),
    ("linear", {"dofs": "3", "M": "2,0.5,0,0.5,1,0,0,0,1", "K": "2,-1,0.5,-1,2,-1,0,-1,2",
                "D": "0.1,0,0.02,0,0.05,0,0.03,0,0.2"}),
])
def test_loaded_damped_systems_equal_the_forms_path(scene, params):
    forms, kron = _both(scene, params, superpose="no", **SMALL)
    assert _rel(kron.x, forms.x) < 1e-9 and _rel(kron.v, forms.v) < 1e-9
    assert kron.error["x_max"] == pytest.approx(forms.error["x_max"], rel=1e-3, abs=1e-11)


@pytest.mark.mpi
def test_a_simulation_run_again_with_other_parameters_preconditions_the_new_scene():
    """The preconditioner's pencil is the scene's: a simulation run first with c = 1 and then
    with c = 1e4 solves the second like a fresh one (same CG counts, same answer)."""
    from fem_dual.integrate.simulation import Simulation

    cfg = dict(coordinates="physical", assembly="kronecker", slabs=2, T=0.5, cells=8, degree=3)
    first = RunConfig.create("column", {"links": "6", "c": "1"}, **cfg)
    second = RunConfig.create("column", {"links": "6", "c": "1e4"}, **cfg)
    sim = Simulation.for_config(first)
    try:
        sim.run(first)
        again = sim.run(second)
    finally:
        sim.close()
    fresh = run(second)
    assert again.solver["ksp_iterations"] == fresh.solver["ksp_iterations"]
    assert _rel(again.x, fresh.x) < 1e-12 and _rel(again.v, fresh.v) < 1e-12


@pytest.mark.mpi
def test_superposition_in_kronecker_form_equals_a_solve_per_slab():
    params = {"links": "6", "P": "0.5"}
    cfg = dict(T=8.0, slabs=16, cells=8, degree=4, assembly="kronecker")
    solved = run(RunConfig.create("column", params, superpose="no", **cfg))
    superposed = run(RunConfig.create("column", params, superpose="yes", **cfg))
    # the solved problem decouples into its modes: 2 probes per place in the largest block (2
    # here) instead of the 12 unit start states
    assert superposed.solver["superposition"] and superposed.solver["slab_solves"] == 4
    assert _rel(superposed.x, solved.x) < 1e-9
    assert solved.error["x_max"] < 1e-11 and superposed.error["x_max"] < 1e-10


@pytest.mark.mpi
def test_auto_takes_the_kronecker_path_from_five_dofs():
    few = RunConfig.create("column", {"links": "4"})
    many = RunConfig.create("column", {"links": "5"})
    assert not few.kronecker and many.kronecker
    assert not RunConfig.create("column", {"links": "5"}, recovery="dtp").kronecker


def _scaled_column(N, P):
    """N links scaled like a continuous column and its lowest mode."""
    scene = scaled_column(N, P)
    return scene, lowest_mode(scene)


@pytest.mark.mpi
def test_a_long_scaled_column_converges_to_the_matrix_exponential():
    """40 links, half the flutter load, two periods of the lowest mode, the whole spectrum
    within 20 radians per cell (the slab map is stable there)."""
    N = 40
    scene, x0 = _scaled_column(N, 9.5)
    assert scene.weighting() == "energy"  # the springs: sym K is indefinite here
    T, cells = 2.5, 4
    slabs = int(np.ceil(scene.fastest_rate() * T / (20 * cells)))
    r = run(RunConfig.create(scene, T=T, slabs=slabs, cells=cells, degree=4, x0=x0,
                             v0=np.zeros(N)))
    assert r.solver["assembly"] == "kronecker" and r.solver["superposition"]
    assert r.error["x_max"] / 0.1 < 1e-5, r.error


@pytest.mark.mpi
@pytest.mark.parametrize("links", [20, pytest.param(40, marks=pytest.mark.slow)])
def test_unresolved_modes_that_the_slab_map_amplifies_stop_the_run(links):
    """The same column with slabs far too long for its fastest modes, on the start base state
    (the slab's start, which amplifies them: the noise grows to 1e20): never that noise with
    status ok, but either exit 3 naming the cause, or slabs shortened until the estimate vouches
    for the answer, and then it is right. (The default zero base damps them: test_stiff.)"""
    scene, x0 = _scaled_column(links, 9.5)
    config = RunConfig.create(scene, T=2.5, slabs=20, cells=4, degree=4, x0=x0,
                              v0=np.zeros(links), base="start", coordinates="physical")
    try:
        r = run(config)
    except SolveError as exc:
        assert re.search("modes the slabs do not resolve|estimated local error", str(exc))
        return
    assert r.solver["rejected_slabs"] > 0 and len(r.slab_lengths) > 20
    actual = max(r.error["x_max"], r.error["v_max"])
    assert actual <= 1e-3 * r.tolerance["scale_x"] and r.error_estimate >= actual


def test_kronecker_input_errors(capsys):
    assert main(["run", "curl3d", "--assembly", "kronecker"]) == 2
    assert "nonlinear" in capsys.readouterr().err
    assert main(["run", "ziegler", "--assembly", "kronecker", "--recovery", "dtp"]) == 2
    assert "momenta" in capsys.readouterr().err
    assert main(["run", "ziegler", "--assembly", "sparse"]) == 2
    assert "sparse" in capsys.readouterr().err


@pytest.mark.mpi
def test_parallel_kronecker_equals_serial():
    cfg = RunConfig.create("column", {"links": "7", "P": "0.4", "d": "0.01"}, T=6.0, slabs=3,
                           cells=6, degree=3, superpose="no")
    par, ser = run(cfg, MPI.COMM_WORLD), run(cfg, MPI.COMM_SELF)
    assert np.array_equal(par.t, ser.t)
    assert _rel(par.x, ser.x) < 1e-10 and _rel(par.v, ser.v) < 1e-10


@pytest.mark.serial
def test_the_predictor_base_is_never_dropped_silently(capsys):
    """The Kronecker form holds the start or zero base only: with --base predictor auto
    assembly takes the forms, and an explicit kronecker assembly is refused, so the zero base
    never runs under the name "predictor"."""
    config = RunConfig.create("column", {"links": "6", "P": "0.1"}, base="predictor")
    assert not config.kronecker and config.base_state == "predictor"
    assert RunConfig.create("column", {"links": "6", "P": "0.1"}, base="zero").kronecker
    capsys.readouterr()
    assert main(["run", "column", "--param", "links=6", "--base", "predictor",
                 "--assembly", "kronecker"]) == 2
    assert "base=predictor needs assembly=forms" in capsys.readouterr().err


def test_the_preconditioners_inverses_and_banded_factors_agree(monkeypatch):
    """Small problems keep the modes' block inverses, large ones banded Cholesky factors: the
    same operator; a slab whose time matrices leave float64 is refused with the frequency."""
    from fem_dual.slab import kronecker_solver
    scene = scaled_column(6, 2.0)
    x0, v0 = lowest_mode(scene), np.zeros(scene.n)
    outputs = []
    for entries in (kronecker_solver.INVERSE_ENTRIES, 0):
        monkeypatch.setattr(kronecker_solver, "INVERSE_ENTRIES", entries)
        r = run(RunConfig.create(scene, T=1.0, x0=x0, v0=v0, slabs=2, cells=4, degree=3,
                                 assembly="kronecker", superpose="no", coordinates="physical",
                                 base="start"))
        outputs.append((r.x, r.v, r.solver["ksp_iterations"]))
    assert _rel(outputs[0][0], outputs[1][0]) < 1e-12
    assert _rel(outputs[0][1], outputs[1][1]) < 1e-12
    assert outputs[0][2] == outputs[1][2]
    S = np.eye(2)
    with pytest.raises(SolveError, match=r"length 1e\+300 overflows float64 .*frequency 1e\+150"):
        kronecker_solver._mode_blocks(S, S, 0 * S, 1e300, np.array([1e-300, 1e300]))
