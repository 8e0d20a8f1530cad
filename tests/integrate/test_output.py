"""Output that scales and survives faults: streamed XDMF/HDF5, kill -9, SIGINT and
SIGTERM, --resume, a full disk, stale files, an error on rank 0 only under MPI."""
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
from mpi4py import MPI

from fem_dual import RunConfig, run
from fem_dual import output as output_module
from fem_dual.cli import main
from fem_dual.errors import SolveError
from fem_dual.output import XdmfSeries, read_series

FEM_DUAL = str(Path(sys.executable).with_name("fem-dual"))
# slab by slab (no superposition): long enough to be signalled while it runs (in chunks of
# slab maps the whole run takes a second)
LONG = ["run", "ziegler", "--T", "40000", "--slabs", "20000", "--cells", "16", "--degree", "5",
        "--superpose", "no"]


def _rows_of(path: Path):
    """(steps the XML names, rows the HDF5 file holds)."""
    with h5py.File(path.with_suffix(".h5"), "r") as h5:
        rows = len(h5["steps/time"])
    return len(read_series(path)[2]), rows


@pytest.mark.serial
def test_series_appends_each_step_once(tmp_path, monkeypatch):
    """The XML bytes written over a run equal the file's size (plus one closing tail per
    flush): nothing is rewritten, so output is linear in the slab count."""
    monkeypatch.setattr(output_module, "FLUSH_SECONDS", 0.0)  # flush every step
    written = []
    real = os.pwrite
    monkeypatch.setattr(os, "pwrite", lambda fd, data, off: written.append(len(data)) or
                        real(fd, data, off))
    fields = {"a": (5,), "b": (5, 2)}
    series = XdmfSeries(tmp_path / "s.xdmf", np.linspace(0, 1, 5), fields, {"r": (3,)}, {})
    steps = 2000
    for k in range(steps):
        series.write(float(k), {"a": np.full(5, k), "b": np.full((5, 2), -k)}, {"r": [k] * 3})
    series.close()
    size = (tmp_path / "s.xdmf").stat().st_size
    tail = len(output_module._TAIL)
    assert len(written) == steps
    assert sum(written) <= size + steps * tail
    _, times, data = read_series(tmp_path / "s.xdmf")
    assert np.array_equal(times, np.arange(steps))
    assert all(np.array_equal(d["b"], np.full((5, 2), -k)) for k, d in enumerate(data))


