"""`fem-dual flutter beck`: the flutter load of Beck's column from its eigenvalues and from dual
simulations read in its two slowest modes, the mode shapes and the flutter motion as XDMF."""
import json
from pathlib import Path

import numpy as np
import pytest
from mpi4py import MPI

from fem_dual.analysis.flutter import flutter
from fem_dual.cli import main
from fem_dual.config import RunConfig
from fem_dual.errors import InputError
from fem_dual.output import read_series

BECK = 20.0509536190  # Beck's flutter load, EI/L^2 (Euler-Bernoulli)
QUICK = ["--param", "elements=20", "--T", "20", "--slabs", "20"]


@pytest.mark.serial  # (demos/demo_beck.py runs the search under mpirun too)
def test_dual_simulations_find_the_eigenvalue_load_and_write_modes_and_motion(tmp_path, capsys):
    tmp_path = Path(MPI.COMM_WORLD.bcast(str(tmp_path), root=0))  # rank 0's, on every rank
    assert main(["flutter", "beck", *QUICK, "--json", "--out", str(tmp_path)]) == 0
    found = MPI.COMM_WORLD.bcast(json.loads(capsys.readouterr().out)
                                 if MPI.COMM_WORLD.rank == 0 else None, root=0)
    assert abs(found["eigen"] - BECK) < 5e-3  # 20 P2 elements
    assert abs(found["dual"] - found["eigen"]) < 1e-4 * found["eigen"]
    lo, hi = found["dual_bracket"]
    assert lo < hi <= lo * (1 + 2e-5) and lo <= found["dual"] <= hi
    assert found["elements"] == 20 and found["runs"] >= 3
    assert abs(found["omega2"] - 121.3425) < 0.1
    modes = tmp_path / "beck_modes.xdmf"
    assert str(modes) in found["files"] and (tmp_path / "beck_fields.xdmf").exists()
    points, steps, fields = read_series(modes)
    assert np.allclose(points[:, 0], np.linspace(0, 1, 21)) and list(steps) == [1.0, 2.0]
    for mode in fields:  # unit deflection, clamped at 0, and the velocity omega times it
        assert np.abs(mode["w"]).max() == pytest.approx(1.0) and mode["w"][0] == 0
        assert np.all(np.isfinite(mode["theta"]))
        # just below the load both frequencies have nearly met the flutter frequency
        assert np.abs(mode["w_dot"]).max() == pytest.approx(found["omega2"] ** 0.5, rel=0.02)


@pytest.mark.serial
def test_the_default_discretisation_meets_beck_within_1e_4():
    from fem_dual.analysis.continuum_flutter import _eigen
    from fem_dual.scenes import get_scene

    beck = get_scene("beck")
    config = RunConfig.create("beck", dict(beck.flutter_params))
    assert abs(_eigen(config.scene).load - BECK) < 1e-4


@pytest.mark.serial
def test_a_window_too_short_is_exit_3_and_out_on_particles_exit_2(capsys, tmp_path):
    assert main(["flutter", "beck", "--param", "elements=10", "--T", "0.001", "--cells", "2",
                 "--degree", "1", "--json"]) == 3
    assert json.loads(capsys.readouterr().out)["status"] == "failed"
    assert main(["flutter", "ziegler", "--out", "somewhere"]) == 2
    (tmp_path / "a_file").write_text("")  # refused before the search, in one line
    assert main(["flutter", "beck", "--out", str(tmp_path / "a_file")]) == 2
    assert "a_file cannot be a directory" in capsys.readouterr().err
    for given in (["--param", "P=5"], ["--u0", "x**2, 2*x"], ["--v0", "0, 0"]):
        assert main(["flutter", "beck", *given]) == 2
        assert "not taken" in capsys.readouterr().err
    with pytest.raises(InputError, match="continuum_flutter"):
        flutter(RunConfig.create("beck", {"elements": "10"}))
