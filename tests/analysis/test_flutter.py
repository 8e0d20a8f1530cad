"""Damped linear systems and the flutter load found by dual simulations (beyond the
reference)."""
import json

import numpy as np
import pytest
from mpi4py import MPI

from fem_dual import RunConfig, run
from fem_dual.cli import main
from fem_dual.analysis.flutter import flutter, growth_rate
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
    assert set(data) == {"eigen", "dual", "eigen_s", "dual_s", "dual_tol"}
    assert data["dual"] == pytest.approx(data["eigen"], rel=1e-2)
    assert 0 < data["dual_tol"] < 1e-6  # relative to the fastest frequency, 1.83 here
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
    from fem_dual.analysis.flutter import critical_load, eigen_rate, eigen_tolerance
    loads = []
    for links in (10, 20, 40):
        scene = get_scene("column").from_params(
            {"links": links, "l": 1 / links, "c": links, "m": 1 / links})
        loads.append(critical_load(eigen_rate(scene), eigen_tolerance(scene), first=1.0))
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


# `flutter` does not blame the input for the noise of its own fit. A window too short for the
# motion, a huge length scale (the frequencies scale like 1/l) and an under-resolved run are not
# "already unstable without load" (exit 2), nor a wrong load (0.40 for 2.086): the eigenvalues at
# P = 0 are purely imaginary. The run says that it cannot resolve the growth (exit 3), or answers.
@pytest.mark.serial
@pytest.mark.parametrize("args, status", [
    (["--param", "l=1e6"], 3),  # slowest period 1.6e7 in a window of 40
    (["--T", "1e-9", "--slabs", "1"], 3),  # the samples do not span the state space
    (["--cells", "4", "--degree", "2"], 0),  # halved slabs: the samples are not uniform
])
def test_flutter_does_not_blame_the_input_for_its_own_noise(args, status, capsys):
    import json
    code = main(["flutter", "ziegler", "--json", *args])
    out, err = capsys.readouterr()
    assert "already unstable" not in err
    assert code == status, err
    if code == 0:
        data = json.loads(out)
        assert data["dual"] == pytest.approx(data["eigen"], rel=1e-2)
        assert data["eigen"] == pytest.approx(3.5 - np.sqrt(2), rel=1e-4)
    else:
        assert "cannot resolve growth" in err and "the eigenvalues are stable" in err
        assert "use a longer --T" in err


@pytest.mark.serial
@pytest.mark.parametrize("param", ["d1=-0.05", "c1=-0.5"])  # negative damping; divergence
def test_flutter_still_reports_a_system_unstable_without_load(param, capsys):
    assert main(["flutter", "ziegler", "--param", param]) == 2
    assert "already unstable without load (P = 0)" in capsys.readouterr().err


def test_critical_load_refuses_a_rate_unstable_at_zero():
    from fem_dual.errors import InputError
    from fem_dual.analysis.flutter import critical_load
    with pytest.raises(InputError, match="already unstable without load"):
        critical_load(lambda P: 0.01 + P, 1e-9)
    assert critical_load(lambda P: P - 1.5, 1e-9) == pytest.approx(1.5, rel=1e-5)


def test_eigen_threshold_is_relative_to_the_frequencies():
    """At l = 1e9 the frequencies are 1e-9: an absolute threshold 1e-9 on the real part would
    put the load at 5.0 l/c instead of 7/2 - sqrt 2."""
    from fem_dual.analysis.flutter import critical_load, eigen_rate, eigen_tolerance
    for l in (1e-3, 1.0, 1e9):
        scene = get_scene("ziegler").from_params({"l": repr(l)})
        load = critical_load(eigen_rate(scene), eigen_tolerance(scene))
        assert load * l == pytest.approx(3.5 - np.sqrt(2), rel=1e-5), l


def _exact_motion(times, P=1.0, shift=0.0):
    """The exact motion of the Ziegler column under load P (its first-order matrix shifted by
    `shift`: growth at that rate) at the given times."""
    from scipy.linalg import expm
    A = get_scene("ziegler").from_params({"P": repr(P)}).first_order_matrix() + shift * np.eye(4)
    z = np.array([expm(A * t) @ [0.1, -0.05, 0.02, 0.03] for t in times])
    return z[:, :2], z[:, 2:]


