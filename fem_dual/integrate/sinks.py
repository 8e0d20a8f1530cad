"""What the slab loop does with each accepted slab, in small sinks it calls (rank 0): the
accumulator of the run's arrays and errors, the streamed XDMF output (with the restart records
`--resume` reads back: fem_dual.integrate.restart), a progress bar.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import numpy as np

from fem_dual.config import RunConfig
from fem_dual.errors import InputError
from fem_dual.output import (XdmfSeries, lock_directory, series_files, write_arrays,
                             write_polyline, written_by_us)
from fem_dual.slab.values import VertexValues
from fem_dual.integrate.conditioning import DataFloor
from fem_dual.integrate.estimate import SlabEstimate, accumulated_floor

__all__ = ["AcceptedSlab", "SlabBatch", "PartialBatch", "Accumulator", "XdmfSink",
           "ProgressSink"]


@dataclass
class AcceptedSlab:
    """What the sinks receive for every accepted slab (rank 0). `schedule` is the slab
    schedule's state after the slab (SlabSchedule.state), `scales` the error weights' scales."""

    index: int
    t0: float
    dt: float
    values: VertexValues
    estimate: SlabEstimate
    schedule: tuple  # SlabSchedule.state after the slab
    scales: tuple  # the error weights' scales of x and v after the slab


class PartialBatch(Exception):
    """A sink took the first `taken` slabs of a batch, then failed on the next with `cause`."""

    def __init__(self, taken: int, cause: BaseException):
        super().__init__(f"{cause} (after {taken} slabs of the batch)")
        self.taken, self.cause = taken, cause


@dataclass
class SlabBatch:
    """Consecutive accepted slabs in arrays with a leading slab axis (rank 0): what a linear
    scene's slab maps produce at once (fem_dual.integrate.simulation), and what the sinks take."""

    first: int  # index of the first slab
    t0: np.ndarray  # (slabs,)
    dt: np.ndarray  # (slabs,)
    values: VertexValues  # x, v, xi, eta: (slabs, vertices, n); hamiltonian (slabs, vertices)
    local: np.ndarray  # (slabs, vertices, 2n)
    glob: np.ndarray  # (slabs, vertices, 2n)
    local_weighted: np.ndarray  # (slabs,)
    global_weighted: np.ndarray  # (slabs,)
    floor: np.ndarray  # (slabs, 2)
    schedule: np.ndarray  # (slabs, SlabSchedule.STATE_SIZE)
    scales: np.ndarray  # (slabs, 2)
    carried: Optional[np.ndarray] = None  # (slabs, 2): grown floors (estimate.carried_floor)

    def __len__(self) -> int:
        return len(self.t0)

    def head(self, count: int) -> "SlabBatch":
        """The first `count` slabs."""
        cut = slice(0, count)
        return SlabBatch(self.first, self.t0[cut], self.dt[cut],
                         self.values.apply(lambda a: a[cut]), self.local[cut],
                         self.glob[cut], self.local_weighted[cut], self.global_weighted[cut],
                         self.floor[cut], self.schedule[cut], self.scales[cut],
                         None if self.carried is None else self.carried[cut])

    @classmethod
    def of(cls, slab: AcceptedSlab) -> "SlabBatch":
        e, one = slab.estimate, slab.values.apply(lambda a: a[None])
        return cls(slab.index, np.array([slab.t0]), np.array([slab.dt]), one, e.local[None],
                   e.glob[None], np.array([e.local_weighted]), np.array([e.global_weighted]),
                   np.array([e.floor]), np.array([slab.schedule]), np.array([slab.scales]),
                   np.array([e.carried]))

    def slab(self, j: int) -> AcceptedSlab:
        values = self.values.apply(lambda a: a[j])
        estimate = SlabEstimate(float(self.t0[j]), float(self.dt[j]), self.local[j],
                                self.glob[j], float(self.local_weighted[j]),
                                float(self.global_weighted[j]), tuple(self.floor[j]),
                                (0.0, 0.0) if self.carried is None else tuple(self.carried[j]))
        return AcceptedSlab(self.first + j, float(self.t0[j]), float(self.dt[j]), values,
                            estimate, tuple(int(a) for a in self.schedule[j]),
                            tuple(self.scales[j]))

    def reported(self) -> np.ndarray:
        """The estimated |error| of x and of v per vertex (max over components) of every slab,
        (slabs, vertices, 2), at least the round-off accumulated up to the slab."""
        slabs, vertices, n2 = self.glob.shape
        g = np.abs(self.glob).reshape(slabs, vertices, 2, n2 // 2).max(axis=-1)
        return np.maximum(g, self.accumulated_floor()[:, None, :])

    def accumulated_floor(self) -> np.ndarray:
        floor = accumulated_floor(self.floor, self.first)
        return floor if self.carried is None else np.maximum(floor, self.carried)


_TINY = np.finfo(float).tiny


def _summaries(batch: SlabBatch, keep: np.ndarray) -> tuple:
    """What the Accumulator keeps of a batch: the reported error at the kept vertices (`keep`,
    (slabs, vertices)) as rows (the larger of x's and v's) and its peak of x's and of v's, the
    last vertex's (x's, v's), each slab's largest reported and local error, and H_d's low,
    high and drift (high - low) / max |H_d| per slab."""
    est = batch.reported()  # (slabs, vertices, 2): x's and v's
    kept = est[keep]
    local = np.abs(batch.local).reshape(len(batch), -1).max(axis=1, initial=0.0)
    h = batch.values.hamiltonian
    low, high = h.min(axis=1), h.max(axis=1)
    scale = np.maximum(np.maximum(high, -low), _TINY)  # max |h|
    return (kept.max(axis=1), kept.max(axis=0), est[-1, -1],
            est.reshape(len(batch), -1).max(axis=1), local, low, high, (high - low) / scale)


def _compiled_summaries(batch: SlabBatch) -> Optional[tuple]:
    """`_summaries` in compiled code (fem_dual.native's `summary`); None where it is not
    compiled or a value is not finite."""
    from fem_dual import native
    from fem_dual.native.estimate import summaries

    if native.library() is None:
        return None
    return summaries(batch.glob, batch.local, batch.accumulated_floor(),
                     batch.values.hamiltonian, batch.first == 0, _TINY)


def _floats(*columns) -> zip:
    """The rows of equal-length columns as Python floats (converted a column at a time)."""
    return zip(*(np.asarray(c, dtype=float).ravel().tolist() for c in columns))


SLAB_RECORD_BYTES = 1200  # a slab's estimate and H_d records (two small dicts of floats)


class Accumulator:
    """Vertex arrays of the whole run and their errors against the reference (rank 0 only)."""

    def __init__(self, config: RunConfig, floor: Optional[DataFloor] = None):
        tic = time.perf_counter()
        self.floor = floor  # the data floor of the estimate (fem_dual.integrate.conditioning)
        self.flow = None
        if config.uses_reference:
            self.flow = config.scene.reference(config.x0, config.v0)
        self.reference_s = 0.0 if self.flow is None else time.perf_counter() - tic
        self.t: List[np.ndarray] = []
        self.x: List[np.ndarray] = []
        self.v: List[np.ndarray] = []
        self.err_x = 0.0
        self.err_v = 0.0
        self.final_err: Tuple[Optional[float], Optional[float]] = (None, None)
        self.reference_lost_at: Optional[float] = None  # the reference overflowed from here on
        self.ham: List[Dict[str, float]] = []
        self.est_x = self.est_v = 0.0
        self.est_final = (0.0, 0.0)
        self.estimates: List[Dict[str, float]] = []
        self.est_rows: List[np.ndarray] = []  # the estimate at every output time
        self.err_rows: List[np.ndarray] = []  # the reference error at every output time
        self._masks: Dict[tuple, np.ndarray] = {}
        self.held = 0  # bytes of what the run holds for its result (about)

    def add(self, slab: AcceptedSlab) -> None:
        self.add_batch(SlabBatch.of(slab))

    def add_batch(self, batch: SlabBatch) -> None:
        vals = batch.values
        keep = self._kept(vals.hamiltonian.shape, batch.first == 0)
        t = (batch.t0[:, None] + batch.dt[:, None] * vals.s)[keep]
        x, v = vals.x[keep], vals.v[keep]
        if self.flow is not None:
            self._compare(t, x, v)
        self.t.append(t), self.x.append(x), self.v.append(v)
        rows, (peak_x, peak_v), final, glob, local, low, high, drift = (
            _compiled_summaries(batch) or _summaries(batch, keep))
        if self.floor is not None:  # at least the data floor, at every vertex and slab end
            at = self.floor.at(t)
            rows = np.maximum(rows, at.max(axis=1, initial=0.0))
            peak_x, peak_v = np.maximum((peak_x, peak_v), at.max(axis=0, initial=0.0))
            final = np.maximum(final, self.floor.at([t[-1]])[0]) if len(t) else final
            glob = np.maximum(glob, self.floor.at(batch.t0 + batch.dt).max(axis=1))
        self.est_rows.append(rows)
        self.est_x, self.est_v = max(self.est_x, peak_x), max(self.est_v, peak_v)
        self.est_final = (float(final[0]), float(final[1]))
        self.estimates += [{"t0": a, "dt": b, "local": c, "global": d, "local_weighted": e,
                            "global_weighted": f}
                           for a, b, c, d, e, f in _floats(batch.t0, batch.dt, local, glob,
                                                           batch.local_weighted,
                                                           batch.global_weighted)]
        self.ham += [{"min": a, "max": b, "drift": c} for a, b, c in _floats(low, high, drift)]
        # (the reference's error rows as many as the estimate's; two dicts a slab)
        rows_held = rows.nbytes * (1 if self.flow is None else 2)
        self.held += t.nbytes + x.nbytes + v.nbytes + rows_held + SLAB_RECORD_BYTES * len(
            batch.t0)

    def _kept(self, shape: Tuple[int, int], first: bool) -> np.ndarray:
        """Which vertices (slabs, vertices) of a batch the run's arrays take: each junction
        once, as a slab's end (the run's start as the first slab's start); found once per
        shape."""
        key = (shape, first)
        if key not in self._masks:
            keep = np.ones(shape, dtype=bool)
            keep[:, 0] = False
            keep[0, 0] = first
            self._masks[key] = keep
        return self._masks[key]

    def _compare(self, t: np.ndarray, x: np.ndarray, v: np.ndarray) -> None:
        """Errors against the reference while it stays finite: an exponentially growing
        reference overflows before the answer does, and its inf or NaN compares with nothing."""
        if self.reference_lost_at is None:
            tic = time.perf_counter()
            x_ref, v_ref = self.flow(t)
            self.reference_s += time.perf_counter() - tic
            with np.errstate(invalid="ignore", over="ignore"):
                ex, ev = np.abs(x - x_ref).max(axis=1), np.abs(v - v_ref).max(axis=1)
        else:
            ex = ev = np.full(len(t), np.nan)
        lost = ~(np.isfinite(ex) & np.isfinite(ev))
        if lost.any():
            self.reference_lost_at = (float(t[lost.argmax()]) if self.reference_lost_at is None
                                      else self.reference_lost_at)
            self.final_err = (None, None)
            ex, ev = np.where(lost, np.nan, ex), np.where(lost, np.nan, ev)
        else:
            self.final_err = (float(ex[-1]), float(ev[-1]))
        self.err_rows.append(np.maximum(ex, ev))
        if not lost.all():
            self.err_x = max(self.err_x, float(np.nanmax(ex)))
            self.err_v = max(self.err_v, float(np.nanmax(ev)))

    def arrays(self, n: int):
        if not self.t:
            return np.zeros(0), np.zeros((0, n)), np.zeros((0, n))
        return np.concatenate(self.t), np.concatenate(self.x), np.concatenate(self.v)

    def hamiltonian(self) -> Dict[str, Any]:
        if not self.ham:
            return {"min": None, "max": None, "drift": None, "per_slab": []}
        return {"min": min(h["min"] for h in self.ham), "max": max(h["max"] for h in self.ham),
                "drift": max(h["drift"] for h in self.ham), "per_slab": self.ham}

    def estimate_max(self) -> Optional[float]:
        """The estimated max-norm error of the state over all output times."""
        return max(self.est_x, self.est_v) if self.t else None

    def estimate(self) -> Dict[str, Optional[float]]:
        if not self.t:
            return {"x_max": None, "v_max": None, "final": None}
        floor = (None, None) if self.floor is None else self._floor_at_end()
        return {"x_max": self.est_x, "v_max": self.est_v, "final": max(self.est_final),
                "final_x": self.est_final[0], "final_v": self.est_final[1],
                "data_floor_x": floor[0], "data_floor_v": floor[1]}

    def _floor_at_end(self) -> Tuple[float, float]:
        """The data floor (x, v) at the last output time."""
        x, v = self.floor.at([self.t[-1][-1]])[0] if len(self.t[-1]) else (0.0, 0.0)
        return float(x), float(v)

    def error(self) -> Dict[str, Optional[float]]:
        if not self.t or self.flow is None:
            return {"x_max": None, "v_max": None, "final": None, "final_x": None, "final_v": None}
        fx, fv = self.final_err
        return {"x_max": float(self.err_x), "v_max": float(self.err_v),
                "final": None if fx is None else max(fx, fv), "final_x": fx, "final_v": fv,
                "reference_lost_at": self.reference_lost_at,
                # errors below this the reference cannot tell: it is exact only for M and K
                # within their round-off too (the data floor)
                "reference_floor": None if self.floor is None else max(self._floor_at_end())}


def _fields(vals: VertexValues, slab: AcceptedSlab,
            floor: Optional[DataFloor] = None) -> Dict[str, np.ndarray]:
    t = slab.t0 + slab.dt * vals.s
    estimate = SlabBatch.of(slab).reported()[0].max(axis=-1)
    if floor is not None:  # at least the data floor, as in the JSON
        estimate = np.maximum(estimate, floor.at(t).max(axis=1))
    return {"t": t, "xi": vals.xi, "eta": vals.eta, "x_hat": vals.x, "v_hat": vals.v,
            "hamiltonian": vals.hamiltonian, "error_estimate": estimate}


def _restart(slab: AcceptedSlab) -> Dict[str, np.ndarray]:
    est = slab.estimate
    return {"slab": np.array([slab.index, slab.t0, slab.dt, *slab.schedule, *slab.scales,
                              est.local_weighted, est.global_weighted, *est.floor,
                              est.t0]),
            "s": slab.values.s, "local": est.local, "glob": est.glob}


class XdmfSink:
    """The dual fields and the recovered motion per slab, streamed into `out/<scene>.xdmf`
    (rank 0); the trajectory polyline when the run ends, however it ends. A fresh run first
    removes the files of an earlier run of the scene, so nothing stale looks current."""

    def __init__(self, config: RunConfig, name: str, resume=None,
                 floor: Optional[DataFloor] = None):
        self.out: Path = config.out
        self.name, self.floor = name, floor
        self.fields: Optional[FieldSeries] = None
        self.identity = config.identity()
        self.series: Optional[XdmfSeries] = resume.series if resume is not None else None
        self.seconds = 0.0
        self._lock = lock_directory(self.out)
        if resume is None:
            for stale in series_files(self.out, name):
                if stale.exists() or stale.is_symlink():
                    if not written_by_us(stale):
                        self.release()
                        raise InputError(f"--out {self.out}: {stale.name} was not written by "
                                         "fem-dual; move it away or choose another directory")
                    stale.unlink()
        if config.scene.continuum:
            # a continuum: its semi-discrete system, to check against, and its fields in space
            write_arrays(self.out / f"{name}_system.npz",
                         config.scene.system_arrays(config.x0, config.v0))
            self.fields = FieldSeries(config, name, resume is not None)

    def add_batch(self, batch: SlabBatch) -> None:
        """Raises PartialBatch when a slab cannot be written (the ones before it are)."""
        for j in range(len(batch)):
            try:
                self.add(batch.slab(j))
            except Exception as exc:  # noqa: BLE001 -- the caller says which slab
                raise PartialBatch(j, exc) from exc

    def add(self, slab: AcceptedSlab) -> None:
        tic = time.perf_counter()
        vals = slab.values
        fields, restart = _fields(vals, slab, self.floor), _restart(slab)
        if self.series is None:
            self.series = XdmfSeries(self.out / f"{self.name}.xdmf", slab.dt * vals.s,
                                     {k: a.shape for k, a in fields.items()},
                                     {k: a.shape for k, a in restart.items()}, self.identity)
        self.series.write(slab.t0, fields, restart)
        if self.fields is not None:
            self.fields.add(slab)
        self.seconds += time.perf_counter() - tic

    def close(self, t: np.ndarray, x: np.ndarray, v: np.ndarray) -> List[str]:
        """Flush the series and write the trajectory; the files written."""
        tic = time.perf_counter()
        if self.series is not None and not self.series.broken:
            self.series.close()
            write_polyline(self.out / f"{self.name}_trajectory.xdmf", x, {"t": t, "v_hat": v})
        if self.fields is not None:
            self.fields.close()
        self.seconds += time.perf_counter() - tic
        self.release()
        return self.files_on_disk()


    def release(self) -> None:
        """Let other runs write into the directory again."""
        self._lock()

    @property
    def slabs_written(self) -> int:
        """Slabs the files on disk hold."""
        return 0 if self.series is None else self.series.count

    def files_on_disk(self) -> List[str]:
        """Our files that exist (after a failed close)."""
        return [str(p) for p in series_files(self.out, self.name) if p.exists()]


class FieldSeries:
    """A continuum's fields and their velocities on its spatial mesh at every time vertex of the
    accepted slabs (`<scene>_fields.xdmf`, one step per time; each slab's first vertex is the
    previous slab's last), streamed like the slab series."""

    def __init__(self, config: RunConfig, name: str, resume: bool):
        self.scene, self.identity = config.scene, config.identity()
        self.path = config.out / f"{name}_fields.xdmf"
        self.series = XdmfSeries.reopen(self.path) if resume and self.path.exists() else None
        self.first = self.series is None

    def add(self, slab: AcceptedSlab) -> None:
        vals = slab.values
        fields = self.scene.vertex_fields(vals.x, vals.v)
        if self.series is None:
            points, cells = self.scene.vertex_mesh()
            self.series = XdmfSeries(self.path, points,
                                     {k: a.shape[1:] for k, a in fields.items()}, {},
                                     self.identity, cells)
        times = slab.t0 + slab.dt * vals.s
        for k in range(0 if self.first else 1, len(times)):
            self.series.write(times[k], {name: a[k] for name, a in fields.items()}, {})
        self.first = False

    def close(self) -> None:
        if self.series is not None and not self.series.broken:
            self.series.close()


class ProgressSink:
    def __init__(self, T: float):
        from tqdm import tqdm

        self.bar = tqdm(total=T, unit="t", desc="slabs", leave=False,
                        bar_format="{l_bar}{bar}| t={n:.4g}/{total:.4g} "
                                   "[{elapsed}<{remaining}, {rate_fmt}]")

    def add(self, slab: AcceptedSlab) -> None:
        self.bar.update(slab.dt)

    def add_batch(self, batch: SlabBatch) -> None:
        self.bar.update(float(batch.dt.sum()))

    def close(self) -> None:
        self.bar.close()
