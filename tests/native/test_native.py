"""The compiled loops (fem_dual.native) compute what their numpy twins compute, on the scene's UFL
force compiled by FFCx; their C sources build warnings-clean; where the library cannot be built
or loaded, the numpy loops run instead, with the same answers."""
import ctypes.util
import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from fem_dual import RunConfig, native, run
from fem_dual.native import build
from fem_dual.scenes import get_scene
from fem_dual.scenes.curl import Curl3D
from fem_dual.slab.base_state import FlowPredictor

compiled = pytest.mark.skipif(native.library() is None,
                              reason=f"no compiled loops here: {native.reason()}")


def _has_compiler() -> bool:
    try:
        build.compiler()
        return True
    except OSError:
        return False


needs_compiler = pytest.mark.skipif(not _has_compiler(), reason="no C compiler (cc, gcc) here")


@dataclasses.dataclass(frozen=True)
class _UnequalMasses(Curl3D):
    """curl3d with M = diag(1, 2, 3): the loop's M^-1 F branch (the scenes have M = m I)."""

    def mass_matrix(self):
        return np.diag([1.0, 2.0, 3.0])


def _scene(name, **params):
    return RunConfig.create(name, {k: str(v) for k, v in params.items()}, x0="1" if name ==
                            "force" else None).scene


def _simulation(scene, params=None, **options):
    """A simulation of `scene` with its first run done (its slab assembly built)."""
    from fem_dual.integrate.simulation import Simulation

    config = RunConfig.create(scene, params, staging="off", reference="none", **options)
    sim = Simulation.for_config(config)
    sim.run(config)
    return sim


# -- the twins: each compiled loop against its numpy code ---------------------------------------

def _rk4(scene, z0, steps=24, end=2.0):
    """The rk4 base's steps and their Hermite read: compiled, then in numpy."""
    t = np.linspace(0.0, end, 13)
    predictor = FlowPredictor(scene, steps)
    assert predictor.compiled
    ours = predictor(np.array(z0), t, end)
    theirs = FlowPredictor(scene, steps, compiled=False)(np.array(z0), t, end)
    assert np.abs(ours - theirs).max() <= 1e-13 * np.abs(theirs).max()


def _hermite(scene, z0, steps=24, end=2.0):
    """The compiled Hermite read of one compiled run against numpy's sums of the same steps."""
    t = np.linspace(0.0, end, 13)
    predictor = FlowPredictor(scene, steps)
    ours = predictor(np.array(z0), t, end)
    _, _, states, rates = predictor._last
    rows, weights, _ = predictor._weights[(t / end).tobytes()]
    theirs = np.einsum("mj,mjc->mc", weights,
                       np.concatenate([states, (end / steps) * rates])[rows])
    assert np.abs(ours - theirs).max() <= 1e-14 * np.abs(theirs).max()


def _band(scene, degree, cells):
    """The Jacobian's band at a random dual state."""
    sim = _simulation(scene, T=1, cells=cells, degree=degree)
    try:
        local = sim.backend.solver.local
        assert local._native_band is not None
        local.set_state(np.random.default_rng(3).uniform(-0.05, 0.05, local.size))
        _, ours = local.residual_and_jacobian()
        local._native_band = None
        _, theirs = local.residual_and_jacobian()
    finally:
        sim.close()
    assert np.abs(ours - theirs).max() <= 1e-14 * np.abs(theirs).max()


def _pack(scene, params):
    """The gather of a slab's coefficients into its density kernel's rows, at a random dual
    state (every coefficient of the expression: the state, the base, an implicit DtP map's)."""
    from fem_dual.native.force import PackedExpression

    sim = _simulation(scene, params, T=1, cells=3, degree=3,
                      x0="0.5" if scene == "force" else None)
    try:
        local = sim.backend.solver.local
        local.set_state(np.random.default_rng(4).uniform(-0.05, 0.05, local.size))
        expr = PackedExpression(local._both.compiled, local.cells)
        assert expr._compiled is not None
        ours = expr.pack().copy()
        expr._compiled = None
        theirs = expr.pack()
    finally:
        sim.close()
    assert len(expr.coefficients) >= 1 and np.array_equal(ours, theirs)


def _dtp_pair(scene, params, scale, seed=5):
    """The implicit DtP map solved at a random dual state by the compiled loop and by numpy:
    (X, iterations, message) of each."""
    from mpi4py import MPI

    sim = _simulation(scene, params, T=1, cells=3, degree=3,
                      x0="0.5" if scene == "force" else None)
    try:
        problem = sim.backend.problem
        dtp = problem.pointwise
        dual = np.random.default_rng(seed).uniform(-scale, scale, problem.w.x.array.size)
        answers = []
        for compiled_loop in (True, False):
            problem.w.x.array[:] = dual
            dtp.reset(problem.x0.value)
            if not compiled_loop:
                dtp._packed = False
            message = dtp.solve(MPI.COMM_SELF)
            answers.append((dtp.X.x.array.copy(), dtp.iterations, message))
        return answers
    finally:
        sim.close()


