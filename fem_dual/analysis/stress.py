"""`fem-dual stress`: every scene pushed to its stiff and extreme corners, measured against its
independent reference (matrix exponential or DOP853 at rtol = atol = 1e-13).

Each case states what must happen: "converge" (relative error, max |x - x_ref| / max |x_ref|,
at most its tolerance), "stop" (exit 3: a SolveError whose message says what to change), or
"either". It records what did happen: the relative error, the run time, the Newton iterations,
and for linear slabs an estimate of the slab matrix's condition number. A case FAILs when the
outcome is not allowed, above all a wrong answer reported as a success. Slow cases (long
horizons) run with `--slow`.
"""
from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Dict, List, Optional, Sequence

import numpy as np
from mpi4py import MPI

from fem_dual.config import RunConfig
from fem_dual.integrate.api import RunResult, Simulation
from fem_dual.errors import InputError, SolveError
from fem_dual.analysis.flutter import critical_load, eigen_rate, growth_rate
from fem_dual.scenes.column import lowest_mode, scaled_column

__all__ = ["Case", "Row", "CASES", "run_case", "stress", "table"]

EXPECT = ("converge", "stop", "either")


@dataclass
class Attempt:
    """One run of a configuration: its result (partial if it stopped) and what it cost."""

    config: RunConfig
    result: Optional[RunResult]
    failure: Optional[str]
    run_s: float
    condition: Optional[float]

    def relative_error(self) -> Optional[float]:
        r = self.result
        if r is None or len(r.t) == 0 or r.error["x_max"] is None:
            return None
        step = max(1, len(r.t) // 4000)
        x_ref, _ = self.config.scene.reference(self.config.x0, self.config.v0)(r.t[::step])
        return float(r.error["x_max"] / max(np.abs(x_ref).max(), 1e-300))


@dataclass
class Row:
    """One line of the stress table (and of `--json`)."""

    case: str
    scene: str
    expect: str
    expected: str
    status: str  # ok, stopped, FAIL
    rel_error: Optional[float]
    run_s: float
    newton_iterations: Optional[int]
    condition: Optional[float]
    measured: str
    details: Dict[str, Any] = field(default_factory=dict)
    estimate_ratio: Optional[float] = None  # error_estimate / actual error (state max-norm)


Check = Callable[[Attempt, MPI.Comm], "tuple[bool, str, Dict[str, Any]]"]


@dataclass
class Case:
    """A configuration, what must happen to it, and an optional extra check of the motion."""

    name: str
    expected: str
    config: Callable[[], RunConfig]
    expect: str = "converge"
    tol: float = 1e-8
    slow: bool = False
    check: Optional[Check] = None


def attempt(config: RunConfig, comm: MPI.Comm, condition: bool = True) -> Attempt:
    """Run `config`; a SolveError is an outcome here, not an exception."""
    sim = Simulation.for_config(config, comm)
    tic = time.perf_counter()
    failure, result = None, None
    try:
        result = sim.run(config)
    except SolveError as exc:
        failure, result = str(exc), exc.partial
    run_s = time.perf_counter() - tic
    cond = None
    if condition and failure is None and sim.scene.linear:
        cond = sim.backend.condition_estimate()
    sim.close()
    return Attempt(config, result, failure, run_s, cond)


def run_case(case: Case, comm: MPI.Comm = MPI.COMM_WORLD) -> Row:
    """Run one case and judge its outcome (collective; the same Row on every rank)."""
    att = attempt(case.config(), comm)
    rel = att.relative_error()
    r = att.result
    newton = None
    if r is not None and r.solver.get("kind") == "snes":
        newton = int(sum(r.solver["newton_iterations"]))
    details: Dict[str, Any] = {}
    if att.failure is not None:
        advice = "use " in att.failure
        status = "stopped" if (case.expect != "converge" and advice) else "FAIL"
        measured = f"exit 3: {att.failure}"
        finite = r is None or r.error["x_max"] is None or math.isfinite(r.error["x_max"])
        if not finite:
            status = "FAIL"
    else:
        good = rel is not None and rel <= case.tol
        measured = f"relative error {rel:.2e}"
        if case.check is not None and good:
            good, text, details = case.check(att, comm)
            measured += "; " + text
        status = "ok" if (good and case.expect != "stop") else "FAIL"
        if not good and case.expect == "converge":
            measured += f" (tolerance {case.tol:g})"
    ratio = None
    if r is not None:
        details.update(slabs_solved=len(r.slab_lengths),
                       halved=len(r.solver.get("halved_slabs", [])))
        actual = max(r.error["x_max"] or 0.0, r.error["v_max"] or 0.0)
        if r.error_estimate is not None and actual > ESTIMATE_JUDGED_ABOVE * _scale(r):
            ratio = r.error_estimate / actual
            if att.failure is None and ratio < 0.1:  # the tool did not know its own error
                status = "FAIL"
                measured += f"; the estimate missed the error (estimate / actual {ratio:.2g})"
    return Row(case.name, att.config.scene.name, case.expect, case.expected, status, rel,
               att.run_s, newton, att.condition, measured, details, ratio)


ESTIMATE_JUDGED_ABOVE = 1e-10  # relative errors below this are the reference's and round-off's


def _scale(r: RunResult) -> float:
    return max(r.tolerance.get("scale_x", 0.0), r.tolerance.get("scale_v", 0.0), 1e-300)


# -- checks ------------------------------------------------------------------------------------
def _growth_matches(att: Attempt, comm: MPI.Comm):
    """The growth rate of the recovered motion equals the largest real part of the eigenvalues
    (flutter is reproduced, not damped away; a stable motion neither grows nor decays)."""
    r, scene = att.result, att.config.scene
    sigma_e = float(scene.spectrum[0].real.max()) + 0.0  # (no -0 printed)
    step = max(1, att.config.slab_cells)  # slab ends: uniform in time
    sigma_d = growth_rate(r.t[::step], r.x[::step], r.v[::step])
    ok = abs(sigma_d - sigma_e) <= 0.01 * abs(sigma_e) + 1e-7
    return ok, f"growth rate {sigma_d:.6g} (eigenvalues {sigma_e:.6g})", {
        "growth_dual": sigma_d, "growth_eigen": sigma_e}


def _amplitude_phase(att: Attempt, comm: MPI.Comm):
    """Modal amplitude and phase error at the final time, Hamiltonian drift per slab, spurious
    growth or damping per period (from the slab-end states)."""
    r, config = att.result, att.config
    lam, U = config.scene.spectrum
    z_ref = np.concatenate(config.scene.reference(config.x0, config.v0)(r.t[-1:]), axis=1)[0]
    z_num = np.concatenate([r.x[-1], r.v[-1]])
    c_ref, c_num = np.linalg.solve(U, z_ref), np.linalg.solve(U, z_num)
    live = np.abs(c_ref) > 1e-8 * np.abs(c_ref).max()
    ratio = c_num[live] / c_ref[live]
    amplitude = float(np.abs(np.abs(ratio) - 1).max())
    phase = float(np.abs(np.angle(ratio)).max())
    step = max(1, config.slab_cells)
    sigma = growth_rate(r.t[::step], r.x[::step], r.v[::step])
    period = 2 * np.pi / np.abs(lam.imag).min()
    drift = r.hamiltonian["drift"]
    ok = amplitude < 1e-6 and phase < 1e-5 and abs(sigma) * period < 1e-9
    text = (f"amplitude error {amplitude:.1e}, phase error {phase:.1e} rad, growth per period "
            f"{sigma * period:.1e}, H_d drift per slab {drift:.1e}")
    return ok, text, {"amplitude_error": amplitude, "phase_error_rad": phase,
                      "growth_per_period": sigma * period, "hamiltonian_drift": drift,
                      "periods": float(r.t[-1] / period)}


def _versus_identity_weights(att: Attempt, comm: MPI.Comm):
    """The same run with the identity weights A = I, B = M^2, for the conditioning rule."""
    scene = att.config.scene
    plain = dataclasses.replace(att.config, scene=dataclasses.replace(scene, weights="identity"))
    other = attempt(plain, comm)
    rel = other.relative_error()
    text = (f"weights {scene.weighting()}; identity weights: relative error {rel:.1e}, "
            f"condition {other.condition:.1e}")
    return True, text, {"weights": scene.weighting(), "identity_rel_error": rel,
                        "identity_condition": other.condition}


def _versus_start_base(att: Attempt, comm: MPI.Comm):
    """The same run on the old base state (the slab's start held constant, physical
    coordinates): the stiff case must cost what its slow motion needs (at most twice the
    requested slabs), where the old base resolves the fast modes or stops."""
    r = att.result
    requested = att.config.slab_count
    old = attempt(dataclasses.replace(att.config, base="start", coordinates="physical"), comm,
                  condition=False)
    solved = len(r.slab_lengths)
    if old.failure is not None:
        other = "start base: exit 3"
    else:
        other = (f"start base: {len(old.result.slab_lengths)} slabs, relative error "
                 f"{old.relative_error():.1e}")
    text = f"base {att.config.base_state}: {solved} slabs for {requested} asked; {other}"
    return solved <= 2 * requested, text, {"base": att.config.base_state, "slabs_asked": requested,
                                           "start_base_failed": old.failure is not None}


def _scaled_column(links: int, P: float, **kw) -> RunConfig:
    """The scaled column (fem_dual.scenes.column) from its lowest mode."""
    scene = scaled_column(links, P)
    return RunConfig.create(scene, x0=lowest_mode(scene), v0=np.zeros(links), **kw)


# -- the cases ---------------------------------------------------------------------------------
def _ziegler(params=None, **kw) -> RunConfig:
    return RunConfig.create("ziegler", params, **kw)


def _critical_load() -> float:
    from fem_dual.scenes import get_scene

    return critical_load(eigen_rate(get_scene("ziegler")()), 1e-12, rel_width=1e-12)


def _resolved(params: Dict[str, str], T: float, cells: int = 4, degree: int = 4,
              radians_per_cell: float = 0.5) -> RunConfig:
    """Slabs of `cells` cells each such that the fastest mode turns at most radians_per_cell
    per cell (the resolution, not the conditioning, limits stiff cases)."""
    rate = _ziegler(params).scene.fastest_rate()
    slabs = max(1, math.ceil(rate * T / (radians_per_cell * cells)))
    return _ziegler(params, T=T, cells=cells, degree=degree, slabs=slabs)


def _long_horizon(periods: float) -> RunConfig:
    scene = _ziegler().scene
    omega = np.abs(scene.spectrum[0].imag).min()
    T = periods * 2 * np.pi / omega
    return _ziegler(T=T, slabs=math.ceil(T), cells=8, degree=4)


DIVERGENCE_LOAD = 7 / 2 + math.sqrt(2)

CASES: List[Case] = [
    Case("flutter-below", "P = 0.99 P_cr: bounded, growth rate 0, rel. error <= 1e-8",
         lambda: _ziegler({"P": str(0.99 * _critical_load())}, T=100.0, slabs=100, cells=8,
                          degree=4), check=_growth_matches),
    Case("flutter-above", "P = 1.01 P_cr: flutter growth = eigenvalue real part (1%)",
         lambda: _ziegler({"P": str(1.01 * _critical_load())}, T=60.0, slabs=60, cells=8,
                          degree=4), check=_growth_matches),
    Case("divergence", "P = 1.05 (7/2 + sqrt 2): static divergence growth reproduced",
         lambda: _ziegler({"P": str(1.05 * DIVERGENCE_LOAD)}, T=10.0, slabs=20, cells=8,
                          degree=4), check=_growth_matches),
    Case("stiff-c1/c2=1e4", "fast and slow modes (omega 70.7 and 1.0), rel. error <= 1e-6",
         lambda: _resolved({"c1": "1e4"}, T=10.0), tol=1e-6, check=_versus_identity_weights),
    Case("stiff-c1/c2=1e-4", "fast and slow modes (omega 173 and 0.41), rel. error <= 1e-6",
         lambda: _resolved({"c2": "1e4"}, T=10.0), tol=1e-6, check=_versus_identity_weights),
    Case("light-tip-m2/m1=1e-4", "fast and slow modes (omega 70.7 and 0.71), rel. error <= 1e-6",
         lambda: _resolved({"m2": "2e-4"}, T=10.0), tol=1e-6, check=_versus_identity_weights),
    Case("long-horizon-100-periods", "no spurious growth or damping, phase error <= 1e-5 rad",
         lambda: _long_horizon(100), check=_amplitude_phase),
    Case("long-horizon-1e4-periods", "no spurious growth or damping, phase error <= 1e-5 rad",
         lambda: _long_horizon(1e4), tol=1e-6, slow=True, check=_amplitude_phase),
    Case("round-off-floor", "Ziegler T = 10, p = 4, 3200 cells: max error <= 1e-11 "
         "(rel. 1e-10)",
         lambda: _ziegler(T=10.0, cells=3200, degree=4), tol=1e-10),
    Case("tiny-T-ziegler", "T = 1e-6: converges (rel. error <= 1e-8)",
         lambda: _ziegler(T=1e-6, v0="1,1")),
    Case("tiny-T-curl3d", "T = 1e-6: converges", lambda: RunConfig.create(
        "curl3d", T=1e-6, v0="1,1,1", cells=10, degree=3)),
    Case("tiny-T-curl2d", "T = 1e-6: converges", lambda: RunConfig.create(
        "curl2d", T=1e-6, v0="1,1", cells=10, degree=3)),
    Case("huge-T-one-slab", "T = 1e6 in one slab of 100 cells: exit 3, under-resolved",
         lambda: _ziegler(T=1e6), expect="stop"),
    Case("huge-T-1e4-slabs", "T = 1e4 in 1e4 slabs: converges (rel. error <= 1e-6)",
         lambda: _ziegler(T=1e4, slabs=10_000, cells=8, degree=4), tol=1e-6),
    Case("huge-T-1e5-slabs", "T = 1e5 in 1e5 slabs: converges (rel. error <= 1e-6)",
         lambda: _ziegler(T=1e5, slabs=100_000, cells=8, degree=4), tol=1e-6, slow=True),
] + [
    Case(f"ziegler-A={value}", f"H weight A = {value} I (B = M^2): converges (rel. error <= "
         f"{tol:g}; the accuracy floor grows with the imbalance)", (lambda value=value: _ziegler(
             {"A": value}, T=10.0, slabs=20, cells=8, degree=4)), tol=tol)
    for value, tol in (("1e-6", 1e-6), ("1e-3", 1e-9), ("1e3", 1e-9), ("1e6", 1e-6))
] + [
    Case(f"curl3d-{name}={value}", f"{name} = {value}: converges (rel. error <= {tol:g}; "
         "alpha / beta = 1e12 costs accuracy, as the weights of ziegler-A do)",
         (lambda name=name, value=value: RunConfig.create(
             "curl3d", {name: value}, cells=20, degree=3)), tol=tol)
    for name, value, tol in (("alpha", "1e-6", 1e-8), ("alpha", "1e6", 1e-7),
                             ("beta", "1e-6", 1e-7), ("beta", "1e6", 1e-8))
] + [
    Case(f"curl2d-{name}={value}", f"{name} = {value}: converges or exit 3 with advice",
         (lambda name=name, value=value: RunConfig.create(
             "curl2d", {name: value}, cells=20, degree=3, slabs=4)), expect="either")
    for name in ("alpha", "beta") for value in ("1e-6", "1e6")
] + [
    Case("curl2d-k=100", "large k (fast, nearly singular DtP): converges (rel. error <= 1e-5)",
         lambda: RunConfig.create("curl2d", {"k": "100"}, T=1.0, cells=20, degree=3, slabs=8),
         tol=1e-5),
    Case("curl2d-k=1000", "k = 1000: converges or exit 3 naming the singular DtP map",
         lambda: RunConfig.create("curl2d", {"k": "1000"}, T=2.0, cells=20, degree=3,
                                  slabs=4), expect="either", tol=1e-4),
    Case("curl2d-near-singular-DtP", "alpha = 1e-3, k = 10: converges or exit 3 with advice",
         lambda: RunConfig.create("curl2d", {"k": "10", "alpha": "1e-3"}, T=2.0, cells=20,
                                  degree=3, slabs=4), expect="either", tol=1e-6),
    Case("curl3d-T=9", "near blow-up: converges (rel. error <= 1e-6)",
         lambda: RunConfig.create("curl3d", T=9.0, cells=20, degree=4, slabs=90), tol=1e-6),
    Case("curl3d-T=9.5", "at blow-up: exit 3 with advice",
         lambda: RunConfig.create("curl3d", T=9.5, cells=20, degree=4, slabs=95), expect="stop"),
] + [  # wrong answers that must never pass as ok, at the user's settings
    Case("unstable-P=3-defaults", "P = 3 (flutter) at the default one slab: converges by "
         "shorter slabs or stops (never a wrong answer reported as ok)",
         lambda: _ziegler({"P": "3"}), expect="either", tol=1e-3),
    Case("unstable-P=3-no-halving", "the same without halvings: exit 3, cannot vouch",
         lambda: _ziegler({"P": "3"}, max_halvings=0), expect="stop"),
    Case("coarse-one-slab-T=100", "T = 100 in one slab of 50 cells (3 rad per cell): converges "
         "or stops (never a wrong answer reported as ok)",
         lambda: _ziegler(T=100.0, cells=50, degree=4), expect="either", tol=1e-3),
    Case("newton-stall-curl3d-T=9", "curl3d T = 9, 45 slabs: the stalled Newton's spurious "
         "solution is retried (never a wrong answer reported as ok)", lambda: RunConfig.create(
             "curl3d", T=9.0, slabs=45, cells=16, degree=3), tol=1e-6),
    Case("lifted-saddle-k=100", "curl2d-lifted k = 100, 8 slabs: converges or stops (never a "
         "wrong answer reported as ok)", lambda: RunConfig.create(
             "curl2d-lifted", {"k": "100"}, T=1.0, slabs=8, cells=20, degree=3),
         expect="either", tol=1e-5),
    Case("tiny-masses-1e-12", "masses 1e-12, T = 1e-4: converges or stops (never a wrong "
         "answer reported as ok)",
         lambda: _ziegler({"m1": "1e-12", "m2": "1e-12"}, T=1e-4, cells=50, degree=4,
                          slabs=10), expect="either", tol=1e-3),
    Case("pc-none-preonly", "pc_type = none with preonly: exit 3 (the true residual is "
         "checked)", lambda: _ziegler(petsc={"pc_type": "none"}), expect="stop"),
    Case("pc-jacobi-preonly", "pc_type = jacobi with preonly: exit 3",
         lambda: _ziegler(petsc={"pc_type": "jacobi"}), expect="stop"),
    Case("curl3d-T=8-coarse", "curl3d T = 8, one slab of 2 cells: converges or stops (never a "
         "wrong answer reported as ok)", lambda: RunConfig.create("curl3d", T=8.0, cells=2,
                                                                  degree=4),
         expect="either", tol=1e-3),
    Case("rtol-unstable-P=3", "--rtol 1e-7 on the flutter motion: within the tolerance",
         lambda: _ziegler({"P": "3"}, rtol=1e-7, cells=4, degree=4), tol=1e-7),
    Case("rtol-curl3d-T=8", "--rtol 1e-8, curl3d T = 8 (near blow-up): within the tolerance",
         lambda: RunConfig.create("curl3d", T=8.0, rtol=1e-8, cells=4, degree=4), tol=1e-8),
    Case("rtol-stiff-c1=1e4", "--rtol 1e-8, fast and slow modes: within the tolerance",
         lambda: _ziegler({"c1": "1e4"}, T=10.0, rtol=1e-8, cells=4, degree=4), tol=1e-8),
] + [  # stiff systems at the cost of their slow motion
    Case("stiff-two-modes-omega=1e3", "omega 1 and 1e3 (shear-coupled), 20 slabs of one P4 "
         "cell: converges (rel. error <= 1e-7) at the slow mode's cost",
         lambda: RunConfig.create("linear", {"dofs": "2", "M": "1,-1,-1,2",
                                             "K": "1,-1,-1,1000001"}, T=10.0, slabs=20,
                                  cells=1, degree=4, x0="1,0", v0="0,0"),
         tol=1e-7, check=_versus_start_base),
    Case("stiff-column-40-links", "40-link follower column (P = 9.5), 20 slabs (the fastest "
         "mode turns 1e3 rad per cell): converges (rel. error <= 1e-6)",
         lambda: _scaled_column(40, 9.5, T=2.5, slabs=20, cells=4, degree=4), tol=1e-6,
         slow=True, check=_versus_start_base),
    Case("stiff-curl3d-spring=1e6", "curl force on a stiff spring (omega = 1e3 in z), slow start, "
         "50 slabs: converges (rel. error <= 1e-8) at the slow motion's cost",
         lambda: RunConfig.create("curl3d", {"K": "0,0,0,0,0,0,0,0,1e6"}, T=10.0, slabs=50,
                                  cells=2, degree=4, x0="0.3,0.2,-6e-8"),
         tol=1e-8, check=_versus_start_base),
]


def stress(names: Optional[Sequence[str]] = None, slow: bool = False,
           comm: MPI.Comm = MPI.COMM_WORLD) -> List[Row]:
    """Run the named cases (default: all fast ones, and the slow ones too with `slow`)."""
    known = {c.name: c for c in CASES}
    for name in names or ():
        if name not in known:
            raise InputError(f"unknown stress case {name!r} (known: {', '.join(known)})")
    chosen = [known[n] for n in names] if names else [c for c in CASES if slow or not c.slow]
    return [run_case(case, comm) for case in chosen]


def table(rows: Sequence[Row]) -> str:
    def num(value, fmt):
        width = int(fmt.split(".")[0].rstrip("de") or 0)
        return "-".rjust(width) if value is None else format(value, fmt)

    head = (f"{'case':28s} {'status':8s} {'rel.err':>9s} {'est/err':>7s} {'time s':>8s} "
            f"{'newton':>6s} {'cond':>8s}  measured")
    lines = [head, "-" * len(head)]
    for r in rows:
        lines.append(f"{r.case:28s} {r.status:8s} {num(r.rel_error, '9.2e')} "
                     f"{num(r.estimate_ratio, '7.2f')} {r.run_s:8.3f} "
                     f"{num(r.newton_iterations, '6d')} {num(r.condition, '8.1e')}  "
                     f"{r.measured}")
    return "\n".join(lines)
