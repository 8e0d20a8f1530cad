"""The first-order spectrum of a linear scene: from the n x n pencil where the scene is undamped
(lambda = +-sqrt(-mu), vectors (w, lambda w)), from the 2n x 2n first-order matrix otherwise;
both give the same eigenvalues, vectors and modal coefficients."""
import numpy as np
import pytest

from fem_dual.scenes.linear import GeneralLinear


def _scene(M, K, D=None):
    rows = lambda A: tuple(map(tuple, A))  # noqa: E731
    return GeneralLinear(dofs=len(M), M=rows(M), K=rows(K),
                         D=None if D is None else rows(D))


def _generic(scene):
    """The same scene with the pencil path switched off."""
    twin = _scene(scene.mass_matrix(), scene.stiffness_matrix(), scene.damping_matrix())
    twin.__dict__["_pencil_modes"] = None
    return twin


def _systems():
    rng = np.random.default_rng(7)
    n = 12
    G = rng.standard_normal((n, n))
    M = G @ G.T / n + np.eye(n)
    S = rng.standard_normal((n, n))
    K = S @ S.T + n * np.eye(n)
    curl = rng.standard_normal((n, n))
    return {"symmetric": (M, K), "curl": (M, K + 0.5 * (curl - curl.T)),
            "flutter": (M, K + 8.0 * (curl - curl.T)),
            "stiff": (M, np.diag(np.logspace(0, 10, n)) + 0.1 * (curl - curl.T))}


@pytest.mark.parametrize("name", ["symmetric", "curl", "flutter", "stiff"])
def test_the_pencil_gives_the_first_order_spectrum(name):
    M, K = _systems()[name]
    scene = _scene(M, K)
    generic = _generic(scene)
    assert scene._pencil_modes is not None
    lam, V = scene.spectrum
    lam_g = generic.spectrum[0]
    A = scene.first_order_matrix()
    # eigenpairs of the first-order matrix, in its norm
    residual = np.linalg.norm(A @ V - V * lam, axis=0) / np.linalg.norm(A, 2)
    assert residual.max() < 1e-9
    assert np.allclose(np.linalg.norm(V, axis=0), 1.0)
    distance = np.abs(lam[:, None] - lam_g[None, :])  # the same set of 2n eigenvalues
    scale = np.abs(lam_g).max()
    assert distance.min(axis=1).max() < 1e-9 * scale and distance.min(axis=0).max() < 1e-9 * scale
    x0, v0 = np.linspace(-1, 1, len(M)), np.cos(np.arange(len(M)))
    c = scene.modal_coefficients(x0, v0)
    assert np.allclose(V @ c, np.concatenate([x0, v0]), atol=1e-10)
    for rel, scales in ((1e-6, None), (5e-3, (1.0, 1.0)), (5e-7, (1.0, 1.0))):
        assert scene.fastest_rate(x0, v0, rel, scales) == pytest.approx(
            generic.fastest_rate(x0, v0, rel, scales), rel=1e-9)


def test_damped_or_rigid_scenes_keep_the_first_order_matrix():
    M, K = _systems()["curl"]
    damped = _scene(M, K, D=0.1 * np.eye(len(M)))
    assert damped._pencil_modes is None
    rigid = _scene(np.eye(2), np.array([[1.0, -1.0], [-1.0, 1.0]]))  # a free pair: mu = 0
    assert rigid._pencil_modes is None
    lam, V = rigid.spectrum
    assert np.abs(lam).min() < 1e-7 and len(lam) == 4


def _exact(M, K, x0, v0, t, digits=40):
    """z(t) of M x'' + K x = 0 from a `digits`-digit eigen-decomposition (mpmath)."""
    import mpmath as mp

    with mp.workdps(digits):
        n = len(M)
        MK = mp.inverse(mp.matrix(M.tolist())) * mp.matrix(K.tolist())
        A = mp.zeros(2 * n, 2 * n)
        for i in range(n):
            A[i, n + i] = 1
            for j in range(n):
                A[n + i, j] = -MK[i, j]
        lam, V = mp.eig(A)
        c = mp.lu_solve(V, mp.matrix(np.concatenate([x0, v0]).tolist()))
        return np.array([[float(mp.re(sum(V[i, k] * mp.exp(lam[k] * s) * c[k]
                                             for k in range(2 * n)))) for i in range(2 * n)]
                         for s in t])


@pytest.mark.parametrize("name", ["symmetric", "curl", "stiff"])
def test_the_undamped_reference_from_the_pencil_is_exact_to_round_off(name):
    """fem_dual.reference.EigenFlow.undamped (QZ on (K, M)) against a 40-digit solution; on the
    stiff system (frequencies 1 to 1e5) QZ on the 2n x 2n first-order pencil is 1.6e-5 off
    (relative) at t = 1.7, the n x n pencil 3e-11."""
    from fem_dual.reference import EigenFlow, first_order_pencil

    M, K = _systems()[name]
    n = len(M)
    x0, v0 = np.linspace(-1, 1, n), np.cos(np.arange(n))
    fast = EigenFlow.undamped(M, K, x0, v0)
    full = EigenFlow.of_pencil(first_order_pencil(M, K), x0, v0)
    t = np.array([1.7])
    # (the 2n x 2n one is the reference where it is exact to round-off: not on the stiff one)
    exact = _exact(M, K, x0, v0, t, digits=30) if name == "stiff" else np.hstack(full(t))
    scale = np.abs(exact).max()
    assert np.abs(np.hstack(fast(t)) - exact).max() <= 1e-10 * scale
    assert np.allclose(np.linalg.norm(fast.V, axis=0), 1.0)
    assert fast.condition == pytest.approx(full.condition, rel=1e-3)
    assert EigenFlow.undamped(np.eye(2), np.array([[1.0, -1.0], [-1.0, 1.0]]),
                              np.ones(2), np.zeros(2)) is None  # a rigid motion
