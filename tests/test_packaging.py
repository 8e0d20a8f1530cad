"""An installable package that leaves its host process alone."""
import logging
import subprocess
import sys
import tomllib
from importlib import metadata
from pathlib import Path

import pytest

from fem_dual import RunConfig, run

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.serial
def test_declared_dependencies_are_the_installed_ones():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    names = [req.split(">")[0].split("<")[0].split("=")[0].strip()
             for req in project["dependencies"]]
    assert {"fenics-dolfinx", "petsc4py", "mpi4py", "numpy", "scipy"} <= set(names)
    for name in names:
        metadata.version(name)  # raises PackageNotFoundError when pip could not see it


@pytest.mark.serial
def test_a_run_leaves_the_logging_configuration_alone():
    loggers = [logging.getLogger(name) for name in ("", "ffcx", "UFL", "dolfinx")]
    before = [(log.level, list(log.handlers), list(log.filters)) for log in loggers]
    run(RunConfig.create("curl2d", T=0.3, slabs=1, cells=3, degree=8))  # a fresh JIT compile
    assert [(log.level, list(log.handlers), list(log.filters)) for log in loggers] == before


@pytest.mark.serial
def test_non_editable_install_runs_from_any_directory(tmp_path):
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--system-site-packages", str(venv)],
                   check=True)
    # the system interpreter behind the test's venv, as a user's fresh venv would have it
    subprocess.run([str(venv / "bin" / "python"), "-m", "pip", "install", "--quiet",
                    "--no-build-isolation", "--no-index", str(ROOT)], check=True,
                   cwd=tmp_path)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    done = subprocess.run([str(venv / "bin" / "fem-dual"), "run", "ziegler", "--T", "1",
                           "--cells", "4", "--json"], capture_output=True, text=True,
                          cwd=elsewhere)
    assert done.returncode == 0, done.stderr
    where = subprocess.run([str(venv / "bin" / "python"), "-c",
                            "import fem_dual; print(fem_dual.__file__)"], capture_output=True,
                           text=True, cwd=elsewhere, check=True).stdout
    assert str(venv) in where and str(ROOT) not in where


_HEAVY = r"""
import sys
from fem_dual.cli import main
try:
    status = main(sys.argv[1:])
except SystemExit as exc:  # --help and --version end through argparse
    status = exc.code
heavy = sorted(m for m in ("dolfinx", "petsc4py", "mpi4py", "ufl", "scipy") if m in sys.modules)
print(f"{status}|{','.join(heavy)}")
"""


@pytest.mark.serial
@pytest.mark.parametrize("argv, status", [(["--version"], 0), (["--help"], 0),
                                          (["run", "--help"], 0),
                                          (["run", "ziegler", "--bogus", "1"], 2),
                                          (["scenes"], 0),
                                          (["run", "ziegler", "--T", "-1"], 2),
                                          (["run", "column", "--param", "links=5", "--x0",
                                            "1,2"], 2),
                                          (["run", "curl2d", "--cells", "0"], 2),
                                          (["run", "curl3d-ufl", "--rtol", "2"], 2),
                                          (["run", "linear", "--param", "dofs=2", "--param",
                                            "M=1,0,0,-1"], 2),
                                          (["run", "ziegler", "--base", "predictor",
                                            "--assembly", "kronecker"], 2),
                                          (["orbit", "ziegler", "--period", "-1"], 2),
                                          (["orbit", "ziegler", "--x0", "0,0", "--period",
                                            "13"], 2),
                                          (["orbit", "ziegler", "--x0", "0.1,0.16", "--param",
                                            "P=1", "--period", "6", "--mode", "energy=1"], 2),
                                          (["orbit", "ziegler", "--period", "6", "--continue",
                                            "Q=0:1:2"], 2)])
def test_help_version_and_bad_options_load_no_heavy_module(argv, status):
    """They answer before DOLFINx, PETSc, MPI, UFL or scipy are imported (about 0.05 s, where
    those imports take 1.7 s), bad values of a run included: checking them imports neither the
    slab problem, nor the scenes' UFL forms, nor MPI for the command line (together 1 s)."""
    done = subprocess.run([sys.executable, "-c", _HEAVY, *argv], capture_output=True, text=True)
    got_status, heavy = done.stdout.strip().splitlines()[-1].split("|")
    assert int(got_status) == status, done.stderr
    assert heavy == "", f"{argv} imported {heavy}"


@pytest.mark.serial
def test_a_bad_modal_request_loads_neither_dolfinx_nor_petsc():
    done = subprocess.run([sys.executable, "-c", _HEAVY, "run", "linear", "--param", "dofs=2",
                           "--param", "M=1,0,0,1", "--param", "K=-1,0,0,4", "--coordinates",
                           "modal"], capture_output=True, text=True)
    got_status, heavy = done.stdout.strip().splitlines()[-1].split("|")
    assert int(got_status) == 2 and "does not oscillate" in done.stderr
    assert heavy == "scipy", heavy  # the pencil's eigenvalues: scipy.linalg only"


@pytest.mark.serial
def test_a_linear_run_does_not_load_the_nonlinear_reference_integrator():
    """scipy.integrate (0.2-0.4 s of imports) serves DOP853 references of nonlinear scenes; a
    linear scene's reference is the eigen-decomposition or expm: a run imports only what it
    needs."""
    script = ("import sys\nfrom fem_dual.cli import main\n"
              "status = main(['run', 'ziegler', '--T', '2', '--slabs', '2', '--cells', '8'])\n"
              "print(status, 'scipy.integrate' in sys.modules)")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert done.stdout.strip().splitlines()[-1] == "0 False", done.stdout + done.stderr
