"""The slab schedule of meshes/."""
import numpy as np
import pytest

from fem_dual.integrate.controller import FIRST_PATIENCE, MAX_PATIENCE, SlabSchedule


def _walk(schedule, fail_at=()):
    slabs = []
    while not schedule.done():
        t0, dt = schedule.current()
        if (t0, dt) in fail_at and schedule.halve():
            continue
        slabs.append((t0, dt))
        schedule.accept()
    return slabs


def test_equal_slabs_start_exactly_at_k_T_over_S():
    slabs = _walk(SlabSchedule(10.0, 7, max_halvings=6))
    assert [t0 for t0, _ in slabs] == [k * 10.0 / 7 for k in range(7)]
    assert all(dt == pytest.approx(10.0 / 7) for _, dt in slabs)


def test_halving_then_growing_back_covers_the_interval():
    slabs = _walk(SlabSchedule(4.0, 2, max_halvings=3), fail_at={(2.0, 2.0), (2.0, 1.0)})
    # the rejected length 1.0 is not tried again for FIRST_PATIENCE slabs
    assert slabs == [(0.0, 2.0), (2.0, 0.5), (2.5, 0.5), (3.0, 0.5), (3.5, 0.5)]
    assert sum(dt for _, dt in slabs) == pytest.approx(4.0)
    slabs = _walk(SlabSchedule(8.0, 2, max_halvings=3), fail_at={(4.0, 4.0), (4.0, 2.0)})
    # after the wait it grows back only where the position is a multiple of the length
    assert slabs == [(0.0, 4.0), (4.0, 1.0), (5.0, 1.0), (6.0, 1.0), (7.0, 1.0)]
    slabs = _walk(SlabSchedule(16.0, 2, max_halvings=3), fail_at={(8.0, 8.0), (8.0, 4.0)})
    assert slabs == [(0.0, 8.0)] + [(8.0 + k * 2.0, 2.0) for k in range(4)]


def test_a_length_rejected_again_waits_twice_as_long():
    """An error just above the tolerance at one length and below it at half of it: each
    attempt at the long length after the wait fails, and the waits double, so the attempts
    thin out (not one every other slab)."""
    schedule = SlabSchedule(1000.0, 1000, max_halvings=1)
    attempts, slabs = 0, 0
    while not schedule.done():
        t0, dt = schedule.current()
        if dt == 1.0:
            attempts += 1
            assert schedule.halve()
            continue
        slabs += 1
        schedule.accept(4.0)
    assert slabs == 2000
    waits = FIRST_PATIENCE * 2 ** np.arange(10)
    assert attempts <= 1 + np.searchsorted(np.cumsum(np.minimum(waits, MAX_PATIENCE)), 2000) + 2
    assert attempts < 20


def test_a_passed_length_is_forgotten():
    schedule = SlabSchedule(100.0, 100, max_halvings=2)
    assert schedule.halve()
    for _ in range(FIRST_PATIENCE):
        schedule.accept(4.0)
    assert schedule.current()[1] == 1.0 and schedule.ceiling == 4
    schedule.accept(4.0)
    assert schedule.ceiling == 0 and schedule.current()[1] == 1.0
    state = schedule.state
    again = SlabSchedule(100.0, 100, max_halvings=2)
    again.state = state
    assert again.state == state and again.current() == schedule.current()


def test_halving_stops_at_the_minimum_length():
    schedule = SlabSchedule(1.0, 1, max_halvings=2)
    assert schedule.halve() and schedule.halve() and not schedule.halve()
    assert schedule.current() == (0.0, 0.25)


def test_fixed_slabs_keep_their_length_until_one_is_rejected():
    """A slab accepted close to the tolerance (factor below 1) does not shorten the next fixed
    slab (an adaptive schedule's does): that would give two half slabs every few dozen slabs,
    each pair breaking a chunk of equal slabs."""
    fixed = SlabSchedule(10.0, 10, max_halvings=3, shrinks=False)
    adaptive = SlabSchedule(10.0, 10, max_halvings=3)
    for schedule in (fixed, adaptive):
        schedule.accept(0.8)
    assert fixed.current() == (1.0, 1.0)
    assert adaptive.current() == (1.0, 0.5)


@pytest.mark.parametrize("shrinks, per_octave", [(True, 1), (False, 1), (True, 2), (True, 4)])
def test_accept_run_gives_the_states_of_accept(shrinks, per_octave):
    """SlabSchedule.accept_run (vectorised for chunks of slabs) gives the states `accept`
    gives slab by slab, stopping after the first slab whose factor changes the length."""
    import copy

    rng = np.random.default_rng(7)
    for trial in range(1500):
        schedule = SlabSchedule(10.0, int(rng.integers(1, 9)), int(rng.integers(0, 7)),
                                first=float(rng.uniform(0.01, 1.0)), shrinks=shrinks,
                                per_octave=per_octave)
        for _ in range(int(rng.integers(0, 5))):  # somewhere along the run
            if schedule.done():
                break
            schedule.accept(float(rng.choice([0.3, 1.0, 1.5, 2.5, 8.0])))
        if trial % 3 == 0 and schedule.length > 1:
            schedule.halve()  # a remembered length, kept below while the wait lasts ...
            for _ in range(int(rng.integers(0, 8))):  # ... then reached again, and cleared
                if schedule.done():
                    break
                schedule.accept(float(rng.choice([1.0, 2.0, 8.0])))
        remaining = (schedule.total - schedule.pos) // max(schedule.length, 1)
        if schedule.done() or remaining < 1:
            continue
        factors = rng.choice([0.2, 0.9, 1.0, 1.3, 2.0, 3.7, 50.0], size=int(rng.integers(1, 40)))
        factors = factors[:remaining]
        one, run = copy.copy(schedule), copy.copy(schedule)
        expected = one.accept_each(factors)
        assert len(expected) and expected[-1].tolist() == list(one.state)
        assert run.accept_run(factors).tolist() == expected.tolist()
        assert run.state == one.state


