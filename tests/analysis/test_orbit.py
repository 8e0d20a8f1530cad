"""`fem-dual orbit`: periods against exact ones, orders per degree, closure by an independent
integration, the command line's statuses, and rank-independence under MPI."""
import json
import subprocess
import sys

import numpy as np
import pytest
import scipy.linalg as sla
from mpi4py import MPI
from scipy.integrate import solve_ivp

from fem_dual.cli import main
from fem_dual.inputs import scene_of
from fem_dual.analysis.floquet import SlabFlow, multiplier_distance, nontrivial
from fem_dual.analysis.orbit import Orbits

FEM_DUAL = [sys.executable, "-m", "fem_dual.cli"]
CURL = {"F": "-x - 0.5*y**2, -2*y - 0.5*x**2"}  # a curl force: dFy/dx - dFx/dy = y - x


def ziegler_modes(params=None):
    """(omega, shapes) of Ziegler's column from the pencil (K, M), slowest first."""
    scene = scene_of("ziegler", params or {})
    lam, V = sla.eig(scene.stiffness_matrix(), scene.mass_matrix())
    order = np.argsort(lam.real)
    return scene, np.sqrt(lam.real[order]), V.real[:, order]


@pytest.fixture(scope="module")
def ziegler_orbits():
    scene = scene_of("ziegler", {})
    orbits = Orbits(scene, 4, 64)
    yield orbits
    orbits.close()


@pytest.mark.parametrize("mode", [0, 1])
def test_ziegler_mode_periods_are_two_pi_over_omega(ziegler_orbits, mode):
    scene, omega, shapes = ziegler_modes()
    exact = 2 * np.pi / omega[mode]
    x0 = 0.1 * shapes[:, mode] / np.abs(shapes[:, mode]).max()
    r = ziegler_orbits.solve(scene, x0, np.zeros(2), 1.05 * exact)
    assert r.status == "ok", r.message
    assert abs(r.period - exact) <= 1e-12 * exact
    assert abs(r.mu) <= 1e-12
    # the other mode turns by omega_other T in one period: multipliers exp(+-i omega_other T)
    other = omega[1 - mode] * r.period
    lam = sorted((complex(*m) for m in r.multipliers), key=lambda z: abs(z - 1))[2:]
    assert sorted(z.imag for z in lam) == pytest.approx(sorted([-np.sin(other), np.sin(other)]),
                                                        abs=1e-9)
    assert all(z.real == pytest.approx(np.cos(other), abs=1e-9) for z in lam)


def _one_orbit(scene, x0, T0, degree=4, cells=64, mode="closest", energy=None, has=None):
    """One orbit from the motion from (x0, 0) over T0, on orbits compiled for it alone."""
    orbits = Orbits(scene, degree, cells, has)
    try:
        return orbits.solve(scene, np.asarray(x0, float), np.zeros(scene.n), T0, mode, energy)
    finally:
        orbits.close()


def _multiplier_error(r, exact):
    """The largest distance of the orbit's nontrivial multipliers to `exact` (complex)."""
    lam = sorted((complex(*m) for m in r.multipliers), key=lambda z: abs(z - 1))[2:]
    return max(min(abs(z - e) for e in exact) for z in lam)


def _period_errors(scene, x0, T0, degree, cells_list, exact):
    errors, closures = [], []
    for cells in cells_list:
        orbits = Orbits(scene, degree, cells)
        try:
            r = orbits.solve(scene, x0, np.zeros(scene.n), T0)
        finally:
            orbits.close()
        errors.append(abs(r.period - exact))
        closures.append(r.closure)
    return np.array(errors), np.array(closures)


