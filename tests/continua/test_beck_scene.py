"""`fem-dual run beck`: Beck's column as a scene, its start fields, the estimate against the exact
motion of its semi-discrete system, and the fast modes the slabs drop (never amplified)."""
import subprocess
import sys

import numpy as np
import pytest
import scipy.linalg as sla

from fem_dual.config import RunConfig
from fem_dual.errors import InputError
from fem_dual.integrate.api import run


def _modal_motion(M, K, x0, v0, T):
    """(x(T), v(T)) of M x'' + K x = 0 from the modes of (K, M) (real below flutter)."""
    lam, U = sla.eig(K, M)
    assert np.abs(lam.imag).max() <= 1e-9 * np.abs(lam).max()
    omega, U = np.sqrt(lam.real), U.real
    a, b = np.linalg.solve(U, x0), np.linalg.solve(U, v0) / omega
    c, s = np.cos(omega * T), np.sin(omega * T)
    return U @ (a * c + b * s), U @ (omega * (b * c - a * s))


@pytest.mark.parametrize("P", [0.0, 10.0, 19.0])
def test_the_estimate_bounds_the_error_against_the_modes_of_the_semi_discrete_system(P):
    config = RunConfig.create("beck", {"P": str(P), "elements": "20"}, T=1, rtol=1e-3)
    r = run(config)
    assert r.status == "ok" and r.solver["base"] == "zero"
    M, K = config.scene.mass_matrix(), config.scene.stiffness_matrix()
    x0, v0 = np.asarray(r.x0, float), np.asarray(r.v0, float)
    xT, vT = _modal_motion(M, K, x0, v0, 1.0)
    error = max(np.abs(np.asarray(r.final["x"]) - xT).max(),
                np.abs(np.asarray(r.final["v"]) - vT).max())
    tol = 1e-3 * max(r.tolerance["scale_x"], r.tolerance["scale_v"])
    assert error <= r.error_estimate <= 10 * tol
    assert error >= tol / 100  # the cost follows the tolerance: not far below it


