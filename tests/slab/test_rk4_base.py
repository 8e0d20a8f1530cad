"""The rk4 base state (fem_dual.slab.base_state.FlowPredictor) lets Newton converge on long
slabs of a nonlinear motion that is not stiff, so --rtol takes the slabs accuracy needs, with the
same error estimate. References: DOP853 at rtol = atol = 1e-13 (the scenes' own)."""
import numpy as np
import pytest

from fem_dual import RunConfig, SolveError, run
from fem_dual.slab.base_state import FlowPredictor
from fem_dual.cli import main
from fem_dual.integrate.simulation import Simulation
from fem_dual.scenes import get_scene

JUDGED_ABOVE = 1e-11  # below this the reference's own error dominates


def _actual(result):
    return max(result.error["x_max"], result.error["v_max"])


def _rtol_run(base, rtol):
    return run(RunConfig.create("curl3d", T=8, cells=4, degree=4, rtol=rtol, base=base,
                                staging="off"))


@pytest.mark.parametrize("rtol", [1e-6, 1e-8])
def test_rk4_base_takes_fewer_slabs_and_its_estimate_bounds_the_error(rtol):
    start, rk4 = _rtol_run("start", rtol), _rtol_run("rk4", rtol)
    assert rk4.status == "ok" and start.status == "ok"
    # Newton limits the start base to 8 slabs (5 of its 13 attempts fail); rk4 needs 2 or 3
    assert len(rk4.slab_lengths) <= len(start.slab_lengths) / 2
    assert abs(sum(rk4.slab_lengths) - 8.0) < 1e-12
    err = _actual(rk4)
    assert err > JUDGED_ABOVE
    assert 1.0 <= rk4.error_estimate / err <= 10.0  # measured 2.1 and 2.1
    scale = max(np.abs(rk4.x).max(), np.abs(rk4.v).max())
    assert rk4.error_estimate <= 10 * rtol * scale  # ACCEPT_GLOBAL


def test_rk4_base_converges_at_the_order_of_the_method():
    """Fixed slabs: the max error falls as (cells)^-2p, as on the start base (p = 2: order 4)."""
    errors = []
    for cells in (4, 8, 16):
        r = run(RunConfig.create("curl2d", T=2, cells=cells, degree=2, slabs=2, base="rk4",
                                 staging="off"))
        errors.append(_actual(r))
    orders = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    assert orders.min() > 3.5, (errors, orders)


def test_held_base_tangent_is_the_slab_maps():
    """The exact tangent with the rk4 base held agrees with a central difference of whole slab
    solves, whose base moves with the start (the base moves the answer by the discretisation
    error only)."""
    config = RunConfig.create("curl3d", T=2, cells=8, degree=4, slabs=1, base="rk4",
                              staging="off")
    sim = Simulation.for_config(config)
    try:
        sim.begin(config)
        z = np.concatenate([config.x0, config.v0])
        values = sim.solve_slab(z, 0.0, 2.0)
        rng = np.random.default_rng(3)
        dz = rng.standard_normal(6)
        held = sim.tangent(z, dz, 0.0, 2.0, values)
        eps = 1e-5
        ends = []
        for sign in (1, -1):
            moved = sim.solve_slab(z + sign * eps * dz, 0.0, 2.0)
            ends.append(np.hstack([moved.x, moved.v]))
        central = (ends[0] - ends[1]) / (2 * eps)
        assert np.abs(held - central).max() <= 1e-6 * np.abs(central).max()
    finally:
        sim.close()


