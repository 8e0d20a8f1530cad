"""The modes of a stiff pencil near coalescence (fem_dual.modes) and the data floor of the
estimate (fem_dual.integrate.conditioning), against a 25-digit eigen-decomposition of the very
M and K the run exports."""
import mpmath as mp
import numpy as np
import pytest

from fem_dual.analysis.continuum_flutter import slow_modes
from fem_dual.config import RunConfig
from fem_dual.errors import SolveError
from fem_dual.integrate.api import run
from fem_dual.integrate.conditioning import data_floor
from fem_dual.modes import block_slices, cancelling, coupling, real_modes


def _beck(P: float, **kwargs) -> RunConfig:
    """Beck's column at 20 elements, started in its two slowest modes at rest (the start of a
    flutter search), a tip deflection of 1 %."""
    scene = RunConfig.create("beck", {"elements": "20", "P": repr(P)}).scene
    x0 = slow_modes(scene)[0].sum(axis=1)
    x0 = 0.01 * x0 / np.abs(x0).max()
    return RunConfig.create("beck", {"elements": "20", "P": repr(P)}, x0=x0.tolist(), **kwargs)


def _exact(config: RunConfig, t: float):
    """(x, v) at t of M x'' + K x = 0 from (x0, 0), 25 digits, M and K taken as exact."""
    mp.mp.dps = 25
    M, K = config.scene.mass_matrix(), config.scene.stiffness_matrix()
    lam, V = mp.eig(mp.inverse(mp.matrix(M.tolist())) * mp.matrix(K.tolist()))
    c = mp.inverse(V) * mp.matrix(config.x0.tolist())
    w = [mp.sqrt(a) for a in lam]
    x = V * mp.matrix([c[k] * mp.cos(w[k] * t) for k in range(len(w))])
    v = V * mp.matrix([-c[k] * w[k] * mp.sin(w[k] * t) for k in range(len(w))])
    return (np.array([complex(a).real for a in x]), np.array([complex(a).real for a in v]))


def test_near_flutter_the_answer_its_estimate_and_its_reference_hold_to_25_digits():
    """P = 20.055, 1e-4 below this mesh's flutter load: in float64 the slow block's K U cancels
    (|K| 7e6 against 120) and its round-off moved the motion 6.8e-7 over T = 20 where the
    tolerance was 1.1e-8 and the estimate said 5.8e-9."""
    config = _beck(20.055, T=20.0, rtol=1e-7)
    result = run(config)
    x, v = _exact(config, result.t[-1])
    err_x = np.abs(result.x[-1] - x).max()
    err_v = np.abs(result.v[-1] - v).max()
    tol_v = config.rtol * result.tolerance["scale_v"]
    assert result.status == "ok"
    assert err_v <= tol_v and err_v <= result.estimate["final_v"], (err_v, tol_v, result.estimate)
    assert err_x <= result.estimate["final_x"]
    # the reference the run compares with (modal blocks) agrees with the 25-digit one
    assert abs(result.error["final_v"] - err_v) <= 0.1 * err_v + 1e-12
    assert result.error["reference_floor"] == result.estimate["data_floor_v"]


def test_two_slow_modes_close_together_beside_a_very_fast_one():
    """omega^2 = 1 and 1.5 beside 1e6 and 1e12 (a random orthogonal basis, M = I): QZ mixes the
    slow pair by eps |K| / 0.5 = 1e-4. The Newton step must take them apart (a gap of 0.5 is not
    a repeated frequency next to 1e12): the answer was 5e-6 off at --rtol 1e-6 with an estimate
    of 1.3e-7, and its reference, sharing the modes, agreed with it."""
    Q, _ = np.linalg.qr(np.random.default_rng(1).standard_normal((4, 4)))
    K = Q @ np.diag([1.0, 1.5, 1e6, 1e12]) @ Q.T
    K = 0.5 * (K + K.T)
    x0 = Q[:, 0] + Q[:, 1]
    config = RunConfig.create("linear", {"dofs": "4", "M": "1",
                                         "K": ",".join(repr(float(a)) for a in K.ravel())},
                              x0=x0.tolist(), v0=[0.0] * 4, T=20.0, rtol=1e-6)
    result = run(config)
    x, v = _exact(config, result.t[-1])
    assert result.status == "ok"
    err_x, err_v = np.abs(result.x[-1] - x).max(), np.abs(result.v[-1] - v).max()
    assert err_x <= result.estimate["final_x"] and err_v <= result.estimate["final_v"]
    assert err_v <= 1e-6 * result.tolerance["scale_v"]


