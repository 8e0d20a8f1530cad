"""`fem-dual flutter beck`: the flutter load of a continuum found two ways, and (with --out) its
two slowest mode shapes and the flutter motion as XDMF for ParaView.

(a) eigen: :func:`fem_dual.continua.flutter.flutter_load` on the condensed column (dense
    eigenvalues in flexibility form).
(b) dual: at each trial load P the column starts in the span of its two slowest modes at P (the
    sum of the two modal coordinates, at rest; the modes of fem_dual.slab.modal, the coordinates
    the slabs are solved in) and moves for T. The motion is read in those two coordinates (rows
    of U^-1: exact for a motion in their span) and :func:`fem_dual.analysis.flutter.fit_growth`
    fits its one-step map. The whole state cannot be fitted: the fast modes of a stiff
    continuum stay at rest, so the motion does not determine their part of the map.

    The dual bracket starts around the eigenvalue load (1.3 SPREAD below, 0.7 SPREAD above: no
    bisection point is the eigenvalue load itself) and widens until a dual simulation finds its
    lower end stable and its upper end growing; then it is bisected to REL_WIDTH on the dual
    simulations alone. Starting there saves the scan up from P = 0
    (about 25 runs instead of 14 for Beck's column); what decides is the simulated motion.

A load counts as growing when the fitted rate exceeds its uncertainty by DUAL_REL_TOL of the
fastest fitted frequency at P = 0, as for particle systems.
"""
from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path
from typing import Dict, Optional

import numpy as np
from mpi4py import MPI

from fem_dual.analysis.flutter import DUAL_REL_TOL, GrowthFit, bisect, fit_growth
from fem_dual.config import RunConfig
from fem_dual.errors import InputError, SolveError
from fem_dual.inputs import output_path
from fem_dual.integrate.api import run

__all__ = ["continuum_flutter", "slow_modes", "SPREAD", "REL_WIDTH"]

SPREAD = 0.01  # the first dual bracket: the eigenvalue load - 1.3 and + 0.7 times this, relative
REL_WIDTH = 1e-5  # the dual bracket is bisected to this width, relative
MODES = 2  # the slow modes the motion starts in and is read in


def slow_modes(scene) -> tuple:
    """(X (n, MODES), W (MODES, n)): the slowest modal coordinates of a linear scene (columns of
    U) and the rows of U^-1 that read them from a state."""
    from fem_dual.slab.modal import ModalBasis

    basis = ModalBasis(scene)
    return basis.U[:, :MODES], basis.Uinv[:MODES]


class DualFits:
    """P -> the growth fit of the dual simulation under load P, read in its slow modes (each P
    solved once, rank 0 fits, every rank gets the fit)."""

    def __init__(self, base: RunConfig, comm: MPI.Comm):
        self.base, self.comm = base, comm
        self.cache: Dict[float, GrowthFit] = {}

    def config(self, P: float, out: Optional[Path] = None) -> RunConfig:
        scene = replace(self.base.scene, P=P).checked()
        X, _ = slow_modes(scene)
        x0 = X.sum(axis=1)
        x0 = 0.01 * scene.L * x0 / np.abs(x0).max()  # a tip deflection of 1 % of the length
        return replace(self.base, scene=scene, x0=x0, v0=np.zeros_like(x0), out=out)

    def __call__(self, P: float) -> GrowthFit:
        if P not in self.cache:
            config = self.config(P)
            try:
                result = run(config, self.comm)
            except SolveError as exc:
                raise SolveError(f"the dual simulation at P = {P:.6g} failed: {exc}",
                                 slab=exc.slab) from exc
            fit = None
            if self.comm.rank == 0:
                _, W = slow_modes(config.scene)
                error = result.error_estimate * float(np.abs(W).sum(axis=1).max())
                fit = fit_growth(result.t, np.asarray(result.x) @ W.T,
                                 np.asarray(result.v) @ W.T, error)
            self.cache[P] = self.comm.bcast(fit, root=0)
        return self.cache[P]


def _eigen(scene) -> tuple:
    from fem_dual.continua.flutter import beck_eigenvalues, flutter_load

    found = flutter_load(lambda P: beck_eigenvalues(scene.condensed, P), step=2.0, P_max=1e3)
    if found.kind != "flutter":
        raise SolveError(f"the eigenvalues of {scene.name} diverge (an eigenvalue crosses 0 at "
                         f"P = {found.load:.6g}) before they flutter")
    return found