def test_flow_predictor_is_fourth_order_and_read_again_without_stepping():
    scene = get_scene("curl3d")()
    z0 = np.array([0.3, 0.2, 0.1, 0.0, 0.0, 0.0])
    t = np.linspace(0.0, 2.0, 9)
    exact = scene.reference(z0[:3], z0[3:])(t)
    exact = np.hstack(exact)
    errors = []
    for steps in (8, 16, 32):
        pred = FlowPredictor(scene, steps)
        errors.append(np.abs(pred(z0, t, 2.0) - exact).max())
    orders = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    assert orders.min() > 3.5, (errors, orders)
    pred = FlowPredictor(scene, 8)
    first = pred(z0, t, 2.0)
    calls = []
    pred._run = lambda z, end, f=pred._run: calls.append(1) or f(z, end)
    again = pred(z0, np.linspace(0.0, 2.0, 5), 2.0)  # other nodes, same slab: no stepping
    assert not calls and np.allclose(again, first[::2], rtol=0, atol=1e-15)


def test_a_repeated_run_steps_its_base_again():
    """Each run of a Simulation steps its rk4 base afresh (the bench times repeats of the same
    run: reading the last run's steps would leave their cost out)."""
    config = RunConfig.create("curl3d", T=2, cells=2, degree=3, slabs=1, base="rk4",
                              reference="none", staging="off")
    sim = Simulation.for_config(config)
    try:
        sim.run(config)
        calls = []
        for predictor in (sim.backend.problem.predictor, sim.companion.backend.problem.predictor):
            predictor._run = lambda z, end, f=predictor._run: calls.append(1) or f(z, end)
        sim.run(config)
        assert len(calls) == 2
    finally:
        sim.close()


def test_the_companion_steps_its_own_base_with_twice_the_steps():
    """A base error the answer and its companion shared would cancel in their difference: on
    a shared base, curl3d T = 8 --rtol 1e-10 at p = 6 and one cell ends ok 6.2e-11 off (a
    30-digit reference agrees) with an estimate of 3.8e-12, the companion about as far off."""
    config = RunConfig.create("curl3d", T=8, cells=1, degree=6, rtol=1e-10, base="rk4")
    sim = Simulation.for_config(config)
    try:
        r = sim.run(config)
        answer, companion = sim.backend.problem.predictor, sim.companion.backend.problem.predictor
        assert companion is not answer and companion.steps == 2 * answer.steps
    finally:
        sim.close()
    assert r.status == "ok" and _actual(r) <= r.error_estimate


def test_rk4_base_refuses_a_stiff_motion_it_cannot_step():
    """Explicit Runge-Kutta on a stiff spring overflows: a clear failure, never NaN as ok."""
    config = RunConfig.create("curl3d", {"K": "1e8"}, T=1, cells=2, degree=2, slabs=1,
                              base="rk4", max_halvings=0, staging="off")
    with pytest.raises(SolveError, match="rk4 base state overflowed"):
        run(config)


