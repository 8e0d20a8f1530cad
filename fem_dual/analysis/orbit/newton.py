"""Newton on the bordered, periodic dual problem of an orbit: the bordered second variation with
the periodic dofs merged, solved by sparse LU, its steps cut where the DtP map has no image."""
from __future__ import annotations

import warnings
from typing import Any, Dict, List, Tuple

import numpy as np
from dolfinx import fem
from scipy import sparse
from scipy.sparse import linalg as spla

from fem_dual.compat import destroy_petsc
from fem_dual.errors import SolveError
from fem_dual.analysis.floquet import stop_if_asked
from fem_dual.analysis.orbit.advice import _orbit_advice
from fem_dual.analysis.orbit.problem import OrbitProblem

__all__ = ["OrbitSolver", "NEWTON_MAX_IT", "STEP_CUTS", "NEWTON_TOL", "NEWTON_STAGNATION"]

NEWTON_MAX_IT = 30
STEP_CUTS = 10  # a Newton step whose end has no DtP image is halved at most this often
NEWTON_TOL = 1e-12  # Newton step: relative change of the orbit's vertex states and period
NEWTON_STAGNATION = 1e-9  # ... or below this, a step no longer 4x smaller than the last


class OrbitSolver:
    """Newton on the bordered, periodic dual problem of an OrbitProblem."""

    def __init__(self, problem: OrbitProblem):
        self.p = problem
        self.A = fem.petsc.create_matrix(problem.forms["J"])
        self.vecs = {k: fem.petsc.create_vector(problem.forms[k])
                     for k in ("R", "R_T", "R_mu", "R_E") if k in problem.forms}
        self.target_energy = 0.0  # mode "energy"

    def close(self) -> None:
        destroy_petsc(self.A, *self.vecs.values())
        self.p.close()

    def _vector(self, name: str) -> np.ndarray:
        vec = self.vecs[name]
        with vec.localForm() as local:
            local.set(0.0)
        fem.petsc.assemble_vector(vec, self.p.forms[name])
        return vec.array_r.copy()

    def _scalar(self, name: str) -> float:
        return float(fem.assemble_scalar(self.p.forms[name]))

    def _matrix(self) -> sparse.csr_matrix:
        self.A.zeroEntries()
        fem.petsc.assemble_matrix(self.A, self.p.forms["J"])
        self.A.assemble()
        indptr, indices, data = self.A.getValuesCSR()
        return sparse.csr_matrix((data, indices, indptr), shape=self.A.getSize())

    def _update_dtp(self) -> None:
        pointwise = self.p.pointwise
        if pointwise is not None:
            message = pointwise.solve(self.p.comm)
            if message:
                raise SolveError(_orbit_advice(message))

    def system(self, mode: str):
        """(H, g): the bordered Hessian and gradient in the unknowns of `mode`."""
        self._update_dtp()
        P = self.p._periodic
        J = (P.T @ self._matrix() @ P).tocsr()
        R = P.T @ self._vector("R")
        cols = {"T": P.T @ self._vector("R_T"), "mu": P.T @ self._vector("R_mu")}
        names = ["mu"] if mode == "period" else ["T", "mu"]
        rows = [sparse.csr_matrix(cols[a][None, :]) for a in names]
        corner = np.array([[self._scalar(f"S_{a}{b}") for b in names] for a in names])
        grad = [self._scalar(f"S_{a}") for a in names]
        if mode == "energy":  # the row of T: the energy, not the action's stationarity in T
            rows[0] = sparse.csr_matrix((P.T @ self._vector("R_E"))[None, :])
            corner[0] = [self._scalar(f"E_{b}") for b in names]
            grad[0] = self._scalar("E") - self.target_energy
        H = sparse.bmat([[J, sparse.csr_matrix(np.column_stack([cols[a] for a in names]))],
                         [sparse.vstack(rows), sparse.csr_matrix(corner)]], format="csc")
        return H, np.concatenate([R, grad]), names

    def solve(self, mode: str) -> Dict[str, Any]:
        """Newton from the current state; returns its history. Raises SolveError."""
        p = self.p
        steps: List[float] = []
        residuals: List[float] = []
        self._update_dtp()
        z_last = np.hstack(self.orbit_vertices()[1:])
        for it in range(NEWTON_MAX_IT):
            stop_if_asked("the orbit's Newton")
            H, g, names = self.system(mode)
            residuals.append(float(np.abs(g).max()))
            if not np.isfinite(g).all():
                raise SolveError("the orbit's Newton met a non-finite residual; give a better "
                                 "guess (--period, --x0, --v0)")
            try:
                with np.errstate(all="raise"), warnings.catch_warnings():
                    warnings.simplefilter("error", spla.MatrixRankWarning)
                    # a symmetric-pattern ordering keeps the banded periodic system and its
                    # border sparse (COLAMD, spsolve's: 3.7 s and 30x the fill at 512 cells;
                    # this: 0.03 s)
                    delta = spla.splu(H, permc_spec="MMD_AT_PLUS_A").solve(-g)
            except (RuntimeError, FloatingPointError, spla.MatrixRankWarning) as exc:
                raise SolveError(f"the orbit's Newton system is singular ({exc}); the orbit is "
                                 "not isolated in this mode, or the guess is too far") from exc
            if not np.isfinite(delta).all():
                raise SolveError("the orbit's Newton system is singular; the orbit is not "
                                 "isolated in this mode, or the guess is too far")
            T = float(p.T_c.value)
            delta = self._step(delta, names)
            k = len(names)
            if not float(p.T_c.value) > 0:
                raise SolveError(f"the period went to {float(p.T_c.value):.6g} in Newton; give a "
                                 "better guess (--period)")
            z = np.hstack(self.orbit_vertices()[1:])
            scale = float(np.abs(z).max())
            if not np.isfinite(z).all() or not scale > 0:
                raise SolveError("the orbit's Newton left the orbit (a non-finite or zero "
                                 "state); give a better guess (--period, --x0, --v0)")
            # the step: how far the orbit (its vertex states) and the period moved
            step = max(float(np.abs(z - z_last).max()) / scale,
                       abs(delta[-k]) / T if "T" in names else 0.0)
            z_last = z
            # converged: a step at the tolerance, or steps that stopped shrinking (round-off)
            stagnant = bool(steps) and step > 0.25 * steps[-1] and step <= NEWTON_STAGNATION
            steps.append(step)
            if step <= NEWTON_TOL or stagnant:
                self._update_dtp()
                return {"iterations": it + 1, "steps": steps, "residuals": residuals}
        raise SolveError(f"the orbit's Newton did not converge in {NEWTON_MAX_IT} iterations "
                         f"(last relative step {steps[-1]:.3g}); give a better guess (--period, "
                         "--x0, --v0)")

    def _step(self, delta: np.ndarray, names: List[str]) -> np.ndarray:
        """Take the Newton step `delta` (merged dual dofs, then the unknowns `names`), halved
        while the DtP map has no solution at its end (at most STEP_CUTS times); returns the step
        taken. Raises SolveError when no cut helps."""
        p, k = self.p, len(names)
        targets = [p.T_c if name == "T" else p.mu_c for name in names]
        w0, values0 = p.w.x.array.copy(), [float(c.value) for c in targets]
        for cut in range(STEP_CUTS + 1):
            taken = delta * 0.5 ** cut
            p.w.x.array[:] = w0 + p._periodic @ taken[:-k]
            for target, value, d in zip(targets, values0, taken[-k:]):
                target.value = value + d
            try:
                self._update_dtp()
                return taken
            except SolveError:
                if cut == STEP_CUTS:
                    p.w.x.array[:] = w0
                    for target, value in zip(targets, values0):
                        target.value = value
                    self._update_dtp()
                    raise

    def orbit_vertices(self) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(s, x, v) at the vertices from s = 0 to 1 (the momenta of the cells, averaged)."""
        p, n = self.p, self.p.n
        ends = p.momenta()  # (cells, 2, 2n)
        msh = p.mesh.msh
        cells = msh.topology.index_map(1).size_local
        vertices = msh.geometry.dofmap.array.reshape(-1, 2)[:cells]
        s_cells = msh.geometry.x[vertices, 0]
        s = np.unique(s_cells.round(15))
        index = np.searchsorted(s, s_cells.round(15))
        sums = np.zeros((len(s), 2 * n))
        counts = np.zeros(len(s))
        np.add.at(sums, index.ravel(), ends.reshape(-1, 2 * n))
        np.add.at(counts, index.ravel(), 1.0)
        sums[0] += sums[-1]  # periodic: s = 0 and s = 1 are one point
        counts[0] += counts[-1]
        sums[-1], counts[-1] = sums[0], counts[0]
        z = sums / counts[:, None]
        M = p.c["M"].value
        v = np.linalg.solve(M, z[:, n:].T).T
        return s, z[:, :n], v
