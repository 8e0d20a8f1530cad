"""Damped linear systems and the flutter load found by dual simulations (issue: beyond the
reference)."""
import numpy as np
import pytest
from mpi4py import MPI

from fem_dual import RunConfig, run
from fem_dual.cli import main
from fem_dual.flutter import flutter, growth_rate
from fem_dual.scenes import get_scene
from helpers import observed_rates

SETTINGS = dict(T=40.0, slabs=40, cells=16, degree=5, x0="0.1,-0.05", v0="0.02,0.03")


@pytest.mark.mpi
def test_damped_ziegler_converges_to_the_matrix_exponential():
    params = {"d1": "0.2", "d2": "0.1", "P": "1.2"}
    errors = [run(RunConfig.create("ziegler", params, T=10.0, slabs=5, cells=c, degree=3,
                                   v0="0.05,-0.02")).error["x_max"] for c in (4, 8, 16)]
    assert errors[-1] < 1e-8
    assert np.all(observed_rates(errors) > 5.5), errors  # order 2p


def test_zero_damping_gives_identical_numbers():
    a = run(RunConfig.create("ziegler", T=5.0, cells=20, degree=3))
    b = run(RunConfig.create("ziegler", {"d1": "0", "d2": "0"}, T=5.0, cells=20, degree=3))
    assert np.array_equal(a.x, b.x)


def test_growth_rate_of_a_known_motion():
    t = np.linspace(0, 10, 501)
    x = np.column_stack([np.exp(0.03 * t) * np.cos(2 * t), np.exp(-0.1 * t) * np.sin(t)])
    v = np.gradient(x, t, axis=0)
    assert growth_rate(t, x, v) == pytest.approx(0.03, abs=1e-3)


@pytest.mark.parametrize("d, expected", [(0.0, 3.5 - np.sqrt(2)), (0.01, None)])
def test_flutter_load_from_dual_simulations_within_one_percent(d, expected):
    base = RunConfig.create("ziegler", {"d1": d, "d2": d}, **SETTINGS)
    found = flutter(base, MPI.COMM_WORLD)
    assert found["dual"] == pytest.approx(found["eigen"], rel=1e-2)
    if expected is not None:
        assert found["eigen"] == pytest.approx(expected, rel=1e-4)
    else:  # Ziegler's paradox: small damping lowers the load towards 41/28
        assert found["eigen"] == pytest.approx(41 / 28, rel=2e-3)
    assert found["eigen_s"] > 0 and found["dual_s"] > 0


@pytest.mark.serial
def test_flutter_cli_json(capsys):
    import json
    assert main(["flutter", "ziegler", "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert set(data) == {"eigen", "dual", "eigen_s", "dual_s"}
    assert data["dual"] == pytest.approx(data["eigen"], rel=1e-2)
    assert main(["flutter", "curl3d"]) == 2


def test_damping_matrix_of_the_ziegler_joints():
    z = get_scene("ziegler").from_params({"d1": "0.3", "d2": "0.2"})
    assert np.array_equal(z.damping_matrix(), [[0.5, -0.2], [-0.2, 0.2]])


def test_column_with_two_links_is_ziegler():
    cfg = dict(T=10.0, slabs=5, cells=20, degree=3)
    z = run(RunConfig.create("ziegler", {"d1": "0.05", "d2": "0.02", "P": "1.5"}, **cfg))
    c = run(RunConfig.create("column", {"links": "2", "m": "2,1", "d": "0.05,0.02", "P": "1.5"},
                             **cfg))
    assert np.array_equal(z.x, c.x) and np.array_equal(z.v, c.v)


@pytest.mark.mpi
def test_damped_column_against_the_matrix_exponential():
    params = {"links": "3", "m": "1,2,1", "c": "3,2,1", "d": "0.05", "P": "0.8"}
    errors = [run(RunConfig.create("column", params, T=8.0, slabs=4, cells=c, degree=3,
                                   x0="0.1,0,-0.05")).error["x_max"] for c in (8, 16, 32)]
    assert errors[-1] < 1e-6
    assert np.all(observed_rates(errors) > 5.5), errors  # order 2p


def test_column_approaches_beck_as_links_grow():
    from fem_dual.flutter import critical_load, eigen_rate
    loads = []
    for links in (10, 20, 40):
        scene = get_scene("column").from_params(
            {"links": links, "l": 1 / links, "c": links, "m": 1 / links})
        loads.append(critical_load(eigen_rate(scene), 1e-9, first=1.0))
    assert loads[0] < loads[1] < loads[2] < 20.05  # Beck: P_cr = 20.05 EI / L^2
    assert 20.05 - loads[2] < 0.55 * (20.05 - loads[1])  # the gap closes like 1/N


def test_flutter_of_a_damped_column_within_one_percent():
    params = {"links": "2", "m": "2,1", "d": "0.02"}
    found = flutter(RunConfig.create("column", params, **SETTINGS), MPI.COMM_WORLD)
    assert found["dual"] == pytest.approx(found["eigen"], rel=1e-2)


def test_general_linear_scene_is_ziegler_with_its_matrices():
    cfg = dict(T=10.0, slabs=5, cells=20, degree=3)
    z = run(RunConfig.create("ziegler", {"P": "1.5", "d1": "0.1", "d2": "0.05"}, **cfg))
    scene = get_scene("ziegler").from_params({"P": "1.5", "d1": "0.1", "d2": "0.05"})
    flat = {k: ",".join(map(repr, m.ravel())) for k, m in
            (("M", scene.mass_matrix()), ("K", scene.stiffness_matrix()),
             ("D", scene.damping_matrix()))}
    g = run(RunConfig.create("linear", flat, **cfg))
    assert np.array_equal(z.x, g.x)


@pytest.mark.mpi
def test_general_damped_linear_system_against_the_matrix_exponential():
    params = {"dofs": "3", "M": "2,0.5,0,0.5,1,0,0,0,1", "K": "2,-1,0.5,-1,2,-1,0,-1,2",
              "D": "0.1,0,0.02,0,0.05,0,0.03,0,0.2"}
    errors = [run(RunConfig.create("linear", params, T=10.0, slabs=5, cells=c, degree=3,
                                   x0="0.1,0,-0.1", v0="0,0.1,0")).error["x_max"]
              for c in (8, 16, 32)]
    assert errors[-1] < 1e-7
    assert np.all(observed_rates(errors) > 5.5), errors  # order 2p