def test_rk4_base_on_a_linear_scene_is_bad_input(capsys):
    assert main(["run", "ziegler", "--base", "rk4", "--cells", "4"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "base=rk4" in err[0]


@pytest.mark.mpi
@pytest.mark.parametrize("assembly", ["forms", "pointwise"])
def test_rk4_base_in_parallel_equals_serial(assembly):
    """On forms distributed over the processes each holds the nodes of its own cells: the rk4
    steps must still be those of the whole slab (steps over the local nodes' span alone give,
    under `mpirun -n 2`, an error of 7.4e-10 and an estimate of 1.5e-9 against the serial
    3.2e-10 and 6.7e-10)."""
    from mpi4py import MPI

    cfg = RunConfig.create("curl3d", T=8, cells=4, degree=4, rtol=1e-8, base="rk4",
                           assembly=assembly, staging="off")
    par, ser = run(cfg, MPI.COMM_WORLD), run(cfg, MPI.COMM_SELF)
    assert par.slab_lengths == ser.slab_lengths
    scale = np.abs(ser.x).max()
    assert np.abs(par.x - ser.x).max() <= 1e-11 * scale
    assert np.abs(par.v - ser.v).max() <= 1e-11 * np.abs(ser.v).max()
    assert par.error_estimate == pytest.approx(ser.error_estimate, rel=1e-3)


def test_snes_stops_at_the_residuals_round_off_unless_the_user_sets_atol():
    """The rk4 base's first residual is ~1e-8: SNES's relative test (1e-13) is out of reach, and
    alone it takes ten steps at 1e-16; the absolute round-off test of the pointwise path ends
    it."""
    common = dict(T=4, slabs=2, cells=4, degree=4, base="rk4", staging="off")
    ours = run(RunConfig.create("curl3d", assembly="forms", **common))
    pointwise = run(RunConfig.create("curl3d", assembly="pointwise", **common))
    users = run(RunConfig.create("curl3d", petsc={"snes_atol": "0"}, **common))
    assert ours.solver["newton_iterations"] == pointwise.solver["newton_iterations"]
    assert max(ours.solver["newton_iterations"]) <= 2
    assert min(users.solver["newton_iterations"]) > 2  # the user's atol = 0 holds
    assert np.abs(ours.x - pointwise.x).max() <= 1e-12 * np.abs(pointwise.x).max()


@pytest.mark.mpi
@pytest.mark.parametrize("case", [
    ("force", {"F": "1"}, dict(x0="1", v0="0", base="rk4")),  # the rk4 base is the motion
    ("curl3d", None, dict(x0="1,0,0")),  # at rest in an equilibrium
    ("force", {"F": "1+exp(-10*x*x)"}, dict(x0="0", v0="1", T=4, slabs=4, base="rk4"))])
def test_forms_path_with_no_newton_step_has_its_jacobian(case):
    """A slab that starts at the residual's round-off takes no SNES step: the estimate's
    tangent and extra Newton step need the Jacobian assembled at that state (not missing:
    'Not for unassembled matrix', nor an earlier slab's). Both paths agree."""
    from mpi4py import MPI

    scene, params, extra = case
    common = dict(dict(T=2, cells=4, degree=2, staging="off"), **extra)
    forms = run(RunConfig.create(scene, params, assembly="forms", **common), MPI.COMM_WORLD)
    pointwise = run(RunConfig.create(scene, params, assembly="pointwise", **common))
    assert forms.status == "ok" and 0 in forms.solver["newton_iterations"]
    assert np.abs(forms.x - pointwise.x).max() <= 1e-12 * max(1.0, np.abs(pointwise.x).max())
    assert forms.error_estimate == pytest.approx(pointwise.error_estimate, rel=1e-3, abs=1e-14)


def test_new_parameter_values_reach_the_base():
    """A Simulation compiled once runs new parameter values of its scene (the forms take
    them as constants); the rk4 base steps the motion of those values, not the first ones."""
    first = RunConfig.create("curl3d", T=1, cells=2, degree=3, slabs=1, base="rk4",
                             reference="none", staging="off")
    sim = Simulation.for_config(first)
    try:
        sim.run(first)
        second = RunConfig.create("curl3d", {"K": "2,0,0,0,2,0,0,0,2"}, T=1, cells=2, degree=3,
                                  slabs=1, base="rk4", reference="none", staging="off")
        sim.run(second)
        for problem in (sim.backend.problem, sim.companion.backend.problem):
            assert problem.predictor.scene == second.scene
    finally:
        sim.close()


def test_a_force_that_answers_a_list_steps_as_an_array_does():
    """A scene file's force_numpy may return a list: the rk4 sums must not concatenate it."""
    scene = get_scene("curl2d")()

    class ListForce:
        n = 2

        def mass_matrix(self):
            return np.eye(2)

        def force_numpy(self, x):
            return list(scene.force_numpy(x))

    z0, t = np.array([1.0, 1.0, 0.0, 0.0]), np.linspace(0.0, 1.0, 5)
    expected = FlowPredictor(scene, 10, compiled=False)(z0, t, 1.0)
    assert np.array_equal(FlowPredictor(ListForce(), 10, compiled=False)(z0, t, 1.0), expected)
