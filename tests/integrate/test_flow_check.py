"""A nonlinear slab's answer against classical Runge-Kutta from the same start
(fem_dual.integrate.flow_check): an answer on the motion passes, one that leaves it by more than
its estimate says is named, and a motion RK4 cannot follow tells nothing."""
import numpy as np
import pytest
from scipy.integrate import solve_ivp

from fem_dual import RunConfig
from fem_dual.integrate.estimate import SlabEstimate
from fem_dual.integrate.flow_check import FLOW_FACTOR, FlowCheck
from fem_dual.slab.values import VertexValues

CELLS = 4


def _slab(scene, z0, dt, local):
    """The exact motion's vertex values over a slab of CELLS cells (DOP853 at 1e-13) and an
    estimate whose companion differs from it by `local` everywhere."""
    n = scene.n
    s = np.linspace(0.0, 1.0, CELLS + 1)
    exact = solve_ivp(lambda t, z: np.concatenate([z[n:], scene.force_numpy(z[:n]) / scene.m]),
                      (0.0, dt), z0, method="DOP853", rtol=1e-13, atol=1e-14, t_eval=s * dt).y.T
    vals = VertexValues(s, exact[:, :n].copy(), exact[:, n:].copy(), np.zeros(CELLS + 1))
    estimate = SlabEstimate(0.0, dt, np.full((CELLS + 1, 2 * n), local), np.zeros((1, 2 * n)),
                            0.0, 0.0)
    return vals, estimate


def test_the_motion_passes_and_a_jump_is_named():
    scene = RunConfig.create("curl3d").scene
    check = FlowCheck.of(scene, CELLS)
    z0 = np.array([0.3, 0.2, 0.1, 0.0, 0.0, 0.0])
    vals, estimate = _slab(scene, z0, 0.5, 1e-9)
    assert check.excess(z0, 0.5, vals, estimate) is None
    # a velocity jump in the third cell, 100 times the estimate: named at the vertex after it
    vals.v[3:, 1] += 100 * 1e-9
    why = check.excess(z0, 0.5, vals, estimate)
    assert why is not None and "vertex 3" in why and "1e-07" in why, why
    # within FLOW_FACTOR of the estimate it stands
    vals.v[3:, 1] -= 100 * 1e-9 - 0.5 * FLOW_FACTOR * 1e-9
    assert check.excess(z0, 0.5, vals, estimate) is None


def test_a_motion_rk4_cannot_follow_tells_nothing():
    """RK4 overflows (a motion far faster than the cells): no verdict either way."""
    scene = RunConfig.create("curl3d").scene
    check = FlowCheck.of(scene, CELLS)
    z0 = np.array([1e150, 1e150, 1e150, 0.0, 0.0, 0.0])
    vals = VertexValues(np.linspace(0, 1, CELLS + 1), np.zeros((CELLS + 1, 3)),
                        np.zeros((CELLS + 1, 3)), np.zeros(CELLS + 1))
    estimate = SlabEstimate(0.0, 1.0, np.zeros((CELLS + 1, 6)), np.zeros((1, 6)), 0.0, 0.0)
    assert check.excess(z0, 1.0, vals, estimate) is None


@pytest.mark.mpi
def test_a_check_that_fails_ends_the_run_with_its_reason(monkeypatch):
    """A failure inside the check (on rank 0) ends the run on every rank with its reason,
    keeping the slabs before it, instead of leaving the other ranks waiting."""
    from fem_dual import run
    from fem_dual.errors import SolveError

    def broken(self, *args):
        raise RuntimeError("the check broke")

    monkeypatch.setattr(FlowCheck, "excess", broken)
    with pytest.raises(SolveError, match="the check broke") as info:
        run(RunConfig.create("curl3d", T=1.0, slabs=2, cells=4, degree=3))
    assert info.value.partial is not None and info.value.partial.t.size == 0
