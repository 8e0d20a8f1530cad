"""Every answer carries an error estimate computed without a reference; no wrong answer is
reported as a success; --rtol chooses the slab lengths.

The references are independent: the matrix exponential (linear scenes) and DOP853 at
rtol = atol = 1e-13 (nonlinear scenes), which is why errors below about 1e-11 are not judged.
"""
import json
import math
import time

import numpy as np
import pytest

from fem_dual import RunConfig, SolveError, run
from fem_dual.cli import main
from fem_dual.config import Tolerance
from fem_dual.integrate.controller import SlabSchedule, step_factor
from fem_dual.integrate.estimate import ErrorWeights
from fem_dual.slab.snes import stalled

JUDGED_ABOVE = 1e-11  # below this the reference's own error and round-off dominate


def _actual(result):
    return max(result.error["x_max"], result.error["v_max"])


def _ratio(result):
    return result.error_estimate / _actual(result)


# scene, parameters, T, slabs, cells, degree: linear (forms and Kronecker), explicit, implicit
# and lifted nonlinear scenes, coarse to fine.
RATIO_CASES = [
    ("ziegler", {}, 20.0, 1, 100, 2),
    ("ziegler", {}, 20.0, 4, 10, 3),
    ("ziegler", {}, 100.0, 20, 8, 4),
    ("ziegler", {"P": "3"}, 20.0, 8, 4, 4),
    ("ziegler", {"d1": "0.1"}, 20.0, 10, 4, 2),
    ("column", {"links": "6"}, 10.0, 10, 8, 4),
    ("curl3d", {}, 2.0, 1, 4, 2),
    ("curl3d", {}, 8.0, 16, 8, 2),
    ("curl3d", {}, 8.0, 8, 4, 3),
    ("curl2d", {}, 2.0, 4, 8, 3),
    ("curl2d-lifted", {}, 2.0, 4, 8, 3),
    ("curl2d-ufl", {}, 2.0, 4, 8, 2),
]


@pytest.mark.mpi
@pytest.mark.parametrize("scene, params, T, slabs, cells, degree", RATIO_CASES)
def test_estimate_over_actual_error(scene, params, T, slabs, cells, degree):
    """The estimate sits within [1, 10] times the true error (README: "Error estimate")."""
    r = run(RunConfig.create(scene, params, T=T, slabs=slabs, cells=cells, degree=degree))
    assert _actual(r) > JUDGED_ABOVE, "the case must be coarse enough to judge"
    assert 1.0 <= _ratio(r) <= 10.0, (r.error_estimate, r.error)
    assert len(r.solver["estimates"]) == len(r.slab_lengths)


@pytest.mark.mpi
@pytest.mark.parametrize("degree, rate", [(2, 3.6), (3, 5.4)])
def test_estimate_converges_with_the_error(degree, rate):
    """Refining the cells, the estimate falls at the order of the error (2p) and keeps its
    ratio: it is an estimate of this error, not a bound of another order."""
    results = [run(RunConfig.create("curl3d", T=4.0, slabs=2, cells=c, degree=degree))
               for c in (4, 8, 16)]
    assert all(len(r.slab_lengths) == 2 for r in results)  # none retried: the asked resolution
    estimates = np.array([r.error_estimate for r in results])
    assert np.all(np.log2(estimates[:-1] / estimates[1:]) > rate), estimates
    assert all(1.0 <= _ratio(r) <= 10.0 for r in results), [_ratio(r) for r in results]


