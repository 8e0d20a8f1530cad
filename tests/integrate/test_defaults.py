"""The defaults follow the problem: base state, cells and degree, each stated in the JSON."""
import pytest

from fem_dual import RunConfig, run
from fem_dual.config import adaptive_degree


@pytest.mark.parametrize("rtol, degree", [(1e-4, 3), (1e-6, 4), (1e-8, 5), (1e-10, 6),
                                          (1e-2, 2), (1e-12, 6)])
def test_the_degree_grows_with_the_digits_asked(rtol, degree):
    assert adaptive_degree(rtol) == degree
    config = RunConfig.create("curl3d", rtol=rtol)
    assert (config.cells, config.degree) == (4, degree)


def test_fixed_slabs_keep_100_cells_of_degree_2():
    config = RunConfig.create("curl3d")
    assert (config.cells, config.degree) == (100, 2)
    assert RunConfig.create("curl3d", rtol=1e-6, cells=8, degree=3).degree == 3


@pytest.mark.parametrize("scene, kw, base", [
    ("curl3d", {"rtol": 1e-6}, "rk4"),
    ("curl3d", {}, "start"),
    ("ziegler", {}, "start"),
    ("column", {"params": {"links": "40", "P": "4"}, "rtol": 1e-6}, "zero"),
    ("curl3d", {"base": "predictor", "rtol": 1e-6}, "predictor"),
])
def test_the_base_and_why(scene, kw, base):
    config = RunConfig.create(scene, kw.pop("params", None), **kw)
    chosen, reason = config.base_choice
    assert chosen == base == config.base_state
    assert reason.startswith("auto:") != ("base" in kw)


def test_the_json_states_the_base_and_why():
    r = run(RunConfig.create("curl3d", T=2, rtol=1e-6))
    assert r.solver["base"] == "rk4" and "not stiff" in r.solver["base_reason"]
    assert r.error["x_max"] <= r.error_estimate <= 1e-6 * r.tolerance["scale_x"] * 10
