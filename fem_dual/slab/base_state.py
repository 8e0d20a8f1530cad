"""Base states of H on a slab (the (xbar, vbar) of forms.predual), beyond the constant ones.

Only the residual of the base state, L zbar = zbar' - f(zbar) with f(z) = (v, M^-1 F(x)), enters
a slab's dual action: the constant start state leaves f(z0), an O(omega) forcing that
modes the cells do not resolve turn into growth; zero leaves -f(0), nothing for a linear system
or a force with F(0) = 0, but the dual fields must then carry the whole state through a
nonlinear DtP map. The predictor below is close to the motion and nearly residual-free in every
mode: the linearly implicit Euler step from the start,

    zbar(t) = z0 + t (I - t J)^-1 f(z0),   J = df/dz (z0),

follows the slow motion to first order and, for a mode with |lambda t| >> 1, sits at its
quasi-static state z0 - J^-1 f(z0) (a stiff spring at the position where it balances the other
forces), so unresolved modes are not forced.

The flow predictor ("rk4") is for motions that are not stiff: classical Runge-Kutta from the
start, RK4_STEPS_PER_NODE (p + 1) steps per cell, read at the base state's nodes by cubic
Hermites. Near the motion to O(h^4), it leaves the dual fields only a small correction, so
Newton converges from the zero dual state on slabs several times longer than from the constant
start state (curl3d T = 8 at rtol 1e-6: 2 slabs of 4 against 8 slabs and 5 failed Newtons), and
the correction's discretisation error is small with it.
"""
from __future__ import annotations

import math
from typing import Dict

import numpy as np

__all__ = ["Predictor", "FlowPredictor", "predictor", "force_jacobian", "grows_within",
           "stiff_at_start", "motion_rate", "STIFF_RATIO"]

STIFF_RATIO = 5.0  # fastest linearised frequency / the start's rate beyond which it is stiff
# rk4 steps per node of the dual fields (p + 1 a cell). Fewer cost accuracy: curl3d T = 8
# --rtol 1e-8 at p = 4, 4 cells ended 3.2e-10 off with 5 a cell, 1.03e-8 off with 2; when the
# companion read the same run, its estimate (7e-9) missed that. More leave Newton less to do:
# its first residual is the base's defect, O(h^4) (curl3d T = 8, p = 8, 8 cells, one slab: 9
# steps a cell left 5.5e-5, Newton took two steps for the answer and for the companion, 72
# steps a cell left 3.8e-7 and one step each; and the answer, the correction of a base that
# far closer, was 4.2e-13 off instead of 3.8e-11). A step costs a tenth of a microsecond in
# compiled code (curl3d: 576 steps in 45 us).
RK4_STEPS_PER_NODE = 8


def force_jacobian(force, x: np.ndarray) -> np.ndarray:
    """dF/dx at x by central differences (n force evaluations x 2; F is smooth)."""
    n = len(x)
    J = np.empty((n, n))
    for j in range(n):
        h = 1e-6 * max(1.0, abs(x[j]))
        e = np.zeros(n)
        e[j] = h
        J[:, j] = (force(x + e) - force(x - e)) / (2 * h)
    return J


class Predictor:
    """zbar(t) = z0 + t (I - t J)^-1 f(z0) for a scene (linear: J is its first-order matrix)."""

    compiled = False  # (numpy only; FlowPredictor may step in compiled code)

    def __init__(self, scene):
        self.use_scene(scene)

    def forget(self) -> None:
        """Nothing is kept between runs (FlowPredictor keeps its last run)."""

    def use_scene(self, scene) -> None:
        """Predict the motion of `scene` (new parameter values of the same kind of scene)."""
        self.scene = scene
        self.n = scene.n
        self.Minv = np.linalg.inv(scene.mass_matrix())

    def _rate_and_jacobian(self, z0: np.ndarray):
        n, scene = self.n, self.scene
        if scene.linear:
            J = scene.first_order_matrix()
            return J @ z0, J
        x0, v0 = z0[:n], z0[n:]
        J = np.zeros((2 * n, 2 * n))
        J[:n, n:] = np.eye(n)
        J[n:, :n] = self.Minv @ force_jacobian(scene.force_numpy, x0)
        return np.concatenate([v0, self.Minv @ scene.force_numpy(x0)]), J

    def __call__(self, z0: np.ndarray, t: np.ndarray, end: float = 0.0) -> np.ndarray:
        """(len(t), 2n): the predictor at the times t after the slab's start (a function of
        the time alone: the slab's length `end` is not needed)."""
        f0, J = self._rate_and_jacobian(np.asarray(z0, dtype=float))
        eye = np.eye(len(f0))
        out = np.empty((len(t), len(f0)))
        for i, ti in enumerate(np.asarray(t, dtype=float)):
            out[i] = z0 + ti * np.linalg.solve(eye - ti * J, f0)
        return out

    def along(self, z0: np.ndarray, fractions: np.ndarray, end: float) -> np.ndarray:
        """The predictor at the times fractions * end (as FlowPredictor.along)."""
        return self(z0, fractions * end, end)


