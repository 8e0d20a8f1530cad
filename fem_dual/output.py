"""Output files: an XDMF time series over slabs streamed while the run goes, the trajectory as a
polyline in configuration space.

DOLFINx 0.5.2's XDMFFile writes 1D meshes with topology type `PolyLine`, which Debian's meshio
cannot read, and its meshio TimeSeriesWriter rewrites everything per step; so the XDMF (XML +
HDF5 through h5py) is written here, on rank 0, from values gathered there:

- `<name>.h5` holds the slab mesh once and, per field, one dataset extended along its first axis
  (one row per slab); `/restart` holds what `--resume` needs to go on from the last slab.
- `<name>.xdmf` holds the mesh grid and a temporal collection whose step k reads row k of each
  field (the XDMF 3 hyperslab syntax `file:/path|start:stride:count:dims`, which ParaView's
  default readers read; `read_series` here reads it too).

Rows are buffered and flushed at most every FLUSH_SECONDS (and at the end): the HDF5 file is
opened (without HDF5's file lock: a viewer reading the file must not stop the run), extended
and closed, then the new steps are written over the XML's closing tags in one
write. So the cost per slab is constant, and at every moment the directory holds a closed HDF5
file and an XML that names only rows already in it: what a `kill -9` leaves behind is readable
and holds every slab flushed so far.
"""
from __future__ import annotations

import errno
import json
import os
import tempfile
import time
from pathlib import Path
from typing import Dict, List, Mapping, Optional, Tuple

import numpy as np

from fem_dual.errors import InputError

__all__ = ["XdmfSeries", "write_polyline", "check_output_dir", "check_output_dir_on_root",
           "read_series", "FLUSH_SECONDS", "series_files", "written_by_us", "lock_directory",
           "MARK"]

FLUSH_SECONDS = 0.5  # buffered slabs reach the disk at least this often
FLUSH_ROWS_BYTES = 64 << 20  # ... or when the buffer holds this much
SPACE_MARGIN = 1 << 18  # free bytes kept beyond the data of a write (HDF5 metadata, chunks)
CHUNK_BYTES = 8 * 2**12  # HDF5 chunk of an extended dataset (allocated whole)
XML_ROW_BYTES = 400  # XML per field and slab (measured: about 330)
_TAIL = "</Grid>\n</Domain>\n</Xdmf>\n"


def check_output_dir(path: "str | os.PathLike", option: str = "--out",
                     create: bool = True) -> Path:
    """The output directory, created if missing (`create`; else only checked, leaving nothing
    behind: its nearest existing folder must take a new directory); InputError (naming
    `option`) if it cannot hold our files."""
    if not isinstance(path, (str, os.PathLike)) or not str(path).strip():
        raise InputError(f"{option} {path!r} is not a directory name")
    out = Path(path)
    try:
        if create:
            out.mkdir(parents=True, exist_ok=True)
        probe_in = out
        while not create and not probe_in.exists() and probe_in.parent != probe_in:
            probe_in = probe_in.parent  # the nearest part of it that exists
        if not probe_in.is_dir():
            raise NotADirectoryError(20, "Not a directory")
        probe = tempfile.mkdtemp(prefix=".fem-dual-probe-", dir=probe_in)
        os.rmdir(probe)
    except OSError as exc:
        raise InputError(f"{option} {str(path)!r} is not a writable directory "
                         f"({exc.strerror or exc})") from None
    return out


def check_output_dir_on_root(comm, path: "str | os.PathLike", option: str = "--out",
                             create: bool = True) -> Optional[Path]:
    """check_output_dir on rank 0 (which writes), its InputError raised on every rank, so no rank
    goes on into collective work alone. The directory on rank 0, None elsewhere."""
    from fem_dual.mpi import input_on_root

    return input_on_root(comm, lambda: check_output_dir(path, option, create))


def free_bytes(directory: Path) -> int:
    """Bytes the file system of `directory` still gives an unprivileged writer."""
    st = os.statvfs(directory)
    return st.f_bavail * st.f_frsize


def ensure_space(directory: Path, needed: int) -> None:
    """OSError(ENOSPC) unless `directory` has `needed` bytes free: HDF5 is never let run into a
    full disk (after a failed write it may leave the file damaged and the process unstable)."""
    free = free_bytes(directory)
    if free < needed:
        raise OSError(errno.ENOSPC, f"{os.strerror(errno.ENOSPC)} ({free} bytes free in "
                      f"{directory}, {needed} needed)")


