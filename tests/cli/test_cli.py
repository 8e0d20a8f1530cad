"""The command line: JSON contract, exit statuses, one-line errors, output files."""
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Optional

import meshio
import numpy as np
import pytest
from fem_dual.output import read_series
from mpi4py import MPI

from fem_dual.cli import main

FEM_DUAL = [sys.executable, "-m", "fem_dual.cli"]

BAD_INPUTS = [
    (["run", "nosuchscene"], "nosuchscene"),
    (["run", "ziegler", "--param", "nosuch=1"], "nosuch"),
    (["run", "ziegler", "--param", "m1"], "m1"),
    (["run", "ziegler", "--param", "P=abc"], "abc"),
    (["run", "ziegler", "--T", "0"], "T="),
    (["run", "ziegler", "--T", "-3"], "-3"),
    (["run", "ziegler", "--T", "inf"], "inf"),
    (["run", "ziegler", "--cells", "0"], "cells"),
    (["run", "ziegler", "--cells", "2.5"], "cells"),
    (["run", "ziegler", "--degree", "0"], "degree"),
    (["run", "ziegler", "--slabs", "0"], "slabs"),
    (["run", "ziegler", "--slabs", "many"], "many"),
    (["run", "ziegler", "--x0", "1,2,3"], "x0"),
    (["run", "ziegler", "--x0", "1,nan"], "nan"),
    (["run", "ziegler", "--v0", "1,inf"], "inf"),
    (["run", "ziegler", "--param", "m1=0"], "m1"),
    (["run", "ziegler", "--param", "m2=-1"], "m2"),
    (["run", "ziegler", "--param", "l=0"], "l="),
    (["run", "ziegler", "--param", "A=1,2,2,1"], "A="),
    (["run", "ziegler", "--param", "A=1,0.5,0,1"], "A="),
    (["run", "ziegler", "--param", "B=-1"], "B="),
    (["run", "ziegler", "--param", "B=1,2,3"], "B="),
    (["run", "ziegler", "--cells", "100000000", "--slabs", "10"], "too large"),
    (["run", "curl2d", "--max-halvings", "-2"], "max-halvings"),
    (["run", "curl3d", "--param", "alpha=0"], "alpha"),
    (["run", "curl2d", "--x0", "1"], "x0"),
    (["run", "column", "--param", "links=1"], "links"),
    (["run", "column", "--param", "links=2.5"], "links"),
    (["run", "column", "--param", "links=3", "--param", "m=1,2"], "m="),
    (["run", "column", "--param", "m=0"], "m="),
    (["run", "linear", "--param", "M=1,2,2,1"], "M="),
    (["run", "linear", "--param", "dofs=0"], "dofs"),
    (["run", "linear", "--param", "dofs=3", "--param", "K=1,2"], "K="),
]


