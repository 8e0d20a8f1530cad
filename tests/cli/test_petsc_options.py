"""PETSc options are input: bad types and values, on the forms, Kronecker and
SNES paths, by --petsc-option or PETSC_OPTIONS, are exit 2 with one line naming the option
before any work; options a solver's set-up leaves unused are exit 2 naming them; legit options
run. Under MPI every rank raises the same InputError."""
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from mpi4py import MPI
from petsc4py import PETSc

from fem_dual import RunConfig, run
from fem_dual.errors import InputError
from fem_dual.petsc_check import (SNES_TYPES, available_types, check_options, options_used,
                                  solver_packages)

ROOT = Path(__file__).resolve().parents[2]
_SCRIPT = ROOT / ".venv" / "bin" / "fem-dual"
FEM_DUAL = [str(_SCRIPT)] if _SCRIPT.exists() else [sys.executable, "-m", "fem_dual.cli"]

ZIEGLER = ["run", "ziegler", "--T", "1", "--cells", "10"]  # forms path (KSP, LU)
CURL3D = ["run", "curl3d", "--T", "0.5", "--cells", "10"]  # SNES path
COLUMN = ["run", "column", "--param", "links=6", "--T", "1", "--cells", "10"]  # Kronecker path


def _options(*pairs):
    return [arg for pair in pairs for arg in ("--petsc-option", pair)]