def test_run_without_options_takes_the_continuum_default_tolerance(capsys):
    """`fem-dual run beck` as typed: slab lengths chosen for --rtol 1e-3 (one slab of 100
    cells, halved six times, cannot follow the spread of the beam's modes), the answer within
    that of the exact motion of the semi-discrete system, and the JSON says the tolerance was
    the default. --slabs keeps fixed slabs; particle scenes keep fixed slabs by default."""
    import json

    from fem_dual.cli import main

    assert main(["run", "beck", "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    tol = data["tolerance"]
    assert tol == {**tol, "rtol": 1e-3, "adaptive": True, "given": False}
    scene = RunConfig.create("beck").scene
    xT, vT = _modal_motion(scene.mass_matrix(), scene.stiffness_matrix(),
                           np.asarray(data["x0"], float), np.asarray(data["v0"], float),
                           data["T"])
    error = max(np.abs(np.asarray(data["final"]["x"]) - xT).max(),
                np.abs(np.asarray(data["final"]["v"]) - vT).max())
    scale = max(tol["scale_x"], tol["scale_v"])
    assert scale / 1e5 <= error <= data["error_estimate"] <= 10 * 1e-3 * scale
    assert RunConfig.create("beck", slabs=2).tolerance.adaptive is False
    assert RunConfig.create("curl3d").tolerance.adaptive is False
    assert RunConfig.create("beck", rtol=1e-4).rtol_given
    beside = RunConfig.create("beck", atol=1e-9)  # (--atol joins the default)
    assert beside.tolerance == type(beside.tolerance)(1e-3, 1e-9, True)
    assert not beside.rtol_given


@pytest.mark.parametrize("P", [20.05, 21.0])
def test_near_and_past_the_flutter_load_the_modes_stay_well_conditioned(P):
    """Modes about to coalesce (20.05) or coalesced (21, growing) share one balanced block, so the
    modal coordinates stay usable and the estimate honest against the exponential of the
    first-order system."""
    from fem_dual.reference import first_order_matrix
    from fem_dual.slab.modal import ModalBasis

    config = RunConfig.create("beck", {"P": str(P), "elements": "20"}, T=1, rtol=1e-3)
    assert np.linalg.cond(ModalBasis(config.scene).U) < 1e4
    r = run(config)
    assert r.status == "ok" and r.solver["coordinates"] == "modal"
    M, K = config.scene.mass_matrix(), config.scene.stiffness_matrix()
    z = sla.expm(first_order_matrix(M, K, np.zeros_like(M))) @ np.concatenate([r.x0, r.v0])
    n = len(M)
    error = max(np.abs(np.asarray(r.final["x"]) - z[:n]).max(),
                np.abs(np.asarray(r.final["v"]) - z[n:]).max())
    tol = 1e-3 * max(r.tolerance["scale_x"], r.tolerance["scale_v"])
    assert error <= r.error_estimate <= 10 * tol


def test_without_load_the_energy_is_kept_and_never_grows():
    """P = 0: K is symmetric and the energy 1/2 v'Mv + 1/2 w'Kw is conserved; the modes the slabs
    drop take their (tiny) energy away, never add any."""
    config = RunConfig.create("beck", {"P": "0", "elements": "20"}, T=2, rtol=1e-3)
    r = run(config)
    M, K = config.scene.mass_matrix(), config.scene.stiffness_matrix()

    def energy(x, v):
        x, v = np.asarray(x, float), np.asarray(v, float)
        return 0.5 * v @ M @ v + 0.5 * x @ K @ x

    start, end = energy(r.x0, r.v0), energy(r.final["x"], r.final["v"])
    assert r.status == "ok"
    assert end <= start * (1 + 1e-12)
    assert end >= start * (1 - 1e-4)  # (measured: 2.8e-7 lower)


def test_default_start_is_the_static_deflection_under_a_uniform_load():
    config = RunConfig.create("beck", {"elements": "10"}, rtol=1e-3)
    scene, x0 = config.scene, np.asarray(config.x0)
    load = np.linalg.solve(scene.mass_matrix(), scene.condensed.K_el @ x0)
    assert np.allclose(load, load[0], rtol=1e-8)  # K_el w = M 1 c: a uniform load
    assert np.abs(x0).max() == pytest.approx(0.01)
    assert not np.any(config.v0)


def test_start_fields_from_expressions_of_x():
    config = RunConfig.create("beck", {"elements": "10", "degree": "2"},
                              u0="0.01*x**2, 0.02*x", v0="0, 0", rtol=1e-3)
    w = np.asarray(config.x0)
    assert w.max() == pytest.approx(0.01, rel=1e-6)  # the tip of 0.01 x^2 (w in P2: exact)


def test_start_fields_that_excite_the_fastest_modes_are_named_as_the_cost(capsys):
    """The fields of x put more than 1e-6 of the motion into the mesh's fastest modes (10
    elements: 16,394 slabs of 1.2e-4 at P = 10, T = 2), which every slab must follow: the
    budget's refusal says so (exit 3, one line), instead of advising a looser --rtol alone.
    The budget is given: left at its default, chunked slabs this cheap run within its time."""
    from fem_dual.cli import main

    args = ["run", "beck", "--param", "P=10", "--param", "elements=10", "--u0",
            "0.01*x**2, 0.02*x", "--v0", "0, 0", "--T", "2", "--rtol", "1e-6",
            "--max-slabs", "5000"]
    assert main(args) == 3
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "beyond the budget" in err
    assert "excites modes up to |lambda|" in err and "coarser mesh" in err
    rate = float(err.split("|lambda| = ")[1].split(" ")[0])
    scene = RunConfig.create("beck", {"P": "10", "elements": "10"}).scene
    speeds = np.abs(scene.spectrum[0])
    assert speeds.max() / 2 <= rate <= speeds.max() * (1 + 1e-9)  # (the mesh's fastest)


@pytest.mark.parametrize("u0, words", [("0.01*x**2", "expected 2"),
                                       ("0.01*x**2, 0.02*q", "q"),
                                       ("0.01*x**2, 0.02*x, 1", "expected 2")])
def test_bad_start_fields_name_the_bad_value(u0, words):
    with pytest.raises(InputError, match=words):
        RunConfig.create("beck", {"elements": "10"}, u0=u0, rtol=1e-3)


def test_u0_on_a_particle_scene_is_refused():
    with pytest.raises(InputError, match="u0"):
        RunConfig.create("ziegler", {}, u0="1, 2")


def test_command_line_refuses_bad_fields_in_one_line():
    done = subprocess.run([sys.executable, "-m", "fem_dual.cli", "run", "beck", "--u0", "x, y",
                           "--rtol", "1e-3"], capture_output=True, text=True)
    assert done.returncode == 2
    assert len(done.stderr.strip().splitlines()) == 1 and "y" in done.stderr


def test_out_holds_the_semi_discrete_system_that_reproduces_the_run(tmp_path):
    """`<scene>_system.npz`: M, K, D of the free dofs and u0, v0 in the order of the JSON's
    final.x / final.v; the matrix exponential of that system lands within the run's estimate."""
    config = RunConfig.create("beck", {"elements": "10"}, T=0.5, rtol=1e-3, out=str(tmp_path))
    r = run(config)
    path = tmp_path / "beck_system.npz"
    assert str(path) in r.output_files
    z = np.load(path)
    M, K, D = z["M"], z["K"], z["D"]
    n = len(M)
    assert K.shape == D.shape == (n, n) and z["dof_coordinates"].shape == (n, 1)
    A = np.block([[np.zeros((n, n)), np.eye(n)],
                  [-np.linalg.solve(M, K), -np.linalg.solve(M, D)]])
    end = sla.expm(0.5 * A) @ np.concatenate([z["u0"], z["v0"]])
    error = max(np.abs(end[:n] - r.final["x"]).max(), np.abs(end[n:] - r.final["v"]).max())
    assert 0 < error <= r.error_estimate


def test_fields_on_the_beam_at_every_time_vertex(tmp_path):
    """`beck_fields.xdmf`: w, theta and their velocities at the mesh's vertices, one step per
    time vertex, from the start state to the final one."""
    from fem_dual.output import read_series

    config = RunConfig.create("beck", {"elements": "10"}, T=0.25, rtol=1e-3, out=str(tmp_path))
    r = run(config)
    points, times, steps = read_series(tmp_path / "beck_fields.xdmf")
    assert np.allclose(points[:, 0], np.linspace(0, 1, 11))
    assert len(times) == len(steps) == r.cells * len(r.slab_lengths) + 1  # the time vertices
    assert np.all(np.diff(times) > 0) and times[0] == 0 and times[-1] == pytest.approx(0.25)
    assert set(steps[0]) == {"w", "theta", "w_dot", "theta_dot"}
    x_dofs = config.scene.dof_coordinates()[:, 0]
    tip = np.argmax(x_dofs)  # the free w dof at x = L, the mesh's last vertex
    assert steps[-1]["w"][-1] == pytest.approx(r.final["x"][tip], rel=1e-12)
    assert steps[-1]["w_dot"][-1] == pytest.approx(r.final["v"][tip], rel=1e-12)
    assert steps[0]["w"][0] == 0 and steps[0]["theta"][0] == 0  # clamped
    assert np.abs(steps[0]["w_dot"]).max() <= 1e-14  # at rest (the recovered start)


def test_what_is_dropped_stays_in_the_estimate_to_the_end(tmp_path):
    """A mode dropped at t ~ 1 is gone from the answer for good: the estimate at T still
    carries it (it had shrunk back to 7.4e-7 against a true error of 5.2e-6 when the slab maps,
    which drop the mode again, carried it)."""
    config = RunConfig.create("beck", {"P": "5", "kGA": "10", "elements": "10"}, T=2, rtol=1e-4,
                              out=str(tmp_path))
    r = run(config)
    z = np.load(tmp_path / "beck_system.npz")
    xT, vT = _modal_motion(z["M"], z["K"], z["u0"], z["v0"], 2.0)
    assert r.status == "ok"
    assert np.abs(np.asarray(r.final["x"]) - xT).max() <= r.estimate["final_x"]
    assert np.abs(np.asarray(r.final["v"]) - vT).max() <= r.estimate["final_v"]
    assert max(r.error["x_max"], r.error["v_max"]) <= r.error_estimate


def test_a_resumed_run_goes_on_with_its_fields(tmp_path, monkeypatch):
    """Interrupted after its third check for signals, then resumed: the fields series goes on
    where it stopped, and the answer is the uninterrupted one."""
    import signal

    from fem_dual import faults
    from fem_dual.output import read_series

    args = dict(T=0.5, rtol=1e-3)
    whole = run(RunConfig.create("beck", {"elements": "8"}, out=tmp_path / "a", **args))
    config = RunConfig.create("beck", {"elements": "8"}, out=tmp_path / "b", **args)
    with monkeypatch.context() as patch:
        asked = iter([0, 0, signal.SIGINT])
        patch.setattr(faults, "requested", lambda: next(asked, 0))
        with pytest.raises(faults.Interrupted):
            run(config)
    resumed = run(config, resume=True)
    assert resumed.solver["resumed_from"] is not None and resumed.status == "ok"
    _, times, steps = read_series(tmp_path / "b" / "beck_fields.xdmf")
    _, whole_times, _ = read_series(tmp_path / "a" / "beck_fields.xdmf")
    assert np.array_equal(times, whole_times)
    assert np.allclose(resumed.final["x"], whole.final["x"], rtol=0, atol=1e-15)
    tip = int(np.argmax(config.scene.dof_coordinates()[:, 0]))
    assert steps[-1]["w"][-1] == pytest.approx(resumed.final["x"][tip], rel=1e-12)
    assert resumed.error_estimate >= whole.error_estimate  # (d and the drops, merged, carried)


@pytest.mark.parametrize("u0, words", [("0.01*x**2, ", "empty"),
                                       ("sqrt(-1-x), 0", "not finite"),
                                       ("1e308*x*10, 0", "not finite at"),
                                       ("0, -x*1e308*1e308", "not finite at"),
                                       ("0.01*x**2*P/EI, 0.02*x*L", None)])
def test_start_fields_are_checked_and_may_use_the_parameters(u0, words):
    if words is None:
        assert RunConfig.create("beck", {"elements": "4"}, u0=u0, rtol=1e-3).x0 is not None
    else:
        with pytest.raises(InputError, match=words):
            RunConfig.create("beck", {"elements": "4"}, u0=u0, rtol=1e-3)
