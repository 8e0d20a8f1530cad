"""Linear scenes in chunks: the slabs of one length come from their slab maps
in a few array products, judged and recorded as the slab loop does one by one."""
import numpy as np
import pytest

from fem_dual import RunConfig, run
from fem_dual.integrate import chunks, loop, state
from fem_dual.integrate.simulation import Simulation
from fem_dual.errors import SolveError
from fem_dual.slab.kronecker import KroneckerSuperposition, decoupled_blocks, probes


def _close(a, b, rel):
    return np.abs(a - b).max() <= rel * np.abs(b).max()


@pytest.mark.mpi
@pytest.mark.parametrize("scene, params", [("ziegler", {"d1": "0.05", "d2": "0.02"}),
                                           ("column", {"links": "6", "P": "1.0"})])
def test_batched_slabs_agree_with_solving_every_slab(scene, params, monkeypatch):
    args = dict(T=40.0, slabs=40, cells=6, degree=4)
    batched = run(RunConfig.create(scene, params, superpose="yes", **args))
    direct = run(RunConfig.create(scene, params, superpose="no", **args))
    with monkeypatch.context() as patch:  # the same bases, slab by slab
        patch.setattr(loop, "batch_step", lambda *a: (0, None))
        one_by_one = run(RunConfig.create(scene, params, superpose="yes", **args))
    assert batched.solver["batched_slabs"] == 40 and direct.solver["batched_slabs"] == 0
    assert one_by_one.solver["batched_slabs"] == 0
    for other in (direct, one_by_one):
        assert np.array_equal(batched.t, other.t)
        assert batched.slab_lengths == other.slab_lengths
        assert [e["t0"] for e in batched.solver["estimates"]] == \
            [e["t0"] for e in other.solver["estimates"]]
    assert _close(batched.x, direct.x, 1e-10) and _close(batched.v, direct.v, 1e-10)
    assert _close(batched.x, one_by_one.x, 1e-13) and _close(batched.v, one_by_one.v, 1e-13)
    # the estimate is a difference of two close solutions: its last digits are round-off (and,
    # with CG, the solver's tolerance), differently cancelled
    assert batched.error_estimate == pytest.approx(one_by_one.error_estimate, rel=1e-4)
    assert batched.estimate_at_t == pytest.approx(one_by_one.estimate_at_t, rel=1e-3,
                                                  abs=1e-6 * batched.error_estimate)
    drift = [np.array([h["drift"] for h in r.hamiltonian["per_slab"]])
             for r in (batched, one_by_one)]
    assert np.abs(drift[0] - drift[1]).max() < 1e-9


@pytest.mark.serial
def test_chunks_give_the_numbers_of_one_chunk(monkeypatch):
    config = RunConfig.create("ziegler", T=200.0, slabs=100, cells=8, degree=4)
    whole = run(config)
    monkeypatch.setattr(chunks, "CHUNK_SLABS", 7)
    monkeypatch.setattr(state, "CHUNK_SLABS", 7)
    chunked = run(config)
    assert whole.solver["batched_slabs"] == chunked.solver["batched_slabs"] == 100
    assert np.array_equal(whole.x[-1], chunked.x[-1])  # the slab-to-slab recurrence
    assert _close(chunked.x, whole.x, 1e-14)
    assert chunked.error_estimate == pytest.approx(whole.error_estimate, rel=1e-12)


@pytest.mark.serial
def test_a_length_refused_at_the_first_slab_keeps_the_chunks_whole(monkeypatch):
    """250 slabs of T = 1000 are too long for the default tolerance: the first chunk is refused
    at its first slab, the slab loop halves it, and the other 499 slabs come in one chunk (not
    in chunks restarted small), as the slabs of a run asked for 500 do."""
    args = dict(T=1000.0, cells=4, degree=4, reference="none")
    asked = run(RunConfig.create("ziegler", slabs=500, **args))
    chunked = []
    original = chunks._chunk
    monkeypatch.setattr(chunks, "_chunk", lambda sim, config, state, schedule, weights, bound,
                        count: chunked.append((schedule.current()[1], count)) or original(
                            sim, config, state, schedule, weights, bound, count))
    halved = run(RunConfig.create("ziegler", slabs=250, **args))
    assert halved.solver["rejected_slabs"] == 1 and halved.slab_lengths == [2.0] * 500
    assert chunked == [(4.0, 250), (2.0, 499)]
    assert halved.solver["batched_slabs"] == 499 and asked.solver["batched_slabs"] == 500
    assert _close(halved.x, asked.x, 1e-13) and _close(halved.v, asked.v, 1e-13)
    assert halved.error_estimate == pytest.approx(asked.error_estimate, rel=1e-6)