@pytest.mark.parametrize("degree", [2, 3])
def test_multipliers_of_fem_duals_own_slabs_converge_at_order_2p(ziegler_orbits, degree):
    """Ziegler's slow mode: the fast mode turns by omega_fast T in one period, so the exact
    nontrivial multipliers are exp(+-i omega_fast T); the monodromy of fem-dual's slab maps
    along the orbit reaches them at order 2p, and its degree p + 1 estimate is the error's size
    (relative to 1 + |multiplier| = 2: half of it)."""
    scene, omega, shapes = ziegler_modes()
    x0 = 0.1 * shapes[:, 0] / np.abs(shapes[:, 0]).max()
    r = ziegler_orbits.solve(scene, x0, np.zeros(2), 1.05 * 2 * np.pi / omega[0])
    assert r.status == "ok", r.message
    turn = omega[1] * r.period
    exact = np.array([np.exp(1j * turn), np.exp(-1j * turn)])
    z0 = np.concatenate([r.x[0], r.v[0]])
    flow = SlabFlow(degree)
    errors, estimates = [], []
    try:
        for cells in (32, 64):
            _, Phi, Phi_c = flow(scene, z0, r.period, cells)
            lam = nontrivial(np.linalg.eigvals(Phi))
            errors.append(max(np.abs(exact - z).min() for z in lam))
            estimates.append(multiplier_distance(lam, nontrivial(np.linalg.eigvals(Phi_c))))
    finally:
        flow.close()
    # measured 32 -> 64 -> 128 cells: orders 4.5, 4.3 (p = 2), 6.4, 6.2 (p = 3), 8.3, 8.3 (p = 4)
    assert 2 * degree - 0.5 <= np.log2(errors[0] / errors[1]) <= 2 * degree + 1
    assert all(0.4 * e <= est <= 0.6 * e for e, est in zip(errors, estimates))
    # the orbit's own multipliers: the flow refined until the estimate met its target
    assert _multiplier_error(r, exact) <= 1e-9 and r.estimate["multipliers"] <= 1e-10


@pytest.mark.parametrize("degree", [2, 3])
def test_period_and_closure_converge_at_order_2p_plus_2(degree):
    """Ziegler's slow mode (exact period) and the curl force's orbit (period of p = 6, 64
    cells): the period and the closure of the orbit's start converge at order 2p + 2, the
    order of the orbit solved once more on itself as the base state (order 2p from the guess
    alone: measured 3.99 and 6.00 for Ziegler at p = 2, 3)."""
    scene, omega, shapes = ziegler_modes()
    exact = 2 * np.pi / omega[0]
    x0 = 0.1 * shapes[:, 0] / np.abs(shapes[:, 0]).max()
    cells = [32, 64] if degree == 2 else [16, 32]  # (p = 3 at 64 cells: 1e-12, round-off)
    errors, closures = _period_errors(scene, x0, 1.05 * exact, degree, cells, exact)
    assert np.log2(errors[0] / errors[1]) == pytest.approx(2 * degree + 2, abs=0.5)
    assert np.log2(closures[0] / closures[1]) >= 2 * degree + 1.5
    force = scene_of("force", CURL)
    fine = Orbits(force, 6, 64)
    try:
        reference = fine.solve(force, np.array([0.3, 0.0]), np.zeros(2), 6.3).period
    finally:
        fine.close()
    errors, closures = _period_errors(force, np.array([0.3, 0.0]), 6.3, degree, [16, 32],
                                      reference)
    assert np.log2(errors[0] / errors[1]) == pytest.approx(2 * degree + 2, abs=0.5)
    assert np.log2(closures[0] / closures[1]) >= 2 * degree + 1.5


def test_a_nonlinear_orbit_closes_under_an_independent_integration():
    force = scene_of("force", CURL)
    r = _one_orbit(force, [0.3, 0.0], 6.3, cells=64)
    assert r.status == "ok" and r.newton["iterations"] <= 8
    z0 = np.concatenate([r.x[0], r.v[0]])

    def rhs(_t, z):
        x, y = z[:2]
        return [z[2], z[3], -x - 0.5 * y ** 2, -2 * y - 0.5 * x ** 2]

    end = solve_ivp(rhs, (0, r.period), z0, method="DOP853", rtol=1e-13, atol=1e-13).y[:, -1]
    assert np.abs(end - z0).max() <= 1e-11
    # an orbit, not a point: it moves, and returns only after the period
    half = solve_ivp(rhs, (0, r.period / 2), z0, method="DOP853", rtol=1e-13, atol=1e-13).y[:, -1]
    assert np.abs(half - z0).max() > 0.1
    # reversible and volume preserving: the multipliers come as lambda, 1/lambda, product 1
    lam = np.array([complex(*m) for m in r.multipliers])
    assert abs(np.prod(lam) - 1) <= 1e-9
    assert np.sort(np.abs(lam)) == pytest.approx(np.ones(4), abs=1e-8)
    # fem-dual's multipliers (its own slab maps) against the monodromy of DOP853 on the
    # variational equation, written here: to 1e-10, and the estimate says as much
    def variational(_t, y):
        x, y_ = y[:2]
        J = np.array([[0, 0, 1, 0], [0, 0, 0, 1], [-1, -y_, 0, 0], [-x, -2, 0, 0]])
        return np.concatenate([rhs(_t, y[:4]), (J @ y[4:].reshape(4, 4)).ravel()])

    y = solve_ivp(variational, (0, r.period), np.concatenate([z0, np.eye(4).ravel()]),
                  method="DOP853", rtol=1e-13, atol=1e-13).y[:, -1]
    reference = np.linalg.eigvals(y[4:].reshape(4, 4))
    reference = sorted(reference, key=lambda z: abs(z - 1))[2:]
    assert _multiplier_error(r, reference) <= 1e-10
    assert r.estimate["multipliers"] <= 1e-10 and r.check["multipliers"] <= 1e-10


