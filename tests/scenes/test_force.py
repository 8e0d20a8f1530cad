"""Your own force end to end: `run force --F`, output at any time, --reference none,
--csv, --plot, bad input."""
from __future__ import annotations

import csv
import json

import numpy as np
import pytest
from mpi4py import MPI

from fem_dual import InputError, RunConfig, run
from fem_dual.cli import main
from helpers import observed_rates

CURL2D = "-k*x*y**2, -k*x**3"


@pytest.mark.mpi
def test_a_typed_force_gives_the_numbers_of_the_built_in_scene():
    """curl2d typed as text: the same forms up to UFL's derivation of G, the same numbers (to
    the solver tolerance), serial and under mpirun."""
    typed = run(RunConfig.create("force", {"F": CURL2D, "k": "1.5"}, T=2, slabs=2, cells=20,
                                 x0="1,1"))
    built = run(RunConfig.create("curl2d", {"k": "1.5"}, T=2, slabs=2, cells=20, x0="1,1"))
    assert typed.status == "ok" and typed.scene == "force"
    assert np.abs(typed.x - built.x).max() < 1e-11
    assert abs(typed.error["x_max"] - built.error["x_max"]) < 1e-11
    assert typed.parameters["k"] == 1.5 and typed.parameters["F"] == CURL2D


def test_any_number_of_components_with_x1_to_xn():
    F = "-x1 + 0.1*x2*x3*x4, -x2 - 0.1*x1*x3, -x3 + 0.1*sin(x4), -x4 + 0.1*x1*x2"
    r = run(RunConfig.create("force", {"F": F}, T=1, cells=10, degree=3, x0="0.1,0.2,0.3,0.4"))
    assert r.x.shape[1] == 4 and r.error["x_max"] < 1e-8
    assert r.error["x_max"] <= r.error_estimate


@pytest.mark.parametrize("degree,cells", [(2, (16, 32, 64)), (4, (4, 8, 16))])
def test_dense_output_converges_and_stays_near_the_vertex_error(degree, cells):
    """--t-eval between the vertices (Hermite of degree 7 with the equation of motion at the
    vertices): order 2p up to p = 4, and no worse than 10x the vertex error at the same
    resolution (measured: 1.0x)."""
    times = np.linspace(0.013, 1.987, 37)  # never on a vertex
    dense, vertex = [], []
    for c in cells:
        r = run(RunConfig.create("force", {"F": CURL2D, "k": "1"}, T=2, cells=c, degree=degree,
                                 x0="1,1", t_eval=times, base="start"))
        e = r.t_eval["error"]
        dense.append(max(e["x_max"], e["v_max"]))
        vertex.append(max(r.error["x_max"], r.error["v_max"]))
        assert len(r.t_eval["t"]) == len(times) and r.t_eval["omitted"] == 0
    assert np.all(observed_rates(dense) > 2 * degree - 0.5), dense
    assert all(d <= 10 * v for d, v in zip(dense, vertex)), (dense, vertex)


def test_dense_output_is_exact_at_the_vertices_and_in_the_api():
    r = run(RunConfig.create("ziegler", T=2, cells=8, degree=3, t_eval="0:2:5"))
    x, v = r.at(r.t[[0, 3, -1]])
    assert np.abs(x - r.x[[0, 3, -1]]).max() < 1e-14
    assert np.abs(v - r.v[[0, 3, -1]]).max() < 1e-14
    assert r.t_eval["t"] == [0.0, 0.5, 1.0, 1.5, 2.0]
    with pytest.raises(InputError, match="outside"):
        r.at([2.5])


def test_reference_none_skips_it():
    r = run(RunConfig.create("force", {"F": CURL2D, "k": "1"}, T=1, cells=8, x0="1,1",
                             reference="none", t_eval="0.5"))
    assert r.error["x_max"] is None and r.timings["reference_s"] == 0.0
    assert r.error_estimate > 0 and r.t_eval["error"] is None