def _dtp_newton(scene, params, scale=0.05):
    """The implicit DtP map's pointwise Newton: the same root and iterations, or, far off the
    base state's branch (scale 50), the same refusal naming the same time."""
    (X, its, message), (X_numpy, its_numpy, message_numpy) = _dtp_pair(scene, params, scale)
    assert its == its_numpy
    if scale >= 1.0:
        assert message is not None and message == message_numpy
        return
    assert message is None and message_numpy is None and its >= 1
    assert np.abs(X - X_numpy).max() <= 1e-13 * np.abs(X_numpy).max()


def _slab_newton_run(scene, params, base, dt, x0, v0, compiled=True, bail=False, warm=None):
    """One slab solved by PointwiseNewtonSolver from the zero dual state (or from `warm`, a
    dual state's free unknowns, with its residual norm as the start's): (x, history, floor,
    error message, whether the compiled Newton answered)."""
    from mpi4py import MPI

    from fem_dual.errors import SolveError
    from fem_dual.integrate.simulation import Simulation

    config = RunConfig.create(scene, params, T=dt, cells=2, degree=3, base=base,
                              staging="off", reference="none", x0=x0, v0=v0)
    sim = Simulation.for_config(config, MPI.COMM_SELF)
    try:
        sim.begin(config)
        solver, local = sim.backend.solver, sim.backend.solver.local
        assert local.compiled_newton
        answered = []
        run_compiled = local._native_newton.run

        def watched(x, **tests):
            if bail:  # no step lowers the residual enough: the numpy iteration decides
                tests["decrease"] = 2.0
            result = run_compiled(x, **tests)
            answered.append(result is not None)
            return result
        local._native_newton.run = watched
        if not compiled:
            local._native_newton = None
        sim.backend.problem.set_slab(config.x0, config.v0, dt, 0.0)
        start = None
        if warm is not None:
            local.set_state(warm[0])
            start = warm[1]
        try:
            solver.solve(warm=start)
        except SolveError as exc:
            return None, None, None, str(exc), answered
        if sim.backend.problem.pointwise is not None:  # the implicit DtP map's root and G_x^-1 too
            dtp = sim.backend.problem.pointwise
            answered.append((dtp.X.x.array.copy(), dtp.Ginv.x.array.copy()))
        return (solver.x.copy(), solver.histories[-1], solver._floor, None, answered)
    finally:
        sim.close()


def _slab_newton(scene, params, base, dt, x0, v0):
    """A slab's compiled Newton takes the numpy iteration's steps: the same residual history,
    iterate and round-off floor (and the same root of an implicit DtP map and its G_x^-1),
    without the numpy loop."""
    x, history, floor, message, answered = _slab_newton_run(scene, params, base, dt, x0, v0)
    x_np, history_np, floor_np, message_np, answered_np = _slab_newton_run(
        scene, params, base, dt, x0, v0, compiled=False)
    assert message is None and message_np is None
    if len(answered) == 2:
        for ours, theirs in zip(answered.pop(), answered_np.pop()):
            assert np.abs(ours - theirs).max() <= 1e-12 * np.abs(theirs).max()
    assert answered == [True] and answered_np == []
    assert len(history) == len(history_np) and (len(history) >= 2 or x0 == "0,0,0")
    assert np.allclose(history, history_np, rtol=1e-9, atol=1e-15 * history_np[0])
    assert np.abs(x - x_np).max() <= 1e-12 * max(np.abs(x_np).max(), 1e-300)
    assert floor == pytest.approx(floor_np, rel=1e-9)


def _tangents(scene, params, base, cells, x0, v0):
    """The exact tangents of a solved slab and its Newton change, mapped to the vertices in
    compiled code after their banded solve (a run takes them), against the numpy products."""
    from fem_dual.integrate.simulation import Simulation

    config = RunConfig.create(scene, params, T=1.5, cells=cells, degree=4, base=base,
                              staging="off", reference="none", x0=x0, v0=v0)
    sim = Simulation.for_config(config)
    try:
        local = sim.backend.solver.local
        assert local._native_tangents is not None
        calls = []
        compiled_tangents = local._compiled_tangents
        local._compiled_tangents = lambda *a: calls.append(1) or compiled_tangents(*a)
        sim.run(config)
        assert calls
        ours = local.tangent_matrix(), local.newton_change()
        local._native_tangents, local._tangent_at = None, None
        theirs = local.tangent_matrix(), local.newton_change()
        for a, b in zip(ours, theirs):
            assert np.abs(a - b).max() <= 1e-12 * max(np.abs(b).max(), 1e-300)
    finally:
        sim.close()


