"""Independent reference solutions of the primal initial-value problem.

Linear scenes: the exact flow exp(t A) of the first-order system z' = A z, z = (x, v): followed
mode block by mode block for an undamped system whose modes are refined or about to coalesce
(BlockFlow: slow modes of a stiff system, near a flutter load), else an eigen-decomposition when
its eigenvectors are well conditioned (EigenFlow: QZ on (K, M) for an undamped system, on the
first-order pencil for a damped one), else BlockFlow where undamped, else through scipy's matrix
exponential (LinearFlow); with sparse matrices, expm_multiply (SparseFlow). For a stiff system the
float64 expm is not a reference: its error is relative to |A| = |M^-1 K| (2.6e10 for a 200-link
column), and it drifts 4.5e-7 in the slow mode's phase over ten periods, measured against a
certified 500-bit eigen-decomposition and a 1024-bit Taylor/doubling propagator, which agree bit
for bit in float64 (benchmarks/hp_reference); the reference there (BlockFlow: its slow modes are
refined) is within 7e-16 in x and 1.5e-12 in v of them, EigenFlow within 6e-12 and 9e-11 (scales
0.1 and 0.51).
Nonlinear scenes: scipy's DOP853 at rtol = 1e-13, atol = 1e-16.

References are evaluated chunk by chunk (one slab at a time, increasing times) so that long runs
never hold more than one slab of reference values.
"""
from __future__ import annotations

from typing import Callable, Optional, Tuple

import numpy as np


__all__ = ["LinearFlow", "EigenFlow", "FirstOrderModes", "BlockFlow", "SparseFlow", "IVPFlow",
           "first_order_matrix", "linear_reference", "linear_flow", "EIGEN_MAX_CONDITION"]

EIGEN_MAX_CONDITION = 1e6  # eigenvectors beyond this (near flutter, defective): expm instead


def _expm(A: np.ndarray) -> np.ndarray:
    """scipy's matrix exponential (imported on first use: validating a scene needs none)."""
    from scipy.linalg import expm

    return expm(A)