def test_the_fine_grid_has_four_lengths_an_octave():
    from fem_dual.integrate.controller import grid_floor

    units = np.arange(1, 300)
    grid = grid_floor(units.astype(float), 4)
    assert (grid <= units).all() and (np.diff(grid) >= 0).all()
    lengths = sorted(set(grid.tolist()))
    assert lengths[:12] == [1, 2, 3, 4, 5, 6, 7, 8, 10, 12, 14, 16]
    assert max(b / a for a, b in zip(lengths[3:], lengths[4:])) == 1.25
    assert grid_floor(np.array([2.0 ** 40]), 4)[0] == 2 ** 40
    assert grid_floor(np.array([5.9, 9.99]), 1).tolist() == [4, 8]
    assert grid_floor(np.array([1.5, 2.9, 3.5, 5.9, 7.9]), 2).tolist() == [1, 2, 3, 4, 6]


def test_a_fine_schedule_grows_in_small_steps_and_ends_short():
    """Under a tolerance the next length is the slab's times its factor rounded down to the
    fine grid (not to a power of two), a rejected one shrinks by at most FINE_SHRINK, an
    accepted one keeps its length for a factor in [SAFETY, 1), and the last slab ends at T."""
    schedule = SlabSchedule(10.0, 1, 10, first=0.1, per_octave=4)
    t0, dt = schedule.current()
    assert dt == pytest.approx(10.0 * 96 / 1024)  # 102.4 units: 6 x 16
    schedule.accept(1.3)  # 124.8 -> 112 = 7 x 16 (a power of two: 64)
    assert schedule.current()[1] == pytest.approx(10.0 * 112 / 1024)
    schedule.accept(0.95)  # within the tolerance: kept
    assert schedule.current()[1] == pytest.approx(10.0 * 112 / 1024)
    assert schedule.halve(0.9)  # at most FINE_SHRINK: 89.6 -> 80 = 5 x 16
    assert schedule.current()[1] == pytest.approx(10.0 * 80 / 1024)
    schedule.accept(1.0)
    assert schedule.halve(0.8)  # 64 = 4 x 16
    assert schedule.current()[1] == pytest.approx(10.0 * 64 / 1024)
    slabs = []
    while not schedule.done():
        slabs.append(schedule.current())
        schedule.accept(1.0)
    assert (dt + (112 + 80) * 10.0 / 1024 + sum(length for _, length in slabs)
            == pytest.approx(10.0))
    assert all(length == pytest.approx(10.0 * 64 / 1024) for _, length in slabs[:-1])
    assert slabs[-1][1] < slabs[-2][1]  # the short last slab, ending at T in floats
    assert slabs[-1][0] + slabs[-1][1] == 10.0


@pytest.mark.parametrize("per_octave", [1, 2, 4])
def test_an_error_wall_costs_few_rejections_on_any_grid(per_octave):
    """An error that jumps above the tolerance beyond one length: after a rejection the
    schedule waits below the shortest length rejected, and each return past it doubles the
    wait, on the fine grids as on powers of two (a cascade of rejections, one fine step down
    at a time, took as many solves as the accepted slabs)."""
    from fem_dual.integrate.controller import step_factor

    schedule = SlabSchedule(10.0, 1, 20, first=0.001, per_octave=per_octave)
    accepted = rejected = 0
    while not schedule.done():
        t0, dt = schedule.current()
        err = 1.5 if dt > 0.0025 * 10.0 else 1e-3
        if err > 1.0:
            rejected += 1
            assert schedule.halve(step_factor(err, 4))
            continue
        accepted += 1
        schedule.accept(step_factor(err, 4))
    assert accepted >= 100 and rejected <= 12


def test_a_rejected_short_last_slab_is_shortened():
    """The last slab, short where it meets T, is halved from its own length (not from the
    nominal one, which left the same slab to be solved again)."""
    schedule = SlabSchedule(20.0, 1, 10, first=0.5, per_octave=2)
    schedule.accept(1.0)
    schedule.state = (896, 512, 0, 0, 0, 0, 0)  # 128 units left before T
    t0, dt = schedule.current()
    assert schedule.halve(0.9)
    assert schedule.current()[1] < dt and schedule.current()[0] == t0
