"""Output files: an XDMF time series over slabs, the trajectory as a polyline in configuration
space, and the discipline that files are complete or absent.

DOLFINx 0.5.2's XDMFFile writes 1D meshes with topology type `PolyLine`, which Debian's meshio
cannot read, and its meshio TimeSeriesWriter puts the HDF5 file in the working directory; so the
XDMF (XML + HDF5 through h5py) is written here, in the layout meshio's TimeSeriesReader and
ParaView's XDMF readers expect: the slab mesh once, then one time step per slab.

Everything is written on rank 0 from values gathered there, into a hidden temporary directory
inside the output directory; `commit()` moves the finished files into place.
"""
from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path
from typing import Dict, List, Optional

import numpy as np

from fem_dual.errors import InputError

__all__ = ["OutputDir", "XdmfSeries", "write_polyline", "check_output_dir",
           "check_output_dir_on_root"]


def check_output_dir(path: "str | os.PathLike", option: str = "--out") -> Path:
    """The output directory, created if missing; InputError (naming `option`) if it cannot
    hold our files."""
    if not str(path).strip():
        raise InputError(f"{option} {str(path)!r} is not a directory name")
    out = Path(path)
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = tempfile.mkdtemp(prefix=".fem-dual-probe-", dir=out)
        os.rmdir(probe)
    except OSError as exc:
        raise InputError(f"{option} {str(path)!r} is not a writable directory "
                         f"({exc.strerror or exc})") from None
    return out


def check_output_dir_on_root(comm, path: "str | os.PathLike",
                             option: str = "--out") -> Optional[Path]:
    """check_output_dir on rank 0 (which writes), its InputError raised on every rank, so no rank
    goes on into collective work alone. The directory on rank 0, None elsewhere."""
    from fem_dual.mpi import bcast

    out, problem = None, None
    if comm.rank == 0:
        try:
            out = check_output_dir(path, option)
        except InputError as exc:
            problem = str(exc)
    problem = bcast(comm, problem)
    if problem:
        raise InputError(problem)
    return out


class OutputDir:
    """A temporary directory inside `path` whose files are moved into `path` on commit."""

    def __init__(self, path: "str | os.PathLike"):
        self.path = check_output_dir(path)
        self.tmp = Path(tempfile.mkdtemp(prefix=".fem-dual-tmp-", dir=self.path))
        self.written: List[Path] = []

    def file(self, name: str) -> Path:
        return self.tmp / name

    def commit(self) -> List[Path]:
        """Move every finished file into place (each rename atomic) and remove the temporary dir."""
        for item in sorted(self.tmp.iterdir()):
            target = self.path / item.name
            os.replace(item, target)
            self.written.append(target)
        self.discard()
        return self.written

    def discard(self) -> None:
        shutil.rmtree(self.tmp, ignore_errors=True)


def _points3(points: np.ndarray) -> np.ndarray:
    """Pad points of dimension 1..3 to 3D (ParaView draws XYZ)."""
    points = np.asarray(points, dtype=float)
    if points.ndim == 1:
        points = points[:, None]
    if points.shape[1] > 3:
        return points[:, :3]
    return np.hstack([points, np.zeros((len(points), 3 - points.shape[1]))])


def _attribute_type(data: np.ndarray) -> str:
    if data.ndim == 1:
        return "Scalar"
    return "Vector" if data.shape[1] == 3 else "Matrix"


def _data_item(h5name: str, path: str, shape: tuple, integer: bool = False) -> str:
    kind = "Int" if integer else "Float"
    dims = " ".join(str(d) for d in shape)
    return (f'<DataItem DataType="{kind}" Dimensions="{dims}" Format="HDF" '
            f'Precision="8">{h5name}:{path}</DataItem>')


