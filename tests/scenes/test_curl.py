"""Nonlinear curl forces (reference, sections 3.1, 3.2) against DOP853 at rtol = atol = 1e-13."""
import json

import h5py
import numpy as np
import pytest
from dolfinx import fem
from dolfinx.fem import petsc as fem_petsc
from mpi4py import MPI

from fem_dual import RunConfig, SolveError, run
from fem_dual.cli import main
from fem_dual.slab.snes import NewtonSlabSolver
from fem_dual.slab.problem import SlabProblem
from fem_dual.scenes import get_scene
from helpers import observed_rates

CASES = {  # scene: (slabs, cells for the accuracy target)
    "curl3d": 1,
    "curl2d": 4,
    "curl2d-lifted": 4,
}


@pytest.mark.mpi
@pytest.mark.parametrize("scene", list(CASES))
@pytest.mark.parametrize("degree, rate, cells", [(2, 3.8, (5, 10, 20, 40)), (3, 5.5, (3, 6, 12))])
def test_convergence_order(scene, degree, rate, cells):
    """Order 2p at the vertices (momentum recovery) from the start base, down to about 1e-11."""
    errors = [run(RunConfig.create(scene, cells=c, degree=degree, slabs=CASES[scene],
                                   base="start"))
              .error["x_max"] for c in cells]
    assert np.all(observed_rates(errors) > rate), (errors, observed_rates(errors))


@pytest.mark.mpi
@pytest.mark.parametrize("scene", list(CASES))
@pytest.mark.parametrize("degree, rate, cells", [(2, 5.5, (1, 2, 4, 8)), (3, 7.5, (1, 2, 4))])
def test_convergence_order_of_the_rk4_base(scene, degree, rate, cells):
    """The rk4 base (the default with --rtol for motion that is not stiff): order 2p + 2 at the
    vertices (measured 5.7-6.0 at p = 2, 7.8-8.1 at p = 3), down to about 1e-11."""
    errors = [run(RunConfig.create(scene, cells=c, degree=degree, slabs=CASES[scene],
                                   base="rk4"))
              .error["x_max"] for c in cells]
    assert np.all(observed_rates(errors) > rate), (errors, observed_rates(errors))


@pytest.mark.mpi
@pytest.mark.parametrize("scene, slabs, cells", [("curl3d", 1, 80), ("curl2d", 4, 40),
                                                 ("curl2d-lifted", 4, 40)])
def test_accuracy_target_of_the_issue(scene, slabs, cells):
    r = run(RunConfig.create(scene, T=2.0, cells=cells, degree=3, slabs=slabs, base="start"))
    assert r.error["x_max"] <= 1e-6
    assert r.hamiltonian["drift"] < 1e-5
    assert len(r.solver["newton_iterations"]) == slabs


@pytest.mark.parametrize("scene, params, x0, v0, T, slabs", [
    ("curl3d", {"alpha": "3", "beta": "0.5", "m": "2"}, "0.5,-0.2,0.3", "0.1,0,-0.2", 2.0, 2),
    ("curl2d", {"k": "2", "m": "0.5"}, "0.5,-0.4", "0.2,0.1", 3.0, 24),
    ("curl2d-lifted", {"k": "2", "alpha": "2"}, "0.5,-0.4", "0.2,0.1", 3.0, 24),
])
def test_other_parameters_and_states(scene, params, x0, v0, T, slabs):
    r = run(RunConfig.create(scene, params, T=T, cells=40, degree=3, slabs=slabs, x0=x0, v0=v0))
    assert r.error["x_max"] <= 1e-6, r.error


def _converged_histories(scene):
    """Newton from the start base (the rk4 base starts it within round-off of the answer)."""
    r = run(RunConfig.create(scene, T=2.0, cells=40, degree=3, slabs=4, base="start"))
    return r.solver["residual_histories"]


@pytest.mark.parametrize("scene", ["curl3d", "curl2d", "curl2d-ufl"])
def test_newton_converges_quadratically(scene):
    """rho_{k+1} <= 10 rho_k^2 for the normalised residuals once rho_k < 0.1, above round-off."""
    for history in _converged_histories(scene):
        r = np.array(history)
        rho = r / r[0]
        checked = 0
        for k in range(len(r) - 1):
            if rho[k] < 0.1 and r[k + 1] > 1e-12:
                assert rho[k + 1] <= 10 * rho[k] ** 2, history
                checked += 1
        assert checked >= 1, history