def _dyadic_times(lengths, cells=4):
    """Vertex times of slabs of the given lengths, `cells` cells each (as halved slabs give)."""
    ends = np.concatenate([[0.0], np.cumsum(lengths)])
    return np.unique(np.concatenate([np.linspace(a, b, cells + 1)
                                     for a, b in zip(ends[:-1], ends[1:])]))


@pytest.mark.parametrize("P", [1.0, 2.2])  # stable; flutter
def test_growth_fit_of_non_uniform_samples(P):
    """Slabs of different lengths: only pairs a common step apart obey one map (a fit taking
    t[1] - t[0] for every step would mix maps)."""
    from fem_dual.analysis.flutter import fit_growth
    t = _dyadic_times([0.25] * 8 + [0.5] * 12 + [0.25] * 8 + [1.0] * 10)
    x, v = _exact_motion(t, P)
    lam = np.linalg.eigvals(get_scene("ziegler").from_params({"P": repr(P)})
                            .first_order_matrix())
    fit = fit_growth(t, x, v)
    assert fit.step == pytest.approx(0.25) and fit.resolved  # the step most pairs share
    assert fit.rate == pytest.approx(lam.real.max(), abs=1e-8)
    assert abs(fit.rate - lam.real.max()) <= fit.noise + 1e-12 and fit.noise < 1e-8
    assert fit.frequency == pytest.approx(np.abs(lam).max(), rel=1e-8)


def test_growth_fit_knows_a_window_too_short():
    from fem_dual.analysis.flutter import fit_growth
    t = np.linspace(0, 1e-9, 17)
    x, v = _exact_motion(t)
    assert not fit_growth(t, x, v).resolved
    t = np.linspace(0, 40, 641)
    x, v = _exact_motion(t)
    assert fit_growth(t, x, v).resolved
    fit = fit_growth(t, x, v, error=1e-3)  # the run's error estimate widens the uncertainty
    assert fit.noise > 100 * fit_growth(t, x, v).noise


def _fake_run(shift=0.0, fail=None):
    """A stand-in for the dual simulation: the exact motion (grown at `shift`), or a failure."""
    from types import SimpleNamespace

    from fem_dual.errors import SolveError

    def fake(config, comm=None):
        if fail is not None:
            raise SolveError(fail, slab=3)
        t = np.linspace(0, config.T, 641)
        x, v = _exact_motion(t, config.scene.P, shift)
        return SimpleNamespace(t=t, x=x, v=v, error_estimate=1e-11)
    return fake


def test_growth_the_eigenvalues_contradict_is_a_solve_error(monkeypatch):
    """Growth at P = 0 in the dual simulation but not in the eigenvalues: the run's numerical
    growth, exit 3, not the input's instability, exit 2."""
    import fem_dual.analysis.flutter as fl
    from fem_dual.errors import SolveError
    monkeypatch.setattr(fl, "run", _fake_run(shift=0.01))
    with pytest.raises(SolveError, match="grows without load where the eigenvalues do not"):
        flutter(RunConfig.create("ziegler", **SETTINGS), MPI.COMM_WORLD)
    monkeypatch.setattr(fl, "run", _fake_run())  # the exact motion: the exact load
    found = flutter(RunConfig.create("ziegler", **SETTINGS), MPI.COMM_WORLD)
    assert found["dual"] == pytest.approx(3.5 - np.sqrt(2), rel=1e-5)


@pytest.mark.serial
def test_a_failed_dual_simulation_is_a_solve_error(monkeypatch, capsys):
    import fem_dual.analysis.flutter as fl
    monkeypatch.setattr(fl, "run", _fake_run(fail="slab 3: the slab matrix is singular"))
    assert main(["flutter", "ziegler"]) == 3
    err = capsys.readouterr().err
    assert "the dual simulation at P = 0 failed: slab 3: the slab matrix is singular" in err


@pytest.mark.serial
def test_flutter_needs_a_moving_start_state(capsys):
    assert main(["flutter", "ziegler", "--x0", "0,0", "--v0", "0,0"]) == 2
    assert "start state that moves" in capsys.readouterr().err


def test_flutter_json_failure_is_one_json_object(capsys):
    assert main(["flutter", "ziegler", "--json", "--T", "1e-6"]) == 3
    captured = capsys.readouterr()
    assert captured.err.count("\n") == 1
    data = json.loads(captured.out)
    assert data["status"] == "failed" and "window" in data["message"]