@pytest.mark.serial
@pytest.mark.parametrize("argv, named", BAD_INPUTS)
def test_bad_input_is_one_line_exit_2_and_touches_nothing(argv, named, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(argv + ["--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("fem-dual: error:"), err
    assert named in err
    assert "Traceback" not in err
    assert not out.exists()


@pytest.mark.serial
def test_unwritable_out_is_bad_input(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    assert main(["run", "ziegler", "--cells", "4", "--out", str(blocker / "sub")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--out" in err
    assert blocker.read_text() == "not a directory"


@pytest.mark.serial
def test_bad_input_through_the_installed_entry_point(tmp_path):
    proc = subprocess.run(FEM_DUAL + ["run", "ziegler", "--T", "nan"], capture_output=True,
                          text=True, stdin=subprocess.DEVNULL, cwd=tmp_path)
    assert proc.returncode == 2
    assert proc.stderr.strip() == "fem-dual: error: T='nan' is not finite"
    assert proc.stdout == ""


@pytest.mark.mpi
def test_json_contract(capsys):
    assert main(["run", "ziegler", "--cells", "20", "--degree", "3", "--slabs", "2",
                 "--T", "4", "--x0", "-0.1,0.05", "--json"]) == 0
    out = capsys.readouterr().out
    if MPI.COMM_WORLD.rank != 0:
        assert out == ""
        return
    data = json.loads(out)
    for key in ("scene", "T", "cells", "degree", "slabs", "t", "x", "v", "final", "error",
                "hamiltonian", "timings"):
        assert key in data
    assert data["x0"] == [-0.1, 0.05]
    assert len(data["t"]) == 2 * 20 + 1 and data["t"][-1] == pytest.approx(4.0)
    assert np.array(data["x"]).shape == (41, 2) and np.array(data["v"]).shape == (41, 2)
    assert data["final"]["x"] == data["x"][-1] and data["final"]["v"] == data["v"][-1]
    assert set(data["error"]) >= {"x_max", "v_max", "final"}
    assert data["error"]["x_max"] < 1e-4
    assert set(data["hamiltonian"]) >= {"min", "max", "drift"}
    tm = data["timings"]
    assert set(tm) >= {"total_s", "compile_s", "setup_s", "solve_s"}
    # the total holds the set-up (building and checking the inputs), the compile and the slabs
    assert tm["setup_s"] > 0 and tm["solve_s"] > 0
    assert tm["total_s"] >= tm["setup_s"] + tm["compile_s"] + tm["solve_s"] + tm["estimate_s"]


@pytest.mark.mpi
def test_xdmf_output_matches_json(tmp_path_factory, capsys):
    comm = MPI.COMM_WORLD
    out = Path(comm.bcast(str(tmp_path_factory.mktemp("out")) if comm.rank == 0 else None))
    assert main(["run", "ziegler", "--cells", "10", "--slabs", "3", "--T", "3", "--json",
                 "--out", str(out)]) == 0
    if comm.rank != 0:
        return
    data = json.loads(capsys.readouterr().out)
    names = sorted(os.listdir(out))
    assert names == ["ziegler.h5", "ziegler.xdmf", "ziegler_trajectory.h5",
                     "ziegler_trajectory.xdmf"]  # no temporary directory left behind
    points, times, steps = read_series(out / "ziegler.xdmf")
    assert len(steps) == 3 and len(points) == 11
    assert np.allclose(times, [0.0, 1.0, 2.0])
    t_all = []
    for k, pdata in enumerate(steps):
        assert set(pdata) == {"t", "xi", "eta", "x_hat", "v_hat", "hamiltonian",
                              "error_estimate"}
        assert np.isfinite(pdata["x_hat"]).all()
        assert np.allclose(pdata["xi"][-1], 0) and np.allclose(pdata["eta"][-1], 0)
        t_all.append(pdata["t"] if k == 0 else pdata["t"][1:])
    x_all = np.concatenate([s["x_hat"][(0 if k == 0 else 1):] for k, s in enumerate(steps)])
    assert np.array_equal(x_all, np.array(data["x"]))  # float64, bit for bit
    assert np.allclose(np.concatenate(t_all), data["t"])
    traj = meshio.read(out / "ziegler_trajectory.xdmf")
    assert np.allclose(traj.points[:, :2], data["x"])
    assert np.allclose(traj.point_data["t"], data["t"])


@pytest.mark.serial
def test_progress_bar_goes_to_stderr_and_never_with_json(capsys, monkeypatch):
    from fem_dual import RunConfig, run
    run(RunConfig.create("ziegler", cells=4, slabs=5, T=1.0), progress=True)
    captured = capsys.readouterr()
    assert captured.out == "" and "slabs" in captured.err
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True, raising=False)
    assert main(["run", "ziegler", "--cells", "4", "--slabs", "5", "--T", "1", "--json"]) == 0
    captured = capsys.readouterr()
    json.loads(captured.out)
    assert captured.err == ""
    assert main(["run", "ziegler", "--cells", "4", "--slabs", "5", "--T", "1"]) == 0
    assert "slabs" in capsys.readouterr().err  # the terminal case shows the bar


@pytest.mark.serial
def test_bench_takes_a_user_force_with_its_start_state(tmp_path, capsys):
    assert main(["bench", "force", "--param", "F=-x - 2*x*y, -y - x**2 + y**2", "--x0",
                 "0.3,0.1", "--T", "1", "--cells", "2", "--degrees", "3", "--repeats", "1",
                 "--rtols", "1e-6", "--out", str(tmp_path), "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)["rows"]
    adaptive = [r for r in rows if r["method"] == "fem-dual-rtol"]
    assert len(adaptive) == 1 and adaptive[0]["max_error"] <= adaptive[0]["estimate"]


def test_bench_runs_on_a_tiny_configuration(tmp_path, capsys):
    import csv

    assert main(["bench", "curl3d", "--T", "0.5", "--cells", "2,4", "--degrees", "2",
                 "--repeats", "1", "--rtols", "1e-7", "--out", str(tmp_path), "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)["rows"]
    methods = {r["method"] for r in rows}
    assert methods == {"fem-dual", "fem-dual-rtol", "RK45", "DOP853", "DOP853-f", "Radau",
                       "LSODA"}  # no expm: a nonlinear scene
    adaptive = [r for r in rows if r["method"] == "fem-dual-rtol"]
    assert [r["rtol"] for r in adaptive] == [1e-7] and adaptive[0]["max_error"] <= 1e-6
    assert {r["rtol"] for r in rows if r["method"] == "DOP853"} >= {1e-7}  # the same tolerance
    for r in rows:
        assert set(r) >= {"method", "degree", "cells", "slabs", "rtol", "max_error",
                          "final_error", "wall_s"}
        assert r["wall_s"] > 0 and np.isfinite(r["max_error"])
    fem = [r for r in rows if r["method"] == "fem-dual"]
    assert fem[1]["max_error"] < fem[0]["max_error"]  # refinement pays
    with open(tmp_path / "bench.csv") as f:
        assert len(list(csv.DictReader(f))) == len(rows)
    png = (tmp_path / "bench.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 5000


@pytest.mark.serial
def test_version(capsys):
    from fem_dual import __version__

    with pytest.raises(SystemExit) as exit_info:
        main(["--version"])
    assert exit_info.value.code == 0
    assert capsys.readouterr().out.strip() == f"fem-dual {__version__}"


def test_a_failed_run_writes_its_partial_json_with_infinite_residuals_as_null(capsys,
                                                                            monkeypatch):
    """A rejected attempt whose first residual overflows keeps inf in the residual history:
    the partial result's JSON writes it as null, and the run ends with exit 3 and the slabs
    kept, not a ValueError (a traceback, exit 1). An rk4 base of p + 1 steps a cell
    (RK4_STEPS_PER_NODE = 1; the default is 8 (p + 1)) leads there."""
    monkeypatch.setattr("fem_dual.slab.problem.RK4_STEPS_PER_NODE", 1)
    assert main(["run", "curl3d", "--base", "rk4", "--T", "50", "--rtol", "1e-10", "--degree",
                 "6", "--cells", "8", "--json"]) == 3
    data = json.loads(capsys.readouterr().out)
    assert data["status"] == "failed" and len(data["t"]) > 1
    assert None in data["solver"]["residual_norms"]
    assert np.isfinite(np.array(data["x"])).all()


def test_a_cache_home_that_is_a_file_is_bad_input(tmp_path, monkeypatch, capsys):
    """FFCx and the compiled loops keep their libraries under $XDG_CACHE_HOME: a file there is
    exit 2 naming it, not a traceback from the JIT (exit 1); so is a file above it (a cache
    home below a file) or in place of its fenics folder. Listing the scenes compiles nothing
    and still answers."""
    cache = tmp_path / "cache"
    cache.write_text("")
    monkeypatch.setenv("XDG_CACHE_HOME", str(cache))
    for home in (cache, cache / "below", cache / "below" / "fenics"):
        monkeypatch.setenv("XDG_CACHE_HOME", str(home))
        assert main(["run", "curl3d", "--T", "1", "--cells", "2"]) == 2
        err = capsys.readouterr().err
        assert str(cache) in err and "not a directory" in err and "Traceback" not in err
    (tmp_path / "home").mkdir()
    (tmp_path / "home" / "fenics").write_text("")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "home"))
    assert main(["run", "curl3d", "--T", "1", "--cells", "2"]) == 2
    assert "fenics is not a directory" in capsys.readouterr().err
    assert main(["scenes"]) == 0


@pytest.mark.serial
def test_a_process_without_a_launcher_skips_mpis_pml_probe_and_a_launched_one_keeps_it(
        monkeypatch, tmp_path):
    """The command alone takes Open MPI's ob1 pml (probing the others costs 0.2 s of its
    start-up); a launcher's rank, or a user's own choice in the environment or in a parameter
    file, keeps what it has. A file that only excludes other pmls leaves ob1 free."""
    from fem_dual import cli

    for name in cli._LAUNCHED + ("OMPI_MCA_pml", "OMPI_MCA_mca_base_param_files"):
        monkeypatch.delenv(name, raising=False)
    params = tmp_path / "mca-params.conf"
    monkeypatch.setattr(cli, "_MCA_FILES", (str(params),))

    def chosen(text=None, **env) -> Optional[str]:
        if text is not None:
            params.write_text(text)
        with monkeypatch.context() as patch:
            patch.delenv("OMPI_MCA_pml", raising=False)
            for name, value in env.items():
                patch.setenv(name, value)
            cli._singleton_mpi_defaults()
            return os.environ.get("OMPI_MCA_pml")
    assert chosen() == "ob1"  # no file
    assert chosen("# none\nbtl = ^openib\n") == "ob1"
    assert chosen("pml = ^ucx  # excluded only\n") == "ob1"
    assert chosen("pml = ucx\n") is None  # the user's choice
    assert chosen("pml = ^cm, ob1\n") is None  # ob1 excluded
    assert chosen("btl = self\n", OMPI_MCA_pml="ucx") == "ucx"
    assert chosen(OMPI_COMM_WORLD_SIZE="2") is None  # a launcher's rank
    other = tmp_path / "other.conf"
    other.write_text("pml = cm\n")
    assert chosen("", OMPI_MCA_mca_base_param_files=str(other)) is None
    # Open MPI's list is comma-separated, and replaces its default files
    assert chosen("", OMPI_MCA_mca_base_param_files=f"{tmp_path / 'none'},{other}") is None
    assert chosen("pml = ucx\n", OMPI_MCA_mca_base_param_files=str(tmp_path / "none")) == "ob1"
    # what is not a regular file is not read (a FIFO would block, a device never end)
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    assert chosen("", OMPI_MCA_mca_base_param_files=f"{fifo},/dev/zero") == "ob1"


@pytest.mark.serial
def test_odd_launcher_and_cache_variables_are_not_a_traceback(tmp_path):
    """A launcher variable that is not a number is no launcher's; an empty XDG_CACHE_HOME is the
    default cache (~/.cache), not a `fenics` directory in the working directory."""
    env = dict(os.environ, OMPI_COMM_WORLD_SIZE="\u00b2", PMI_SIZE="two", XDG_CACHE_HOME="")
    for name in ("PMIX_RANK", "PMI_RANK", "SLURM_PROCID"):
        env.pop(name, None)
    fem_dual = str(Path(sys.executable).parent / "fem-dual")
    done = subprocess.run([fem_dual, "--version"], capture_output=True, text=True, env=env,
                          cwd=tmp_path, timeout=60)
    assert done.returncode == 0 and not done.stderr, done.stderr
    env = dict(os.environ, XDG_CACHE_HOME="")
    done = subprocess.run([fem_dual, "run", "ziegler", "--T", "1", "--json"], capture_output=True,
                          text=True, env=env, cwd=tmp_path, timeout=300)
    assert done.returncode == 0, done.stderr
    assert not (tmp_path / "fenics").exists()


@pytest.mark.serial
def test_a_damaged_jit_cache_is_one_line_not_a_traceback(monkeypatch, capsys):
    """A compiled module that FFCx's cache marks ready but cannot load (deleted, truncated)."""
    from fem_dual.integrate import simulation

    def damaged(*args, **kwargs):
        raise ModuleNotFoundError("Unable to find JIT module.")
    monkeypatch.setattr(simulation, "make_backend", damaged)
    status = main(["run", "ziegler", "--T", "1"])
    err = capsys.readouterr().err
    assert status == 3 and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert "FFCx's cache of compiled forms" in err and "remove that directory" in err


def test_a_compilation_left_unfinished_is_compiled_again_not_waited_for(tmp_path):
    """A process killed while it compiled leaves a module's C file without FFCx's `.c.cached`
    marker; the next run takes the module's lock (no fem-dual process compiles it) and compiles
    it again, where FFCx alone waited its whole timeout (600 s). While another process holds
    the lock, the module is left to it."""
    from fem_dual import jit_lock

    env = dict(os.environ, XDG_CACHE_HOME=str(tmp_path / "cache"))
    fem_dual = str(Path(sys.executable).parent / "fem-dual")
    command = [fem_dual, "run", "ziegler", "--T", "1", "--json"]
    first = subprocess.run(command, capture_output=True, text=True, env=env, timeout=600)
    assert first.returncode == 0, first.stderr
    cache = tmp_path / "cache" / "fenics"
    markers = sorted(cache.glob("libffcx_expressions_*.c.cached"))
    assert markers
    markers[0].unlink()  # as a compilation killed before its end leaves it
    again = subprocess.run(command, capture_output=True, text=True, env=env, timeout=120)
    assert again.returncode == 0, again.stderr
    assert markers[0].exists()  # compiled again
    assert json.loads(again.stdout)["final"] == json.loads(first.stdout)["final"]
    # a lock held elsewhere: this process does not take it
    name = markers[0].name[:-len(".c.cached")]
    holder = subprocess.Popen([sys.executable, "-c", (
        "import fcntl, sys, time; f = open(sys.argv[1], 'a'); "
        "fcntl.flock(f, fcntl.LOCK_EX); print('held', flush=True); time.sleep(30)"),
        str(cache / f"{name}.lock")], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        assert not jit_lock._take(cache, name)
    finally:
        holder.kill()
        holder.wait()
    assert jit_lock._take(cache, name)  # free again
    jit_lock._release(name)
    # a run already waiting when the compiling process ends without its marker compiles the
    # module itself once the lock is free
    markers[0].unlink()
    holder = subprocess.Popen([sys.executable, "-c", (
        "import fcntl, sys, time; f = open(sys.argv[1], 'a'); "
        "fcntl.flock(f, fcntl.LOCK_EX); print('held', flush=True); time.sleep(3)"),
        str(cache / f"{name}.lock")], stdout=subprocess.PIPE, text=True)
    assert holder.stdout.readline().strip() == "held"
    waited = subprocess.run(command, capture_output=True, text=True, env=env, timeout=120)
    holder.wait()
    assert waited.returncode == 0 and markers[0].exists(), waited.stderr
    # a marker without its C file (two compilations collided: FFCx then failed on every run)
    # is compiled again; a FIFO at a lock's path is no lock (FFCx's own protocol), not a hang
    element = sorted(cache.glob("libffcx_elements_*.c.cached"))[0].name[:-len(".c.cached")]
    (cache / f"{element}.c").unlink()
    repaired = subprocess.run(command, capture_output=True, text=True, env=env, timeout=120)
    assert repaired.returncode == 0 and (cache / f"{element}.c").exists(), repaired.stderr
    (cache / f"{element}.lock").unlink()
    os.mkfifo(cache / f"{element}.lock")
    fifo = subprocess.run(command, capture_output=True, text=True, env=env, timeout=120)
    assert fifo.returncode == 0, fifo.stderr