def _cli(args, tmp_path):
    return subprocess.run(FEM_DUAL + ["orbit", *args], capture_output=True, text=True,
                          stdin=subprocess.DEVNULL, cwd=tmp_path)


@pytest.mark.parametrize("args, named", [
    (["nosuch", "--period", "6"], "nosuch"),
    (["ziegler", "--period", "-1"], "period"),
    (["ziegler", "--period", "nan"], "nan"),
    (["ziegler", "--period", "6", "--mode", "sideways"], "sideways"),
    (["ziegler", "--period", "6", "--mode", "energy=1"], "energy"),
    (["ziegler", "--param", "P=0", "--period", "6", "--mode", "energy=-1"], "-1"),
    (["curl3d", "--period", "6", "--mode", "energy=1"], "energy"),
    (["force", "--F", CURL["F"], "--x0", "0.3,0", "--period", "6.3", "--mode", "energy=1"],
     "energy"),
    (["force", "--F", "1/x**3 - x**3", "--x0", "1.1", "--period", "2.56", "--mode",
      "energy=0.78"], "potential"),
    (["ziegler", "--period", "6", "--continue", "Q=0:1:3"], "Q"),
    (["ziegler", "--period", "6", "--continue", "P=0:1:0"], "steps"),
    (["ziegler", "--period", "6", "--continue", "P=0:1"], "P=0:1"),
    (["ziegler", "--period", "6", "--x0", "1,2,3"], "x0"),
    (["ziegler", "--period", "6", "--cells", "0"], "cells"),
    (["ziegler", "--period", "6", "--degree", "0"], "degree"),
    (["curl2d-lifted", "--period", "6"], "curl2d"),
    (["ziegler", "--x0", "0,0", "--period", "13"], "equilibrium"),
    (["ziegler", "--x0", "0.1,0.16", "--period", "1e6"], "period=1e+06"),
    (["ziegler", "--x0", "0.1,0.16", "--period", "1e-320"], "period='1e-320'"),
    # a member past the first is bad: refused before any orbit is computed
    (["force", "--F", "-x - 0.1235*x**3", "--x0", "0.3", "--period", "6.3", "--continue",
      "m=1:0:2"], "m=0"),
    # ... or loses the energy its mode needs
    (["ziegler", "--x0", "-0.074,-0.1", "--period", "16", "--mode", "energy=1", "--param",
      "P=0", "--continue", "P=0:1:2"], "P=0.5"),
])
def test_bad_input_is_one_line_and_exit_2(tmp_path, args, named):
    proc = _cli(args, tmp_path)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and named in lines[0] and "Traceback" not in proc.stderr


def test_no_orbit_past_flutter_is_exit_3_with_the_reason(tmp_path):
    proc = _cli(["ziegler", "--param", "P=3", "--x0", "0.1,0.16", "--period", "10", "--json",
                 "--cells", "16", "--no-estimate"], tmp_path)
    assert proc.returncode == 3
    record = json.loads(proc.stdout)
    assert record["status"] == "failed" and record["message"]
    assert "no orbit" in proc.stderr


def test_continuation_follows_the_mode_to_flutter_and_stops_there(tmp_path):
    proc = _cli(["ziegler", "--x0", "0.1,0.16", "--period", "13", "--cells", "32",
                 "--continue", "P=1.6:2.2:3", "--json", "--no-estimate", "--out", "o",
                 "--plot", "p"], tmp_path)
    assert proc.returncode == 3, proc.stderr
    record = json.loads(proc.stdout)
    steps = record["continuation"]
    assert [s["P"] for s in steps[:3]] == pytest.approx([1.6, 1.8, 2.0])
    for step in steps[:3]:  # each equals the slow mode's period at its load, and closes
        scene, omega, _ = ziegler_modes({"P": step["P"]})
        assert step["status"] == "ok"
        assert step["period"] == pytest.approx(2 * np.pi / omega[0], rel=1e-9)
        M, K = scene.mass_matrix(), scene.stiffness_matrix()
        A = np.block([[np.zeros((2, 2)), np.eye(2)], [-np.linalg.solve(M, K), np.zeros((2, 2))]])
        z0 = np.concatenate([step["x0"], step["v0"]])
        closure = np.abs(sla.expm(A * step["period"]) @ z0 - z0).max()  # 32 cells: ~4e-9
        assert closure <= 1e-7 * np.abs(z0).max()
        assert closure == pytest.approx(step["closure"], rel=1e-2, abs=1e-12)  # as reported
    assert "P=2.2" in record["message"]  # Ziegler's flutter load is 2.09 for these parameters
    assert (tmp_path / "o" / "orbit.json").is_file() and (tmp_path / "p" / "continuation.png").is_file()


