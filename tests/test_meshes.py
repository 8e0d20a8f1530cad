"""The slab schedule of meshes/."""
import pytest

from meshes import SlabSchedule


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
    # after 2.5 the length grows back only where the position is a multiple of it
    assert slabs == [(0.0, 2.0), (2.0, 0.5), (2.5, 0.5), (3.0, 1.0)]
    assert sum(dt for _, dt in slabs) == pytest.approx(4.0)


def test_halving_stops_at_the_minimum_length():
    schedule = SlabSchedule(1.0, 1, max_halvings=2)
    assert schedule.halve() and schedule.halve() and not schedule.halve()
    assert schedule.current() == (0.0, 0.25)
