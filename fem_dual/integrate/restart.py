"""The completed slabs of an earlier run with --out, read back for --resume (rank 0): the
restart records the XDMF sink writes beside the fields (fem_dual.integrate.sinks)."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Dict, List

import numpy as np

from fem_dual.config import RunConfig
from fem_dual.errors import InputError
from fem_dual.integrate.controller import SlabSchedule
from fem_dual.integrate.estimate import SlabEstimate
from fem_dual.integrate.sinks import AcceptedSlab
from fem_dual.output import XdmfSeries
from fem_dual.slab.values import VertexValues

__all__ = ["Restart"]


_RESTART_FIELDS = {"slab": 10 + SlabSchedule.STATE_SIZE, "s": None, "local": None, "glob": None}


def _check_restart(path: Path, stored, steps: Dict[str, np.ndarray],
                   restart: Dict[str, np.ndarray]) -> None:
    """InputError unless the stored run is whole: an options record, as many rows of every
    field as slabs, finite values (a damaged or edited file must not reach the results)."""
    what = None
    if not isinstance(stored, dict):
        what = "its options record is not one"
    elif set(restart) != set(_RESTART_FIELDS) or not {"x_hat", "v_hat", "hamiltonian"} <= set(
            steps):
        what = "datasets are missing"
    else:
        rows = {name: len(a) for name, a in {**steps, **restart}.items()}
        if len(set(rows.values())) != 1:
            what = f"its datasets hold different numbers of slabs ({rows})"
        elif restart["slab"].ndim != 2 or restart["slab"].shape[1] != _RESTART_FIELDS["slab"]:
            what = "its slab records have the wrong shape"
        elif not all(np.isfinite(a).all() for a in (*steps.values(), *restart.values())):
            what = "it holds values that are not finite"
    if what:
        raise InputError(f"--resume: {path} cannot be resumed: {what}")


class Restart:
    """The completed slabs of an earlier run with --out, read back for --resume (rank 0)."""

    def __init__(self, config: RunConfig, name: str):
        import h5py

        path = config.out / f"{name}.xdmf"
        if not path.with_suffix(".h5").exists():
            raise InputError(f"--resume: {path.with_suffix('.h5')} does not exist (no earlier "
                             f"run of {name} with --out {config.out})")
        try:
            with h5py.File(path.with_suffix(".h5"), "r", locking=False) as h5:
                stored = json.loads(h5.attrs["fem_dual"])
                steps = {k: h5["steps"][k][:] for k in h5["steps"]}
                restart = {k: h5["restart"][k][:] for k in h5["restart"]}
        except (OSError, KeyError, ValueError, TypeError) as exc:
            raise InputError(f"--resume: {path.with_suffix('.h5')} cannot be read ({exc})") \
                from None
        _check_restart(path.with_suffix(".h5"), stored, steps, restart)
        mine = config.identity()
        for key in mine:
            if stored.get(key) != json.loads(json.dumps(mine[key])):
                raise InputError(f"--resume: the run in {config.out} has {key}="
                                 f"{stored.get(key)!r}, this one {key}={mine[key]!r}")
        self.series = XdmfSeries.reopen(path)
        self.slabs: List[AcceptedSlab] = []
        n = config.scene.n
        for k, row in enumerate(restart["slab"]):
            (index, t0, dt), row = row[:3], row[3:]
            schedule, (sx, sv, lw, gw, fx, fv, et0) = (row[:SlabSchedule.STATE_SIZE],
                                                       row[SlabSchedule.STATE_SIZE:])
            vals = VertexValues(restart["s"][k], steps["x_hat"][k].reshape(-1, n),
                                steps["v_hat"][k].reshape(-1, n), steps["hamiltonian"][k])
            est = SlabEstimate(et0, dt, restart["local"][k], restart["glob"][k], lw, gw,
                               (fx, fv))
            self.slabs.append(AcceptedSlab(int(index), t0, dt, vals, est,
                                           tuple(int(a) for a in schedule), (sx, sv)))