def test_lifted_newton_ends_quadratically():
    """The lifted saddle needs backtracking far away; near the solution the rate is quadratic."""
    for history in _converged_histories("curl2d-lifted"):
        r = np.array(history)
        tail = [k for k in range(len(r) - 1) if r[k] < 1e-3 and r[k + 1] > 1e-12]
        assert tail, history
        assert all(r[k + 1] <= 1e3 * r[k] ** 2 for k in tail), history


@pytest.mark.parametrize("assembly", ["pointwise", "forms"])
def test_unbalanced_weights_converge_at_their_round_off(assembly):
    """alpha = 1e3, beta = 1e-3: |J| ~ 3e5, so the residual stalls near |J| eps |w| ~ 1e-10,
    where the slab is solved (the error 1.8e-10 within the estimate). The round-off floor
    includes |J| eps |w|, so Newton is not called diverged there (residual 3.4e-11, exit 3)."""
    r = run(RunConfig.create("curl3d", {"alpha": "1e3", "beta": "1e-3"}, T=0.5, cells=8,
                             degree=3, max_halvings=0, assembly=assembly))
    err = max(r.error["x_max"], r.error["v_max"])
    assert r.status == "ok" and err <= r.error_estimate < 1e-8


@pytest.mark.serial
@pytest.mark.parametrize("scene", ["curl3d", "curl2d", "curl2d-ufl", "curl2d-lifted"])
def test_jacobian_symmetric(scene):
    """At a converged, non-zero dual state the assembled Jacobian is symmetric to round-off."""
    cls = get_scene(scene)
    problem = SlabProblem(cls(), degree=2, cells=8, comm=MPI.COMM_SELF)
    problem.set_slab(np.array(cls.default_x0), np.array(cls.default_v0), 0.5)
    solver = NewtonSlabSolver(problem, "test_sym_", {})
    solver.solve()
    assert np.abs(problem.w.x.array).max() > 1e-6
    A = fem_petsc.assemble_matrix(fem.form(problem.jacobian), bcs=problem.bcs)
    A.assemble()
    dense = A.convert("dense").getDenseArray()
    assert np.abs(dense - dense.T).max() <= 1e-12 * np.abs(dense).max()


def test_the_implicit_map_is_solved_once_per_dual_state_and_start():
    """SNES asks for the Jacobian where it took the last residual: the pointwise DtP solve is
    skipped there, and redone (to the same values as from scratch) when the dual state or the
    start state changes."""
    cls = get_scene("curl2d")
    problem = SlabProblem(cls(), degree=2, cells=8, comm=MPI.COMM_SELF)
    x0, v0 = np.array(cls.default_x0), np.array(cls.default_v0)
    problem.set_slab(x0, v0, 0.5)
    solver = NewtonSlabSolver(problem, "test_once_", {})
    solver.solve()
    calls = []
    solve = problem.pointwise.solve
    problem.pointwise.solve = lambda comm: calls.append(1) or solve(comm)
    solver._update(solver.x)
    assert calls == []  # the converged state is the one held
    problem.set_start(x0 * 1.01, v0)
    solver._update(solver.x)
    assert len(calls) == 1
    moved = problem.pointwise.X.x.array.copy()
    problem.pointwise.X.x.array[:] = 0.0  # from scratch: the same root
    problem.pointwise.reset(x0 * 1.01)
    solve(MPI.COMM_SELF)
    assert np.abs(problem.pointwise.X.x.array - moved).max() <= 1e-13
    problem.set_start(x0, v0)
    solver._update(solver.x)
    assert len(calls) == 2


@pytest.mark.mpi
def test_hand_derived_lifted_and_user_defined_agree():
    cfg = dict(T=2.0, cells=40, degree=3, slabs=4)
    hand, ufl_, lifted = (run(RunConfig.create(s, **cfg)) for s in
                          ("curl2d", "curl2d-ufl", "curl2d-lifted"))
    assert np.abs(hand.x - ufl_.x).max() < 1e-11  # same discrete problem, G by hand or by UFL
    assert np.abs(hand.x - lifted.x).max() < 1e-6  # different discretisation, same motion
    h3, u3 = (run(RunConfig.create(s, T=2.0, cells=40, degree=3)) for s in
              ("curl3d", "curl3d-ufl"))
    assert np.abs(h3.x - u3.x).max() < 1e-11  # explicit A(eta)^-1 vs implicit UFL-derived path


@pytest.mark.mpi
@pytest.mark.parametrize("scene", ["curl2d", "curl2d-lifted"])
def test_parallel_matches_serial(scene):
    cfg = RunConfig.create(scene, T=2.0, cells=20, degree=3, slabs=4)
    par, ser = run(cfg, MPI.COMM_WORLD), run(cfg, MPI.COMM_SELF)
    assert np.abs(par.x - ser.x).max() <= 1e-10 * np.abs(ser.x).max()
    assert np.abs(par.v - ser.v).max() <= 1e-10 * np.abs(ser.v).max()