def _grid_xml(h5name: str, prefix: str, npoints: int, ncells: int) -> List[str]:
    return [f'<Topology TopologyType="Polyline" NumberOfElements="{ncells}" NodesPerElement="2">',
            _data_item(h5name, f"/{prefix}/topology", (ncells, 2), integer=True), "</Topology>",
            '<Geometry GeometryType="XYZ">',
            _data_item(h5name, f"/{prefix}/geometry", (npoints, 3)), "</Geometry>"]


def _attributes_xml(h5, h5name: str, group: str, data: Dict[str, np.ndarray]) -> List[str]:
    lines = []
    for name, values in data.items():
        values = np.asarray(values, dtype=float)
        h5.create_dataset(f"{group}/{name}", data=values)
        lines += [f'<Attribute Name="{name}" AttributeType="{_attribute_type(values)}" '
                  'Center="Node">', _data_item(h5name, f"/{group}/{name}", values.shape),
                  "</Attribute>"]
    return lines


def _write_xml(path: Path, body: List[str]) -> None:
    text = "\n".join(['<?xml version="1.0"?>',
                      '<Xdmf Version="3.0" xmlns:xi="http://www.w3.org/2001/XInclude">',
                      "<Domain>", *body, "</Domain>", "</Xdmf>", ""])
    path.write_text(text)


class XdmfSeries:
    """XDMF time series of the slab mesh: mesh once, then the vertex fields of each slab at the
    slab's start time. The XML is rewritten after each slab, so the file is valid at every step.

    Args:
        path: the .xdmf file; its HDF5 data goes beside it with suffix .h5.
        points: mesh vertex coordinates (local time of the slab, in the first coordinate).
    """

    def __init__(self, path: Path, points: np.ndarray):
        import h5py

        self.path = path
        self.h5name = path.with_suffix(".h5").name
        self.h5 = h5py.File(path.with_suffix(".h5"), "w")
        pts = _points3(points)
        lines = np.column_stack([np.arange(len(pts) - 1), np.arange(1, len(pts))]).astype(np.int64)
        self.h5.create_dataset("mesh/geometry", data=pts)
        self.h5.create_dataset("mesh/topology", data=lines)
        self.mesh_xml = (['<Grid Name="mesh" GridType="Uniform">']
                         + _grid_xml(self.h5name, "mesh", len(pts), len(lines)) + ["</Grid>"])
        self.steps: List[str] = []

    def write(self, time: float, data: Dict[str, np.ndarray]) -> None:
        k = len(self.steps)
        ptr = ('xpointer(//Grid[@Name="mesh"]/*[self::Topology or self::Geometry])')
        step = (['<Grid Name="step" GridType="Uniform">', f'<xi:include xpointer=\'{ptr}\'/>',
                 f'<Time Value="{time!r}"/>']
                + _attributes_xml(self.h5, self.h5name, f"step{k}", data) + ["</Grid>"])
        self.steps.append("\n".join(step))
        self.h5.flush()
        _write_xml(self.path, self.mesh_xml + [
            '<Grid Name="TimeSeries" GridType="Collection" CollectionType="Temporal">',
            *self.steps, "</Grid>"])

    def close(self) -> None:
        self.h5.close()


def write_polyline(path: Path, points: np.ndarray, data: Dict[str, np.ndarray]) -> None:
    """A static XDMF polyline through `points` (configuration space) with vertex data."""
    import h5py

    h5name = path.with_suffix(".h5").name
    pts = _points3(points)
    lines = np.column_stack([np.arange(len(pts) - 1), np.arange(1, len(pts))]).astype(np.int64)
    with h5py.File(path.with_suffix(".h5"), "w") as h5:
        h5.create_dataset("mesh/geometry", data=pts)
        h5.create_dataset("mesh/topology", data=lines)
        body = (['<Grid Name="trajectory" GridType="Uniform">']
                + _grid_xml(h5name, "mesh", len(pts), len(lines))
                + _attributes_xml(h5, h5name, "data", data) + ["</Grid>"])
    _write_xml(path, body)