@pytest.mark.serial
def test_cli_force_with_csv_plot_and_json(tmp_path, capsys):
    out = tmp_path / "pics"
    out.mkdir()
    args = ["run", "force", "--F", CURL2D, "--param", "k=1", "--x0", "1,0.5", "--T", "2",
            "--slabs", "2", "--cells", "10", "--t-eval", "0.25,1.75", "--csv",
            str(tmp_path / "m.csv"), "--plot", str(out), "--json"]
    assert main(args) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["t_eval"]["t"] == [0.25, 1.75] and len(d["t_eval"]["x"][0]) == 2
    with open(tmp_path / "m.csv") as f:
        rows = list(csv.reader(f))
    assert rows[0] == ["t", "x1", "x2", "v1", "v2"] and len(rows) == 1 + len(d["t"])
    assert np.allclose(np.array(rows[-1], dtype=float)[1:3], d["final"]["x"], rtol=0, atol=0)
    for name in ("motion", "phase", "error", "hamiltonian"):
        assert (out / f"{name}.png").read_bytes()[:4] == b"\x89PNG"


@pytest.mark.serial
@pytest.mark.parametrize("args,piece", [
    (["--F", "x*y, __import__('os')"], "__import__"),
    (["--F", "x.real, y"], "real"),
    (["--F", "q*x, y"], "q"),
    (["--F", "x/0, y"], "zero"),
    (["--F", "-x, -y", "--param", "k=1"], "k"),  # a parameter the force does not use
    (["--F", "-x, -y", "--x0", "1,2,3"], "x0"),
    (["--F", "-x, -y", "--t-eval", "5"], "t-eval"),
    (["--F", "-x, log(y)", "--x0", "1,0"], "not finite"),
    ([], "--F"),
])
def test_bad_force_input_is_one_line_and_exit_2(args, piece, capsys):
    argv = ["run", "force", "--T", "1", "--json"] + args
    if "--x0" not in args:
        argv += ["--x0", "1,1"]
    assert main(argv) == 2
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err.count("\n") == 1 and piece in captured.err


@pytest.mark.serial
def test_F_belongs_to_scene_force(capsys):
    assert main(["run", "ziegler", "--F", "-x, -y"]) == 2
    assert "scene force" in capsys.readouterr().err


def test_scene_force_needs_a_start_state():
    with pytest.raises(InputError, match="x0"):
        RunConfig.create("force", {"F": "-x, -y"})


@pytest.mark.mpi
def test_force_and_dense_output_identical_under_mpi():
    r = run(RunConfig.create("force", {"F": CURL2D, "k": "1"}, T=1, cells=8, x0="1,1",
                             t_eval="0.3,0.7"))
    gathered = MPI.COMM_WORLD.allgather((r.x[-1].tolist(), r.t_eval["x"]))
    assert all(g == gathered[0] for g in gathered)


SCENE_FILE = '''
import dataclasses, ufl
from typing import ClassVar
from fem_dual.scenes import ForceScene
from fem_dual.forms import implicit
from fem_dual.forms.predual import isotropic_quadratic

@dataclasses.dataclass(frozen=True)
class FileSwirl(ForceScene):
    name: ClassVar[str] = "file-swirl"
    n: ClassVar[int] = 2
    forms: ClassVar = implicit.make(
        lambda x, c: ufl.as_vector([-x[0] - c["a"] * x[1] ** 3, c["a"] * x[0] - x[1]]),
        lambda dx, dv, c: isotropic_quadratic(dx, dv, c["alpha"], c["beta"]))
    default_T: ClassVar[float] = 1.0
    default_x0: ClassVar[tuple] = (1.0, 0.0)
    default_v0: ClassVar[tuple] = (0.0, 0.5)
    a: float = 0.5
'''