@pytest.mark.mpi
def test_blow_up_exits_3_keeps_completed_slabs_and_writes_no_nan(tmp_path_factory, capsys):
    comm = MPI.COMM_WORLD
    out = comm.bcast(str(tmp_path_factory.mktemp("blowup")) if comm.rank == 0 else None)
    status = main(["run", "curl3d", "--T", "12", "--slabs", "24", "--cells", "20", "--degree",
                   "3", "--json", "--out", out])
    assert status == 3
    captured = capsys.readouterr()
    if comm.rank != 0:
        return
    assert captured.err.count("\n") == 1 and "slab" in captured.err
    data = json.loads(captured.out)  # strict JSON: no NaN
    assert data["status"] == "failed" and "slab" in data["message"]
    assert 0 < data["t"][-1] < 12 and np.isfinite(data["x"]).all()
    assert data["output_slabs"] == len(data["slab_lengths"]) > 0
    with h5py.File(f"{out}/curl3d.h5") as h5:
        assert len(h5["steps/x_hat"]) == len(data["slab_lengths"])
        assert np.isfinite(h5["steps/x_hat"][()]).all()


@pytest.mark.serial
def test_dtp_map_without_solution_stops_with_slab_and_time():
    with pytest.raises(SolveError) as info:
        run(RunConfig.create("curl2d", {"k": "20"}, T=2.0, cells=20, max_halvings=0,
                             base="start"))
    assert "slab 0" in str(info.value) and "t = " in str(info.value)
    assert "smaller slabs" in str(info.value)
    assert info.value.partial.status == "failed" and len(info.value.partial.t) == 0


@pytest.mark.mpi
def test_slab_halving_recovers_a_failing_slab():
    """A slab length that fails outright (max_halvings=0) succeeds when halving is allowed."""
    args = dict(T=3.0, cells=40, degree=3, slabs=3, x0="0.5,-0.4", v0="0.2,0.1", base="start")
    params = {"k": "2", "m": "0.5"}
    with pytest.raises(SolveError):
        run(RunConfig.create("curl2d", params, max_halvings=0, **args))
    r = run(RunConfig.create("curl2d", params, **args))
    assert r.status == "ok" and r.error["x_max"] < 1e-5
    assert min(r.slab_lengths) < 1.0 and sum(r.slab_lengths) == pytest.approx(3.0)
    assert r.solver["halved_slabs"]


@pytest.mark.serial
@pytest.mark.parametrize("scene, slabs, sym, num", [("curl2d", 4, 2, None), ("ziegler", 4, 2, 2)])
def test_factorisations_counted_by_petsc(scene, slabs, sym, num, tmp_path):
    """Symbolic LU once per run and degree (the answer's and its error companion's); numeric per
    Newton step (nonlinear) or once (linear). Solves per slab: the answer, the companion, and
    from the second slab on the tangent that carries the error estimate forward, and for
    nonlinear slabs one more Newton step and the 2n difference tangents of the volume check
    (no new factorisations). (Nonlinear slabs on the PETSc SNES: the default pointwise Newton
    uses no PETSc.)"""
    import os
    import subprocess
    import sys

    log = tmp_path / "log.txt"
    env = {**os.environ, "PETSC_OPTIONS": f"-log_view :{log}"}
    subprocess.run([sys.executable, "-m", "fem_dual.cli", "run", scene, "--T", "2", "--slabs",
                    str(slabs), "--cells", "20", "--degree", "3", "--assembly", "forms",
                    "--base", "start"],
                   check=True, env=env,
                   capture_output=True, stdin=subprocess.DEVNULL)
    counts = {line.split()[0]: int(line.split()[1]) for line in log.read_text().splitlines()
              if line.split()[:1] and line.split()[0] in ("MatLUFactorSym", "MatLUFactorNum",
                                                           "KSPSolve")}
    assert counts["MatLUFactorSym"] == sym
    tangents = slabs - 1
    if num is not None:
        assert counts["MatLUFactorNum"] == num and counts["KSPSolve"] == 2 * slabs + tangents
    else:  # nonlinear: one more Newton step per slab measures the algebraic error
        tangents += 2 * 2 * slabs  # the volume check's, 2n a slab (curl2d: n = 2)
        assert counts["MatLUFactorNum"] == counts["KSPSolve"] - tangents - slabs > 2 * slabs