def _band_storage(A: np.ndarray, kd: int) -> np.ndarray:
    """A (symmetric, half-bandwidth kd) in dgbtrf's storage: band[2 kd + i - j, j]."""
    N = len(A)
    band = np.zeros((3 * kd + 1, N))
    for i in range(N):
        for j in range(max(0, i - kd), min(N, i + kd + 1)):
            band[2 * kd + i - j, j] = A[i, j]
    return band


def _band_cholesky(N, kd):
    """The compiled banded Cholesky leaves LAPACK's dpbtrf factor (to round-off), its solves
    equal a dense solve for one and many right-hand sides, and a matrix that is not positive
    definite falls back to LU with pivoting."""
    from scipy.linalg import lapack

    from fem_dual.slab.banded import BandedLU

    rng = np.random.default_rng(N)
    A = np.zeros((N, N))
    for i in range(N):
        for j in range(max(0, i - kd), i + 1):
            A[i, j] = A[j, i] = rng.uniform(-1.0, 1.0)
    A += 2.0 * (kd + 1) * np.eye(N)
    band = _band_storage(A, kd)
    lu = BandedLU(band.copy(), kd)
    expected, info = lapack.dpbtrf(band[kd:2 * kd + 1])
    assert info == 0 and lu.cholesky is not None
    assert np.abs(lu.cholesky - expected).max() <= 1e-14 * np.abs(expected).max()
    B = rng.uniform(-1.0, 1.0, (N, 3))
    dense = np.linalg.solve(A, B)
    assert np.abs(lu.solve(B) - dense).max() <= 1e-13 * np.abs(dense).max()
    assert np.abs(lu.solve(B[:, 0]) - dense[:, 0]).max() <= 1e-13 * np.abs(dense).max()
    A[N // 2, N // 2] = -A[N // 2, N // 2]  # indefinite
    lu = BandedLU(_band_storage(A, kd), kd)
    assert lu.cholesky is None and not lu.singular
    assert np.abs(A @ lu.solve(B) - B).max() <= 1e-12 * np.abs(B).max()


def _estimate_case(rng, slabs: int, vertices: int, n: int, with_alg: bool, with_psi: bool,
                   with_lost: bool, still: bool):
    """Random answer and companion vertex values of `slabs` slabs (the companion a little off),
    with the optional terms of _estimates; `still`: v is zero (a part that has not moved)."""
    from fem_dual.slab.values import VertexValues

    def values(z):
        block = np.concatenate([np.zeros(z.shape[:2] + (1,)), z,
                                np.ones(z.shape[:2] + (1,))], axis=-1)
        return VertexValues(np.linspace(0, 1, vertices), block[..., 1:1 + n],
                            block[..., 1 + n:1 + 2 * n], block[..., -1], z=block[..., 1:-1],
                            block=block)
    z = rng.uniform(-2.0, 2.0, (slabs, vertices, 2 * n))
    if still:
        z[..., n:] = 0.0
    zc = z + rng.uniform(-1e-6, 1e-6, z.shape)
    shape = (slabs, vertices, 2 * n)
    return (values(z), values(zc), rng.uniform(-1e-9, 1e-9, shape) if with_alg else None,
            rng.uniform(-1e-7, 1e-7, shape) if with_psi else None,
            rng.uniform(-1e-8, 1e-8, (slabs, 2 * n)) if with_lost else None)


def _estimate(slabs, vertices, n):
    """The compiled estimate gives the numpy code's local and global errors, scales, floors
    and weighted errors exactly, with and without the Newton change, the propagated error and
    the damped part, from a start's scales that lead or lag, for a part that has not moved,
    with and without atol, and with the interpolation error asked for; a value that is not
    finite, or a weight that is zero, leaves the slab to the numpy code."""
    from fem_dual.config import Tolerance
    from fem_dual.integrate.estimate import ErrorWeights
    from fem_dual.integrate.estimate import _compiled_estimates
    from fem_dual.integrate.estimate import estimate_slabs as _estimates

    rng = np.random.default_rng(10 * slabs + vertices + n)
    checked = 0
    for flags in np.ndindex(2, 2, 2, 2, 2):
        with_alg, with_psi, with_lost, still, with_atol = map(bool, flags)
        vals, comp, alg, psi, lost = _estimate_case(rng, slabs, vertices, n, with_alg,
                                                    with_psi, with_lost, still)
        tol = Tolerance(1e-6, 1e-9 if with_atol else 0.0, True)
        start = 0.5 if with_lost else 5.0  # (below, then above the motion's size)
        weights = ErrorWeights(tol, np.full(n, start), np.zeros(n) if still else np.ones(n))
        dt = 0.25 if slabs == 1 else np.full(slabs, 0.25)
        args = (vals, comp, alg, psi, lost, weights, dt, 2.0)
        assert _compiled_estimates(*args) is not None or (still and not with_atol)
        ours, theirs = _estimates(*args), _estimates(*args, compiled=False)
        for name in ("local", "glob", "scales", "floor", "err_local", "err_global", "finite"):
            assert np.array_equal(getattr(ours, name), getattr(theirs, name)), name
        checked += 1
    assert checked == 32
    if n == 3:  # output times between the vertices: the interpolation error joins both alike
        output = (get_scene("curl3d")(), 6)
        ours = _estimates(*args, output=output)
        theirs = _estimates(*args, output=output, compiled=False)
        assert ours.err_output is not None
        for name in ("err_output", "err_local", "err_global"):
            assert np.array_equal(getattr(ours, name), getattr(theirs, name)), name
    vals, comp, alg, psi, lost = _estimate_case(rng, slabs, vertices, n, True, True, True,
                                                False)
    weights = ErrorWeights(Tolerance(1e-6, 1e-9, True), np.ones(n), np.ones(n))
    comp.z[0, -1, 0] = np.nan
    args = (vals, comp, alg, psi, lost, weights, 0.25, 2.0)
    assert _compiled_estimates(*args) is None
    ours, theirs = _estimates(*args), _estimates(*args, compiled=False)
    assert not ours.finite[0] and np.array_equal(ours.finite, theirs.finite)
    assert np.array_equal(ours.err_global, theirs.err_global, equal_nan=True)


def _summary(slabs, vertices, n, first):
    """What the run's accumulator keeps of accepted slabs (the reported errors at the kept
    vertices, their peaks, the last vertex's, each slab's largest errors and H_d's range and
    drift) is the numpy code's exactly, with errors below and above the round-off floor and
    H_d of either sign; a value that is not finite leaves the batch to the numpy code."""
    from fem_dual.integrate.sinks import SlabBatch, _compiled_summaries, _summaries

    rng = np.random.default_rng(100 * slabs + 10 * vertices + n)
    vals, _, _, _, _ = _estimate_case(rng, slabs, vertices, n, False, False, False, False)
    vals.block[..., -1] = rng.uniform(-3.0, 1.0, (slabs, vertices))  # H_d
    local = rng.uniform(-1e-6, 1e-6, (slabs, vertices, 2 * n))
    glob = local + rng.uniform(-1e-6, 1e-6, local.shape)
    glob[0, 0, :n] = 1e-20  # below its floor
    floor = rng.uniform(1e-13, 1e-11, (slabs, 2))
    batch = SlabBatch(0 if first else 3, np.arange(slabs, dtype=float), np.full(slabs, 0.5),
                      vals, local, glob, np.ones(slabs), np.ones(slabs), floor,
                      np.zeros((slabs, 5)), np.ones((slabs, 2)))
    keep = np.ones((slabs, vertices), dtype=bool)
    keep[:, 0] = False
    keep[0, 0] = first
    ours, theirs = _compiled_summaries(batch), _summaries(batch, keep)
    assert ours is not None and len(ours) == len(theirs) == 8
    for a, b in zip(ours, theirs):
        assert np.array_equal(a, b)
    glob[-1, 1, 0] = np.inf
    assert _compiled_summaries(batch) is None


_FORCE = {"F": "-sin(x) - a*x**3", "a": "0.5"}
_CURL3D = [0.3, 0.2, 0.1, 0.1, -0.2, 0.05]
# (the C functions a row checks, its check, the check's arguments)
TWINS = [
    (("rk4", "hermite"), _rk4, (get_scene("curl3d")(m=2.0), _CURL3D)),
    (("rk4", "hermite"), _rk4, (_scene("curl3d", K="2,0,0,0,3,0,0,0,4"),
                                [0.3, 0.2, 0.1, 0.0, 0.0, 0.0])),
    (("rk4", "hermite"), _rk4, (get_scene("curl2d")(), [1.0, 0.5, 0.0, 0.2])),
    (("rk4", "hermite"), _rk4, (get_scene("curl2d-lifted")(), [1.0, 0.5, 0.0, 0.2])),
    (("rk4", "hermite"), _rk4, (_scene("force", F="-sin(x) - a*x**3", a=0.5), [2.5, 0.3])),
    (("rk4", "hermite"), _rk4, (_UnequalMasses(), [0.3, 0.2, 0.1, 0.0, 0.1, 0.0])),
    (("hermite",), _hermite, (get_scene("curl3d")(m=2.0), _CURL3D)),
    (("hermite",), _hermite, (_UnequalMasses(), [0.3, 0.2, 0.1, 0.0, 0.1, 0.0])),
    (("band",), _band, ("curl3d", 6, 3)),
    (("band",), _band, ("curl2d", 4, 2)),
    (("band",), _band, ("curl2d-lifted", 3, 2)),
    (("band",), _band, ("curl3d", 10, 1)),
    (("pack",), _pack, ("curl3d", None)),
    (("pack",), _pack, ("curl2d", None)),  # with the implicit DtP map's X and G_x^-1
    (("pack",), _pack, ("force", {"F": "-sin(x) - x**3"})),
    (("dtp_newton",), _dtp_newton, ("curl2d", None)),
    (("dtp_newton",), _dtp_newton, ("curl3d-ufl", None)),
    (("dtp_newton",), _dtp_newton, ("force", {"F": "-sin(x) - x**3"})),
    (("dtp_newton",), _dtp_newton, ("curl2d", None, 50.0)),  # off the branch: refused alike
    (("slab_newton",), _slab_newton, ("curl3d", None, "start", 0.5, "1,0.5,0.2", "0,0.3,0")),
    (("slab_newton",), _slab_newton, ("curl3d", None, "rk4", 2.0, "1,0.5,0.2", "0,0.3,0")),
    (("slab_newton",), _slab_newton, ("curl3d", None, "zero", 0.5, "1,0.5,0.2", "0,0.3,0")),
    (("slab_newton",), _slab_newton, ("curl3d", {"m": "2", "K": "2,0,0,0,3,0,0,0,4"}, "rk4",
                                      3.0, "0.3,0.2,0.1", "0.1,0,0")),
    (("slab_newton",), _slab_newton, ("curl2d-lifted", None, "start", 0.5, "1,1", "0,0")),
    # at rest at an equilibrium: no step
    (("slab_newton",), _slab_newton, ("curl3d", None, "rk4", 1.0, "0,0,0", "0,0,0")),
    # implicit DtP maps: solved inside the loop
    (("slab_newton",), _slab_newton, ("curl2d", None, "rk4", 2.0, "1,1", "0,0")),
    (("slab_newton",), _slab_newton, ("curl2d", None, "start", 2.0, "1,1", "0,0")),
    (("slab_newton",), _slab_newton, ("curl3d-ufl", None, "rk4", 2.0, None, None)),
    (("slab_newton",), _slab_newton, ("force", _FORCE, "rk4", 3.0, "2.5", "0.3")),
    # residual at round-off from the start
    (("slab_newton",), _slab_newton, ("force", {"F": "1 - x"}, "rk4", 1.0, "0", "0")),
    (("tangents",), _tangents, ("curl3d", None, "rk4", 3, "1,0.5,0.2", "0,0.3,0")),
    (("tangents",), _tangents, ("curl3d", {"m": "2", "K": "2,0,0,0,3,0,0,0,4"}, "rk4", 2,
                                "0.3,0.2,0.1", "0.1,0,0")),
    (("tangents",), _tangents, ("curl3d", None, "zero", 2, "1,0.5,0.2", "0,0.3,0")),
    (("tangents",), _tangents, ("curl2d", None, "rk4", 2, "1,1", "0,0")),  # an implicit map
    # multipliers: bs > 2n
    (("tangents",), _tangents, ("curl2d-lifted", None, "predictor", 2, "1,1", "0,0")),
    (("tangents",), _tangents, ("force", _FORCE, "rk4", 1, "2.5", "0.3")),
    (("band_cholesky", "band_solve"), _band_cholesky, (50, 7)),
    (("band_cholesky", "band_solve"), _band_cholesky, (384, 53)),
    (("band_cholesky", "band_solve"), _band_cholesky, (1, 0)),
    (("band_cholesky", "band_solve"), _band_cholesky, (6, 5)),
    (("estimate",), _estimate, (1, 2, 3)),
    (("estimate",), _estimate, (1, 9, 2)),
    (("estimate",), _estimate, (5, 3, 1)),
    (("estimate",), _estimate, (4, 5, 3)),
    (("summary",), _summary, (1, 2, 3, True)),
    (("summary",), _summary, (1, 9, 2, False)),
    (("summary",), _summary, (5, 3, 1, True)),
    (("summary",), _summary, (4, 5, 3, False)),
]


@compiled
@pytest.mark.parametrize("loops, check, args", TWINS,
                         ids=[f"{check.__name__[1:]}-{i}" for i, (_, check, _) in
                              enumerate(TWINS)])
def test_compiled_loop_is_its_numpy_twin(loops, check, args):
    check(*args)


@compiled
def test_every_compiled_loop_has_a_row_in_the_table():
    _, lib = native.library()
    declared = set(dir(lib))
    assert declared == {f"fem_dual_{loop}" for loops, _, _ in TWINS for loop in loops}


# -- the loops in a run ---------------------------------------------------------------------------

@compiled
def test_compiled_rk4_takes_new_parameter_values():
    first, second = get_scene("curl3d")(), _scene("curl3d", m=3, K="1,1,1,1,4,1,1,1,5")
    z0, t = np.array([0.3, 0.2, 0.1, 0.0, 0.0, 0.0]), np.linspace(0.0, 1.0, 5)
    predictor = FlowPredictor(first, 10)
    predictor(z0, t, 1.0)
    predictor.use_scene(second)
    expected = FlowPredictor(second, 10, compiled=False)(z0, t, 1.0)
    assert np.abs(predictor(z0, t, 1.0) - expected).max() <= 1e-14


@compiled
def test_compiled_rk4_stops_at_a_blow_up():
    """x'' = x^3 from x = 10 blows up within the slab: the loop says so, no NaN is kept."""
    scene = _scene("force", F="x**3")
    predictor = FlowPredictor(scene, 50)
    with pytest.raises(Exception, match="overflowed"):
        predictor(np.array([10.0, 0.0]), np.linspace(0.0, 5.0, 3), 5.0)


@compiled
def test_a_compiled_newton_that_gives_up_leaves_the_start_to_the_numpy_iteration():
    """Where a full step does not lower the residual enough, the numpy iteration starts over
    from the same start state, warm or zero, and ends where it ends without the compiled
    one; a slab whose full steps fail (curl3d, start base, dt = 2) is solved by the numpy
    line search alone."""
    args = ("curl3d", None, "start", 0.5, "1,0.5,0.2", "0,0.3,0")
    x_np, history_np, _, _, _ = _slab_newton_run(*args, compiled=False)
    x, history, _, message, answered = _slab_newton_run(*args, bail=True)
    assert message is None and answered == [False]
    assert np.array_equal(x, x_np) and history == history_np
    warm = (0.9 * x_np, history_np[0])
    x_w, history_w, _, _, _ = _slab_newton_run(*args, compiled=False, warm=warm)
    x_b, history_b, _, message, answered = _slab_newton_run(*args, bail=True, warm=warm)
    assert message is None and answered == [False]
    assert np.array_equal(x_b, x_w) and history_b == history_w
    hard = ("curl3d", None, "start", 2.0, "1,0.5,0.2", "0,0.3,0")
    x, history, _, message, answered = _slab_newton_run(*hard)
    x_np, history_np, _, _, _ = _slab_newton_run(*hard, compiled=False)
    assert message is None and answered == [False]
    assert np.array_equal(x, x_np) and history == history_np and len(history) > 10


@compiled
def test_a_compiled_newton_that_gives_up_leaves_the_implicit_map_as_it_was():
    """The C loop solves the implicit DtP map at its trial states in place: when it gives up,
    the map's root goes back to where it was, and the numpy iteration ends where it ends
    alone (a slab of curl2d from the zero base, whose full steps the numpy line search
    shortens)."""
    for args in (("curl2d", None, "start", 0.5, "1,1", "0,0"),
                 ("curl2d-ufl", None, "zero", 0.5, None, None)):
        x_np, history_np, _, _, answered_np = _slab_newton_run(*args, compiled=False)
        x, history, _, message, answered = _slab_newton_run(*args, bail=True)
        assert message is None and answered[0] is False
        assert np.array_equal(x, x_np) and history == history_np
        for ours, theirs in zip(answered[1], answered_np[0]):
            assert np.abs(ours - theirs).max() <= 1e-12 * np.abs(theirs).max()


@compiled
def test_a_run_says_its_newton_was_compiled():
    r = run(RunConfig.create("curl3d", T=1, cells=2, degree=3, base="rk4", staging="off"))
    assert r.status == "ok" and {"newton", "tangents"} <= set(r.solver["compiled_loops"])
    assert r.solver["compiled_loops_unavailable"] is None
    r = run(RunConfig.create("curl2d", T=1, cells=2, degree=3, base="rk4", staging="off"))
    assert r.status == "ok" and {"newton", "dtp"} <= set(r.solver["compiled_loops"])
    r = run(RunConfig.create("curl3d", T=1, cells=2, degree=3, base="rk4", staging="off",
                             assembly="forms"))
    assert "newton" not in r.solver["compiled_loops"]  # (PETSc's SNES)


@compiled
def test_the_compiled_newton_factors_the_jacobian_at_its_solution():
    """The slab's tangents need the Jacobian factored at the solution: the compiled Newton
    factors it from the band it assembled there (a last step of 1.5e-5 relative here, too far
    for the last step's factors), and the tangents equal those of a fresh factorisation; the
    error companion, which takes no tangents, does without."""
    from fem_dual.integrate.simulation import Simulation
    from fem_dual.slab.native_newton import FACTORS_KEPT_STEP

    config = RunConfig.create("curl3d", T=8, cells=8, degree=8, base="rk4", staging="off",
                              reference="none")
    sim = Simulation.for_config(config)
    try:
        local = sim.backend.solver.local
        answers = []
        run_compiled = local._native_newton.run
        local._native_newton.run = lambda x, **tests: answers.append(
            run_compiled(x, **tests)) or answers[-1]
        sim.run(config)
        answer = answers[0]
        assert answer.last_step > FACTORS_KEPT_STEP
        assert answer.at_x is not None and answer.at_x is not answer.lu
        assert local._held_factors() is answer.at_x
        held = local.tangent_matrix()
        local._factors_at = local._tangent_at = None
        fresh = local.tangent_matrix()
        assert np.abs(held - fresh).max() <= 1e-12 * np.abs(fresh).max()
        assert sim.companion.backend.solver.local.factor_solution is False
    finally:
        sim.close()


def test_the_reference_of_a_scene_with_a_mass_matrix_takes_it():
    """A scene file may give M other than m I: its DOP853 reference takes M^-1 F, and the rk4
    base's M^-1 branch answers within its estimate."""
    from scipy.integrate import solve_ivp

    scene = _UnequalMasses()
    M = scene.mass_matrix()
    r = run(RunConfig.create(scene, T=2, cells=4, degree=4, base="rk4", staging="off"))
    z0 = np.concatenate([r.x[0], r.v[0]])
    sol = solve_ivp(lambda t, z: np.concatenate([z[3:], np.linalg.solve(M, scene.force_numpy(
        z[:3]))]), (0.0, 2.0), z0, method="DOP853", rtol=1e-13, atol=1e-13)
    assert np.abs(r.x[-1] - sol.y[:3, -1]).max() <= r.error_estimate
    assert r.status == "ok" and max(r.error["x_max"], r.error["v_max"]) <= r.error_estimate


@compiled
def test_a_reused_simulation_reports_the_loops_of_each_run():
    """Whether the implicit DtP map ran compiled is known once it has run: a simulation whose
    first run failed before any DtP solve (the rk4 base overflowed) says `dtp` for its next
    run, as a fresh one does (not the first run's list)."""
    from fem_dual.errors import SolveError
    from fem_dual.integrate.simulation import Simulation

    options = dict(assembly="forms", base="rk4", staging="off", reference="none")
    bad = RunConfig.create("curl2d", x0="1e40,1e40", max_halvings=0, **options)
    good = RunConfig.create("curl2d", slabs=2, **options)
    sim = Simulation.for_config(bad)
    try:
        with pytest.raises(SolveError, match="overflowed"):
            sim.run(bad)
        reused = sim.run(good).solver["compiled_loops"]
    finally:
        sim.close()
    fresh = Simulation.for_config(good)
    try:
        assert reused == fresh.run(good).solver["compiled_loops"]
    finally:
        fresh.close()
    assert "dtp" in reused


# -- the build: install time, run time, no compiler ------------------------------------------------

def _no_compiler(monkeypatch):
    """As on a machine without a C compiler."""
    def missing():
        raise OSError("no C compiler (cc, gcc) on PATH")
    monkeypatch.setattr(build, "compiler", missing)


def _fresh(monkeypatch, tmp_path, packaged: Path):
    """fem_dual.native as in a new process, with the package's library at `packaged` and the
    user cache under tmp_path."""
    monkeypatch.setattr(build, "PACKAGED", packaged)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.setattr(native, "_loaded", {})


@needs_compiler
def test_the_sources_compile_warnings_clean(tmp_path):
    """-Wall -Wextra (and -Werror), with the compiler the FFCx JIT uses: not one warning."""
    messages = build.compile_library(tmp_path / "lib.so", extra=("-Werror",))
    assert messages.strip() == "", messages
    assert build.current(tmp_path / "lib.so")


def test_cffi_reads_the_header_without_preprocessor_lines():
    import cffi

    text = build.declarations()
    assert not any(line.lstrip().startswith("#") for line in text.splitlines())
    ffi = cffi.FFI()
    ffi.cdef(text)  # (raises on anything cffi cannot parse)
    assert ffi.sizeof("fem_dual_dtp") > 0


@needs_compiler
def test_the_install_step_builds_the_library_into_the_package(tmp_path, monkeypatch):
    """`python3 -m fem_dual.native.build` (make install) leaves the library and its stamp;
    loaded from there, nothing is compiled at run time, even without a compiler."""
    packaged = tmp_path / "package" / "libfem_dual_native.so"
    monkeypatch.setattr(build, "PACKAGED", packaged)
    assert build.main([]) == 0 and build.current(packaged)
    _fresh(monkeypatch, tmp_path, packaged)
    _no_compiler(monkeypatch)
    assert native.library() is not None and native.path() == packaged
    assert not (tmp_path / "cache").exists()


@needs_compiler
def test_a_stale_packaged_library_is_compiled_again_into_the_cache(tmp_path, monkeypatch):
    """A package library built from other sources (edited since `make install`) is not
    loaded: the present sources are compiled into the user cache, with the same flags."""
    packaged = tmp_path / "package" / "libfem_dual_native.so"
    build.compile_library(packaged)
    stamp = packaged.with_name(packaged.name + ".json")
    record = json.loads(stamp.read_text())
    stamp.write_text(json.dumps(dict(record, sources="0" * 64)))
    _fresh(monkeypatch, tmp_path, packaged)
    assert not build.current(packaged)
    assert native.library() is not None
    assert native.path() == build.cached() and build.current(native.path())


@needs_compiler
@pytest.mark.parametrize("where", ["package", "cache"])
@pytest.mark.parametrize("damage", ["empty", "truncated", "another library"])
def test_a_damaged_library_is_not_loaded(tmp_path, monkeypatch, where, damage):
    """A library file that is not the one compiled (a truncated one that dlopen accepts would
    kill the process at a call; one without the functions, a traceback) is compiled again
    into the cache; the library file of the package is never rewritten at run time."""
    packaged = tmp_path / "package" / "libfem_dual_native.so"
    _fresh(monkeypatch, tmp_path, packaged)
    built = build.cached() if where == "cache" else packaged
    build.compile_library(built)
    good = built.read_bytes()
    libm = next(p for p in (ctypes.util.find_library("m") or "",
                            "/lib/x86_64-linux-gnu/libm.so.6",
                            "/usr/lib/x86_64-linux-gnu/libm.so.6") if Path(p).is_file())
    built.write_bytes({"empty": b"", "truncated": good[:5000],
                       "another library": Path(libm).read_bytes()}[damage])
    assert native.library() is not None and native.path() == build.cached()
    assert build.current(build.cached()) and build.cached().read_bytes() == good
    if where == "package":
        assert not build.current(packaged)


def test_no_compiler_means_the_numpy_loops(tmp_path, monkeypatch):
    _fresh(monkeypatch, tmp_path, tmp_path / "package" / "libfem_dual_native.so")
    monkeypatch.setenv("PATH", str(tmp_path))  # no cc, no gcc
    monkeypatch.setattr("sysconfig.get_config_var", lambda name: "no-such-cc")
    assert native.library() is None and "compiler" in native.reason()
    assert native.path() is None
    assert FlowPredictor(get_scene("curl3d")(), 4).compiled is False


@compiled
def test_runs_without_the_compiled_loops_give_the_same_answer(tmp_path, monkeypatch):
    """Without a compiler and without a built library the numpy twins run: the same answer,
    and the JSON says that no loop ran compiled, and why."""
    config = dict(T=2, cells=2, degree=4, base="rk4", staging="off")
    ours = run(RunConfig.create("curl3d", **config))
    _fresh(monkeypatch, tmp_path, tmp_path / "package" / "libfem_dual_native.so")
    _no_compiler(monkeypatch)
    theirs = run(RunConfig.create("curl3d", **config))
    assert ours.status == theirs.status == "ok"
    assert np.abs(ours.x - theirs.x).max() <= 1e-13
    # equal to round-off: the estimate (1e-11 here) is a difference of states of size 0.3
    assert abs(ours.error_estimate - theirs.error_estimate) <= 1e-6 * theirs.error_estimate + 1e-15
    assert {"rk4", "band", "newton", "tangents"} <= set(ours.solver["compiled_loops"])
    assert theirs.solver["compiled_loops"] == []
    assert "no C compiler" in theirs.solver["compiled_loops_unavailable"]


def test_the_build_command_without_a_compiler_succeeds_and_says_so(tmp_path):
    """`make install` on a machine without a compiler: the build step says the numpy loops
    will run, and the installation goes on."""
    script = ("import sysconfig, sys\n"
              "sysconfig.get_config_var = lambda name: 'no-such-cc'\n"
              "from fem_dual.native import build\n"
              f"build.PACKAGED = __import__('pathlib').Path({str(tmp_path / 'lib.so')!r})\n"
              "sys.exit(build.main([]))\n")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          env={"PATH": str(tmp_path)})
    assert done.returncode == 0, done.stderr
    assert "numpy loops will run" in done.stderr and not (tmp_path / "lib.so").exists()
