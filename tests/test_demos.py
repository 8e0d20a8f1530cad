"""Demos are tested by running them, in a temporary directory (DOLFINx python/demo/test.py)."""
import os
import subprocess
import sys
from pathlib import Path

import pytest

DEMOS = sorted((Path(__file__).parent.parent / "demos").glob("demo_*.py"))
ENV = {**os.environ, "OMPI_ALLOW_RUN_AS_ROOT": "1", "OMPI_ALLOW_RUN_AS_ROOT_CONFIRM": "1",
       "OMPI_MCA_rmaps_base_oversubscribe": "1"}


def _check(proc, cwd, demo):
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "error against" in proc.stdout or "error" in proc.stdout
    scene = demo.stem.removeprefix("demo_")
    written = sorted(p.name for p in (cwd / f"out_{scene}").iterdir())
    scene = {"cauchy": "cauchy2d"}.get(scene, scene)  # (the demo of the scene family)
    assert f"{scene}.xdmf" in written or f"{scene}.png" in written, written
    if demo.stem == "demo_cauchy":  # the sparse run within its estimate of the exact motion
        line = proc.stdout.split("estimated error ")[-1].split("\n")[0]
        estimate, error = float(line.split(";")[0]), float(line.split("u' ")[-1])
        assert error <= estimate, line


@pytest.mark.serial
@pytest.mark.parametrize("demo", DEMOS, ids=[d.stem for d in DEMOS])
def test_demo_runs(demo, tmp_path):
    proc = subprocess.run([sys.executable, str(demo)], cwd=tmp_path, capture_output=True,
                          text=True, stdin=subprocess.DEVNULL, env=ENV, timeout=600)
    _check(proc, tmp_path, demo)


# the flutter demo's two searches per damping take 20 s under mpirun: with --slow
UNDER_MPIRUN = [pytest.param(d, marks=pytest.mark.slow) if d.stem == "demo_flutter" else d
                for d in DEMOS]


@pytest.mark.serial
@pytest.mark.parametrize("demo", UNDER_MPIRUN, ids=[d.stem for d in DEMOS])
def test_demo_runs_under_mpirun(demo, tmp_path):
    proc = subprocess.run(["mpirun", "-n", "2", sys.executable, str(demo)], cwd=tmp_path,
                          capture_output=True, text=True, stdin=subprocess.DEVNULL, env=ENV,
                          timeout=600)
    _check(proc, tmp_path, demo)
    assert proc.stdout.count("wrote ") == 1  # printed on rank 0 only