# Settings that invite a wrong answer reported as ok (growth, long horizons, coarse slabs, tiny
# masses, weak preconditioners), as the user gives them: each must either converge (relative error
# below the acceptance rule, 1e-3 of the motion's scale) or stop.
WRONG_BEFORE = [
    ("ziegler", {"P": "3"}, {}),
    ("ziegler", {}, {"T": 100, "cells": 50, "degree": 4}),
    ("curl3d", {}, {"T": 9, "slabs": 45, "cells": 16, "degree": 3}),
    ("curl2d-lifted", {"k": "100"}, {"T": 1, "slabs": 8, "cells": 20, "degree": 3}),
    ("ziegler", {"m1": "1e-12", "m2": "1e-12"}, {"T": 1e-4, "cells": 50, "degree": 4,
                                                 "slabs": 10}),
    ("ziegler", {}, {"petsc": {"pc_type": "none"}}),
    ("ziegler", {}, {"petsc": {"pc_type": "jacobi"}}),
    ("curl3d", {}, {"T": 8, "cells": 2, "degree": 4}),
    ("curl3d", {}, {"T": 8, "cells": 16, "degree": 2}),
    # a slab whose Newton ends on another solution of its equations, 2.6e-2 off (the companion
    # must not start from it)
    ("curl3d", {}, {"T": 9.3, "slabs": 45, "cells": 8, "degree": 4}),
    ("curl3d", {}, {"T": 9.3, "slabs": 45, "cells": 16, "degree": 4}),
    # ... and answers whose companions, solved from zero, crept to the same other solution
    ("curl3d", {}, {"T": 9.3, "slabs": 15, "cells": 10, "degree": 4}),
    ("curl3d", {}, {"T": 9.096, "slabs": 14, "cells": 9, "degree": 4}),
    # ... and one whose companion crept there from a warm start a third of zero's residual away,
    # as near as correct coarse slabs' (a velocity jump of 1.5e-2 in one cell: RK4 sees it)
    ("curl3d", {}, {"T": 9.3, "slabs": 12, "cells": 6, "degree": 3}),
    # perturbations outgrow the motion (the tangent 9e6-fold): round-off that sqrt(k) floors
    # of the scale do not cover
    ("curl3d", {}, {"T": 9.3, "slabs": 30, "cells": 16, "degree": 3}),
    ("curl3d", {}, {"T": 9.2, "slabs": 45, "cells": 16, "degree": 3}),
]


@pytest.mark.mpi
@pytest.mark.parametrize("scene, params, kw", WRONG_BEFORE)
def test_no_wrong_answer_reported_as_success(scene, params, kw):
    try:
        r = run(RunConfig.create(scene, params, **kw))
    except SolveError as exc:
        assert "slab" in str(exc)
        kept = exc.partial
        if kept is not None and kept.t.size > 1:  # what it keeps, it vouches for
            assert kept.error_estimate >= _actual(kept), (kept.error, kept.error_estimate)
        return
    x_ref_scale = r.tolerance["scale_x"]
    assert r.error["x_max"] <= 1e-3 * x_ref_scale, r.error
    assert r.error_estimate >= _actual(r)


def test_refuses_when_it_cannot_shorten():
    """Without halvings the coarse unstable run cannot be repaired: exit 3, naming the slab
    and what to change, and keeping nothing it cannot vouch for."""
    with pytest.raises(SolveError) as info:
        run(RunConfig.create("ziegler", {"P": "3"}, max_halvings=0))
    text = str(info.value)
    assert "slab 0" in text and "no shorter slab left" in text and "--rtol" in text
    assert info.value.partial.t.size == 0


@pytest.mark.mpi
def test_refining_by_slabs_keeps_order_2p():
    """Short slabs' Newton stops relative to what the slab can reach, not at an absolute 1e-10
    (which leaves 3.5e-10 with 4 slabs, 1.4e-10 with 8, against 9.9e-14 with 1)."""
    errors = [run(RunConfig.create("curl3d", T=2.0, cells=8, degree=4, slabs=k)).error["x_max"]
              for k in (1, 4, 8)]
    assert max(errors) < 2e-12, errors


