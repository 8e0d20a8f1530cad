"""The stress suite: every case behaves as it must; the judge itself can fail."""
import json

import pytest

from fem_dual import RunConfig
from fem_dual.cli import main
from fem_dual.analysis.stress import CASES, Case, run_case


@pytest.mark.mpi
@pytest.mark.parametrize("case", [pytest.param(c, id=c.name,
                                               marks=[pytest.mark.slow] if c.slow else [])
                                  for c in CASES])
def test_case_behaves_as_it_must(case):
    row = run_case(case)
    assert row.status != "FAIL", row
    if case.expect == "converge":
        assert row.status == "ok" and row.rel_error <= case.tol
    if case.expect == "stop":
        assert row.status == "stopped" and "use " in row.measured


def _tiny(T=2.0):
    return RunConfig.create("ziegler", T=T, cells=4, degree=2)


def test_a_wrong_answer_reported_as_ok_fails_the_case():
    coarse = Case("coarse", "impossible tolerance", lambda: _tiny(), tol=1e-14)
    assert run_case(coarse).status == "FAIL"


def test_a_case_that_should_stop_but_converges_fails():
    assert run_case(Case("x", "must stop", lambda: _tiny(), expect="stop", tol=1.0)).status \
        == "FAIL"


def test_a_stop_without_advice_is_not_enough_when_convergence_is_required():
    row = run_case(Case("y", "must converge", lambda: _tiny(T=1e6), expect="converge"))
    assert row.status == "FAIL" and "under-resolved" in row.measured


def test_stress_command_json_and_exit_status(capsys):
    assert main(["stress", "--case", "divergence", "--case", "huge-T-one-slab", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["passed"] and [r["status"] for r in out["rows"]] == ["ok", "stopped"]
    assert out["rows"][0]["condition"] > 1 and out["rows"][0]["details"]["growth_eigen"] > 1


def test_unknown_stress_case_is_bad_input(capsys):
    assert main(["stress", "--case", "no-such-case"]) == 2
    assert "no-such-case" in capsys.readouterr().err
