"""Start states and motions at the ends of the float range: a run either vouches for its answer
or says why not, and its JSON stays JSON.

- An exponentially growing motion whose reference overflows before the answer does: the error
  is compared while the reference is finite, and the JSON says where it stopped (a NaN there
  would make the JSON encoder raise: a traceback after a successful solve).
- A growing mode absent from the start state adds 0 to the reference, not inf * 0 = NaN.
- A start state of size 1e-200: the growth bound's |z0| does not underflow to 0 (which would
  refuse every slab).
- A motion past e^700: the growth bound's exponent is not capped at 700 (which would refuse the
  run there).
- A particle at rest: its velocity's round-off is not the scale its velocity errors are weighed
  against (which would refuse every slab).
"""
import json

import numpy as np
import pytest

from fem_dual import RunConfig, run
from fem_dual.cli import main
from fem_dual.reference import linear_flow

pytestmark = pytest.mark.serial


def _unstable(x0: str, T: int, **kw):
    return RunConfig.create("linear", {"dofs": str(len(x0.split(","))), "M": "1",
                                       "K": "-1" if "," not in x0 else "-1,0,0,-4"},
                            x0=x0, v0=x0, T=T, slabs=T, degree=3, cells=4, **kw)


def test_an_absent_growing_mode_adds_zero_to_the_reference():
    flow = linear_flow(np.eye(2), np.diag([-1.0, -4.0]), None, np.array([1.0, 0.0]),
                       np.array([1.0, 0.0]))
    x, v = flow(np.array([400.0]))  # e^(2 * 400) overflows, its coefficient is 0
    assert np.isfinite(x).all() and np.isfinite(v).all()
    assert x[0, 1] == 0.0 and x[0, 0] == pytest.approx(np.exp(400.0), rel=1e-10)


def test_a_reference_that_overflows_is_compared_until_it_does(capsys):
    result = run(_unstable("1e-200", 800))
    assert result.status == "ok", result.message
    # e^t 1e-200 overflows in the reference's e^t at t ~ 709.8, the answer stays ~ 1e147
    assert 709 < result.error["reference_lost_at"] <= 711
    assert result.error["final"] is None
    assert np.isfinite(result.x).all() and abs(result.x[-1, 0]) > 1e140
    rel = result.error["x_max"] / np.abs(result.x).max()
    assert rel < 1e-6  # the error over the compared part is measured, and small
    capsys.readouterr()
    assert main(["run", "linear", "--param", "dofs=1", "--param", "M=1", "--param", "K=-1",
                 "--x0", "1e-200", "--v0", "1e-200", "--T", "800", "--slabs", "800",
                 "--degree", "3", "--cells", "4", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["error"]["reference_lost_at"] == result.error["reference_lost_at"]
    assert main(["run", "linear", "--param", "dofs=1", "--param", "M=1", "--param", "K=-1",
                 "--x0", "1e-200", "--v0", "1e-200", "--T", "800", "--slabs", "800",
                 "--degree", "3", "--cells", "4"]) == 0
    assert "where the reference overflowed" in capsys.readouterr().out


def test_a_growing_motion_with_an_absent_mode_writes_json(capsys):
    """Reference x = inf * 0 in its second dof, a NaN that would crash the JSON encoder."""
    capsys.readouterr()
    assert main(["run", "linear", "--param", "dofs=2", "--param", "M=1", "--param",
                 "K=-1,0,0,-4", "--slabs", "357", "--T", "357", "--degree", "3", "--cells", "4",
                 "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["status"] == "ok"
    assert out["error"]["final"] / abs(out["final"]["x"][0]) < 1e-6


@pytest.mark.parametrize("size", ["1e-200", "1e+100"])
def test_the_growth_bound_scales_with_the_start_state(size):
    result = run(_unstable(size, 100))  # 1e-200 e^100: its square underflows no more
    assert result.status == "ok", result.message
    x_exact = float(size) * np.exp(100.0)
    assert abs(result.x[-1, 0] - x_exact) < 1e-6 * x_exact


def test_a_particle_at_rest_stays_at_rest():
    for kw in ({"slabs": 5}, {"rtol": 1e-8}):
        result = run(RunConfig.create("linear", {"dofs": "2", "M": "1", "K": "0"}, T=3,
                                      cells=8, degree=2, **kw))
        assert result.status == "ok", result.message
        np.testing.assert_allclose(result.x[-1], [0.1, 0.0], atol=1e-15)
        assert np.abs(result.v).max() < 1e-15
        assert result.estimate["x_max"] < 1e-10


def test_a_motion_that_overflows_h_d_says_so():
    """Flutter grows until H_d, quadratic in the state, overflows at |z| ~ 1e154: the run keeps
    what it computed and says why it stopped, not "try more slabs" (a growth bound whose 2-norm
    overflowed first would refuse the motion as noise)."""
    with pytest.raises(Exception) as info:
        run(RunConfig.create("ziegler", {"P": "3"}, T=1000, slabs=1000, cells=4, degree=3))
    message = str(info.value)
    assert "overflows float64" in message and "more slabs" not in message, message
    kept = info.value.partial
    assert np.isfinite(kept.x).all() and np.abs(kept.x).max() > 1e150
