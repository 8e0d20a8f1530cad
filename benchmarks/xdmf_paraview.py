"""Check that ParaView's XDMF readers read fem-dual's output (needs Debian's `paraview`, which
the project does not install: `apt-get install paraview`). Run with pvpython:

    pvpython benchmarks/xdmf_paraview.py DIR/ziegler.xdmf

For each reader it prints the steps it sees, the point arrays and the largest difference of
`x_hat` and `t` from the HDF5 rows at the first and last step.
"""
import sys

import h5py
import numpy as np
import paraview.simple as pvs
from paraview import servermanager
from vtkmodules.util.numpy_support import vtk_to_numpy


def leaves(obj):
    if obj.IsA("vtkMultiBlockDataSet"):
        return [leaf for i in range(obj.GetNumberOfBlocks()) for leaf in leaves(obj.GetBlock(i))]
    return [obj]


def check(reader_name: str, path: str) -> None:
    kw = {"FileNames" if reader_name == "XDMFReader" else "FileName": [path]}
    reader = getattr(pvs, reader_name)(**kw)
    reader.UpdatePipelineInformation()
    times = list(reader.TimestepValues or [])
    with h5py.File(path[:-5] + ".h5", "r", locking=False) as h5:
        worst, names = 0.0, set()
        for k in (0, len(times) - 1):
            reader.UpdatePipeline(times[k])
            for ds in leaves(servermanager.Fetch(reader)):
                pd = ds.GetPointData()
                names |= {pd.GetArrayName(i) for i in range(pd.GetNumberOfArrays())}
                for name in ("x_hat", "t"):
                    if pd.GetArray(name) is None:
                        continue
                    got = vtk_to_numpy(pd.GetArray(name)).reshape(len(h5[f"steps/{name}"][k]), -1)
                    want = h5[f"steps/{name}"][k].reshape(len(got), -1)
                    worst = max(worst, float(np.abs(got[:, :want.shape[1]] - want).max()))
    print(f"{reader_name}: {len(times)} steps, arrays {sorted(names) or 'none'}, "
          f"max difference {worst:.3g}")


for name in ("Xdmf3ReaderS", "Xdmf3ReaderT", "XDMFReader"):
    check(name, sys.argv[1])