MARK = "<!-- written by fem-dual; its next run into this directory replaces it -->"


def written_by_us(path: Path) -> bool:
    """Whether `path` is a file fem-dual wrote (an XDMF with our mark, an HDF5 file with our
    attribute): a run replaces those, never a user's file of the same name."""
    if path.is_symlink() or not path.is_file():
        return False
    try:
        if path.suffix == ".h5":
            import h5py

            with h5py.File(path, "r", locking=False) as h5:
                return "fem_dual" in h5.attrs
        with open(path, "rb") as f:
            return MARK.encode() in f.read(400)
    except (OSError, ValueError):
        return False


def lock_directory(directory: Path):
    """An exclusive lock on `directory` for one run (released by calling what is returned, or
    when the process ends): two runs writing the same files would mix their slabs."""
    import fcntl

    fd = os.open(directory, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        raise InputError(f"--out {directory} is in use by another fem-dual run") from None

    def release(fd=fd) -> None:
        try:
            os.close(fd)
        except OSError:
            pass
    return _Release(release)


class _Release:
    """Calls `release` once."""

    def __init__(self, release):
        self._release = release

    def __call__(self) -> None:
        release, self._release = self._release, None
        if release is not None:
            release()

    def __del__(self) -> None:
        self()


def series_files(out: Path, name: str) -> List[Path]:
    """The files a run of scene `name` writes into `out` (series and trajectory)."""
    return [out / f"{name}{tail}" for tail in (".xdmf", ".h5", "_trajectory.xdmf",
                                               "_trajectory.h5", "_system.npz", "_fields.xdmf",
                                               "_fields.h5")]


def write_arrays(path: Path, arrays: Mapping[str, np.ndarray]) -> None:
    """`arrays` as an uncompressed .npz (numpy.load reads it), marked as ours: its first entry,
    `fem_dual`, holds MARK, which `written_by_us` finds in the file's first bytes."""
    marked = {"fem_dual": np.frombuffer(MARK.encode(), dtype=np.uint8), **arrays}

    def write(tmp: Path) -> None:
        with open(tmp, "wb") as f:
            np.savez(f, **marked)
    _replace_atomically(path, write)


def _points3(points: np.ndarray) -> np.ndarray:
    """Pad points of dimension 1..3 to 3D (ParaView draws XYZ)."""
    points = np.asarray(points, dtype=float)
    if points.ndim == 1:
        points = points[:, None]
    if points.shape[1] > 3:
        return points[:, :3]
    return np.hstack([points, np.zeros((len(points), 3 - points.shape[1]))])


def _attribute_type(shape: tuple) -> str:
    """Scalar per vertex, or a vector of any length per vertex (VTK's XDMF reader turns a
    "Matrix" of one row per vertex into a single tuple, a "Vector" into one tuple per vertex)."""
    return "Scalar" if len(shape) == 1 else "Vector"


def _data_item(h5name: str, path: str, shape: tuple, integer: bool = False) -> str:
    kind = "Int" if integer else "Float"
    dims = " ".join(str(d) for d in shape)
    return (f'<DataItem DataType="{kind}" Dimensions="{dims}" Format="HDF" '
            f'Precision="8">{h5name}:{path}</DataItem>')


def _row_item(h5name: str, path: str, row: int, shape: tuple) -> str:
    """Row `row` of the dataset `path` (rows, *shape), in the XDMF 3 library's hyperslab syntax
    `file:/path|start:stride:count:dims` (one entry per axis), which ParaView's default XDMF
    readers (Xdmf3 Reader S/T) read; they load no array from an XDMF `HyperSlab` item (measured
    with ParaView 5.11: "Skipping unrecognized array type"). The source's declared rows are
    row + 1, which it has since it was flushed."""
    start = " ".join(["%d" % row] + ["0"] * len(shape))
    stride = " ".join(["1"] * (1 + len(shape)))
    count = " ".join(["1"] + [str(d) for d in shape])
    full = " ".join([str(row + 1)] + [str(d) for d in shape])
    dims = " ".join(str(d) for d in shape)
    return (f'<DataItem DataType="Float" Dimensions="{dims}" Format="HDF" Precision="8">'
            f"{h5name}:{path}|{start}:{stride}:{count}:{full}</DataItem>")


def _grid_xml(h5name: str, prefix: str, npoints: int, ncells: int,
              corners: int = 2) -> List[str]:
    """A polyline (2 vertices per cell) or a triangle mesh (3)."""
    kind = "Polyline" if corners == 2 else "Triangle"
    return [f'<Topology TopologyType="{kind}" NumberOfElements="{ncells}" '
            f'NodesPerElement="{corners}">',
            _data_item(h5name, f"/{prefix}/topology", (ncells, corners), integer=True),
            "</Topology>",
            '<Geometry GeometryType="XYZ">',
            _data_item(h5name, f"/{prefix}/geometry", (npoints, 3)), "</Geometry>"]


def _head_xml(body: List[str]) -> str:
    return "\n".join(['<?xml version="1.0"?>', MARK,
                      '<Xdmf Version="3.0" xmlns:xi="http://www.w3.org/2001/XInclude">',
                      "<Domain>", *body, ""])


def _replace_atomically(path: Path, write) -> None:
    """write(tmp_path), then rename over `path`: readers see the old file or the new one."""
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def _polyline(points: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    pts = _points3(points)
    lines = np.column_stack([np.arange(len(pts) - 1), np.arange(1, len(pts))]).astype(np.int64)
    return pts, lines


class XdmfSeries:
    """XDMF time series of the slab mesh, streamed: the mesh once, then the vertex fields of
    each slab at the slab's start time, appended in O(1) per slab (see the module docstring).

    Args:
        path: the .xdmf file; its HDF5 data goes beside it with suffix .h5.
        points: mesh vertex coordinates (local time of the slab, in the first coordinate).
        fields: name -> shape of one slab's values (vertices[, components]) shown in ParaView.
        restart: name -> shape of one slab's restart record (kept in the HDF5 file only).
        attrs: JSON-able facts stored with the file (the run's options, for --resume).
    """

    def __init__(self, path: Path, points: np.ndarray, fields: Mapping[str, tuple],
                 restart: Mapping[str, tuple], attrs: Mapping[str, object],
                 cells: Optional[np.ndarray] = None):
        import h5py

        self.path, self.h5path = path, path.with_suffix(".h5")
        self.h5name = self.h5path.name
        self.fields, self.restart = dict(fields), dict(restart)
        pts, lines = _polyline(points)
        if cells is not None:  # a triangle mesh (the points in any order)
            lines = np.asarray(cells, dtype=np.int64)
        for stale in (self.path, self.h5path):  # an earlier run's files are not this run's
            if stale.exists():
                stale.unlink()

        def write_h5(tmp: Path) -> None:
            with h5py.File(tmp, "w", locking=False) as h5:
                h5.create_dataset("mesh/geometry", data=pts)
                h5.create_dataset("mesh/topology", data=lines)
                h5.create_dataset("steps/time", shape=(0,), maxshape=(None,), chunks=(1024,),
                                  dtype="f8")
                for group, shapes in (("steps", self.fields), ("restart", self.restart)):
                    for name, shape in shapes.items():
                        rows = max(1, CHUNK_BYTES // 8 // max(1, int(np.prod(shape))))
                        h5.create_dataset(f"{group}/{name}", shape=(0,) + tuple(shape),
                                          maxshape=(None,) + tuple(shape),
                                          chunks=(rows,) + tuple(shape), dtype="f8")
                h5.attrs["fem_dual"] = json.dumps(dict(attrs))

        ensure_space(path.parent, SPACE_MARGIN + 2 * pts.nbytes)
        _replace_atomically(self.h5path, write_h5)
        self.corners = lines.shape[1]
        self.broken = ""
        self._start_xml(len(pts), len(lines), steps=0)
        self.buffer: List[Tuple[float, Dict[str, np.ndarray], Dict[str, np.ndarray]]] = []
        self.buffered_bytes = 0
        self.last_flush = time.monotonic()

    def _start_xml(self, npoints: int, ncells: int, steps: int) -> None:
        """The XML of the mesh and the first `steps` rows, written whole (atomically)."""
        self.count = steps  # rows on disk, in the HDF5 file and the XML alike
        head = _head_xml(['<Grid Name="mesh" GridType="Uniform">']
                         + _grid_xml(self.h5name, "mesh", npoints, ncells, self.corners)
                         + ["</Grid>",
                         '<Grid Name="TimeSeries" GridType="Collection" '
                         'CollectionType="Temporal">'])
        text = head + "".join(self._step_xml(k, None) for k in range(steps))
        _replace_atomically(self.path, lambda tmp: tmp.write_text(text + _TAIL))
        self.tail_offset = len(text.encode())

    @classmethod
    def reopen(cls, path: Path) -> "XdmfSeries":
        """The series of an earlier run in `path`, to go on appending (--resume). Its XML is
        rewritten from the HDF5 rows (the XML may lag one flush behind them)."""
        import h5py

        self = cls.__new__(cls)
        self.broken = ""
        self.path, self.h5path = path, path.with_suffix(".h5")
        self.h5name = self.h5path.name
        with h5py.File(self.h5path, "r", locking=False) as h5:
            self.fields = {k: h5["steps"][k].shape[1:] for k in h5["steps"] if k != "time"}
            self.restart = {k: h5["restart"][k].shape[1:] for k in h5.get("restart", {})}
            steps = len(h5["steps/time"])
            self._times = h5["steps/time"][:]
            npts, ncells = len(h5["mesh/geometry"]), len(h5["mesh/topology"])
            self.corners = h5["mesh/topology"].shape[1]
        self._start_xml(npts, ncells, steps)
        del self._times
        self.buffer, self.buffered_bytes = [], 0
        self.last_flush = time.monotonic()
        return self

    def _step_xml(self, k: int, time_value: Optional[float]) -> str:
        if time_value is None:
            time_value = float(self._times[k])
        ptr = 'xpointer(//Grid[@Name="mesh"]/*[self::Topology or self::Geometry])'
        lines = ['<Grid Name="step" GridType="Uniform">', f'<xi:include xpointer=\'{ptr}\'/>',
                 f'<Time Value="{time_value!r}"/>']
        for name, shape in self.fields.items():
            lines += [f'<Attribute Name="{name}" AttributeType="{_attribute_type(shape)}" '
                      'Center="Node">', _row_item(self.h5name, f"/steps/{name}", k, shape),
                      "</Attribute>"]
        return "\n".join(lines + ["</Grid>", ""])

    def write(self, time_value: float, data: Mapping[str, np.ndarray],
              restart: Mapping[str, np.ndarray]) -> None:
        """Buffer one slab's fields and restart record; flushed when due."""
        data = {k: np.asarray(data[k], dtype=float) for k in self.fields}
        restart = {k: np.asarray(restart[k], dtype=float) for k in self.restart}
        self.buffer.append((float(time_value), data, restart))
        self.buffered_bytes += sum(a.nbytes for a in (*data.values(), *restart.values()))
        if (time.monotonic() - self.last_flush >= FLUSH_SECONDS
                or self.buffered_bytes >= FLUSH_ROWS_BYTES):
            self.flush()

    def flush(self) -> None:
        """Append the buffered slabs to the HDF5 file (closed again), then to the XML. On a write
        error (OSError) what is on disk still covers the slabs flushed before."""
        if not self.buffer:
            return
        if self.broken:
            raise OSError(f"{self.h5path} was not written after an earlier failure: {self.broken}")
        import h5py

        first, rows = self.count, len(self.buffer)
        row_bytes = self.buffered_bytes / rows + XML_ROW_BYTES * len(self.fields)
        margin = SPACE_MARGIN + CHUNK_BYTES * (len(self.fields) + len(self.restart) + 1)
        fit = int((free_bytes(self.h5path.parent) - margin) // row_bytes)
        if fit < rows:  # keep what fits, then fail
            self.buffer, rows = self.buffer[:max(fit, 0)], max(fit, 0)
            self.broken = (f"{os.strerror(errno.ENOSPC)} (at most {max(fit, 0)} more slabs "
                           f"fit in {self.h5path.parent})")
        try:
            if rows:
                self._append_h5(h5py, first, rows)
                self._append_xml("".join(self._step_xml(first + i, item[0])
                                         for i, item in enumerate(self.buffer)))
                self.count += rows
        except Exception as exc:  # noqa: BLE001 -- HDF5 must not be touched again
            self.broken = str(exc).split("\n")[0]
        self.buffer, self.buffered_bytes = [], 0
        self.last_flush = time.monotonic()
        if self.broken:
            raise OSError(f"writing {self.h5path.name} failed: {self.broken}; it holds the "
                          f"first {self.count} slabs")

    def _append_h5(self, h5py, first: int, rows: int) -> None:
        with h5py.File(self.h5path, "a", locking=False) as h5:
            for group, key, names in (("steps", 1, self.fields), ("restart", 2, self.restart)):
                for name in names:
                    dset = h5[f"{group}/{name}"]
                    dset.resize(first + rows, axis=0)
                    dset[first:] = np.stack([item[key][name] for item in self.buffer])
            times = h5["steps/time"]
            times.resize(first + rows, axis=0)
            times[first:] = [item[0] for item in self.buffer]

    def _append_xml(self, text: str) -> None:
        """Write `text` over the closing tags, then the tags again, in one write; on failure
        put the closing tags back where they were."""
        data = (text + _TAIL).encode()
        fd = os.open(self.path, os.O_WRONLY)
        try:
            try:
                written = os.pwrite(fd, data, self.tail_offset)
                if written != len(data):
                    raise OSError(28, os.strerror(28), str(self.path))
            except OSError:
                os.pwrite(fd, _TAIL.encode(), self.tail_offset)
                os.ftruncate(fd, self.tail_offset + len(_TAIL))
                raise
        finally:
            os.close(fd)
        self.tail_offset += len(text.encode())

    def close(self) -> None:
        """Flush what is buffered (nothing more after a failed write)."""
        if self.broken:
            self.buffer = []
            return
        self.flush()


def write_polyline(path: Path, points: np.ndarray, data: Dict[str, np.ndarray]) -> None:
    """A static XDMF polyline through `points` (configuration space) with vertex data; each of
    the two files replaced atomically."""
    import h5py

    h5name = path.with_suffix(".h5").name
    pts, lines = _polyline(points)
    body = (['<Grid Name="trajectory" GridType="Uniform">']
            + _grid_xml(h5name, "mesh", len(pts), len(lines)))

    def write_h5(tmp: Path) -> None:
        with h5py.File(tmp, "w", locking=False) as h5:
            h5.attrs["fem_dual"] = "trajectory"
            h5.create_dataset("mesh/geometry", data=pts)
            h5.create_dataset("mesh/topology", data=lines)
            for name, values in data.items():
                values = np.asarray(values, dtype=float)
                h5.create_dataset(f"data/{name}", data=values)
                body.extend([f'<Attribute Name="{name}" AttributeType='
                             f'"{_attribute_type(values.shape)}" Center="Node">',
                             _data_item(h5name, f"/data/{name}", values.shape), "</Attribute>"])

    ensure_space(path.parent, SPACE_MARGIN + 3 * pts.nbytes)
    _replace_atomically(path.with_suffix(".h5"), write_h5)
    text = _head_xml(body + ["</Grid>"]) + "</Domain>\n</Xdmf>\n"
    _replace_atomically(path, lambda tmp: tmp.write_text(text))


def read_series(path: "str | os.PathLike") -> Tuple[np.ndarray, np.ndarray, List[Dict]]:
    """(mesh points, times, [fields per step]) of an XDMF series as written here, read through
    its XML (hyperslabs resolved with h5py), as a viewer would."""
    import xml.etree.ElementTree as ET

    import h5py

    path = Path(path)
    root = ET.parse(path).getroot()
    files: Dict[str, "h5py.File"] = {}

    def item(node) -> np.ndarray:
        """The values of an HDF DataItem, of its hyperslab `|start:stride:count:dims` if it
        names one (only that part is read)."""
        name, h5path = node.text.strip().split(":", 1)
        h5path, _, slab = h5path.partition("|")
        if name not in files:
            files[name] = h5py.File(path.parent / name, "r", locking=False)
        dims = tuple(int(d) for d in node.get("Dimensions").split())
        data = files[name][h5path]
        if not slab:
            if data.shape[0] < dims[0] or data.shape[1:] != dims[1:]:
                raise ValueError(f"{path}: {h5path} holds {data.shape}, the XML declares {dims}")
            return data[:dims[0]]
        start, stride, count, full = (np.array(part.split(), dtype=int)
                                      for part in slab.split(":"))
        if data.shape[0] < full[0] or tuple(data.shape[1:]) != tuple(full[1:]):
            raise ValueError(f"{path}: {h5path} holds {data.shape}, the XML declares "
                             f"{tuple(full)}")
        if any(a + s * (c - 1) >= d for a, s, c, d in zip(start, stride, count, full)):
            raise ValueError(f"{path}: a hyperslab of {h5path} reaches beyond {tuple(full)}")
        index = tuple(slice(a, a + s * c, s) for a, s, c in zip(start, stride, count))
        return data[index].reshape(dims)

    try:
        grids = root.find("Domain").findall("Grid")
        points = item(grids[0].find("Geometry/DataItem"))
        times, steps = [], []
        for step in grids[1].findall("Grid"):
            times.append(float(step.find("Time").get("Value")))
            steps.append({a.get("Name"): item(a.find("DataItem"))
                          for a in step.findall("Attribute")})
    finally:
        for f in files.values():
            f.close()
    return points, np.array(times), steps