@pytest.mark.serial
def test_scene_file_declares_a_scene_with_the_numbers_of_the_typed_force(tmp_path, capsys):
    from fem_dual.scenes import SCENES

    path = tmp_path / "swirl.py"
    path.write_text(SCENE_FILE)
    try:
        assert main(["run", "file-swirl", "--scene-file", str(path), "--cells", "20",
                     "--json"]) == 0
        from_file = json.loads(capsys.readouterr().out)
    finally:
        SCENES.pop("file-swirl", None)
    typed = run(RunConfig.create("force", {"F": "-x - a*y**3, a*x - y", "a": "0.5"}, T=1,
                                 cells=20, x0="1,0", v0="0,0.5"))
    assert np.abs(np.array(from_file["x"]) - typed.x).max() < 1e-12


@pytest.mark.serial
@pytest.mark.parametrize("text,piece", [("raise ValueError('boom')", "boom"),
                                        ("x = 1", "declares no scene"),
                                        ("def (", "SyntaxError")])
def test_a_bad_scene_file_is_one_line_and_exit_2(tmp_path, capsys, text, piece):
    path = tmp_path / "bad.py"
    path.write_text(text)
    assert main(["run", "whatever", "--scene-file", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and piece in err


# -- edge cases: one component, t-eval times, the estimate between vertices, bad input ---------
def test_one_component_on_the_predictor_base():
    r = run(RunConfig.create("force", {"F": "-x"}, T=0.5, cells=10, x0="0.5", base="predictor"))
    assert r.status == "ok" and r.error["x_max"] < 1e-8


def test_repeated_and_unsorted_t_eval_times():
    r = run(RunConfig.create("force", {"F": "-x"}, T=0.5, cells=10, x0="1",
                             t_eval="0.3,0.1,0.1,0.25"))
    assert r.t_eval["t"] == [0.3, 0.1, 0.1, 0.25] and r.t_eval["x"][1] == r.t_eval["x"][2]
    assert r.t_eval["error"]["x_max"] < 1e-8


def test_the_estimate_covers_the_t_eval_times_at_high_degree():
    """p = 5: the vertices beat the Hermite's O(h^8); the estimate must still cover the
    values between them (an estimate of the vertices alone misses them by 240x here)."""
    r = run(RunConfig.create("force", {"F": "-x - a*y**3, a*x - y", "a": "0.5"}, T=4, cells=1,
                             degree=5, rtol=1e-9, x0="1,0", v0="0,0.5",
                             t_eval="0.1:3.9:39"))
    actual = max(r.t_eval["error"]["x_max"], r.t_eval["error"]["v_max"])
    assert r.t_eval["error_estimate"] >= actual and r.error_estimate >= actual


def test_rtol_holds_at_the_t_eval_times_between_far_vertices():
    """p = 8 with one cell per slab: the vertices meet rtol 1e-8 with 14 slabs, where the times
    between them are 1.3e-3 off (estimate 4e-2), which a run judged at its vertices alone would
    call ok. The gaps between vertices are judged with the slab: the controller keeps the slabs
    short enough for the t-eval times."""
    common = dict(T=2, rtol=1e-8, cells=1, degree=8, x0="1")
    plain = run(RunConfig.create("force", {"F": "-100*x"}, **common))
    dense = run(RunConfig.create("force", {"F": "-100*x"}, t_eval="0:2:201", **common))
    actual = max(dense.t_eval["error"]["x_max"], dense.t_eval["error"]["v_max"])
    allowed = 10 * 1e-8 * max(dense.tolerance["scale_x"], dense.tolerance["scale_v"])
    assert dense.status == "ok" and actual <= dense.t_eval["error_estimate"] <= allowed
    assert len(dense.slab_lengths) > len(plain.slab_lengths)


def test_t_eval_beyond_what_the_run_vouches_for_fails(monkeypatch):
    """Without the slab loop's judging of the gaps (patched out), the estimate at the t-eval
    times exceeds the tolerance: the run fails (exit 3) with its results kept, never ok."""
    from fem_dual import SolveError
    from fem_dual.integrate import loop

    monkeypatch.setattr(loop, "output_request", lambda config: None)
    with pytest.raises(SolveError, match="--t-eval times is estimated") as caught:
        run(RunConfig.create("force", {"F": "-100*x"}, T=2, rtol=1e-8, cells=1, degree=8,
                             x0="1", t_eval="0:2:201"))
    partial = caught.value.partial
    assert partial.status == "failed" and len(partial.t_eval["t"]) == 201


def test_slab_gaps_are_the_dense_estimate_at_their_points():
    from fem_dual.inputs import scene_of
    from fem_dual.integrate.dense import GAP_POINTS, hermite_estimate, slab_interpolation_gaps

    scene = scene_of("force", {"F": "-x - x**3, -2*y + 0.3*x*y"})
    r = run(RunConfig.create(scene, T=3, slabs=3, cells=4, degree=3, x0="1,0.5", v0="0,1"))
    rows = [np.arange(4 * k, 4 * k + 5) for k in range(3)]  # each slab's vertices, ends shared
    x, v = np.stack([r.x[i] for i in rows]), np.stack([r.v[i] for i in rows])
    gaps = slab_interpolation_gaps(scene, np.linspace(0, 1, 5), 1.0, x, v)
    for k in range(3):
        t = r.t[rows[k]]
        times = (t[:-1, None] + np.diff(t)[:, None] * np.array(GAP_POINTS)).ravel()
        _, _, est = hermite_estimate(scene, r.t, r.x, r.v, times)
        assert abs(gaps[k].max() - est.max()) <= 1e-9 * est.max()
    assert gaps.min() > 0


def test_at_rejects_nan_and_accepts_nothing():
    r = run(RunConfig.create("ziegler", T=1, cells=4))
    with pytest.raises(InputError, match="finite"):
        r.at([float("nan")])
    assert r.at([])[0].shape == (0, 2)


@pytest.mark.serial
@pytest.mark.parametrize("args,piece", [
    (["--F", "-x # , -y", "--x0", "1"], "#"),
    (["--F", "-k*x", "--param", "k=1", "--param", "k=3", "--x0", "1"], "twice"),
    (["--F", "-k*x", "--param", "F=-x", "--param", "k=1", "--x0", "1"], "twice"),
    (["--F", "-x", "--x0", "1", "--plot", ""], "--plot"),
])
def test_more_bad_input_is_one_line_and_exit_2(args, piece, capsys, tmp_path):
    assert main(["run", "force", "--T", "0.5", "--cells", "4"] + args) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and piece in err


@pytest.mark.serial
def test_bad_input_creates_no_plot_directory(tmp_path, capsys):
    target = tmp_path / "never"
    assert main(["run", "force", "--F", "-x +", "--x0", "1", "--plot", str(target)]) == 2
    assert not target.exists()


@pytest.mark.serial
def test_an_unwritable_csv_is_exit_3_with_one_line(capsys):
    assert main(["run", "force", "--F", "-x", "--x0", "1", "--T", "0.5", "--cells", "4",
                 "--csv", "/dev/full"]) == 3
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "could not write" in err


@pytest.mark.serial
@pytest.mark.parametrize("name,text,piece", [("swirl.txt", "x = 1", "not a Python file"),
                                             ("exits.py", "import sys; sys.exit(0)",
                                              "SystemExit")])
def test_scene_files_that_are_not_scenes(tmp_path, capsys, name, text, piece):
    path = tmp_path / name
    path.write_text(text)
    assert main(["run", "whatever", "--scene-file", str(path)]) == 2
    assert piece in capsys.readouterr().err


@pytest.mark.parametrize("assembly", ["pointwise", "forms"])
def test_a_start_at_rest_at_the_origin_under_a_force_converges(assembly):
    """x'' = 1 - x from rest at 0 with the rk4 base: the first residual is at round-off, and
    an absolute floor scaled with the start state (zero) would leave Newton no test it could
    reach (every halving failing with DIVERGED_LINE_SEARCH at 1e-17). The floor scales with the
    slab's impulse dt |F(x0)|."""
    r = run(RunConfig.create("force", {"F": "1 - x"}, x0="0", base="rk4", assembly=assembly))
    assert r.status == "ok"
    assert abs(r.x[-1, 0] - (1 - np.cos(r.t[-1]))) <= max(r.error_estimate, 1e-13)
