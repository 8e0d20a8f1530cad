"""Linear scenes by superposition give the numbers of solving every slab; a compiled Simulation
can be run again (with new parameters) and agrees with a fresh run."""
import h5py
import numpy as np
import pytest
from mpi4py import MPI

from fem_dual import RunConfig, run
from fem_dual.integrate.simulation import Simulation

CASES = {"ziegler-damped": ("ziegler", {"d1": "0.05", "d2": "0.02"}),
         "column-3": ("column", {"links": "3", "P": "1.5"}),
         "ziegler-flutter": ("ziegler", {"P": "3.0"})}  # growing: the basis must be exact


def _same(a, b, rel=1e-11):
    return np.abs(a - b).max() <= rel * np.abs(b).max()


@pytest.mark.mpi
@pytest.mark.parametrize("case", list(CASES))
def test_superposition_equals_solving_every_slab(case, tmp_path_factory):
    scene, params = CASES[case]
    out = tmp_path_factory.mktemp("superposed") if MPI.COMM_WORLD.rank == 0 else None
    out = MPI.COMM_WORLD.bcast(out)
    args = dict(T=12.0, cells=6, degree=4, slabs=12)
    direct = run(RunConfig.create(scene, params, superpose="no", out=out / "d", **args))
    superposed = run(RunConfig.create(scene, params, superpose="yes", out=out / "s", **args))
    n = superposed.x.shape[1]
    assert superposed.solver["superposition"] and superposed.solver["slab_solves"] == 2 * n
    assert not direct.solver["superposition"] and direct.solver["slab_solves"] == 12
    assert np.array_equal(direct.t, superposed.t)
    assert _same(superposed.x, direct.x) and _same(superposed.v, direct.v)
    drift_d, drift_s = (np.array([h["drift"] for h in r.hamiltonian["per_slab"]])
                        for r in (direct, superposed))
    assert np.abs(drift_s - drift_d).max() < 1e-9
    assert superposed.hamiltonian["max"] == pytest.approx(direct.hamiltonian["max"], rel=1e-10)
    if MPI.COMM_WORLD.rank == 0:  # the XDMF output (dual fields included) agrees too
        with h5py.File(out / "d" / f"{scene}.h5") as d, h5py.File(out / "s" / f"{scene}.h5") as s:
            names = []
            d.visititems(lambda name, obj: names.append(name)
                         if isinstance(obj, h5py.Dataset) else None)
            assert len(names) > 12
            for name in names:
                if name.endswith(("error_estimate", "restart/local", "restart/glob",
                                  "restart/slab")):  # the estimate carries round-off
                    if name == "restart/slab":  # index, t0, dt, schedule: exact
                        assert np.array_equal(s[name][:, :8], d[name][:, :8]), name
                        continue
                    if name.startswith("restart/"):  # components of the estimate: round-off
                        a, b = s[name][()], d[name][()]
                        assert np.abs(a - b).max() <= 0.05 * np.abs(b).max() + 1e-12, name
                        continue
                    assert np.allclose(s[name][()], d[name][()], rtol=1e-2, atol=1e-12), name
                else:
                    assert _same(s[name][()], d[name][()], rel=1e-10), name


@pytest.mark.mpi
def test_shorter_last_slab_gets_its_own_basis():
    cfg = dict(T=10.0, cells=5, degree=3, slabs=7)  # the default schedule: equal slabs
    direct = run(RunConfig.create("ziegler", superpose="no", **cfg))
    superposed = run(RunConfig.create("ziegler", superpose="yes", **cfg))
    assert _same(superposed.x, direct.x)


@pytest.mark.mpi
def test_auto_superposes_when_slabs_exceed_twice_the_dofs():
    few = run(RunConfig.create("ziegler", T=4.0, cells=4, degree=2, slabs=4))
    many = run(RunConfig.create("ziegler", T=4.0, cells=4, degree=2, slabs=5))
    assert not few.solver["superposition"] and many.solver["superposition"]
    curl = run(RunConfig.create("curl3d", T=0.5, cells=4, degree=2, slabs=8))
    assert not curl.solver["superposition"]


@pytest.mark.mpi
def test_simulation_reruns_with_new_parameters_like_fresh_runs():
    first = RunConfig.create("ziegler", T=5.0, cells=10, degree=3, slabs=2)
    sim = Simulation(first.scene, 3, 10)
    again = sim.run(first)
    assert again.timings["compile_s"] > 0.0
    again = sim.run(first)
    assert again.timings["compile_s"] == 0.0
    assert again.solver["solves"] == 3  # 2 slabs, 1 tangent of the estimate
    assert again.solver["slab_solves"] == 2 and again.solver["tangent_solves"] == 1
    assert _same(again.x, run(first).x, rel=1e-14)
    loaded = RunConfig.create("ziegler", {"P": "1.7", "d1": "0.1"}, T=5.0, cells=10, degree=3,
                              slabs=2)
    assert _same(sim.run(loaded).x, run(loaded).x, rel=1e-13)
    with pytest.raises(ValueError):
        sim.run(RunConfig.create("ziegler", T=5.0, cells=11, degree=3, slabs=2))


def test_superpose_input_is_validated():
    from fem_dual.errors import InputError

    with pytest.raises(InputError, match="superpose='maybe'"):
        RunConfig.create("ziegler", superpose="maybe")
    with pytest.raises(InputError, match="nonlinear"):
        RunConfig.create("curl3d", superpose="yes")


@pytest.mark.serial
def test_the_slab_map_check_refuses_growth_not_round_off():
    """Within one radian of the fastest mode per slab every mode is resolved: an excess of the
    map's radius there is round-off of the basis or truncation error (a 4.5e-12 slab of the
    6-link column chosen by rtol 1e-10 is not amplifying for 3e-12 times 1e12 slabs);
    a decaying map is not refused for its distance from the exact decay; a map that grows
    where the flow does not is."""
    from fem_dual.errors import SolveError
    from fem_dual.slab.superposition import check_slab_map

    scene = RunConfig.create("ziegler", {"d1": "1", "d2": "1"}).scene
    rate = float(np.abs(scene.spectrum[0]).max())
    check_slab_map(scene, (1 + 1e-11) * np.eye(4), 0.5 / rate, 1e12)
    check_slab_map(scene, 0.93 * np.eye(4), 10.0 / rate, 1e6)
    with pytest.raises(SolveError, match="amplifies"):
        check_slab_map(scene, 1.01 * np.eye(4), 10.0 / rate, 1e3)