class LinearFlow:
    """z(t) = exp(t A) z0, evaluated as exp((t - a) A) z(a) with a the chunk's first time.

    z(a) is exp(a A) z0 computed directly, except that a chunk starting one step after the last
    one (equal to the previous step to 1e-9: t0 + dt - t0 carries rounding) reuses that step's
    exponential, for at most `reanchor` chunks in a row (then a direct exponential again): 32
    for small systems, where the accumulated round-off stays at a few ulps, up to 2048 for large
    ones (a 200-link column: an expm of 400 x 400 costs half a second), where it stays below
    1e-12 relative. The offsets of equal slabs repeat, so their exponentials are computed once
    and reused.
    """

    def __init__(self, A: np.ndarray, x0: np.ndarray, v0: np.ndarray):
        self.A = A
        self.n = len(x0)
        self.z0 = np.concatenate([x0, v0])
        self._offsets: Optional[np.ndarray] = None  # the offsets whose exponentials _E holds
        self._E: Optional[np.ndarray] = None
        self._anchor: Optional[Tuple[float, np.ndarray]] = None  # (a, z(a)) of the last chunk
        self._step: Optional[Tuple[float, np.ndarray]] = None  # (h, exp(h A))
        self._chained = 0
        self.reanchor = int(min(2048, max(32, 8 * len(self.z0))))

    def _state_at(self, a: float) -> np.ndarray:
        if self._anchor is not None and self._chained < self.reanchor:
            h = a - self._anchor[0]
            if h > 0:
                if self._step is None or abs(self._step[0] - h) > 1e-9 * h:
                    self._step = (h, _expm(h * self.A))
                self._chained += 1
                return self._step[1] @ self._anchor[1]
        self._chained = 0
        return _expm(a * self.A) @ self.z0

    def __call__(self, t: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        t = np.asarray(t, dtype=float)
        a = t[0]
        za = self._state_at(a)
        self._anchor = (a, za)
        offsets = t - a
        cached = self._offsets
        # equal slabs: the same offsets up to the rounding of t0 + dt s - t0 (relative 1e-12
        # of dt at t / dt ~ 1e4); reusing their exponentials errs by |A| times that mismatch
        if (cached is None or cached.shape != offsets.shape
                or np.abs(cached - offsets).max() > 1e-9 * max(offsets[-1], 1e-300)):
            self._E = _expm(offsets[:, None, None] * self.A)
            self._offsets = offsets
        z = self._E @ za
        return z[:, :self.n], z[:, self.n:]


class FirstOrderModes:
    """The eigen-decomposition of the first-order system of M x'' + K x = 0 from the n x n pencil
    K W = M W diag(mu): lambda = +-sqrt(-mu) with the vectors (w, +-lambda w), unit columns
    (as QZ's on the 2n x 2n pencil, at a fraction of its cost)."""

    def __init__(self, mu: np.ndarray, W: np.ndarray):
        self.W, self.rate = W, np.sqrt(-mu.astype(complex))
        V = np.block([[W, W], [W * self.rate, -W * self.rate]])
        self.norms = np.linalg.norm(V, axis=0)
        self.lam, self.V = np.concatenate([self.rate, -self.rate]), V / self.norms

    @classmethod
    def of(cls, mu: np.ndarray, W: np.ndarray) -> Optional["FirstOrderModes"]:
        """None where a mu is near 0 (a rigid motion: a Jordan block of the first-order
        system, no basis) or not finite."""
        size = np.abs(mu)
        if not (len(mu) and np.isfinite(mu).all() and np.isfinite(W).all()) or (
                size.min() <= 1e3 * np.finfo(float).eps * size.max()):
            return None
        return cls(mu, W)

    def coefficients(self, x0: np.ndarray, v0: np.ndarray) -> np.ndarray:
        """c with V c = (x0, v0): n x n solves with W."""
        with np.errstate(all="ignore"):
            a, b = np.linalg.solve(self.W, np.stack([x0, v0], axis=1).astype(complex)).T
        b = b / self.rate
        return np.concatenate([a + b, a - b]) / 2 * self.norms


class EigenFlow:
    """z(t) = V exp(t Lambda) V^-1 z0 with (Lambda, V) from QZ on the first-order pencil
    F z = lambda E z, E = diag(I, M), F = [[0, I], [-K, -D]]: its backward error is relative to
    |K|, |M| and |D|, not to |M^-1 K| as the float64 expm's is (`of_pencil`). `undamped` takes
    them from QZ on the n x n pencil (K, M) instead (a 450-dof square: 1 s where the 2n x 2n
    pencil takes 15 s). c: the start state's coefficients, V c = z0."""

    def __init__(self, lam: np.ndarray, V: np.ndarray, c: np.ndarray):
        self.n = len(c) // 2
        self.lam, self.V, self.c = lam, V, c

    @classmethod
    def of_pencil(cls, pencil: Tuple[np.ndarray, np.ndarray], x0: np.ndarray,
                  v0: np.ndarray) -> "EigenFlow":
        """From QZ on the first-order pencil (F, E) (first_order_pencil)."""
        import scipy.linalg as sla

        lam, V = sla.eig(*pencil)
        return cls(lam, V, np.linalg.solve(V, np.concatenate([x0, v0])))

    @classmethod
    def undamped(cls, M: np.ndarray, K: np.ndarray, x0: np.ndarray,
                 v0: np.ndarray) -> Optional["EigenFlow"]:
        """From QZ on the pencil (K, M) (FirstOrderModes); None where it is no basis."""
        import scipy.linalg as sla

        with np.errstate(all="ignore"):
            modes = FirstOrderModes.of(*sla.eig(K, M))
        if modes is None:
            return None
        return cls(modes.lam, modes.V, modes.coefficients(x0, v0))

    @property
    def condition(self) -> float:
        """cond(V), the smaller of it as computed and with the velocity rows in units of the
        mean frequency sqrt(|lambda|_min |lambda|_max) (the eigenvectors (x, lambda x) of a
        stiff system differ in size by |lambda|: a beam with frequencies 5 to 1.2e6 has
        cond(V) = 2.3e6, 2.2e3 in those units)."""
        plain = float(np.linalg.cond(self.V))
        size = np.abs(self.lam[self.lam != 0])
        if not len(size):
            return plain
        scaled = self.V.copy()
        scaled[self.n:] /= np.sqrt(size.min() * size.max())
        scaled /= np.maximum(np.linalg.norm(scaled, axis=0), 1e-300)
        return min(plain, float(np.linalg.cond(scaled)))

    def __call__(self, t: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        t = np.asarray(t, dtype=float)
        with np.errstate(over="ignore", invalid="ignore"):  # overflow: inf, seen by callers
            growth = np.exp(np.multiply.outer(t, self.lam))
            modes = np.multiply(growth, self.c, out=np.zeros_like(growth), where=self.c != 0)
            z = modes @ self.V.T  # an absent growing mode adds 0, not inf * 0
        return z.real[:, :self.n], z.real[:, self.n:]


class BlockFlow:
    """The motion of an undamped M x'' + K x = 0 in its real modes (fem_dual.modes): x = U r,
    each block of r'' + Kr r = 0 exact on its own. Near a flutter load the two modes about to
    coalesce have nearly parallel eigenvectors (EigenFlow's V ill-conditioned) and the float64
    expm is off by |M^-1 K| eps per unit of time; their joint span is well conditioned, and the
    block's exponential has its own frequency as its norm."""

    def __init__(self, modes: Tuple[np.ndarray, np.ndarray], x0: np.ndarray, v0: np.ndarray):
        from fem_dual.modes import block_slices

        self.U, self.Kr = modes
        self.slices = block_slices(self.Kr)
        self.r0, self.rv0 = np.linalg.solve(self.U, x0), np.linalg.solve(self.U, v0)

    def __call__(self, t: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        from fem_dual.modes import block_motion

        r, rv = block_motion(self.Kr, self.slices, self.r0, self.rv0, np.asarray(t, float))
        return r @ self.U.T, rv @ self.U.T


class SparseFlow:
    """z(t) of M x'' + D x' + K x = 0 with sparse M, K, D (scipy): scipy's expm_multiply on the
    first-order operator, one sparse LU of M, nothing n x n. The velocity is carried in units
    of `omega` (the fastest frequency: y = v / omega), so that the operator's norm is omega, not
    omega^2, and the work of a step of length h grows like omega h. Times are taken in
    increasing order from the last one asked (a call that starts earlier starts again from 0);
    equally spaced times are one expm_multiply."""

    def __init__(self, M, K, D, x0: np.ndarray, v0: np.ndarray, omega: float):
        from scipy.sparse.linalg import LinearOperator, splu

        self.n, n = len(x0), len(x0)
        lu = splu(M.tocsc())
        w = float(omega) if omega > 0 else 1.0
        K, D = K.tocsr(), D.tocsr()
        KT, DT = K.T.tocsr(), D.T.tocsr()

        def matvec(z):
            x, y = z[:n], z[n:]
            return np.concatenate([w * y, -lu.solve(K @ x + w * (D @ y)) / w])

        def rmatvec(z):
            a, b = z[:n], z[n:]
            c = lu.solve(np.ascontiguousarray(b), trans="T") / w
            return np.concatenate([-(KT @ c), w * a - w * (DT @ c)])

        self.A = LinearOperator((2 * n, 2 * n), matvec=matvec, rmatvec=rmatvec, dtype=float)
        self.omega = w
        self.z0 = np.concatenate([x0, v0 / w])
        self._at = (0.0, self.z0)

    def _step(self, z: np.ndarray, h: float) -> np.ndarray:
        from scipy.sparse.linalg import expm_multiply

        return z if h == 0 else expm_multiply(self.A * h, z, traceA=0.0)

    def __call__(self, t: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        from scipy.sparse.linalg import expm_multiply

        t = np.asarray(t, dtype=float)
        gaps = np.diff(t)
        if np.any(gaps < 0):
            raise ValueError("SparseFlow: times must increase within a call")
        a, z = self._at if t[0] >= self._at[0] else (0.0, self.z0)
        z = self._step(z, t[0] - a)
        grid = np.linspace(t[0], t[-1], len(t))
        # equally spaced to a few units in the last place (a slab's vertices): one call
        if len(t) > 2 and np.abs(t - grid).max() <= 4 * np.finfo(float).eps * np.abs(t).max():
            Z = expm_multiply(self.A, z, start=0.0, stop=t[-1] - t[0], num=len(t),
                              endpoint=True, traceA=0.0)
        else:
            Z = [z]
            for h in gaps:
                Z.append(self._step(Z[-1], h))
            Z = np.array(Z)
        self._at = (float(t[-1]), Z[-1])
        return Z[:, :self.n], Z[:, self.n:] * self.omega


def first_order_pencil(M: np.ndarray, K: np.ndarray, D: Optional[np.ndarray] = None):
    """(F, E) with E z' = F z for M x'' + D x' + K x = 0."""
    n = M.shape[0]
    D = np.zeros((n, n)) if D is None else D
    I, Z = np.eye(n), np.zeros((n, n))
    return np.block([[Z, I], [-K, -D]]), np.block([[I, Z], [Z, M]])


def linear_flow(M: np.ndarray, K: np.ndarray, D: Optional[np.ndarray], x0: np.ndarray,
                v0: np.ndarray):
    """The reference of M x'' + D x' + K x = 0: BlockFlow for an undamped system with modes
    about to coalesce, a complex pair, or slow modes that fem_dual.modes refines (EigenFlow is
    2.4e-4 off at Beck's column, 20 elements, P = 20.055; BlockFlow, whose blocks are two-sided
    Rayleigh quotients, within the data floor); else EigenFlow when its eigenvectors are well
    conditioned (EIGEN_MAX_CONDITION); else BlockFlow where the system is undamped; else
    LinearFlow (expm)."""
    from fem_dual.modes import block_slices, refined_blocks

    x0, v0 = np.asarray(x0, float), np.asarray(v0, float)
    modes = None if (D is not None and np.any(D)) else _block_modes(M, K)
    if modes is not None:
        U, Kr = modes
        slices = block_slices(Kr)
        if len(slices) < len(M) or refined_blocks(M, K).any():
            # modes about to coalesce, a complex pair, or slow modes of a stiff system whose
            # K U cancels: QZ's eigenvectors carry that round-off (Beck's column at 20
            # elements, P = 20: 2.4e-6 off where the refined blocks are 8e-10 off)
            return BlockFlow(modes, x0, v0)
    flow = None
    if D is None or not np.any(D):
        flow = EigenFlow.undamped(M, K, x0, v0)
    if flow is None:
        flow = EigenFlow.of_pencil(first_order_pencil(M, K, D), x0, v0)
    if np.isfinite(flow.lam).all() and flow.condition <= EIGEN_MAX_CONDITION:
        return flow
    if modes is not None:
        return BlockFlow(modes, x0, v0)
    return LinearFlow(first_order_matrix(M, K, D), np.asarray(x0), np.asarray(v0))


def _block_modes(M: np.ndarray, K: np.ndarray) -> Optional[Tuple[np.ndarray, np.ndarray]]:
    """(U, Kr) of fem_dual.modes.real_modes, or None where they are incomplete, U is no
    better conditioned than EIGEN_MAX_CONDITION, or they do not reproduce K (modes_hold: a
    defective repeated frequency, whose grouped blocks are not invariant)."""
    from fem_dual.modes import finite_real_modes, modes_hold

    modes = finite_real_modes(M, K)
    if modes is None:
        return None
    if not (np.linalg.cond(modes[0]) <= EIGEN_MAX_CONDITION and modes_hold(M, K)[0]):
        return None
    return modes[0], modes[1]


KINK_STEP = 1e-9  # past a kink, DOP853 goes on without events for this fraction of the horizon


class IVPFlow:
    """DOP853 at rtol = 1e-13 of x' = v, v' = M^-1 F(x), continued chunk by chunk; atol = 1e-16
    (times the start's size where it is below 1) keeps components far below 1 to their own
    digits (a perturbation of 1e-9 growing near an unstable equilibrium at 1e3 was 1.6e-6 off at
    atol = 1e-13, 4e-9 at 1e-16).

    `kinks(x)` (points, kinks), where given: values whose sign changes are kinks of the force
    (its abs), and `branch(signs)` the acceleration on the branch where they have those signs
    (smooth across them). DOP853 then integrates each smooth piece on its branch, stops at the
    next kink as at an event and goes on from there: a step over a kink, or stages evaluated
    across it, lose the order (3.6e-11 off at 1e-13 on a force whose derivative jumps by 100,
    against 1e-12 this way)."""

    def __init__(self, acceleration: Callable[[np.ndarray], np.ndarray], x0: np.ndarray,
                 v0: np.ndarray, rtol: float = 1e-13, atol: float = 1e-16,
                 kinks: Optional[Callable[[np.ndarray], np.ndarray]] = None,
                 branch: Optional[Callable] = None):
        self.n = len(x0)
        self.acc = acceleration
        self.t = 0.0
        self.z = np.concatenate([x0, v0]).astype(float)
        # a motion far below 1 keeps its own digits: atol follows its start's size (a Duffing
        # force from x0 = 1e-8 was 1e-16 off at atol = 1e-16, 55 times fem-dual's error)
        size = float(np.abs(self.z).max(initial=0.0))
        self.rtol, self.atol = rtol, atol * min(1.0, size) if size > 0 else atol
        self.kinks, self.branch = kinks, branch

    def _rhs(self, _t, z):
        return np.concatenate([z[self.n:], self.acc(z[:self.n])])

    def _rhs_on(self, z0: np.ndarray):
        """The right-hand side on the branch the motion at z0 is on (the full force where there
        is no branch to choose, or z0 sits on a kink)."""
        if self.kinks is None or self.branch is None:
            return self._rhs
        signs = np.sign(self.kinks(z0[None, :self.n])[0])
        if not signs.all():
            return self._rhs
        acc, n = self.branch(signs), self.n
        return lambda _t, z: np.concatenate([z[n:], acc(z[:n])])

    def _solve(self, t0: float, z0: np.ndarray, t: np.ndarray):
        """(times reached, states there, status, final state) from (t0, z0) over the times t
        (all after t0), stopping at every kink and going on from there: first a stretch of
        KINK_STEP without events, so that the kink just crossed does not stop it again."""
        from scipy.integrate import solve_ivp  # 0.3 s of imports that linear scenes skip

        done_t, done_z, quiet, was_quiet = [], [], False, False
        while True:
            # a start on a kink: off it quietly first, as after a crossing (then the kinks the
            # motion still sits on are left out of the events)
            quiet = quiet or (not was_quiet and self._on_kink(z0))
            end = min(t0 + KINK_STEP * max(abs(t[-1]), 1.0), t[-1]) if quiet else t[-1]
            want = t[(t > t0) & (t <= end)]
            grid = want if want.size and want[-1] == end else np.append(want, end)
            sol = solve_ivp(self._rhs if quiet else self._rhs_on(z0), (t0, end), z0,
                            method="DOP853", t_eval=grid,
                            rtol=self.rtol, atol=self.atol,
                            events=None if quiet else self._events(z0))
            y = np.asarray(sol.y, dtype=float).reshape(2 * self.n, -1)  # (none may be reached)
            reached = np.asarray(sol.t, dtype=float)
            asked = np.isin(reached, want)  # (solve_ivp returns the times asked, exactly)
            done_t.append(reached[asked]), done_z.append(y.T[asked])
            if sol.status == 1:  # at a kink: on from there, quietly for a moment
                hit = next(i for i, e in enumerate(sol.t_events) if len(e))
                t0, z0 = float(sol.t_events[hit][0]), sol.y_events[hit][0].copy()
                quiet, was_quiet = True, False
                continue
            if sol.status != 0 or end >= t[-1]:  # a failure, or the end
                last = y[:, -1] if sol.status == 0 else z0
                return np.concatenate(done_t), np.concatenate(done_z), sol.status, last
            t0, z0, quiet, was_quiet = end, y[:, -1], False, quiet

    def _on_kink(self, z0: np.ndarray) -> bool:
        """Whether z0 sits exactly on a kink (an argument of abs is 0 there)."""
        return self.kinks is not None and not np.all(self.kinks(z0[None, :self.n])[0])

    def _events(self, z0: np.ndarray):
        """Terminal events at the kinks (None without kinks), but not at those the motion sits
        on at z0: scipy counts a zero as a crossing, so a motion that stays on a kink (at rest
        in it) would stop again at every step."""
        if self.kinks is None:
            return None
        events = []
        for k in np.flatnonzero(self.kinks(z0[None, :self.n])[0]):
            def event(_t, z, k=k):
                return float(self.kinks(z[None, :self.n])[0, k])
            event.terminal = True
            events.append(event)
        return events or None

    def __call__(self, t: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        t = np.asarray(t, dtype=float)
        out = np.empty((len(t), 2 * self.n))
        ahead = t > self.t
        out[~ahead] = self.z  # times at the current point (a slab junction)
        if ahead.any():
            distinct, where = np.unique(t[ahead], return_inverse=True)  # (increasing times)
            times, states, status, last = self._solve(self.t, self.z, distinct)
            if status != 0 or len(times) != len(distinct):
                reached = where < len(times)
                out[ahead] = np.nan
                out[np.flatnonzero(ahead)[reached]] = states[where[reached]]
            else:
                out[ahead] = states[where]
                self.t, self.z = t[-1], last.copy()
        return out[:, :self.n], out[:, self.n:]


def first_order_matrix(M: np.ndarray, K: np.ndarray,
                       D: Optional[np.ndarray] = None) -> np.ndarray:
    """A of z' = A z for M x'' + D x' + K x = 0."""
    n = M.shape[0]
    D = np.zeros((n, n)) if D is None else D
    return np.block([[np.zeros((n, n)), np.eye(n)],
                     [-np.linalg.solve(M, K), -np.linalg.solve(M, D)]])


def linear_reference(M, K, t, x0, v0, D=None) -> Tuple[np.ndarray, np.ndarray]:
    """Exact (x, v) at the times t for M x'' + D x' + K x = 0 (one chunk)."""
    return linear_flow(M, K, D, x0, v0)(t)