class FlowPredictor:
    """zbar(t): classical RK4 of z' = f(z) from z0 in `steps` equal steps over the slab,
    read at the times t by the cubic Hermite of the step ends (O(h^4), as the steps). The last
    run is kept within a run of the slab loop: its repeated starts of a slab (tangents, Newton
    probes) read it again without stepping. The error companion steps its own, with twice the
    steps (fem_dual.integrate.simulation.Simulation.companion).

    The steps run in compiled code (fem_dual.native) on the scene's UFL force compiled by FFCx,
    where a C compiler is found (`compiled`); else in numpy on the scene's `force_numpy`.

    Args:
        scene: the nonlinear scene.
        steps: RK4 steps per slab.
        force: a compiled force of the same scene to share
            (fem_dual.native.force.CompiledForce);
            None: compile one (if the compiled loops are available).
        compiled: False: step in numpy whatever is available.
    """

    def __init__(self, scene, steps: int, force=None, compiled: bool = True):
        from fem_dual import native

        self.steps = steps
        self._weights: Dict[bytes, tuple] = {}  # Hermite weights of given fractions
        self.force = None
        if compiled and native.library() is not None:
            from fem_dual.native.force import CompiledForce

            self.force = force or CompiledForce.of(scene)
        self.use_scene(scene)

    @property
    def compiled(self) -> bool:
        """Whether the steps run in compiled code."""
        return self.force is not None

    def with_steps(self, steps: int) -> "FlowPredictor":
        """A predictor of the same scene with `steps` steps a slab (the compiled force
        shared)."""
        return FlowPredictor(self.scene, steps, self.force, self.compiled)

    def use_scene(self, scene) -> None:
        """Step the motion of `scene` (new parameter values of the same kind of scene)."""
        self.scene = scene
        self.n = scene.n
        self.Minv = np.linalg.inv(scene.mass_matrix())
        scale = float(self.Minv[0, 0])  # M = m I: 1/m scales the force (no matrix product)
        self._scale = scale
        self._minv = None if np.array_equal(self.Minv, scale * np.eye(self.n)) else \
            np.ascontiguousarray(self.Minv)
        self._loop = None
        if self.force is not None:
            from fem_dual.native.rk4 import Rk4

            # the run's step ends are the loop's, reused by every run (the kept run is dropped
            # before the next)
            self._loop = Rk4(self.force.kernel, self.force.pack(scene), self.n, self.steps,
                             scale, self._minv)
        self.forget()

    def forget(self) -> None:
        """Drop the kept run: a new run of the slab loop steps again (a timed repeat of the
        same run must not read the last one's)."""
        self._last: tuple = (None, None, None, None)
        self._reads: Dict[bytes, np.ndarray] = {}  # the run read at given times

    def ends(self, z0: np.ndarray, end: float) -> np.ndarray:
        """(steps + 1, 2n): the states at the step ends of the run over a slab of length
        `end` > 0 from z0: the kept run where it is that one, else a new kept run (valid until
        the next run).

        Raises:
            SolveError: a value was not finite.
        """
        return self._kept(np.asarray(z0, dtype=float), float(end))[2]

    def _kept(self, z0: np.ndarray, end: float) -> tuple:
        """The kept run (z0, end, states, rates), made the run from z0 over `end` first."""
        if not (self._last[0] is not None and self._last[1] == end
                and np.array_equal(self._last[0], z0)):
            self.forget()  # (a run that fails leaves no kept run: its step ends are reused)
            self._last = (z0.copy(), end) + ((np.array([z0]), np.zeros((1, len(z0))))
                                              if end <= 0 else self._run(z0, end))
        return self._last

    def _run(self, z0: np.ndarray, end: float):
        """(states, rates) at the step ends: (steps + 1, 2n) each. Classical RK4 of z' = f(z)
        for z = (x, v), f = (v, a(x)), in its Nystrom form (the same stages and sums, with
        the velocity stages folded into the positions: a dozen array operations a step
        fewer; a 20-step slab of curl3d in 0.3 ms, 1 ms as four stages of z)."""
        h = end / self.steps
        if self._loop is not None:  # (the C loop checks every value after the start's)
            failed = self._loop.run(z0, h)
            states, rates = self._loop.states, self._loop.rates
            failed = failed or not np.isfinite(rates[0]).all()
        else:
            states, rates = self._numpy_run(z0, h)
            failed = not (np.isfinite(states).all() and np.isfinite(rates).all())
        if failed:
            from fem_dual.errors import SolveError

            raise SolveError("the rk4 base state overflowed on the slab: the motion blows up, "
                             "or it is stiff, where explicit Runge-Kutta is unstable (use "
                             "--base predictor)")
        return states, rates

    def _numpy_run(self, z0: np.ndarray, h: float):
        """_run's steps in numpy, on the scene's force_numpy."""
        n, steps = self.n, self.steps
        force, Minv = self.scene.force_numpy, self.Minv
        scale = float(Minv[0, 0])
        if np.array_equal(Minv, scale * np.eye(n)):  # M = m I: 1/m joins the step constants
            def accel(x):  # (a scene file's force may answer a list: sums must be numpy's)
                return np.asarray(force(x), dtype=float)
            if isinstance(force(z0[:n]), np.ndarray):
                accel = force
        else:
            def accel(x):
                return Minv @ force(x)
            scale = 1.0
        half, h2, hh2 = 0.5 * h, 0.25 * h * h * scale, 0.5 * h * h * scale
        hh6, h6 = h * h * scale / 6.0, h * scale / 6.0
        xs, vs, ks = [z0[:n]], [z0[n:]], []
        with np.errstate(all="ignore"):  # an overflow is judged below, once
            x, v = xs[0], vs[0]
            k1 = accel(x)
            ks.append(k1)
            for _ in range(steps):
                x2 = x + half * v
                k2 = accel(x2)
                k3 = accel(x2 + h2 * k1)
                ahead = x + h * v
                k4 = accel(ahead + hh2 * k2)
                x = ahead + hh6 * (k1 + k2 + k3)
                v = v + h6 * (k1 + 2.0 * (k2 + k3) + k4)
                k1 = accel(x)
                xs.append(x), vs.append(v), ks.append(k1)
            v_all = np.array(vs)
            states = np.hstack([np.array(xs), v_all])
            rates = np.hstack([v_all, scale * np.array(ks)])
        return states, rates

    def __call__(self, z0: np.ndarray, t: np.ndarray, end: float) -> np.ndarray:
        """(len(t), 2n): the predictor at the times t (in [0, end]) after the start of a slab of
        length `end`. The steps are those of the whole slab whatever part of it t covers (a
        process of a distributed slab holds the nodes of its cells only)."""
        t, end = np.asarray(t, dtype=float), float(end)
        return self.along(z0, t / end if end > 0 else np.zeros_like(t), end)

    def along(self, z0: np.ndarray, fractions: np.ndarray, end: float) -> np.ndarray:
        """The predictor at the times fractions * end of a slab of length `end` (a slab's
        nodes: their cubic Hermite weights are found once per array of fractions)."""
        end = float(end)
        _, _, states, rates = self._kept(np.asarray(z0, dtype=float), end)
        key = fractions.tobytes()
        if key in self._reads:  # the same slab read again (a restore after a probe)
            return self._reads[key]
        if end <= 0:
            return np.repeat(states[:1], len(fractions), axis=0)
        if key not in self._weights:
            self._weights[key] = self._hermite(np.asarray(fractions, dtype=float))
        rows, weights, table = self._weights[key]
        h = end / self.steps
        if self._loop is not None:  # (the same sums in compiled code, of the run's step ends)
            out = self._loop.read(table, h)
        else:
            out = np.einsum("mj,mjc->mc", weights, np.concatenate([states, h * rates])[rows])
        self._reads[key] = out
        return out

    def _hermite(self, fractions: np.ndarray) -> tuple:
        """(rows, weights, their table for the compiled read or None), rows and weights
        (len(fractions), 4): the cubic Hermite of the step ends at the fractions of the slab, as
        weights of rows of [states; h rates]."""
        steps = self.steps
        u = np.clip(fractions * steps, 0.0, steps)
        k = np.minimum(u.astype(int), steps - 1)  # the step of each time
        s = u - k
        weights = np.stack([(1 + 2 * s) * (1 - s) ** 2, s * (1 - s) ** 2,
                            s ** 2 * (3 - 2 * s), s ** 2 * (s - 1)], axis=1)
        rows = np.stack([k, steps + 1 + k, k + 1, steps + 2 + k], axis=1).astype(np.int64)
        weights = np.ascontiguousarray(weights)
        if self.force is None:
            return rows, weights, None
        from fem_dual.native.rk4 import HermiteTable

        return rows, weights, HermiteTable(rows, weights)


