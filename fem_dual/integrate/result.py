"""What a run computed: `RunResult` (the JSON object of `fem-dual run --json`), its dense output
at any time, and the state at the --t-eval times with its error estimate."""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import numpy as np

from fem_dual import faults
from fem_dual.config import RunConfig
from fem_dual.errors import InputError, SolveError
from fem_dual.integrate.dense import hermite_at, hermite_estimate

__all__ = ["RunResult", "t_eval_output", "unvouched_output"]


@dataclass
class RunResult:
    """What a run computed (the JSON object of `fem-dual run --json`)."""

    scene: str
    parameters: Dict[str, Any]
    T: float
    cells: int
    degree: int
    slabs: int
    x0: List[float]
    v0: List[float]
    dofs_per_slab: int
    t: np.ndarray
    x: np.ndarray
    v: np.ndarray
    error: Dict[str, float]
    hamiltonian: Dict[str, Any]
    timings: Dict[str, float]
    solver: Dict[str, Any]
    slab_lengths: List[float]
    status: str = "ok"
    message: str = ""
    output_files: List[str] = field(default_factory=list)
    staging: Dict[str, Any] = field(default_factory=dict)
    recovery: str = "momentum"
    error_estimate: Optional[float] = None
    estimate: Dict[str, Any] = field(default_factory=dict)
    tolerance: Dict[str, Any] = field(default_factory=dict)
    t_eval: Optional[Dict[str, Any]] = None
    output_slabs: Optional[int] = None  # slabs the --out files hold (None: no --out)
    scene_object: Any = field(default=None, repr=False, compare=False)
    estimate_at_t: Optional[np.ndarray] = field(default=None, repr=False, compare=False)
    error_at_t: Optional[np.ndarray] = field(default=None, repr=False, compare=False)

    def at(self, times) -> Tuple[np.ndarray, np.ndarray]:
        """(x, v) at any times within the computed part of [0, T], by quintic Hermite
        interpolation with the equation of motion at the vertices (fem_dual.integrate.dense)."""
        times = np.atleast_1d(np.asarray(times, dtype=float))
        if len(times) == 0:
            n = self.x.shape[1]
            return np.zeros((0, n)), np.zeros((0, n))
        if not np.isfinite(times).all():
            raise InputError("times must be finite numbers")
        if len(self.t) < 2 or times.min() < self.t[0] or times.max() > self.t[-1]:
            span = f"[{self.t[0]:g}, {self.t[-1]:g}]" if len(self.t) else "nothing"
            raise InputError(f"times outside the computed part of the motion ({span})")
        return hermite_at(self.scene_object, self.t, self.x, self.v, times)

    def write_csv(self, path) -> None:
        """Columns t, x1..xn, v1..vn at the output times."""
        n = self.x.shape[1] if self.x.ndim == 2 else 0
        head = ",".join(["t"] + [f"x{i + 1}" for i in range(n)] + [f"v{i + 1}" for i in range(n)])
        rows = np.column_stack([self.t, self.x, self.v])
        path = Path(path)
        if path.exists() and not path.is_file():  # a device or a pipe: write into it
            np.savetxt(path, rows, delimiter=",", header=head, comments="", fmt="%.17g")
            return
        tmp = path.with_name(f".{path.name}.tmp")  # complete or absent: a full disk left a
        try:  # file cut mid-number that parsed as a row
            np.savetxt(tmp, rows, delimiter=",", header=head, comments="", fmt="%.17g")
            os.replace(tmp, path)
        finally:
            if tmp.exists():
                tmp.unlink()

    @property
    def final(self) -> Dict[str, List[float]]:
        if len(self.t) == 0:
            return {"t": None, "x": None, "v": None}
        return {"t": float(self.t[-1]), "x": self.x[-1].tolist(), "v": self.v[-1].tolist()}

    def write_json(self, stream, chunk: int = 4096) -> None:
        """Write `to_dict()` as one JSON object, streaming the vertex arrays in chunks of rows so
        that long runs never hold their JSON text in memory."""
        with faults.signals_deferred():
            self._write_json(stream, chunk)
            stream.flush()

    def _write_json(self, stream, chunk: int) -> None:
        head = null_where_not_finite(self.to_dict(arrays=False))
        stream.write(json.dumps(head, allow_nan=False)[:-1])
        for name in ("t", "x", "v"):
            values = getattr(self, name)
            stream.write(f', "{name}": [')
            for start in range(0, len(values), chunk):
                if start:
                    stream.write(", ")
                stream.write(json.dumps(values[start:start + chunk].tolist(),
                                        allow_nan=False)[1:-1])
            stream.write("]")
        stream.write("}\n")

    def to_dict(self, arrays: bool = True) -> Dict[str, Any]:
        out = {
            "scene": self.scene, "parameters": self.parameters, "T": self.T, "cells": self.cells,
            "degree": self.degree, "slabs": self.slabs, "x0": self.x0, "v0": self.v0,
            "status": self.status, "message": self.message,
            "dofs_per_slab": self.dofs_per_slab, "slab_lengths": self.slab_lengths,
            "final": self.final, "error": self.error, "hamiltonian": self.hamiltonian,
            "solver": self.solver, "timings": self.timings, "output_files": self.output_files,
            "staging": self.staging, "recovery": self.recovery,
            "error_estimate": self.error_estimate, "estimate": self.estimate,
            "tolerance": self.tolerance, "t_eval": self.t_eval,
            "output_slabs": self.output_slabs,
        }
        if arrays:
            out.update(t=self.t.tolist(), x=self.x.tolist(), v=self.v.tolist())
        return out