def test_the_newton_step_decouples_the_slow_modes():
    """At P = 20 the two slowest modes are separate blocks 22 apart; QZ's eigenvectors leave
    them coupled by 5e-7 (extended precision), which the blocks off the diagonal drop."""
    scene = RunConfig.create("beck", {"elements": "20", "P": "20"}).scene
    M, K = scene.mass_matrix(), scene.stiffness_matrix()
    U, Kr = real_modes(M, K)[:2]
    slices = block_slices(Kr)
    refine = cancelling(K, U, slices, K @ U)
    assert refine[:2].all() and slices[0] == slice(0, 1) and slices[1] == slice(1, 2)
    full = np.linalg.solve(U, np.linalg.solve(M, K @ U))
    C = coupling(M, K, U, slices, refine, full)
    assert abs(C[1, 0]) + abs(C[0, 1]) < 1e-9  # was 1.2e-6 before the step
    assert np.allclose(np.diag(Kr)[:2], [110.498, 133.010], atol=1e-3)


@pytest.mark.parametrize("P", [20.06, 21.0])
def test_the_data_floor_refuses_a_tolerance_float64_cannot_reach(P):
    config = _beck(P, T=20.0, rtol=1e-11)
    floor = data_floor(config.scene, config.x0, config.v0, config.T)
    assert floor is not None and (floor.final() > 0).all()
    assert np.all(np.diff(floor.floor, axis=0) >= 0)
    with pytest.raises(SolveError, match="round-off of M and K alone"):
        run(config)


def test_no_data_floor_for_a_damped_or_nonlinear_scene():
    damped = RunConfig.create("linear", {"dofs": "2", "D": "0.1, 0, 0, 0.1"}, x0=[1, 0])
    assert data_floor(damped.scene, damped.x0, damped.v0, damped.T) is None
    curl = RunConfig.create("curl3d")
    assert data_floor(curl.scene, curl.x0, curl.v0, curl.T) is None


def test_the_data_floor_reaches_the_fields_written(tmp_path):
    """Fixed slabs resolve P = 20.06 far below its data floor: the estimate the JSON and the
    XDMF series report is the floor."""
    from fem_dual.output import read_series

    config = _beck(20.06, T=20.0, slabs=40, cells=16, degree=5, out=str(tmp_path))
    result = run(config)
    floor = data_floor(config.scene, config.x0, config.v0, config.T)
    assert result.estimate["final_v"] == pytest.approx(floor.final()[1])
    _, _, steps = read_series(tmp_path / "beck.xdmf")
    assert steps[-1]["error_estimate"].max() == pytest.approx(floor.final().max())


def test_modes_of_graded_masses_hold_and_defective_ones_do_not():
    """The componentwise backward error of the modes does not see how unevenly rows are
    scaled: a column whose masses alternate 1 and 1e-4 (or grow by 1e6) keeps its modal
    coordinates; cauchy2d at |delta| = lam + mu (defective) does not."""
    from fem_dual.modes import HOLD_BACKWARD, modes_hold
    from fem_dual.slab.modal import modal_obstacle

    for masses in (["1", "1e-4"] * 25, [f"{10 ** (6 * i / 49):g}" for i in range(50)]):
        scene = RunConfig.create("column", {"links": "50", "P": "0", "m": ",".join(masses)},
                                 T=1.0).scene
        hold, error = modes_hold(scene.mass_matrix(), scene.stiffness_matrix())
        assert hold and error < 1e-3 * HOLD_BACKWARD
        assert modal_obstacle(scene) is None
    scene = RunConfig.create("cauchy2d", {"elements": "4", "delta": "-3", "lam": "2"},
                             T=1.0).scene
    hold, error = modes_hold(scene.mass_matrix(), scene.stiffness_matrix())
    assert not hold and error > 0.1
    assert "do not hold" in modal_obstacle(scene)