def _fem_dual(args, petsc_env=None, mpi=0):
    env = {k: v for k, v in os.environ.items() if k != "PETSC_OPTIONS"}
    if petsc_env is not None:
        env["PETSC_OPTIONS"] = petsc_env
    command = FEM_DUAL + list(args)
    if mpi:
        env.update(OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1")
        command = ["mpirun", "-n", str(mpi)] + command
    return subprocess.run(command, capture_output=True, text=True, env=env, timeout=600,
                          stdin=subprocess.DEVNULL, cwd=ROOT)


def _assert_input_error(proc, *names):
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2, (proc.returncode, proc.stderr[-2000:])
    assert "Traceback" not in proc.stderr and "PETSC ERROR" not in proc.stderr, proc.stderr
    assert len(lines) == 1 and lines[0].startswith("fem-dual: error: "), proc.stderr
    for name in names:
        assert name in lines[0], (name, lines[0])
    return lines[0]


# --- bad options through the command line (a process each) ----------------------------------

REPRODUCTIONS = [
    pytest.param(ZIEGLER + _options("ksp_type=bogus"), None, ["ksp_type=bogus", "KSP"],
                 id="ksp_type-forms"),
    pytest.param(ZIEGLER + _options("pc_type=nonsense"), None, ["pc_type=nonsense"],
                 id="pc_type-forms"),
    pytest.param(CURL3D + _options("snes_max_it=abc"), None, ["snes_max_it=abc", "integer"],
                 id="snes_max_it-snes"),
    pytest.param(ZIEGLER, "-dual_ziegler_ksp_type bogus",
                 ["-dual_ziegler_ksp_type bogus", "PETSC_OPTIONS"], id="PETSC_OPTIONS-ksp_type"),
    pytest.param(CURL3D, "-dual_curl3d_snes_max_it abc",
                 ["-dual_curl3d_snes_max_it abc", "integer"], id="PETSC_OPTIONS-snes_max_it"),
    pytest.param(COLUMN + _options("ksp_type=bogus"), None, ["ksp_type=bogus"],
                 id="ksp_type-kronecker"),
    pytest.param(COLUMN + _options("pc_type=lu"), None, ["pc_type=lu", "kronecker"],
                 id="lu-kronecker"),  # unchecked: a traceback
    pytest.param(ZIEGLER + _options("pc_factor_mat_solver_type=nope"), None,  # unchecked: exit 3
                 ["pc_factor_mat_solver_type=nope", "mumps"], id="mat_solver_type"),
    pytest.param(ZIEGLER + _options("ksp_typ=cg"), None, ["not used by the forms solver",
                                                          "ksp_typ", "ksp_type?"],
                 id="misspelt-forms"),  # unchecked: ignored
    pytest.param(ZIEGLER, "-dual_ziegler_ksp_typ cg",
                 ["not used by the forms solver", "-dual_ziegler_ksp_typ cg"],
                 id="PETSC_OPTIONS-misspelt"),
]


@pytest.mark.serial
@pytest.mark.parametrize("args, petsc_env, names", REPRODUCTIONS)
def test_reproductions_exit_2_with_one_line(args, petsc_env, names):
    _assert_input_error(_fem_dual(args, petsc_env), *names)


@pytest.mark.serial
@pytest.mark.parametrize("args, petsc_env", [
    (ZIEGLER + _options("ksp_type=cg", "pc_type=jacobi", "ksp_rtol=1e-12"), None),
    (ZIEGLER, "-dual_ziegler_pc_factor_mat_solver_type mumps"),
], ids=["iterative-forms", "PETSC_OPTIONS"])
def test_legit_options_run_cli(args, petsc_env):
    proc = _fem_dual(args, petsc_env)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stderr == ""


# --- more of them in-process (fem_dual.cli.main: the same exit status and stderr line) --------

BAD = [
    pytest.param(CURL3D + _options("snes_linesearch_typ=bt"),
                 ["not used by the snes solver", "snes_linesearch_typ"], id="misspelt-snes"),
    pytest.param(COLUMN + _options("ksp_rtoll=1e-12"),
                 ["not used by the kronecker solver", "ksp_rtoll"], id="misspelt-kronecker"),
    # ksp_type=preonly (the forms default) reads no tolerance: the option would do nothing
    pytest.param(ZIEGLER + _options("ksp_rtol=1e-12"), ["ksp_rtol", "preonly"],
                 id="unused-tolerance"),
    pytest.param(ZIEGLER + _options("snes_rtol=1e-8"), ["snes_rtol", "no SNES"],
                 id="snes-option-linear"),
    pytest.param(ZIEGLER + _options("ksp_rtol=nan", "ksp_type=cg"), ["ksp_rtol=nan"],
                 id="nan-rtol"),
    pytest.param(ZIEGLER + _options("ksp_type=cg", "ksp_atol=-1"), ["ksp_atol=-1"],
                 id="negative-atol"),
    pytest.param(ZIEGLER + _options("ksp_error_if_not_converged=maybe"),
                 ["ksp_error_if_not_converged=maybe", "boolean"], id="boolean"),
    pytest.param(ZIEGLER + _options("pc_type=python"), ["pc_type=python"],
                 id="python-pc"),  # unchecked: PETSc crashes (signal 11)
    pytest.param(ZIEGLER + _options("ksp_type=gmres", "ksp_monitor_python="),
                 ["ksp_monitor_python"], id="python-monitor"),  # unchecked: PETSc crashes
    pytest.param(CURL3D + _options("snes_type=aspin"), ["snes_type=aspin"],
                 id="aspin"),  # unchecked: PETSc crashes
    pytest.param(CURL3D + _options("snes_type=ngs"), ["snes_type=ngs"],
                 id="ngs"),  # unchecked: PETSc crashes
    pytest.param(ZIEGLER + _options("ksp_type=gmres", "pc_type=bddc"), ["bddc", "MATIS"],
                 id="set-up-failure"),  # unchecked: exit 3 after a slab's work
    pytest.param(COLUMN + _options("pc_type=jacobi"), ["pc_type=jacobi"],
                 id="jacobi-kronecker"),  # unchecked: a traceback
    pytest.param(COLUMN + _options("pc_factor_mat_solver_type=mumps"),
                 ["pc_factor_mat_solver_type=mumps", "kronecker"], id="factor-kronecker"),
    pytest.param(COLUMN + _options("ksp_type=bicg"), ["ksp_type=bicg", "transpose"],
                 id="transpose-kronecker"),
    pytest.param(COLUMN + _options("ksp_type=preonly"), ["ksp_type=preonly"],
                 id="preonly-kronecker"),
]


@pytest.mark.serial
@pytest.mark.parametrize("args, names", BAD)
def test_bad_options_exit_2_with_one_line(args, names, capsys):
    from fem_dual.cli import main

    assert main(args) == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("fem-dual: error: "), captured.err
    for name in names:
        assert name in lines[0], (name, lines[0])


@pytest.mark.serial
@pytest.mark.parametrize("args", [
    ZIEGLER + _options("pc_factor_mat_solver_type=mumps", "mat_mumps_icntl_14=50"),
    CURL3D + _options("snes_rtol=1e-12", "snes_linesearch_type=bt", "snes_max_it=40",
                      "pc_factor_mat_solver_type=mumps"),
    COLUMN + _options("ksp_rtol=1e-12", "ksp_max_it=500", "ksp_type=minres"),
    COLUMN + _options("pc_type=none", "ksp_type=cg"),
    COLUMN + _options("ksp_type=chebyshev"),
], ids=["mumps-forms", "snes", "kronecker", "kronecker-no-pc", "kronecker-chebyshev"])
def test_legit_options_run(args, capsys):
    from fem_dual.cli import main

    assert main(args) == 0
    assert capsys.readouterr().err == ""


@pytest.mark.serial
def test_a_snes_type_without_a_jacobian_fails_cleanly(capsys):
    """anderson never forms the Jacobian, whose norm the round-off test takes (unassembled,
    PETSc fails: exit 1, 'Not for unassembled matrix'). It is assembled at the state SNES
    stopped at: a Newton failure that halves the slab, then exit 3 with the reason, or an
    answer."""
    from fem_dual.cli import main

    status = main(CURL3D + _options("snes_type=anderson"))
    err = capsys.readouterr().err
    assert status in (0, 3) and "unassembled" not in err and "internal error" not in err


@pytest.mark.serial
@pytest.mark.parametrize("args, tell", [
    (ZIEGLER + _options("ksp_monitor=", "ksp_view=", "ksp_converged_reason="),
     ["KSP Object: (dual_ziegler_)", "Linear dual_ziegler_ solve converged"]),
    (CURL3D + _options("snes_monitor=", "ksp_monitor=", "ksp_view=", "snes_view=",
                       "snes_converged_reason=", "ksp_converged_reason="),
     ["SNES Function norm", "SNES Object: (dual_curl3d_)",
      "Nonlinear dual_curl3d_ solve converged", "Linear dual_curl3d_ solve converged"]),
    (COLUMN + _options("ksp_monitor=", "ksp_view=", "ksp_converged_reason="),
     ["KSP Residual norm", "type: cg", "Linear dual_column_ solve converged"]),
])
def test_monitors_and_views_are_used(args, tell):
    """Monitors and views are not 'unused', and they act (the converged-reason views are read
    only while solving: the options stay set during the solves)."""
    proc = _fem_dual(args)
    assert proc.returncode == 0, proc.stderr[-2000:]
    for text in tell:
        assert text in proc.stdout, text


# --- the checks themselves (in-process, fast) ----------------------------------------------

@pytest.mark.serial
def test_types_of_this_build():
    assert {"cg", "gmres", "preonly"} <= set(available_types("ksp_type"))
    assert "hpddm" not in available_types("ksp_type")  # not in Debian's PETSc 3.18
    assert {"lu", "jacobi", "hypre"} <= set(available_types("pc_type"))
    assert {"bt", "basic", "l2", "cp"} <= set(available_types("snes_linesearch_type"))
    assert {"petsc", "mumps"} <= set(solver_packages())
    assert "mkl_pardiso" not in solver_packages()
    assert "newtonls" in SNES_TYPES


@pytest.mark.serial
@pytest.mark.parametrize("options, path, text", [
    ({"ksp_max_it": "1.5"}, "forms", "not an integer"),
    ({"ksp_max_it": "-5"}, "forms", "at least 0"),
    ({"ksp_gmres_restart": "0"}, "forms", "at least 1"),
    ({"ksp_rtol": "1e400"}, "forms", "finite"),
    ({"ksp_rtol": "1"}, "forms", "less than 1"),
    ({"snes_stol": "-1e-3"}, "snes", "at least 0"),
    ({"snes_linesearch_type": "zz"}, "snes", "line-search"),
    ({"mat_mumps_icntl_14": "x"}, "forms", "integer"),
    ({"mat_mumps_cntl_1": "inf"}, "forms", "finite"),
    ({"sub_pc_type": "bogus"}, "forms", "preconditioner"),
    ({"ksp type": "cg"}, "forms", "option name"),
    ({"ksp_python_type": "os.system"}, "forms", "Python"),
    ({"snes_max_it": "5"}, "kronecker", "no SNES"),
    ({"mat_mumps_icntl_14": "50"}, "kronecker", "matrix-free"),
])
def test_check_options_refuses(options, path, text):
    with pytest.raises(InputError, match=text):
        check_options(options, path)


@pytest.mark.serial
@pytest.mark.parametrize("options, path", [
    ({"ksp_type": "gmres", "ksp_rtol": "1e-10", "ksp_max_it": "100", "pc_type": "ilu",
      "pc_factor_levels": "1", "ksp_error_if_not_converged": "yes", "ksp_monitor": ""}, "forms"),
    ({"snes_type": "newtontr", "snes_atol": "0", "snes_linesearch_type": "l2",
      "snes_lag_jacobian": "-1", "snes_monitor": "", "mat_mumps_icntl_14": "30"}, "snes"),
    ({"ksp_type": "cg", "pc_type": "none", "ksp_rtol": "1e-13", "ksp_view": ""}, "kronecker"),
])
def test_check_options_accepts(options, path):
    check_options(options, path)


# --- collective under MPI -------------------------------------------------------------------

def _same_error_everywhere(config):
    comm = MPI.COMM_WORLD
    with pytest.raises(InputError) as info:
        run(config, comm)
    messages = comm.allgather(str(info.value))
    assert len(set(messages)) == 1, messages
    return messages[0]


@pytest.mark.mpi
@pytest.mark.parametrize("petsc, assembly, text", [
    ({"ksp_typ": "cg"}, "forms", "not used by the forms solver: ksp_typ"),
    ({"ksp_type": "bogus"}, "forms", "ksp_type=bogus"),
    ({"pc_type": "lu"}, "kronecker", "pc_type=lu"),
    ({"ksp_rtoll": "1e-12"}, "kronecker", "not used by the kronecker solver: ksp_rtoll"),
])
def test_errors_are_collective(petsc, assembly, text):
    scene, params = ("ziegler", None) if assembly == "forms" else ("column", {"links": 6})
    try:  # values are checked by RunConfig.create, use by the solver set-up
        config = RunConfig.create(scene, params, T=1.0, cells=10, petsc=petsc,
                                  assembly=assembly)
    except InputError as exc:
        message = str(exc)
        assert MPI.COMM_WORLD.allgather(message) == [message] * MPI.COMM_WORLD.size
    else:
        message = _same_error_everywhere(config)
    assert text in message


@pytest.mark.mpi
def test_set_up_failure_is_input_error():
    """SuperLU factors sequential matrices only: under MPI the slab matrix is mpiaij, and the
    set-up probe says so before any slab (in serial it runs)."""
    config = RunConfig.create("ziegler", T=1.0, cells=10,
                              petsc={"pc_factor_mat_solver_type": "superlu"})
    if MPI.COMM_WORLD.size == 1:
        assert run(config).status == "ok"
    else:
        assert "superlu" in _same_error_everywhere(config)


@pytest.mark.mpi
def test_options_database_entries_under_the_prefix_are_checked():
    """What PETSC_OPTIONS puts in the database under the solver's prefix is the user's too."""
    opts = PETSc.Options()
    opts["dual_ziegler_ksp_typ"] = "cg"
    try:
        config = RunConfig.create("ziegler", T=1.0, cells=10)
        assert "-dual_ziegler_ksp_typ cg" in _same_error_everywhere(config)
    finally:
        opts.delValue("dual_ziegler_ksp_typ")


@pytest.mark.mpi
@pytest.mark.parametrize("scene, params, petsc", [
    ("ziegler", None, {"ksp_type": "cg", "pc_type": "jacobi", "ksp_rtol": "1e-12"}),
    ("ziegler", None, {"pc_factor_mat_solver_type": "mumps"}),
    ("curl3d", None, {"snes_rtol": "1e-12", "snes_linesearch_type": "bt"}),
    ("column", {"links": 6}, {"ksp_rtol": "1e-12", "ksp_type": "gmres"}),
])
def test_legit_options_run_everywhere(scene, params, petsc):
    T = 0.5 if scene == "curl3d" else 1.0
    result = run(RunConfig.create(scene, params, T=T, cells=10, petsc=petsc))
    assert result.status == "ok"


@pytest.mark.mpi
def test_options_used_is_combined_over_ranks():
    comm = MPI.COMM_WORLD
    opts = PETSc.Options()
    name = "fem_dual_test_used_flag"
    opts[name] = "1"
    try:
        if comm.rank == 0:
            opts.getInt(name)  # queried on rank 0 only
        assert options_used([name], comm) == {name: True}
        assert options_used(["fem_dual_test_not_set"], comm) == {"fem_dual_test_not_set": False}
    finally:
        opts.delValue(name)


@pytest.mark.serial
@pytest.mark.skipif(shutil.which("mpirun") is None, reason="needs mpirun")
@pytest.mark.parametrize("args", [COLUMN + _options("pc_type=lu"),
                                  ZIEGLER + _options("ksp_typ=cg")], ids=["kronecker", "unused"])
def test_cli_under_mpirun(args):
    """Every rank stops with the same error: one line (rank 0 prints), exit 2, no abort."""
    proc = _fem_dual(args, mpi=2)
    assert "MPI_ABORT" not in proc.stderr and "Traceback" not in proc.stderr, proc.stderr
    assert proc.returncode == 2, proc.stderr
    errors = [ln for ln in proc.stderr.splitlines() if ln.startswith("fem-dual: error:")]
    assert len(errors) == 1, proc.stderr


@pytest.mark.serial
@pytest.mark.parametrize("scene, params, options", [
    ("column", {"links": "6", "P": "0.1"}, {"pc_type": "none", "ksp_rtol": "1e-7"}),
    ("ziegler", {}, {"ksp_type": "cg", "pc_type": "jacobi", "ksp_rtol": "1e-6"}),
])
@pytest.mark.parametrize("superpose", ["auto", "no"])
def test_a_loosened_ksp_tolerance_costs_iterations_not_accuracy(scene, params, options,
                                                                superpose):
    """A loose ksp_rtol leaves an algebraic error that no estimate sees (the companion, stopped
    by the same test, does not show it): unrefined, a 6-link column errs by 1.24e-6 with an
    estimate of 6.0e-7 and says ok. The solves are refined to the default's residual."""
    args = dict(T=3.0, slabs=10, degree=3, cells=4, superpose=superpose)
    exact = run(RunConfig.create(scene, params, assembly="auto" if scene == "column" else "forms",
                                 **args))  # (the default KSP, as the loosened one's path)
    loose = run(RunConfig.create(scene, params, petsc=options, **args))
    assert loose.status == exact.status == "ok"
    scale = max(np.abs(exact.x).max(), np.abs(exact.v).max())
    assert np.abs(loose.x - exact.x).max() < 1e-9 * scale
    assert np.abs(loose.v - exact.v).max() < 1e-9 * scale
    assert loose.estimate["x_max"] >= loose.error["x_max"]
    assert sum(loose.solver["ksp_iterations"]) > sum(exact.solver["ksp_iterations"])
