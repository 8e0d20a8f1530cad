"""The eigenvalue flutter search (fem_dual.continua.flutter.flutter_load) on spectra whose
critical load is known exactly: the bracket holds it, is no wider than asked, and costs a
handful of eigen-solves where bisection would take about 25."""
import numpy as np
import pytest

from fem_dual.continua.flutter import flutter_load

P_CR = np.pi


def _coalescing(curvature: float):
    """Two modes meeting at P_CR (a square-root branch point, as at a flutter load), with a
    discriminant that is not linear in P (curvature), and two spectators."""
    def eigenvalues(P):
        disc = (P_CR - P) * (1 + curvature * (P_CR - P))
        root = np.sqrt(complex(disc))
        return np.array([50 + 3 * root, 50 - 3 * root, 7.0 + P, 400.0])
    return eigenvalues


@pytest.mark.parametrize("curvature", [0.0, 0.3, -0.2])
def test_the_bracket_holds_the_coalescence_in_a_few_solves(curvature):
    found = flutter_load(_coalescing(curvature), step=0.5, P_max=10.0, tol=1e-9)
    lo, hi = found.bracket
    assert found.kind == "flutter"
    assert lo <= P_CR <= hi and hi - lo <= 1e-9
    assert found.omega2 == pytest.approx(50.0)
    assert found.evaluations <= 18  # the scan takes 8; bisection alone would add 29


def test_a_divergence_is_bisected():
    found = flutter_load(lambda P: np.array([2.0 - P, 5.0, 9.0]), step=0.7, P_max=10.0,
                         tol=1e-9)
    lo, hi = found.bracket
    assert found.kind == "divergence" and lo <= 2.0 <= hi and hi - lo <= 1e-9


@pytest.mark.parametrize("apart", [1e-6, 1e-12])
def test_a_near_double_spectator_does_not_slow_the_search(apart):
    """Two spectator eigenvalues almost equal (not the pair that coalesces): the discriminant
    follows the pair that meets, found at the first complex load."""
    def eigenvalues(P):
        root = np.sqrt(complex(P_CR - P))
        return np.array([50 + 3 * root, 50 - 3 * root, 7.0, 7.0 * (1 + apart), 400.0])

    found = flutter_load(eigenvalues, step=0.5, P_max=10.0, tol=1e-9)
    lo, hi = found.bracket
    assert lo <= P_CR <= hi and hi - lo <= 1e-9 and found.evaluations <= 18
