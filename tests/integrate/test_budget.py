"""--rtol on a motion far faster than its horizon: the cost is predicted from the first slabs and
a run beyond --max-slabs stops at once with the figure (exit 3), keeping what it computed."""
import json

import numpy as np
import pytest

from fem_dual import RunConfig, SolveError, run
from fem_dual.cli import main
from fem_dual.integrate.budget import BUDGET_WATCH

FAST = ["run", "force", "--F", "-100000000.0*x", "--x0", "1", "--T", "2", "--rtol", "1e-6"]


def _predicted_slabs(message: str) -> int:
    figure = message.split("would take ")[1].split(" slabs at the length")[0]
    return int(figure.replace(",", ""))


def test_a_run_beyond_the_budget_stops_with_the_figure(capsys):
    """omega = 1e4 over T = 2 (3,183 periods) takes about 5,000-8,000 slabs at 1e-6; the
    prediction stops the run within its first slabs."""
    assert main(FAST + ["--json"]) == 3
    captured = capsys.readouterr()
    assert captured.err.count("\n") == 1
    assert _predicted_slabs(captured.err) in range(4_000, 12_001) and "--max-slabs" in captured.err
    assert "loosen --rtol" in captured.err and "modes up to" not in captured.err  # (one mode)
    data = json.loads(captured.out)
    assert data["status"] == "failed"
    assert BUDGET_WATCH <= len(data["slab_lengths"]) <= 2 * BUDGET_WATCH
    assert np.isfinite(data["x"]).all()


def test_particles_keep_the_advice_of_the_horizon(capsys):
    """A free body's zero mode and a stiff spring on purpose: a particle scene has no mesh to
    coarsen, and a shorter --T is what helps (T = 100 needs about 8,200 slabs at 1e-10). The
    budget is given, in slabs: a linear scene's chunked slabs are otherwise held to time."""
    free = ["run", "linear", "--param", "dofs=2", "--param", "K=1,-1,-1,1", "--x0", "1, 0",
            "--v0", "0, 0", "--T", "30000", "--rtol", "1e-10", "--max-slabs", "5000"]
    stiff = ["run", "linear", "--param", "dofs=2", "--param", "K=1,0,0,1e6", "--x0", "1, 1e-3",
             "--v0", "0, 0", "--T", "100", "--rtol", "1e-10", "--max-slabs", "5000"]
    for args in (free, stiff):
        assert main(args) == 3
        err = capsys.readouterr().err
        assert "shorten --T" in err and "mesh" not in err, err


def test_the_budget_is_the_users_to_raise():
    """(curl3d at 1e-10 on degree 2 takes 30 slabs.)"""
    with pytest.raises(SolveError, match="beyond the budget of 10 "):
        run(RunConfig.create("curl3d", T=8, rtol=1e-10, cells=4, degree=2, max_slabs=10))
    r = run(RunConfig.create("curl3d", T=8, rtol=1e-10, cells=4, degree=2, max_slabs=100))
    assert r.status == "ok" and 10 < len(r.slab_lengths) <= 100


def test_fixed_slabs_have_no_budget():
    r = run(RunConfig.create("curl3d", T=1, slabs=20, cells=4, degree=3, max_slabs=1))
    assert r.status == "ok" and len(r.slab_lengths) == 20


@pytest.mark.parametrize("value", ["0", "1.5", "x", "-3"])
def test_bad_budget_is_refused(value, capsys):
    assert main(FAST + ["--max-slabs", value]) == 2
    assert f"max-slabs='{value}'" in capsys.readouterr().err


def test_a_linear_solve_that_fails_at_every_length_stops_after_a_few_halvings():
    """A solve that fails on conditioning fails on shorter slabs too: the run stops after
    LINEAR_SOLVE_RETRIES of them in a row (a follower load of 1e9 on a beam was halved 23
    times, minutes of CG at its iteration limit each)."""
    from fem_dual.integrate.loop import LINEAR_SOLVE_RETRIES

    config = RunConfig.create("ziegler", assembly="kronecker", rtol=1e-6,
                              petsc={"ksp_max_it": "2"})
    with pytest.raises(SolveError, match=f"failed alike on {LINEAR_SOLVE_RETRIES} slabs") as info:
        run(config)
    assert len(info.value.partial.solver["halved_slabs"]) == LINEAR_SOLVE_RETRIES - 1


def test_a_run_stopped_by_its_budget_resumes_with_a_larger_one(tmp_path, capsys):
    out = str(tmp_path / "out")
    base = ["run", "ziegler", "--T", "1000", "--rtol", "1e-8", "--out", out, "--json"]
    assert main(base + ["--max-slabs", "100"]) == 3
    stopped = json.loads(capsys.readouterr().out)
    assert main(base + ["--resume"]) == 0
    resumed = json.loads(capsys.readouterr().out)
    whole = run(RunConfig.create("ziegler", T=1000, rtol=1e-8))
    assert len(stopped["slab_lengths"]) < len(resumed["slab_lengths"]) == len(whole.slab_lengths)
    assert np.allclose(resumed["final"]["x"], whole.x[-1], rtol=0, atol=1e-12)


def test_chunked_linear_slabs_are_held_to_time_not_to_a_count(capsys, monkeypatch):
    """Beck's column at 50 P2 elements, --rtol 1e-4: predicted at 32,768 slabs from its first
    ones, it takes about 8,000 in chunks of slab maps at well under a millisecond each. Left
    at its default the budget is time (and memory) at the measured pace, and the run ends ok
    within its estimate; --max-slabs given keeps the count. (The time allowed is made
    unlimited here: 15 s predicted against 60 s on this machine, a slower one must not fail
    the test; the memory, 0.5 GB predicted against 1 GB, is the machine's no matter.)"""
    monkeypatch.setattr("fem_dual.integrate.budget.BUDGET_SECONDS", 1e9)
    assert main(["run", "beck", "--rtol", "1e-4", "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    budget, tol = data["solver"]["budget"], data["tolerance"]
    assert budget["paced"] and budget["max_slabs"] == 5000 and 0 < budget["pace_s"] < 0.01
    assert len(data["slab_lengths"]) > 5000 and data["solver"]["batched_slabs"] > 5000
    actual = max(data["error"]["x_max"], data["error"]["v_max"])
    assert actual <= data["error_estimate"] <= 10 * 1e-4 * max(tol["scale_x"], tol["scale_v"])
    assert main(["run", "beck", "--rtol", "1e-4", "--max-slabs", "5000"]) == 3
    err = capsys.readouterr().err
    assert "beyond the budget of 5,000 (--max-slabs);" in err and "ms a slab" not in err


def test_chunked_slabs_beyond_their_time_stop_with_the_pace(capsys):
    """--rtol 3e-6 on the same column: predicted at 262,144 slabs at about a millisecond (281 s
    measured), refused once a chunk of 64 slabs has shown its pace, with the time and the
    memory it would take. (At 1e-6 the first chunk comes after 357 slabs or, with
    other BLAS threads, not within PACE_WAIT: the count refuses then.)"""
    assert main(["run", "beck", "--rtol", "3e-6", "--json"]) == 3
    captured = capsys.readouterr()
    assert captured.err.count("\n") == 1
    assert "ms a slab" in captured.err and "beyond 60 s or 1024 MB" in captured.err
    assert _predicted_slabs(captured.err) > 100_000
    data = json.loads(captured.out)
    assert data["status"] == "failed" and len(data["slab_lengths"]) < 5000
    assert data["solver"]["budget"]["pace_s"] > 0