def _start(argv, out, **kw):
    return subprocess.Popen([FEM_DUAL, *argv, "--out", str(out), "--json"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kw)


def _wait_for_steps(out: Path, name="ziegler", steps=1, timeout=60.0):
    """Wait until the series on disk names at least `steps` steps."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        try:
            if _rows_of(out / f"{name}.xdmf")[0] >= steps:
                return
        except (OSError, ValueError, IndexError, KeyError, Exception):
            pass
        time.sleep(0.05)
    raise AssertionError(f"no {steps} steps in {out} after {timeout} s")


@pytest.mark.serial
@pytest.mark.parametrize("delay", [0.0, 0.13, 0.41])
def test_kill_9_leaves_a_readable_series(tmp_path, delay):
    out = tmp_path / "out"
    proc = _start(LONG, out)
    try:
        _wait_for_steps(out)
        time.sleep(delay)
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.communicate()
    assert proc.returncode == -signal.SIGKILL
    named, rows = _rows_of(out / "ziegler.xdmf")
    assert 1 <= named <= rows  # the XML names only rows that are in the HDF5 file
    assert not any(p.name.startswith(".") for p in out.iterdir())  # nothing hidden owns them
    _, times, steps = read_series(out / "ziegler.xdmf")
    assert np.allclose(times, 2.0 * np.arange(named))  # slab k starts at 2k
    assert all(np.isfinite(s["x_hat"]).all() for s in steps)


@pytest.mark.serial
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM, signal.SIGUSR1])
def test_signal_stops_after_a_slab_and_keeps_everything(tmp_path, sig):
    out = tmp_path / "out"
    proc = _start(LONG, out)
    _wait_for_steps(out)
    proc.send_signal(sig)
    stdout, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 128 + sig, stderr
    assert stderr.count("\n") == 1 and "Traceback" not in stderr, stderr
    assert f"interrupted by {signal.Signals(sig).name}" in stderr and "kept" in stderr
    data = json.loads(stdout)
    slabs = len(data["slab_lengths"])
    assert data["status"] == "interrupted" and 0 < slabs < 20000
    assert data["output_slabs"] == slabs  # flushed on the way out
    assert _rows_of(out / "ziegler.xdmf") == (slabs, slabs)
    assert (out / "ziegler_trajectory.xdmf").exists()


@pytest.mark.serial
def test_sigusr1_to_mpirun_stops_every_rank_after_a_slab(tmp_path):
    """mpirun kills its ranks on SIGINT/SIGTERM (what is on disk then is what kill -9 leaves)
    but forwards SIGUSR1: the graceful stop under MPI."""
    out = tmp_path / "out"
    env = dict(os.environ, OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1",
               OMPI_MCA_rmaps_base_oversubscribe="1")
    proc = subprocess.Popen(["mpirun", "-n", "2", FEM_DUAL, *LONG, "--out", str(out), "--json"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    _wait_for_steps(out)
    proc.send_signal(signal.SIGUSR1)
    stdout, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 128 + signal.SIGUSR1, stderr
    assert "interrupted by SIGUSR1" in stderr and "Traceback" not in stderr
    data = json.loads(stdout)
    assert data["status"] == "interrupted" and data["output_slabs"] == len(data["slab_lengths"])


@pytest.mark.serial
def test_resume_ends_where_an_uninterrupted_run_ends(tmp_path):
    argv = ["run", "ziegler", "--T", "4000", "--slabs", "2000", "--cells", "16", "--degree", "5",
            "--superpose", "no"]
    whole = subprocess.run([FEM_DUAL, *argv, "--out", str(tmp_path / "a"), "--json"],
                           capture_output=True, text=True, check=True)
    proc = _start(argv, tmp_path / "b")
    _wait_for_steps(tmp_path / "b")
    proc.send_signal(signal.SIGINT)
    first = json.loads(proc.communicate(timeout=60)[0])
    assert first["status"] == "interrupted"
    again = subprocess.run([FEM_DUAL, *argv, "--out", str(tmp_path / "b"), "--json",
                            "--resume"], capture_output=True, text=True)
    assert again.returncode == 0, again.stderr
    a, b = json.loads(whole.stdout), json.loads(again.stdout)
    assert b["solver"]["resumed_from"]["slab"] == len(first["slab_lengths"])
    assert b["final"] == a["final"]  # bit for bit
    assert b["t"] == a["t"] and b["x"] == a["x"] and b["error_estimate"] == a["error_estimate"]
    assert _rows_of(tmp_path / "b" / "ziegler.xdmf") == (2000, 2000)


@pytest.mark.serial
def test_resume_with_other_options_names_the_difference(tmp_path, capsys):
    args = ["run", "ziegler", "--T", "4", "--slabs", "2", "--cells", "8", "--out", str(tmp_path)]
    assert main(args) == 0
    capsys.readouterr()
    assert main(args[:3] + ["5"] + args[4:] + ["--resume"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "T=4.0" in err and "T=5.0" in err
    assert main(["run", "ziegler", "--T", "4", "--resume"]) == 2  # no --out to go on from
    assert main(["run", "curl2d", "--T", "1", "--out", str(tmp_path), "--resume"]) == 2
    assert "does not exist" in capsys.readouterr().err


def _full_after(monkeypatch, flushes_ok):
    """The disk fills after `flushes_ok` flushes (fem_dual.output measures free space when it
    creates the series and before every flush)."""
    calls = {"n": -1}
    real = output_module.free_bytes

    def free(directory):
        calls["n"] += 1
        return real(directory) if calls["n"] <= flushes_ok else 1000
    monkeypatch.setattr(output_module, "free_bytes", free)
    monkeypatch.setattr(output_module, "FLUSH_SECONDS", 0.0)


@pytest.mark.serial
def test_full_disk_is_a_failure_with_json_and_readable_files(tmp_path, monkeypatch, capsys):
    _full_after(monkeypatch, 3)
    out = tmp_path / "out"
    assert main(["run", "ziegler", "--T", "20", "--slabs", "10", "--cells", "8", "--json",
                 "--out", str(out)]) == 3
    captured = capsys.readouterr()
    assert captured.err.count("\n") == 1 and "No space left on device" in captured.err
    data = json.loads(captured.out)
    assert data["status"] == "failed" and data["output_slabs"] == 3
    assert len(data["slab_lengths"]) == 4  # the slab whose write failed is in the JSON
    assert _rows_of(out / "ziegler.xdmf") == (3, 3)


@pytest.mark.serial
def test_stale_files_of_an_earlier_run_do_not_survive(tmp_path, capsys):
    assert main(["run", "ziegler", "--T", "2", "--slabs", "2", "--cells", "8",
                 "--out", str(tmp_path)]) == 0
    assert len(list(tmp_path.iterdir())) == 4
    # under-resolved from the first slab: fails before any slab is written
    assert main(["run", "ziegler", "--T", "2000", "--slabs", "1", "--cells", "2", "--degree",
                 "2", "--max-halvings", "0", "--out", str(tmp_path)]) == 3
    assert sorted(p.name for p in tmp_path.iterdir()) == []


@pytest.mark.serial
def test_files_fem_dual_did_not_write_are_never_removed(tmp_path, capsys):
    for name in ("ziegler.xdmf", "ziegler.h5", "ziegler_trajectory.h5"):
        (tmp_path / name).write_text("precious")
    assert main(["run", "ziegler", "--T", "2", "--slabs", "2", "--cells", "8",
                 "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "not written by fem-dual" in err
    assert all((tmp_path / name).read_text() == "precious"
               for name in ("ziegler.xdmf", "ziegler.h5", "ziegler_trajectory.h5"))


@pytest.mark.serial
def test_two_runs_never_write_one_directory(tmp_path):
    proc = _start(LONG, tmp_path)
    try:
        _wait_for_steps(tmp_path)
        done = subprocess.run([FEM_DUAL, "run", "curl2d", "--T", "1", "--out", str(tmp_path)],
                              capture_output=True, text=True)
        assert done.returncode == 2 and "in use by another fem-dual run" in done.stderr
    finally:
        proc.send_signal(signal.SIGINT)
        proc.communicate(timeout=60)


def _tamper(path: Path, edit) -> None:
    with h5py.File(path, "a") as h5:
        edit(h5)


@pytest.mark.serial
@pytest.mark.parametrize("edit", [
    lambda h5: h5.attrs.__setitem__("fem_dual", "[1, 2]"),
    lambda h5: h5["steps/x_hat"].resize(1, axis=0),
    lambda h5: h5["restart/slab"].__setitem__((1, 2), np.nan),
    lambda h5: h5.__delitem__("restart/glob"),
])
def test_resume_refuses_a_damaged_file(tmp_path, capsys, edit):
    args = ["run", "ziegler", "--T", "4", "--slabs", "2", "--cells", "8", "--out", str(tmp_path)]
    assert main(args) == 0
    _tamper(tmp_path / "ziegler.h5", edit)
    capsys.readouterr()
    assert main(args + ["--resume"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err and "--resume" in err


@pytest.mark.serial
def test_an_out_that_cannot_take_the_series_is_bad_input(tmp_path, capsys):
    (tmp_path / "ziegler.xdmf").mkdir()  # the series cannot be written there
    assert main(["run", "ziegler", "--T", "2", "--slabs", "2", "--cells", "8", "--json",
                 "--out", str(tmp_path)]) == 2
    captured = capsys.readouterr()
    assert captured.err.count("\n") == 1 and "ziegler.xdmf" in captured.err
    assert captured.out == ""


@pytest.mark.serial
def test_petsc_monitor_output_leaves_json_alone(tmp_path):
    done = subprocess.run([FEM_DUAL, "run", "ziegler", "--T", "2", "--slabs", "2", "--cells",
                           "8", "--json", "--petsc-option", "ksp_monitor=",
                           "--petsc-option", "ksp_view="], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    json.loads(done.stdout)  # one JSON object and nothing else
    assert "KSP Object" in done.stderr or "residual norm" in done.stderr


@pytest.mark.mpi
def test_an_output_error_on_rank_0_only_ends_every_rank(tmp_path_factory, monkeypatch):
    comm = MPI.COMM_WORLD
    out = Path(comm.bcast(str(tmp_path_factory.mktemp("full")) if comm.rank == 0 else None))
    if comm.rank == 0:
        _full_after(monkeypatch, 2)
    config = RunConfig.create("ziegler", T=20.0, slabs=10, cells=8, out=out)
    with pytest.raises(SolveError, match="No space left on device") as info:
        run(config, comm)
    assert info.value.partial.status == "failed"
    assert len(info.value.partial.slab_lengths) == 3
    assert info.value.partial.output_slabs == 2


@pytest.mark.serial
@pytest.mark.parametrize("options", ["-log_view", "-options_left", "-help"])
def test_petsc_printing_at_start_or_exit_leaves_json_alone(options):
    done = subprocess.run([FEM_DUAL, "run", "ziegler", "--T", "2", "--slabs", "2", "--cells",
                           "8", "--json"], capture_output=True, text=True,
                          env=dict(os.environ, PETSC_OPTIONS=options))
    assert done.returncode == 0, done.stderr[-500:]
    assert json.loads(done.stdout)["status"] == "ok"  # one JSON object and nothing else
    assert len(done.stderr) > 100  # PETSc's output went there


@pytest.mark.serial
def test_petsc_integer_beyond_its_range_is_bad_input(capsys):
    assert main(["run", "ziegler", "--T", "2", "--petsc-option", "ksp_type=cg",
                 "--petsc-option", "ksp_max_it=2147483648"]) == 2
    assert "ksp_max_it=2147483648" in capsys.readouterr().err


@pytest.mark.serial
def test_a_failed_csv_write_says_failed_and_leaves_no_partial_file(tmp_path, capsys,
                                                                   monkeypatch):
    import fem_dual.integrate.result as driver_module

    def full(path, *args, **kwargs):
        with open(path, "w") as f:
            f.write("t,x1\n0.0,0.1\n1.5,0.")  # cut mid-number, as a full disk leaves it
        raise OSError(28, "No space left on device", str(path))
    monkeypatch.setattr(driver_module.np, "savetxt", full)
    status = main(["run", "ziegler", "--T", "2", "--slabs", "2", "--cells", "8", "--json",
                   "--csv", str(tmp_path / "x.csv")])
    monkeypatch.undo()
    captured = capsys.readouterr()
    assert status == 3 and "No space left on device" in captured.err
    data = json.loads(captured.out)
    assert data["status"] == "failed" and "No space left" in data["message"]
    assert list(tmp_path.iterdir()) == []