def null_where_not_finite(value):
    """`value` (JSON-like) with every float that is not finite replaced by None: the residual
    history of a failed Newton can hold inf, which JSON has no number for (the vertex arrays
    are finite: a run keeps only the slabs it accepted)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: null_where_not_finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [null_where_not_finite(v) for v in value]
    return value


def t_eval_output(result: RunResult, config: RunConfig) -> Dict[str, Any]:
    """The state at config.t_eval (those within the computed part), and its error against the
    reference when there is one; the same on every rank."""
    times = config.t_eval
    done = times[times <= (result.t[-1] if len(result.t) else -1.0)]
    out: Dict[str, Any] = {"t": done.tolist(), "x": [], "v": [], "error": None,
                           "error_estimate": None, "omitted": int(len(times) - len(done))}
    if len(done) == 0 or len(result.t) < 2:
        return out
    x, v, interpolation = hermite_estimate(config.scene, result.t, result.x, result.v, done)
    if result.estimate_at_t is not None:  # the vertex estimate on both sides, plus the Hermite's
        k = np.clip(np.searchsorted(result.t, done, side="right") - 1, 0, len(result.t) - 2)
        vertex = np.maximum(result.estimate_at_t[k], result.estimate_at_t[k + 1])
        estimate = vertex + interpolation
        out["error_estimate"] = float(estimate.max())
        if result.error_estimate is not None:  # the run's estimate covers every output time
            result.error_estimate = max(result.error_estimate, out["error_estimate"])
    out.update(x=x.tolist(), v=v.tolist())
    if config.uses_reference:  # at the distinct times, in increasing order
        distinct, where = np.unique(done, return_inverse=True)
        x_ref, v_ref = config.scene.reference(config.x0, config.v0)(distinct)
        ex = np.abs(x - x_ref[where]).max(initial=0.0)
        ev = np.abs(v - v_ref[where]).max(initial=0.0)
        out["error"] = {"x_max": float(ex), "v_max": float(ev)}
    return out


def unvouched_output(result: RunResult, config: RunConfig) -> Optional[SolveError]:
    """A failure when the estimate at the --t-eval times exceeds what the run vouches for (the
    slab loop keeps the gaps between vertices within the tolerance; this catches what its
    sample points within each vertex interval missed). The same on every rank."""
    estimate = result.t_eval.get("error_estimate")
    tol = config.tolerance
    scale = max(result.tolerance.get("scale_x", 0.0), result.tolerance.get("scale_v", 0.0))
    allowed = tol.refuse_factor * (tol.atol + tol.rtol * scale)
    if estimate is None or estimate <= allowed:
        return None
    message = (f"the state at the --t-eval times is estimated to be {estimate:.3g} off, more "
               f"than the tolerance allows ({tol.label}): the output vertices are too far apart; "
               "use more --cells or a degree of at most 4")
    result.status, result.message = "failed", message
    return SolveError(message)


