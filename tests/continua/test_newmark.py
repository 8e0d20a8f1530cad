"""benchmarks/newmark.py: Newmark's average acceleration and generalized-alpha on a 2-dof
system against the matrix exponential."""
import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sps

_path = Path(__file__).resolve().parents[2] / "benchmarks" / "newmark.py"
_spec = importlib.util.spec_from_file_location("newmark_benchmark", _path)
nm = importlib.util.module_from_spec(_spec)
sys.modules[_spec.name] = nm  # (dataclasses look their module up there)
_spec.loader.exec_module(nm)

# two coupled modes (omega about 1 and 3.2), light damping, a non-symmetric (follower-like) term
M = sps.csr_matrix([[2.0, 0.3], [0.3, 1.0]])
K = sps.csr_matrix([[3.0, -1.0], [-0.4, 10.0]])
D = sps.csr_matrix([[0.05, 0.0], [0.0, 0.02]])
U0, V0 = np.array([1.0, -0.5]), np.array([0.0, 0.7])
TIMES = [0.5, 1.0, 2.0]

SCHEMES = [nm.newmark_average(), nm.generalized_alpha(1.0), nm.generalized_alpha(0.8),
           nm.generalized_alpha(0.0)]


def errors(scheme, steps_list):
    reference, _ = nm.expm_reference(M, D, K, U0, V0, TIMES)
    out = []
    for steps in steps_list:
        u, _ = nm.integrate(M, D, K, U0, V0, TIMES, steps, scheme)
        out.append(np.abs(u - reference).max())
    return np.array(out)


@pytest.mark.serial
@pytest.mark.parametrize("scheme", SCHEMES, ids=lambda s: s.name)
def test_second_order_against_expm(scheme):
    e = errors(scheme, [160, 320, 640, 1280])  # (rho_inf = 0 is pre-asymptotic below: 1.63)
    rates = np.log2(e[:-1] / e[1:])
    assert np.all(rates > 1.9) and np.all(rates < 2.1), rates


@pytest.mark.serial
def test_average_acceleration_conserves_energy_of_a_symmetric_undamped_system():
    Ks = sps.csr_matrix([[3.0, -1.0], [-1.0, 10.0]])
    times = np.linspace(0.0, 50.0, 11)
    u, v = nm.integrate(M, None, Ks, U0, V0, times, 500, nm.newmark_average())
    energy = [0.5 * (vi @ (M @ vi) + ui @ (Ks @ ui)) for ui, vi in zip(u, v)]
    assert np.ptp(energy) < 1e-12 * energy[0]


@pytest.mark.serial
@pytest.mark.parametrize("rho_inf", [0.0, 0.5, 0.8])
def test_generalized_alpha_damps_unresolved_modes_by_rho_inf(rho_inf):
    """A single oscillator with omega h = 1e4: the step's amplification has the double
    eigenvalue -rho_inf (a Jordan block), so the amplitude goes like n rho_inf^n and shrinks
    per step by rho_inf n / (n - 1)."""
    m, k = sps.csr_matrix([[1.0]]), sps.csr_matrix([[1e8]])
    steps = 40
    times = np.arange(steps + 1)
    u, v = nm.integrate(m, None, k, [1.0], [0.0], times, steps, nm.generalized_alpha(rho_inf))
    z = np.hypot(u[:, 0] * 1e4, v[:, 0])
    if rho_inf == 0.0:
        assert z[-1] < 1e-12 * z[0]
    else:
        assert z[-1] / z[-2] == pytest.approx(rho_inf * steps / (steps - 1), rel=1e-3)


@pytest.mark.serial
def test_converge_halves_until_the_target_and_reports_rows():
    reference, _ = nm.expm_reference(M, D, K, U0, V0, TIMES)
    rows, met = nm.converge(M, D, K, U0, V0, TIMES, reference, 1e-6, nm.newmark_average(),
                            steps=8)
    assert met and rows[-1].error <= 1e-6 < rows[-2].error
    assert [r.steps for r in rows] == [8 * 2**k for k in range(len(rows))]
    assert all(r.wall > 0 for r in rows)


@pytest.mark.serial
def test_requested_times_must_lie_on_the_step_grid():
    with pytest.raises(ValueError, match="multiple"):
        nm.integrate(M, D, K, U0, V0, [0.3, 1.0], 4, nm.newmark_average())


@pytest.mark.serial
def test_runs_on_an_exported_continuum(tmp_path, capsys):
    """The command line on a SpatialSystem export (a coarse Beck column, full (w, theta) with
    rotary inertia so that M is invertible)."""
    from fem_dual.continua.beck import BeckColumn, BeckParameters
    column = BeckColumn(BeckParameters(elements=4, rhoI=0.01, kGA=100.0, P=5.0))
    q = column.system.interpolate(["x**2", "0"])
    column.system.export_npz(tmp_path / "beck.npz", q, column.system.zeros())
    assert nm.main([str(tmp_path / "beck.npz"), "--T", "0.5", "--target", "1e-4",
                    "--scheme", "alpha"]) == 0
    assert "target met" in capsys.readouterr().out
