"""`fem-dual run` of a continuum beyond its dense limit: the sparse, distributed space-time
backend behind the slab loop. The answer is checked against the exact motion of the exported
semi-discrete system (its CSR parts in `<scene>_system.npz`), serially and under
``mpirun -n 2 python3 -m pytest -m mpi tests/continua/test_spacetime_run.py`` (the same answer
on every partition)."""
import json

import numpy as np
import pytest
import scipy.sparse as sps
from scipy.sparse.linalg import expm_multiply
from mpi4py import MPI

from fem_dual.cli import main
from fem_dual.config import RunConfig
from fem_dual.integrate.api import run

SPARSE = {"elements": 20}  # 722 free dofs: beyond cauchy2d's dense limit of 512


def exact(arrays, T: float) -> np.ndarray:
    """(x, v) at T of M x'' + D x' + K x = 0 from the exported CSR parts and start vectors."""
    def csr(name):
        return sps.csr_matrix((arrays[f"{name}_data"], arrays[f"{name}_indices"],
                               arrays[f"{name}_indptr"]), shape=tuple(arrays[f"{name}_shape"]))

    M, K, D = (csr(name).toarray() for name in ("M", "K", "D"))
    n = len(M)
    A = np.block([[np.zeros((n, n)), np.eye(n)],
                  [-np.linalg.solve(M, K), -np.linalg.solve(M, D)]])
    return expm_multiply(sps.csr_matrix(A) * T, np.concatenate([arrays["u0"], arrays["v0"]]))


def _errors(data, arrays):
    z = exact(arrays, data["T"])
    n = len(z) // 2
    return (np.abs(np.array(data["final"]["x"]) - z[:n]).max(),
            np.abs(np.array(data["final"]["v"]) - z[n:]).max(), np.abs(z[n:]).max())


@pytest.mark.parametrize("setting", [
    ["--slabs", "2", "--cells", "4", "--degree", "3", "--T", "0.05"],
    ["--T", "0.2", "--rtol", "1e-6"]])