@pytest.mark.mpi
@pytest.mark.parametrize("scene, params, T, rtol, extra", [
    ("ziegler", {}, 200.0, 1e-6, {}),
    ("ziegler", {}, 200.0, 1e-9, {}),
    ("ziegler", {"P": "3"}, 20.0, 1e-7, {}),
    ("ziegler", {}, 50.0, 1e-8, {"superpose": "no"}),
    ("column", {"links": "6"}, 20.0, 1e-7, {}),
    ("curl3d", {}, 8.0, 1e-6, {}),
    ("curl3d", {}, 8.0, 1e-9, {}),
    ("curl2d", {}, 2.0, 1e-8, {}),
])
def test_rtol_reaches_the_tolerance(scene, params, T, rtol, extra):
    r = run(RunConfig.create(scene, params, T=T, rtol=rtol, cells=4, degree=4, **extra))
    scale = max(r.tolerance["scale_x"], r.tolerance["scale_v"])
    assert r.error["x_max"] <= rtol * r.tolerance["scale_x"]
    assert r.error["v_max"] <= rtol * r.tolerance["scale_v"]
    assert r.error_estimate <= 10 * rtol * scale
    assert r.slabs == len(r.slab_lengths) > 0
    assert math.isclose(sum(r.slab_lengths), T, rel_tol=1e-12)


def test_rtol_lengths_follow_the_tolerance():
    """Tighter tolerances take more (shorter) slabs, at the order of the method: a factor 1000
    in rtol costs about 1000^(1/8) = 2.4 times the slabs with degree 4."""
    counts = [run(RunConfig.create("ziegler", T=200.0, rtol=rtol, cells=4, degree=4)).slabs
              for rtol in (1e-5, 1e-8)]
    assert 1.5 <= counts[1] / counts[0] <= 4.5, counts