@pytest.mark.serial
def test_a_chunk_stops_where_the_slab_loop_refuses():
    # flutter: the motion grows until it overflows at slab 747
    args = dict(T=800.0, slabs=800, cells=8, degree=4, max_halvings=0, reference="none")
    failures = []
    for superpose in ("yes", "no"):
        with pytest.raises(SolveError) as info:
            run(RunConfig.create("ziegler", {"P": "3.0"}, superpose=superpose, **args))
        failures.append(info.value)
    assert failures[0].slab == failures[1].slab > 700
    assert str(failures[0]) == str(failures[1])
    assert "where H_d (quadratic in the state) overflows float64" in str(failures[0])
    kept = [f.partial for f in failures]
    assert kept[0].solver["batched_slabs"] == failures[0].slab
    assert np.isfinite(kept[0].x).all() and len(kept[0].slab_lengths) == failures[0].slab
    assert _close(kept[0].x[:-200], kept[1].x[:-200], 1e-9)


@pytest.mark.serial
def test_probes_give_the_bases_of_the_unit_start_states():
    config = RunConfig.create("column", {"links": "8", "P": "0.2"}, T=3.0, slabs=30, cells=4,
                              degree=3, base="zero", coordinates="modal")
    sim = Simulation.for_config(config)
    sim.begin(config)
    probed = sim.superposition
    assert isinstance(probed, KroneckerSuperposition) and probed.gathers is not None
    # two per place in the largest block (one mode, or a complex pair): positions, velocities
    assert len(probed.starts) == 2 * np.bincount(probed.blocks).max() < 16
    dense = KroneckerSuperposition(sim.backend.problem, sim.backend.solver, sim.backend.sampler)
    dense.starts, dense.gathers = np.eye(16), None
    Z = np.random.default_rng(1).normal(size=(5, 16))
    a, b = probed.batch(Z, 0.1), dense.batch(Z, 0.1)
    for field in ("x", "v", "hamiltonian", "xi", "eta"):
        assert _close(getattr(a, field), getattr(b, field), 1e-12), field
    assert probed.basis_solves == len(probed.starts) and dense.basis_solves == 16
    sim.close()


def test_probes_pair_the_components_of_each_block():
    blocks = decoupled_blocks({"M": np.eye(3), "K": np.array([[1, 2, 0], [3, 4, 0], [0, 0, 5]]),
                               "D": np.zeros((3, 3)), "A": np.eye(3), "B": np.eye(3)})
    assert blocks[0] == blocks[1] != blocks[2]
    starts, gathers = probes(blocks)
    assert len(starts) == 4  # two places in the largest block, positions and velocities
    # every unit start state is read from exactly one probe, in the components of its block
    for column in range(6):
        hits = np.argwhere(gathers[:, :3] == column)
        block = blocks[column % 3]
        assert sorted(hits[:, 1]) == sorted(np.flatnonzero(blocks == block))
        assert len(set(hits[:, 0])) == 1 and starts[hits[0, 0], column] == 1.0


@pytest.mark.serial
def test_a_batched_run_resumed_after_a_signal_ends_bit_for_bit(tmp_path, monkeypatch):
    import signal

    from fem_dual import faults

    args = dict(T=2000.0, slabs=1000, cells=8, degree=4)
    whole = run(RunConfig.create("ziegler", out=tmp_path / "a", **args))
    config = RunConfig.create("ziegler", out=tmp_path / "b", **args)
    with monkeypatch.context() as patch:
        patch.setattr(chunks, "CHUNK_SLABS", 300)
        patch.setattr(state, "CHUNK_SLABS", 300)
        asked = iter([0, 0, signal.SIGINT])  # after the third chunk (8 + 32 + 128 slabs)
        patch.setattr(faults, "requested", lambda: next(asked, 0))
        with pytest.raises(faults.Interrupted) as info:
            run(config)
    first = info.value.partial
    kept = len(first.slab_lengths)
    assert first.status == "interrupted" and 0 < kept < 1000 and first.output_slabs == kept
    again = run(config, resume=True)
    assert again.solver["resumed_from"]["slab"] == kept
    assert again.final == whole.final  # bit for bit
    assert np.array_equal(again.t, whole.t) and np.array_equal(again.x, whole.x)
    assert again.error_estimate == whole.error_estimate