def test_a_continuation_failing_at_its_first_value_keeps_its_shape(tmp_path):
    proc = _cli(["ziegler", "--x0", "0.1,0.16", "--period", "13", "--cells", "16",
                 "--continue", "P=3:3.2:1", "--json", "--no-estimate"], tmp_path)
    assert proc.returncode == 3, proc.stderr
    record = json.loads(proc.stdout)
    assert record["status"] == "failed" and "P=3" in record["message"]
    assert record["continuation_parameter"] == "P" and isinstance(record["continuation"], list)


def test_a_failed_write_is_no_ok_in_orbit_json(tmp_path):
    (tmp_path / "d" / "orbit.csv").mkdir(parents=True)  # orbit.csv cannot be written
    proc = _cli(["force", "--F", CURL["F"], "--x0", "0.3,0", "--period", "6.3", "--cells", "16",
                 "--no-estimate", "--out", "d", "--json"], tmp_path)
    assert proc.returncode == 3 and "output failed" in proc.stderr
    assert json.loads((tmp_path / "d" / "orbit.json").read_text())["status"] == "failed"
    assert json.loads(proc.stdout)["status"] == "failed"


def test_sigint_stops_a_continuation_between_orbits_and_keeps_them(tmp_path):
    import signal

    proc = subprocess.Popen(FEM_DUAL + ["orbit", "force", "--F", "-x - a*y**2, -2*y - a*x**2",
                                        "--param", "a=0.5", "--x0", "0.3,0", "--period", "6.3",
                                        "--cells", "16", "--no-estimate", "--continue",
                                        "a=0.5:0.6:400", "--json"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            stdin=subprocess.DEVNULL, cwd=tmp_path)
    seen = []  # each orbit of a continuation is reported on stderr
    while not (seen and seen[-1].startswith("fem-dual: orbit 1/401: a=0.5, period")):
        seen.append(proc.stderr.readline())
        assert seen[-1], "".join(seen)  # not the end of stderr before the first orbit
    proc.send_signal(signal.SIGINT)  # after the first orbit: the continuation stops after the
    # orbit at hand (it waits for that line: a fixed wait can fall inside the first orbit's guess)
    out, err = proc.communicate(timeout=300)
    assert proc.returncode == 130, err
    assert "Traceback" not in err and "stopped" in err, err
    record = json.loads(out)
    assert record["status"] == "interrupted" and len(record["continuation"]) >= 1, err
    assert all(step["status"] == "ok" for step in record["continuation"])


@pytest.mark.mpi
def test_orbit_under_mpi_equals_serial(tmp_path_factory, capsys):
    comm = MPI.COMM_WORLD
    args = ["orbit", "force", "--F", CURL["F"], "--x0", "0.3,0", "--period", "6.3", "--cells",
            "16", "--json", "--no-estimate"]
    status = main(args, comm)
    out = capsys.readouterr().out
    assert status == 0 and comm.allreduce(status) == 0
    if comm.rank == 0:
        record = json.loads(out)
        assert record["period"] == pytest.approx(6.28318741330, rel=1e-10)
    else:
        assert out == ""
    serial = main(args, MPI.COMM_SELF)
    assert serial == 0


def test_multipliers_it_cannot_vouch_for_are_a_failure(monkeypatch):
    """With the flow held at the orbit's 8 cells (p = 4), the curl force's multipliers differ
    by 1.4e-6 between degrees p and p + 1: status failed, not ok."""
    from fem_dual.analysis.orbit import multipliers

    monkeypatch.setattr(multipliers, "FLOW_MAX_CELLS", 8)
    force = scene_of("force", CURL)
    r = _one_orbit(force, [0.3, 0.0], 6.3, cells=8)
    assert r.status == "failed" and "multipliers are uncertain" in r.message
    assert r.estimate["multipliers"] > multipliers.MULTIPLIER_TOL


def test_an_equilibrium_or_a_multiple_period_is_no_orbit():
    """The linear oscillator around x = 1 (period 2 pi) held at period 6.2832 collapses onto its
    equilibrium (it moves by 1e-7 and does not close): failed, saying so. A guess over twice
    (three times) the period finds the orbit run twice (three times): failed, naming the
    period."""
    shifted = scene_of("force", {"F": "-(x - 1)"})
    r = _one_orbit(shifted, [1.001], 6.2832, cells=64, mode="period")
    assert r.status == "failed" and "equilibrium" in r.message
    force = scene_of("force", CURL)
    r = _one_orbit(force, [0.3, 0.0], 12.6, cells=64)
    assert r.status == "failed" and "T/2 = 6.283187" in r.message


def _duffing_period(E):
    """The period of x'' = -x - x^3 at energy E = v^2/2 + x^2/2 + x^4/4, by quadrature of a
    smooth integrand (x = A sin(theta), V(A) = E)."""
    from scipy.optimize import brentq

    A = brentq(lambda a: 0.5 * a ** 2 + 0.25 * a ** 4 - E, 0.0, 10.0, xtol=1e-15)
    s, w = np.polynomial.legendre.leggauss(80)  # the integrand is analytic: converged
    th = np.pi / 4 * (s + 1)
    return 4 * np.pi / 4 * float(w @ (A / np.sqrt(A ** 2 + 0.5 * A ** 4 * (1 + np.sin(th) ** 2))))


def test_energy_mode_on_forces_with_a_potential():
    """--mode energy=E for a force with a potential (its Jacobian symmetric): Duffing's period
    at E against quadrature, near the guess's energy (one Newton) and far from it (steps in
    energy); a 2-dof potential's orbit has the energy E of an independent potential and closes
    under DOP853; a curl force has no energy."""
    from fem_dual.analysis.orbit import Energy

    duffing = scene_of("force", {"F": "-x - x**3"})
    has = Energy.of(duffing, np.array([0.5]))
    assert has is not None and not has.linear
    orbits = Orbits(duffing, 4, 64, has)
    try:
        for E, far in ((0.16, False), (1.0, True)):  # the guess's energy is 0.139
            r = orbits.solve(duffing, np.array([0.5]), np.zeros(1), 6.0, "energy", E)
            assert r.status == "ok", r.message
            assert abs(r.period - _duffing_period(E)) <= 1e-11
            assert abs(r.energy - E) <= 1e-10
            assert ("amplitude_steps" in r.newton or "energy_stages" in r.newton) == far
    finally:
        orbits.close()
    force = scene_of("force", {"F": "-x - x**3 - x*y, -2*y - 0.5*x**2"})
    has = Energy.of(force, np.array([0.3, 0.0]))
    orbits = Orbits(force, 4, 64, has)
    try:
        r = orbits.solve(force, np.array([0.3, 0.0]), np.zeros(2), 6.3, "energy", 0.06)
    finally:
        orbits.close()
    assert r.status == "ok", r.message
    (x, y), (u, w) = r.x[0], r.v[0]
    assert abs(0.5 * (u * u + w * w) + 0.5 * x * x + y * y + 0.25 * x ** 4 + 0.5 * x * x * y
               - 0.06) <= 1e-10

    def rhs(_t, z):
        return [z[2], z[3], -z[0] - z[0] ** 3 - z[0] * z[1], -2 * z[1] - 0.5 * z[0] ** 2]

    z0 = np.array([x, y, u, w])
    end = solve_ivp(rhs, (0, r.period), z0, method="DOP853", rtol=1e-13, atol=1e-13).y[:, -1]
    assert np.abs(end - z0).max() <= 1e-10
    assert Energy.of(scene_of("force", CURL), np.array([0.3, 0.0])) is None


def test_energy_mode_from_the_linear_limit_to_negative_energies():
    """Near a linear limit the energy row is nearly singular (amplitude 1.4e-4): the closest
    orbits scaled in amplitude reach E = 1e-8, whose orbit closes with that energy (the
    potential by hand). A potential from V(0) = 0 can be negative: E = -0.1 in a well of
    x - x^3 (V = -x^2/2 + x^4/4 + y^2/2). A fast force (sin(40 x)) gets its energy from a finer
    rule of the line integral: the energy of its orbit is (1 - cos 40x) / 40 + v^2 / 2."""
    from fem_dual.analysis.orbit import Energy

    cases = [({"F": "-sin(x) + 0.3*y**2*sin(x), -2*y - 0.6*y*cos(x)"}, [1.4e-4, 0.0], 6.3, 1e-8,
              lambda x, v: 1 - np.cos(x[0]) + x[1] ** 2 * (1 - 0.3 * np.cos(x[0]))
              + 0.5 * v @ v),
             ({"F": "x - x**3, -y"}, [1.2, 0.0], 6.0, -0.1,
              lambda x, v: -0.5 * x[0] ** 2 + 0.25 * x[0] ** 4 + 0.5 * x[1] ** 2 + 0.5 * v @ v),
             ({"F": "-sin(40*x)"}, [np.pi + 0.02], 1.03, 0.0076,
              lambda x, v: (1 - np.cos(40 * x[0])) / 40 + 0.5 * v @ v)]
    for params, x0, T0, E, energy in cases:
        scene = scene_of("force", params)
        has = Energy.of(scene, np.array(x0))
        r = _one_orbit(scene, x0, T0, cells=32, mode="energy", energy=E, has=has)
        assert r.status == "ok", (params, r.message)
        x, v = np.array(r.x[0]), np.array(r.v[0])
        assert abs(energy(x, v) - E) <= 1e-10 * max(1.0, abs(E)) and abs(r.energy - E) <= 1e-10

        def rhs(_t, z, n=scene.n):
            return np.concatenate([z[n:], scene.force_numpy(z[:n])])

        z0 = np.concatenate([x, v])
        end = solve_ivp(rhs, (0, r.period), z0, method="DOP853", rtol=1e-13, atol=1e-13).y[:, -1]
        assert np.abs(end - z0).max() <= 1e-8 * np.ptp(r.x, axis=0).max()


def test_no_energy_where_the_potential_cannot_be_integrated():
    """A force singular at the origin has no potential V(0) = 0 there: no energy (not a
    quadrature's nonsense, -2.8e6), and mode energy is refused (exit 2, in test_bad_orbit_input);
    -sin(40 x) needs more than 12 Gauss points (with 12 its energy is 0.57 % off)."""
    from fem_dual.analysis.orbit_input import Energy

    singular = scene_of("force", {"F": "1/x**3 - x**3"})
    assert Energy.of(singular, np.array([1.1])) is None
    fast = Energy.of(scene_of("force", {"F": "-sin(40*x)"}), np.array([3.16]))
    assert fast is not None and fast.points > 12
    assert abs(fast.value(np.array([3.16]), np.zeros(1)) - (1 - np.cos(40 * 3.16)) / 40) <= 1e-13
    r = _one_orbit(singular, [1.1], 2.56, cells=32)
    assert r.status == "ok" and r.energy is None


def test_orbits_far_from_the_origin_and_many_times_around():
    """Difference steps relative to the orbit's extent, not its offset: the pendulum pair
    -sin(x - 1000), sin(y - 1000) has multiplier exp(T) (y decoupled) to its estimate, and the
    check agrees (steps of 1 at |x| = 1000 would refuse the orbit); a Duffing orbit of amplitude
    1e-3 around x = 1e4 is an orbit, not an equilibrium. A guess over 13 periods finds the orbit
    run 13 times: failed, naming T/13 (the check does not stop at 12)."""
    pair = scene_of("force", {"F": "-sin(x-1000), sin(y-1000)"})
    r = _one_orbit(pair, [1001.0, 1000.0], 6.7, cells=64)
    assert r.status == "ok", r.message
    big = max(m[0] for m in r.multipliers)
    error = abs(big - np.exp(r.period)) / (1 + np.exp(r.period))
    assert error <= max(r.estimate["multipliers"], 1e-9) and r.check["multipliers"] <= 1e-6
    small = scene_of("force", {"F": "-(x-1e4) - 100*(x-1e4)**3, -2*y"})
    r = _one_orbit(small, [10000.001, 0.0], 6.28, cells=64)
    assert r.status == "ok", r.message
    A = 0.5 * np.ptp(np.array(r.x)[:, 0])
    assert 0.9e-3 <= A <= 1.1e-3  # the family's member closest to the guess
    assert abs(r.period - 2 * np.pi * (1 - 3 / 8 * 100 * A ** 2)) <= 1e-7  # Lindstedt, O(A^4)
    duffing = scene_of("force", {"F": "-x - x**3, -2.3*y"})
    r = _one_orbit(duffing, [0.5, 0.0], 75.0293, cells=128)
    assert r.status == "failed" and "T/13" in r.message


def test_multipliers_beyond_double_precision_are_named():
    """Multipliers exp(+-4T) ~ 1e10 and 1e-10: the small one is known only to eps |Phi|
    ~ 1e-5; failed, saying that no resolution helps (not advising to raise --cells)."""
    scene = scene_of("force", {"F": "-x - x**3, 16*y"})
    r = _one_orbit(scene, [0.5, 0.0], 6.0, cells=32)
    assert r.status == "failed" and "double precision" in r.message
    assert "raise --cells" not in r.message
    assert r.estimate["multipliers_roundoff"] > 1e-6


def test_the_pair_at_1_is_deflated_not_split_by_the_jordan_block():
    """An orbit of a family has a Jordan block at 1 in its monodromy (the flow's direction and
    the family's): an error e in the monodromy moves its raw eigenvalues by sqrt(e), so a 1-dof
    orbit near a separatrix has raw multipliers 2.8 and 0.36 beside an estimate of 5e-15. With
    the flow's direction deflated the pair stays within O(e) of 1, and the nontrivial ones are
    the monodromy's own."""
    from fem_dual.analysis.floquet import floquet_multipliers

    f = np.array([0.0, 1.0, 0.0, 0.0])  # the flow's direction; the family's is e_0
    R = np.array([[np.cos(2.0), -np.sin(2.0)], [np.sin(2.0), np.cos(2.0)]])
    Phi = sla.block_diag([[1.0, 0.0], [50.0, 1.0]], 1.7 * R)  # a Jordan block and a pair
    Phi = Phi + 1e-10 * np.random.default_rng(1).standard_normal((4, 4))
    raw = np.linalg.eigvals(Phi)
    assert np.sort(np.abs(raw - 1))[1] > 1e-5  # the raw pair: split by about sqrt(50e-10)
    trivial, rest = floquet_multipliers(Phi, f)
    assert np.abs(trivial - 1).max() <= 1e-8
    assert multiplier_distance(rest, 1.7 * np.exp([2j, -2j])) <= 1e-8

    r = _one_orbit(scene_of("force", {"F": "-x - x**3"}), [1.0], 4.77, cells=32)
    assert r.status == "ok", r.message
    for m in r.multipliers + r.check["multipliers_dop853"]:
        assert abs(complex(*m) - 1) <= 1e-8
    assert r.estimate["trivial_multipliers"] <= 1e-8 and r.nontrivial_multipliers == []


def test_energy_mode_says_what_it_reached_and_what_no_family_member_has(tmp_path):
    """Mode energy prints the energy asked for beside the one reached and the estimate of the
    energy's error (degree p against p + 1); an E below the energy of the equilibrium that the
    guess's family surrounds is named as such, at once (not after 49 s of steps in energy that
    end in "give a guess nearer that energy"), and no orbit's advice names options of `run`."""
    proc = _cli(["force", "--F", "-x - x**3", "--x0", "0.5", "--period", "6", "--cells", "32",
                 "--mode", "energy=0.2"], tmp_path)
    assert proc.returncode == 0, proc.stderr
    line = next(x for x in proc.stdout.splitlines() if x.strip().startswith("energy"))
    assert "asked 0.2, off by" in line and "estimated error" in line
    proc = _cli(["force", "--F", "-x - x**3", "--x0", "0.5", "--period", "6", "--cells", "32",
                 "--mode", "energy=-1", "--json"], tmp_path)
    assert proc.returncode == 3
    assert "below the energy 0 of the equilibrium x = [0.0]" in json.loads(proc.stdout)["message"]
    from fem_dual.analysis.orbit import _orbit_advice

    for advice in ("use smaller slabs (more --slabs)", "loosen --rtol, or raise --cells or "
                   "--degree", "use smaller slabs or larger alpha"):
        text = _orbit_advice(f"it failed; {advice}")
        assert "--rtol" not in text and "--slabs" not in text and "--period" in text


def test_no_energy_says_why(tmp_path):
    """Mode energy refused for a force whose potential a 96-point rule cannot integrate from
    the origin says so, not "no finite potential"."""
    proc = _cli(["force", "--F", "-x - 0.5*sin(40*x)", "--x0", "10", "--period", "6", "--mode",
                 "energy=1"], tmp_path)
    assert proc.returncode == 2 and "varies too fast" in proc.stderr


def test_a_guess_far_from_the_orbit_restarts_on_its_newtons_image():
    """Duffing from x0 = 1 over 5.5 (the orbit through x0 = 1 has period 4.77; the family member
    found is a smaller one): Newton's first try leaves the DtP map singular (left there,
    the orbit fails); started again on the DtP image of its last iterate it converges, and the
    polish on itself puts the period within 1e-12 of the quadrature at the orbit's energy (2e-8
    without it)."""
    scene = scene_of("force", {"F": "-x - x**3"})
    r = _one_orbit(scene, [1.0], 5.5, cells=64)
    assert r.status == "ok", r.message
    assert r.newton.get("base_restarts", 0) >= 1 and "polish_iterations" in r.newton
    assert abs(r.period - _duffing_period(r.energy)) <= 1e-12


def _variational_multipliers(F, DF, z0, T):
    """Multipliers of the orbit through z0 over T by DOP853 at 1e-13 on the motion and its
    variational equation with the exact Jacobian DF (an independent check)."""
    n = len(z0) // 2

    def rhs(_t, y):
        z, Phi = y[:2 * n], y[2 * n:].reshape(2 * n, 2 * n)
        A = np.zeros((2 * n, 2 * n))
        A[:n, n:] = np.eye(n)
        A[n:, :n] = DF(z[:n])
        return np.concatenate([z[n:], F(z[:n]), (A @ Phi).ravel()])

    y0 = np.concatenate([z0, np.eye(2 * n).ravel()])
    y = solve_ivp(rhs, (0, T), y0, method="DOP853", rtol=1e-13, atol=1e-13).y[:, -1]
    return np.linalg.eigvals(y[2 * n:].reshape(2 * n, 2 * n))


def test_multipliers_have_no_difference_step_error():
    """Exact tangents of fem-dual's slab maps and the exact force Jacobian in the DOP853 check:
    on the x-mode (y = 0) of a force whose y**3 and y**5 terms vanish there, the multipliers
    are those of the force without them. Difference steps of 1e-5 of the extent would put
    fem-dual 6.1e-5 off with both the estimate (same step in the companion) and a differenced
    check fooled (status ok: the y**5 term is built to match such a check's error), and fail a
    stiffer y**3 alone with advice that could not help."""
    def F(x):
        return np.array([-x[0] - x[0] ** 3 - 2 * x[0] * x[1] ** 2,
                         -2 * x[1] - 2 * x[0] ** 2 * x[1]])

    def DF(x):
        return np.array([[-1 - 3 * x[0] ** 2 - 2 * x[1] ** 2, -4 * x[0] * x[1]],
                         [-4 * x[0] * x[1], -2 - 2 * x[0] ** 2]])

    for extra, x0, T0 in [("- 10000*y**3 + 37964.085*y**5", [3.0, 0.0], 2.2),
                          ("- 1000000*y**3", [1.0, 0.0], 5.0)]:
        text = f"-x - x**3 - 2*x*y**2, -2*y - 2*x**2*y {extra}"
        r = _one_orbit(scene_of("force", {"F": text}), x0, T0)
        assert r.status == "ok", r.message
        z0 = np.concatenate([r.x[0], r.v[0]])
        exact = _variational_multipliers(F, DF, z0, r.period)
        got = np.array([complex(*m) for m in r.multipliers])
        error = multiplier_distance(nontrivial(exact), nontrivial(got))
        assert error <= max(3 * r.estimate["multipliers"], 1e-10), (error, r.estimate)


def test_period_estimate_covers_the_orbit_through_its_start():
    """At p = 2 the discrete orbit's energy varies along it, and the exact period through its
    reported start differs from the reported one by dT/dE times that (1.6e-8 against an
    estimate of 1.3e-10 from the degree p + 1 difference alone): the estimate takes the return
    time of the check's DOP853 motion (check.period) in."""
    r = _one_orbit(scene_of("force", {"F": "-sin(x)"}), [2.5], 9.0, degree=2, cells=128)
    assert r.status == "ok", r.message
    x0, v0 = r.x[0][0], r.v[0][0]
    E = 1 - np.cos(x0) + v0 ** 2 / 2  # the pendulum's period at energy E: 4 K(E/2)
    from scipy.special import ellipk

    exact = 4 * ellipk(E / 2)
    assert abs(r.check["period"] - exact) <= 1e-11 * exact
    assert abs(r.period - exact) <= r.estimate["period"]


@pytest.mark.serial
def test_orbit_inputs_out_of_range_are_bad_input(capsys):
    """Starts of size 1e-300 or 1e300 are one line asking to rescale (not a traceback of an
    overflow, nor RuntimeWarnings before exit 3), and cells beyond the orbit's limit are named
    without a run's slabs."""
    for x0 in ("1e-300", "1e300"):
        assert main(["orbit", "force", "--F", "-x", "--x0", x0, "--period", "6"]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "rescale" in err, err
    assert main(["orbit", "force", "--F", "-x", "--x0", "1", "--period", "6",
                 "--cells", "1e9"]) == 2
    err = capsys.readouterr().err
    assert "at most 4096" in err and "slabs" not in err