def predictor(scene, base: str, steps: int):
    """The predictor of a base state that is a function of time ("predictor", "rk4"; `steps`:
    the rk4 steps per slab)."""
    return FlowPredictor(scene, steps) if base == "rk4" else Predictor(scene)


def _linearised_modes(scene, x0: np.ndarray) -> np.ndarray:
    """mu: the eigenvalues of M^-1 dF/dx at x0 (the first-order system's are +-sqrt(mu))."""
    Minv = np.linalg.inv(scene.mass_matrix())
    return np.linalg.eigvals(Minv @ force_jacobian(scene.force_numpy, x0))


def grows_within(scene, x0: np.ndarray, dt: float) -> bool:
    """Whether the motion linearised at x0 has a mode that grows by more than a factor e over
    a time dt: an eigenvalue lambda = sqrt(mu) of the first-order system, mu an eigenvalue of
    M^-1 dF/dx, with Re(lambda) dt > 1."""
    mu = _linearised_modes(scene, x0)
    return bool(np.sqrt(mu.astype(complex)).real.max(initial=0.0) * dt > 1.0)


def stiff_at_start(scene, x0: np.ndarray, v0: np.ndarray) -> bool:
    """Whether a nonlinear scene is stiff at its start: the fastest frequency of the force
    linearised there, sqrt |eig(M^-1 dF/dx)|, exceeds STIFF_RATIO times the start's own rate
    (`motion_rate`), so that slabs sized by the motion leave modes unresolved,
    and those modes oscillate: a fast mode that grows (an eigenvalue of M^-1 dF/dx that is not
    negative, beyond the same rate) must be followed, not damped by the predictor, so the start
    is not called stiff (curl3d at x = (1e3, 0, 0) grows at 38 per unit of time)."""
    a0 = np.linalg.solve(scene.mass_matrix(), scene.force_numpy(x0))
    mu = _linearised_modes(scene, x0)
    rate = motion_rate(x0, v0, a0)
    if not rate > 0:
        return False
    fast = np.sqrt(np.abs(mu)) > STIFF_RATIO * rate
    growing = fast & ~((mu.real < 0) & (np.abs(mu.imag) <= 1e-9 * np.abs(mu)))
    return bool(fast.any() and not growing.any())


def motion_rate(x0: np.ndarray, v0: np.ndarray, a0: np.ndarray) -> float:
    """|z'| / |z| of the start state z = (x0, v0), z' = (v0, a0), taken per part so that units
    do not mix: max(|v0| / |x0|, |a0| / |v0|, sqrt(|a0| / |x0|))."""
    nx, nv, na = (float(np.abs(a).max(initial=0.0)) for a in (x0, v0, a0))
    rates = []
    if nx > 0:
        rates += [nv / nx, math.sqrt(na / nx)]
    if nv > 0:
        rates.append(na / nv)
    finite = [r for r in rates if math.isfinite(r)]
    return max(finite) if finite else 0.0