def test_a_large_continuum_runs_sparse_within_its_estimate(tmp_path, capsys, setting):
    out = tmp_path / "out"
    assert main(["run", "cauchy2d", "--param", "elements=20", *setting, "--out", str(out),
                 "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["solver"]["assembly"] == "spacetime" and data["solver"]["base"] == "start"
    assert data["dofs_per_slab"] == 2 * data["cells"] * data["degree"] * 722
    assert all(0 < its < 200 for its in data["solver"]["ksp_iterations"])
    arrays = np.load(out / "cauchy2d_system.npz")
    assert "M" not in arrays and arrays["M_shape"].tolist() == [722, 722]
    ex, ev, scale = _errors(data, arrays)
    assert max(ex, ev) <= data["error_estimate"] <= 1e-5 * scale
    # the run's own reference (expm_multiply of the sparse operator) sees the same final error
    reported = data["error"]
    assert reported["final_x"] == pytest.approx(ex, rel=1e-3, abs=1e-13)
    assert reported["final_v"] == pytest.approx(ev, rel=1e-3, abs=1e-13)
    assert max(reported["x_max"], reported["v_max"]) <= data["error_estimate"]
    assert (out / "cauchy2d_fields.xdmf").exists()


def test_spacetime_assembly_needs_a_continuum_with_a_sparse_path(capsys):
    assert main(["run", "ziegler", "--assembly", "spacetime"]) == 2
    assert "assembly=spacetime" in capsys.readouterr().err


def test_spacetime_assembly_of_a_small_continuum_agrees_with_the_dense_path():
    """Asked for on a scene within its dense limit, the space-time backend gives the answer of
    the dense Kronecker path on the same slabs and base state."""
    common = dict(T=0.1, slabs=2, cells=4, degree=3, base="start", reference="none")
    sparse = run(RunConfig.create("cauchy2d", params={"elements": 8}, assembly="spacetime",
                                  **common))
    dense = run(RunConfig.create("cauchy2d", params={"elements": 8}, assembly="kronecker",
                                 coordinates="physical", **common))
    if MPI.COMM_WORLD.rank == 0:
        assert sparse.solver["assembly"] == "spacetime"
        assert np.abs(sparse.x - dense.x).max() <= 1e-10 * np.abs(dense.x).max()
        assert np.abs(sparse.v - dense.v).max() <= 1e-9 * np.abs(dense.v).max()


@pytest.mark.mpi
def test_a_sparse_run_is_the_same_on_every_partition(tmp_path_factory):
    comm = MPI.COMM_WORLD
    out = comm.bcast(str(tmp_path_factory.mktemp("sparse")) if comm.rank == 0 else None)
    config = RunConfig.create("cauchy2d", params=SPARSE, T=0.05, slabs=2, cells=4, degree=3,
                              out=out)
    result = run(config, comm)
    serial = run(config, MPI.COMM_SELF) if comm.rank == 0 else None
    if comm.rank == 0:
        # (the CG stops at 1e-11 of the residual: partitions agree to about that)
        assert np.abs(result.x - serial.x).max() <= 1e-10 * np.abs(serial.x).max()
        assert np.abs(result.v - serial.v).max() <= 1e-9 * np.abs(serial.v).max()
        data = {"T": 0.05, "final": {"x": result.x[-1], "v": result.v[-1]}}
        ex, ev, scale = _errors(data, np.load(f"{out}/cauchy2d_system.npz"))
        assert max(ex, ev) <= result.error_estimate <= 1e-5 * scale


def test_a_sparse_simulation_runs_other_parameter_values():
    """A Simulation begun again with other parameters of the same size builds its space-time
    slab on the new matrices: the answer is that of a fresh run."""
    from fem_dual.integrate.simulation import Simulation

    common = dict(T=0.02, slabs=1, cells=4, degree=3)
    first = RunConfig.create("cauchy2d", params={**SPARSE, "delta": 0.5}, **common)
    second = RunConfig.create("cauchy2d", params={**SPARSE, "delta": -0.5}, **common)
    sim = Simulation.for_config(first)
    try:
        sim.run(first)
        again = sim.run(second)
        # the companion shares the answer's new system (one assembly, the same rows)
        assert sim.companion.backend.system is sim.backend.system
        assert not sim.companion.backend.owns_system
    finally:
        sim.close()
    fresh = run(second)
    if MPI.COMM_WORLD.rank == 0:
        assert np.abs(again.v - fresh.v).max() <= 1e-12 * np.abs(fresh.v).max()
        assert again.error_estimate == pytest.approx(fresh.error_estimate, rel=1e-6)


def test_every_slab_s_companion_starts_from_the_answer(capsys):
    """On every slab the degree p + 1 companion starts from the answer's dual fields (the
    tangent, solved on the answer's backend too, comes after it): at most 0.7 of the answer's
    CG iterations on the same slab, slab after slab (measured 0.57, 0.42, 0.42; from zero the
    companion takes 0.57, 0.84, 0.81)."""
    assert main(["run", "cauchy2d", "--param", "elements=20", "--slabs", "3", "--cells", "4",
                 "--degree", "3", "--T", "0.06", "--json"]) == 0
    solver = json.loads(capsys.readouterr().out)["solver"]
    answers = solver["ksp_iterations"][::2] if len(solver["ksp_iterations"]) == 5 else None
    assert answers is not None, solver["ksp_iterations"]  # 3 slabs and 2 tangents
    assert all(c <= 0.7 * a for c, a in zip(solver["companion_ksp_iterations"], answers)), \
        solver


def test_output_times_of_a_sparse_run_carry_their_error_and_estimate(capsys):
    """--t-eval on the sparse path: the dense output between vertices (fem_dual.integrate.dense)
    with sparse solves, its estimate above its error against the sparse reference."""
    assert main(["run", "cauchy2d", "--param", "elements=20", "--T", "0.1", "--rtol", "1e-6",
                 "--t-eval", "0.03,0.0777", "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    out = data["t_eval"]
    assert out["t"] == [0.03, 0.0777] and len(out["x"]) == 2
    assert 0 < max(out["error"]["x_max"], out["error"]["v_max"]) <= out["error_estimate"]


def test_the_sparse_reference_is_skipped_beyond_its_budget():
    """Its work grows like dofs x radians of the fastest mode: a horizon whose reference would
    take minutes is run without one (`error` null), a short one with it."""
    from fem_dual.continua.scenes import SPARSE_REFERENCE_BUDGET

    short = RunConfig.create("cauchy2d", params=SPARSE, T=0.2)
    rate = short.scene.fastest_rate()
    assert short.uses_reference and short.scene.n * rate * 0.2 <= SPARSE_REFERENCE_BUDGET
    T = 2 * SPARSE_REFERENCE_BUDGET / (short.scene.n * rate)
    assert not RunConfig.create("cauchy2d", params=SPARSE, T=T).uses_reference
    assert not RunConfig.create("cauchy2d", params=SPARSE, T=0.2, reference="none").uses_reference


def test_the_sparse_reference_is_taken_at_the_times_asked():
    """Times equally spaced but for 1e-10 are not a grid: each is taken where it is (a grid
    evaluation would be off by |v'| 1e-10), and decreasing times are refused."""
    from fem_dual.reference import SparseFlow

    config = RunConfig.create("cauchy2d", params=SPARSE, T=0.3)
    mats, scene = config.scene._csr, config.scene

    def flow():
        return SparseFlow(mats["M"], mats["K"], mats["D"], config.x0, config.v0,
                          scene.fastest_rate())

    t = np.array([0.1, 0.2000000001, 0.3])
    x, v = flow()(t)
    for k, s in enumerate(t):
        xs, vs = flow()(np.array([s]))
        assert np.abs(vs[0] - v[k]).max() <= 1e-12 * np.abs(vs).max()
        assert np.abs(xs[0] - x[k]).max() <= 1e-12 * np.abs(xs).max()
    with pytest.raises(ValueError, match="increase"):
        flow()(t[::-1])