def continuum_flutter(base: RunConfig, comm: MPI.Comm = MPI.COMM_WORLD,
                      out: Optional[Path] = None) -> Dict[str, object]:
    """{eigen, dual, eigen_s, dual_s, dual_tol, omega2, dual_bracket, runs, elements, files}:
    the two loads, the seconds each search took, the growth threshold, the flutter frequency
    squared from the eigenvalues, the dual bracket and how many dual simulations it took.
    With `out`: the two slowest mode shapes just below the eigenvalue load and the dual
    simulation at the upper end of the bracket (the flutter motion) as XDMF.

    SolveError when a dual simulation fails or cannot decide (exit 3)."""
    scene = base.scene
    if not hasattr(scene, "condensed"):
        raise InputError(f"flutter {scene.name}: the continuum has no follower load P")
    if out is not None:  # before the search, not after it
        out = _directory(out, comm)
    tic = time.perf_counter()
    found = _eigen(scene)
    eigen, eigen_s = found.load, time.perf_counter() - tic

    tic = time.perf_counter()
    fits = DualFits(base, comm)
    zero = fits(0.0)
    if not zero.resolved:
        raise SolveError(f"the dual simulation cannot resolve growth at P = 0 (fitted rate "
                         f"{zero.rate:.3g} +- {zero.noise:.3g} over T = {base.T:.3g}): use a "
                         "longer --T, or more --cells or --slabs, or a higher --degree")
    tol = DUAL_REL_TOL * zero.frequency

    def grows(P: float) -> bool:
        fit = fits(P)
        if fit.lower > tol:
            return True
        if not fit.resolved:
            raise SolveError(f"the dual simulation at P = {P:.6g} cannot resolve growth: fitted "
                             f"rate {fit.rate:.3g} +- {fit.noise:.3g} over T = {base.T:.3g}; "
                             "use a longer --T, or more --cells or --slabs, or a higher --degree")
        return False

    if grows(0.0):
        raise SolveError(f"the dual simulation grows without load (rate {zero.rate:.3g} +- "
                         f"{zero.noise:.3g}) where the eigenvalues do not: under-resolved")
    lo, hi = bisect(grows, *_bracket(grows, eigen), REL_WIDTH)
    dual_s = time.perf_counter() - tic
    files = _write(fits, scene, found.bracket[0], hi, out, comm) if out is not None else []
    return {"eigen": eigen, "dual": 0.5 * (lo + hi), "eigen_s": eigen_s, "dual_s": dual_s,
            "dual_tol": tol, "omega2": found.omega2, "dual_bracket": [lo, hi],
            "runs": len(fits.cache), "elements": int(scene.elements), "files": files}


def _directory(out, comm: MPI.Comm) -> Path:
    """`out` made a directory (rank 0), or InputError naming it."""
    out = output_path(out)
    problem = None
    if comm.rank == 0:
        try:
            out.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            problem = f"--out {out} cannot be a directory: {exc.strerror}"
    problem = comm.bcast(problem, root=0)
    if problem:
        raise InputError(problem)
    return out


def _bracket(grows, eigen: float) -> tuple:
    """(lo, hi): lo stable, hi growing by dual simulations, from eigen (1 - 1.3 SPREAD, 1 + 0.7
    SPREAD), the width doubling on the side that did not hold."""
    width = SPREAD * eigen
    # (not centred on eigen: the first bisection point would be the eigenvalue load itself)
    lo, hi = eigen - 1.3 * width, eigen + 0.7 * width
    while lo > 0 and grows(lo):
        hi, lo, width = lo, max(lo - 2 * width, 0.0), 2 * width
    while not grows(hi):
        if hi > 100 * eigen:
            raise SolveError(f"the dual simulations find no growth up to P = {hi:.6g}, where "
                             f"the eigenvalues flutter at {eigen:.6g}")
        lo, hi, width = hi, hi + 2 * width, 2 * width
    return lo, hi


def _write(fits: DualFits, scene, below: float, above: float, out: Path,
           comm: MPI.Comm) -> list:
    """`<scene>_modes.xdmf` (the two slowest modes at `below`, unit tip deflection, velocity
    omega times the shape; step k = mode k) and the dual simulation at `above` with its usual
    output files."""
    from fem_dual.output import XdmfSeries
    from fem_dual.slab.modal import ModalBasis

    loaded = replace(scene, P=below).checked()
    if comm.rank == 0:
        basis = ModalBasis(loaded)
        shapes = basis.U[:, :MODES].T
        shapes = shapes / np.abs(shapes).max(axis=1, keepdims=True)
        fields = loaded.vertex_fields(shapes, shapes * basis.omega[:MODES, None])
        points, cells = loaded.vertex_mesh()
        series = XdmfSeries(out / f"{scene.name}_modes.xdmf", points,
                            {k: a.shape[1:] for k, a in fields.items()}, {},
                            {"P": below}, cells)
        for k in range(MODES):
            series.write(float(k + 1), {name: a[k] for name, a in fields.items()}, {})
        series.close()
    comm.barrier()
    result = run(fits.config(above, out), comm)
    return [str(out / f"{scene.name}_modes.xdmf")] + list(result.output_files)