@pytest.mark.serial
@pytest.mark.parametrize("argv, named", [
    (["--rtol", "0"], "rtol='0'"), (["--rtol", "1"], "rtol='1'"),
    (["--rtol", "nan"], "rtol='nan'"), (["--rtol", "-1e-6"], "rtol='-1e-6'"),
    (["--rtol", "abc"], "rtol='abc'"), (["--rtol", "1e-13"], "rtol='1e-13' is below"),
    (["--rtol", "1e-6", "--atol", "inf"], "atol='inf'"),
    (["--atol", "1e-9"], "atol='1e-9' needs rtol"),
    (["--rtol", "1e-6", "--slabs", "4"], "contradict"),
])
def test_bad_tolerances_exit_2(argv, named, capsys):
    assert main(["run", "ziegler", *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and named in err, err


@pytest.mark.serial
def test_json_carries_the_estimate(capsys):
    assert main(["run", "curl3d", "--T", "2", "--cells", "4", "--degree", "3", "--slabs", "2",
                 "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["error_estimate"] >= max(data["error"]["x_max"], data["error"]["v_max"])
    assert [e["t0"] for e in data["solver"]["estimates"]] == [0.0, 1.0]
    assert data["tolerance"]["adaptive"] is False
    assert main(["run", "curl3d", "--T", "2", "--cells", "4", "--degree", "3"]) == 0
    assert "estimated x_max" in capsys.readouterr().out


def test_failed_attempts_count_in_the_run_time(monkeypatch):
    """Each solve of the answer's slab (accepted or not) is made to last at least PAUSE:
    solve_s holds them all, rejected attempts included (a bound that wall-clock noise cannot
    break, unlike a comparison of two measured phases)."""
    from fem_dual.integrate.simulation import Simulation
    PAUSE, attempts, solve = 0.01, [], Simulation.solve_slab

    def slowed(self, z0, t0, dt, start=None, counted=True):
        if counted and start is None and self.with_dual:  # (the answer's slab)
            attempts.append(t0)
            time.sleep(PAUSE)
        return solve(self, z0, t0, dt, start=start, counted=counted)

    monkeypatch.setattr(Simulation, "solve_slab", slowed)
    r = run(RunConfig.create("curl3d", T=8.0, cells=2, degree=4))
    assert r.solver["rejected_slabs"] > 0
    assert len(attempts) >= r.slabs + r.solver["rejected_slabs"]
    assert r.timings["solve_s"] >= PAUSE * len(attempts)
    assert r.timings["estimate_s"] > 0


# -- the machinery ------------------------------------------------------------------------------
def test_controller_lengths_are_aligned_powers_of_two():
    c = SlabSchedule(T=1.0, slabs=1, max_halvings=10, first=0.3)
    assert c.current() == (0.0, 0.25)
    seen = []
    for err in (0.01, 5.0, 0.5, 1e-6, 1e-6, 1e-6, 1e-6):
        t0, dt = c.current()
        if err > 1:
            assert c.halve(step_factor(err, 4))
            continue
        seen.append((t0, dt))
        c.accept(step_factor(err, 4))
        if c.done():
            break
    for t0, dt in seen:
        assert math.log2(1.0 / dt).is_integer() and (t0 / dt).is_integer()
    assert sum(dt for _, dt in seen) == pytest.approx(c.pos / c.total)


def test_step_factor():
    assert step_factor(None, 4) == 0.5 and step_factor(float("nan"), 4) == 0.125
    assert step_factor(0.0, 4) == 4.0 and step_factor(1e-12, 4) == 4.0
    assert step_factor(1.0, 4) == pytest.approx(0.9) and step_factor(1e12, 4) == 0.125
    assert step_factor(16.0, 4) == pytest.approx(0.45)


def test_controller_reject_stops_at_the_minimum():
    c = SlabSchedule(T=2.0, slabs=4, max_halvings=2)
    assert c.current() == (0.0, 0.5)
    assert c.halve() and c.halve() and not c.halve()
    assert c.current() == (0.0, 0.125)


def test_weights_are_relative_to_the_running_scale():
    w = ErrorWeights(Tolerance(1e-6, 0.0, True), np.array([2.0, 0.0]), np.array([0.0, 0.0]))
    scales = w.with_motion(np.array([[1.0, -3.0]]), np.array([[0.5, 0.0]]))
    assert scales == (3.0, 0.5)
    e = np.array([[3e-6, 0.0, 0.0, 1e-7]])
    assert w.norm(e, scales) == pytest.approx(1.0)
    assert w.norm(np.zeros((1, 4)), scales) == 0.0


def test_stall_detection():
    assert not stalled([1.0, 1e-2, 1e-6, 1e-13])
    assert stalled([1.0, 0.19, 0.19, 0.19, 0.18, 1e-3, 1e-8, 1e-14])


# -- user options, tight tolerances, equilibria and unstable motions ----------------------------
@pytest.mark.parametrize("scene, option", [
    ("curl2d", {"snes_stol": "0.5"}), ("curl2d-lifted", {"snes_stol": "0.5"}),
    ("curl3d", {"snes_rtol": "1e-2"}), ("curl3d", {"snes_type": "ksponly"}),
    ("curl2d", {"snes_max_it": "1"}),
])
def test_loosened_newton_options_cannot_hide_the_error(scene, option):
    """Newton stopped early by user options stops the companion by the same test, so their
    difference alone misses the algebraic error (by 50x to 1e5x in these cases): the answer's
    own Newton error (one more Newton step) is part of the estimate.""" 
    try:
        r = run(RunConfig.create(scene, petsc=option))
    except SolveError as exc:
        assert "slab" in str(exc)
        return
    assert r.error_estimate >= _actual(r)


@pytest.mark.serial
@pytest.mark.parametrize("option", ["ksp_type=nonsense", "pc_type=nonsense"])
def test_unknown_petsc_types_are_bad_input(option, capsys):
    for scene in ("ziegler", "curl3d"):
        assert main(["run", scene, "--petsc-option", option]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and option in err, err


@pytest.mark.mpi
@pytest.mark.parametrize("rtol", [1e-10, 1e-11])
def test_tight_rtol_on_a_linear_scene(rtol):
    """Round-off-level local errors do not drive the slabs towards 1e-11 and a refusal."""
    r = run(RunConfig.create("ziegler", rtol=rtol, degree=6, cells=4))
    assert r.error["x_max"] <= rtol * r.tolerance["scale_x"]
    assert min(r.slab_lengths) > 1e-3


@pytest.mark.mpi
@pytest.mark.parametrize("scene, params, x0", [("curl3d", {}, "1,0,0"), ("curl2d", {}, "0,1"),
                                               ("curl2d", {"k": "0"}, None),
                                               ("curl3d", {}, "0,0,0")])
def test_equilibria_are_answered(scene, params, x0):
    """A start at rest in an equilibrium (F = 0) is answered: a residual of 0 is a solved slab,
    not "Newton did not converge (residual 0 after 0 iterations)"."""
    r = run(RunConfig.create(scene, params, x0=x0))
    assert r.status == "ok" and _actual(r) <= 1e-14 and r.error_estimate <= 1e-11


# Near curl3d's unstable equilibrium x = (1e3, 0, 0) a perturbation of 1e-9 grows 3000-fold per
# 0.25 of time. Slabs of 8 cells miss the growth, and so does their degree p + 1 companion: judged
# by their difference alone the run would end ok with an estimate of 5e-8 against a true error of
# 1e9. The slab tangent's phase-space volume (det = 1 for any force F(x)) shows the slab does not
# follow the motion.
UNSTABLE = dict(x0="1e3,0,0", v0="0,1e-9,0", cells=8, degree=3)


@pytest.mark.parametrize("base", ["auto", "start"])
def test_a_slab_that_misses_an_unstable_motion_is_not_vouched_for(base):
    try:
        r = run(RunConfig.create("curl3d", T=0.5, slabs=2, base=base, **UNSTABLE))
    except SolveError:  # (the start base: refused, exit 3)
        pass
    else:  # (the predictor base: shorter slabs followed it)
        assert len(r.slab_lengths) > 2
        assert _actual(r) <= r.error_estimate
    with pytest.raises(SolveError):  # over T = 1 the motion outgrows what it can vouch for
        run(RunConfig.create("curl3d", T=1, slabs=4, base=base, **UNSTABLE))


@pytest.mark.mpi
def test_the_snes_path_judges_volume_by_difference_tangents():
    """PETSc's SNES on the forms has no exact tangent: its 2n difference tangents give the
    volume check there (serial and distributed), without which `curl3d --x0 1e3,0,0 --v0
    0,1e-9,0 --cells 8 --assembly forms` would end ok 444 off with an estimate of 1.6e-8."""
    try:
        r = run(RunConfig.create("curl3d", assembly="forms", **UNSTABLE))
    except SolveError:
        return
    assert _actual(r) <= r.error_estimate


def test_volume_defect_of_exact_flows():
    from scipy.linalg import expm

    from fem_dual.integrate.judge import volume_defect

    rng = np.random.default_rng(4)
    n = 3
    M = np.diag([1.0, 2.0, 0.5])
    K, D = rng.standard_normal((n, n)), np.diag([0.3, 0.1, 0.2])
    A = np.block([[np.zeros((n, n)), np.eye(n)], [-np.linalg.solve(M, K), -np.linalg.solve(M, D)]])
    assert volume_defect(expm(A * 0.7), M, D, 0.7) < 1e-12
    A[n:, n:] = 0.0
    assert volume_defect(expm(A * 0.7), M, None, 0.7) < 1e-12
    assert volume_defect(0.5 * np.eye(2 * n), M, None, 0.7) > 0.9


def test_the_predictor_base_is_judged_by_volume_where_a_mode_grows():
    """The predictor base damps what the cells do not resolve; a saddle's growth is no fast
    oscillation. Without the volume check `--base predictor` on the stable manifold of F = 1e4 x
    would end ok 13 off with an estimate of 2e-3, and curl3d's unstable equilibrium ok 444 off."""
    cases = [("force", {"F": "1e4*x"}, dict(x0="1", v0="-100", T=0.15, cells=16, degree=4)),
             ("curl3d", None, dict(T=2, **UNSTABLE))]
    for scene, params, args in cases:
        try:
            r = run(RunConfig.create(scene, params, base="predictor", **args))
        except SolveError:
            continue
        assert _actual(r) <= r.error_estimate


def test_the_stiff_spring_keeps_its_predictor_base_and_one_slab():
    r = run(RunConfig.create("curl3d", {"K": "0,0,0,0,0,0,0,0,1e6"}, x0="0.3,0.2,-0.06e-6",
                             cells=16, degree=2))
    assert r.solver["base"] == "predictor" and len(r.slab_lengths) == 1


@pytest.mark.parametrize("fast, rtol, most", [("1e-9", 1e-6, 16), ("1e-6", 1e-4, None)])
def test_a_damped_mode_is_judged_once(fast, rtol, most):
    """The zero base damps a mode the slabs do not resolve; what it takes away is lost once,
    whatever the slab's length: within the tolerance it is accepted (a fast mode of amplitude
    1e-9 took 2,048 slabs when it was judged per unit of time, now 5), beyond it the slabs
    resolve the mode (amplitude 1e-6: its speed 1e-3 exceeds 1e-4)."""
    r = run(RunConfig.create("linear", {"dofs": "2", "K": "1,0,0,1000000"}, T=10,
                             x0=f"1,{fast}", rtol=rtol))
    assert r.solver["base"] == "zero" and r.status == "ok"
    assert _actual(r) <= r.error_estimate <= 10 * rtol * max(r.tolerance["scale_x"],
                                                              r.tolerance["scale_v"])
    if most is not None:
        assert len(r.slab_lengths) <= most
    else:
        assert len(r.slab_lengths) > 1000


def test_carried_round_off_follows_the_tangent():
    """The carried round-off is the floors' covariance grown by the slab maps' tangents: with
    the identity, k floors add in quadrature; with a map that grows one component g-fold per
    slab, that component's floor grows as the geometric sum; without a tangent, as the
    identity."""
    from fem_dual.integrate.estimate import CARRIED_SHARE, SlabEstimate, carried_floor, carry

    zero = np.zeros((3, 2))
    slab = SlabEstimate(0.0, 1.0, zero, zero, 0.0, 0.0, (1.0, 2.0))
    C = np.zeros((2, 2))
    for _ in range(16):
        C = carry(C, slab, np.eye(2))
    assert np.allclose(carried_floor(C), np.array([4.0, 8.0]) * CARRIED_SHARE)
    g, C = 3.0, np.zeros((2, 2))
    for _ in range(5):
        C = carry(C, slab, np.diag([g, 1.0]))
    geometric = math.sqrt(sum(g ** (2 * j) for j in range(5)))
    assert np.isclose(carried_floor(C)[0], geometric * CARRIED_SHARE)
    assert np.isclose(carried_floor(C)[1], math.sqrt(5) * 2.0 * CARRIED_SHARE)
    assert np.allclose(carry(C, slab), C + np.diag([1.0, 4.0]) * CARRIED_SHARE ** 2)


def test_the_reference_of_a_tiny_motion_keeps_its_digits():
    """DOP853's atol follows the start's size below 1: from x0 = 1e-8 a Duffing force's
    reference was 1e-16 off, which read as fem-dual's error (55 times its estimate)."""
    r = run(RunConfig.create("force", {"F": "-x - x**3"}, x0=[1e-8], T=10.0, rtol=1e-8))
    assert r.error_estimate >= max(r.error["x_max"], r.error["v_max"]), (r.error,
                                                                          r.error_estimate)
