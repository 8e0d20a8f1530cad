"""A force with a kink (abs in the expression): the slab that contains it ends there, and the
reference stops at it as at an event; both against the exact piecewise-harmonic motion."""
import numpy as np
import pytest

from fem_dual import RunConfig, run
from fem_dual.integrate.controller import SlabSchedule

# x'' = -x for x < 0 and -101 x for x > 0: from x = -1 at rest, harmonic halves of frequencies
# 1 and sqrt(101) alternate, each crossing x = 0 with speed 1.
KINKED = "-x - 50*(x + abs(x))"
FAST = np.sqrt(101.0)


def exact(t: np.ndarray):
    """(x, v) of the kinked oscillator from x = -1, v = 0."""
    t = np.asarray(t, dtype=float)
    x, v = -np.cos(t), np.sin(t)
    start, sign = np.pi / 2, 1.0  # first crossing, then alternately into x > 0 and x < 0
    while start < t.max():
        omega = FAST if sign > 0 else 1.0
        end = start + np.pi / omega
        inside = t > start
        tau = t[inside] - start
        x[inside] = sign * np.sin(omega * tau) / omega
        v[inside] = sign * np.cos(omega * tau)
        start, sign = end, -sign
    return x, v


def _error(r) -> float:
    x, v = exact(r.t)
    return max(np.abs(r.x[:, 0] - x).max(), np.abs(r.v[:, 0] - v).max())


@pytest.mark.mpi
@pytest.mark.parametrize("base", ["auto", "start"])
def test_slabs_end_at_the_kinks_and_the_estimate_holds(base):
    """Without the cut both the answer and its companion lose their order in the kinked slab
    identically: an estimate of 4.8e-9 stood against a true error of 1.2e-5."""
    r = run(RunConfig.create("force", {"F": KINKED}, x0="-1", v0="0", T=6, rtol=1e-8, cells=4,
                             degree=4, base=base))
    assert r.status == "ok"
    assert _error(r) <= r.error_estimate <= 1e-7, (_error(r), r.error_estimate)
    cuts = [h for h in r.solver["halved_slabs"] if "kink" in h["reason"]]
    crossings = np.pi / 2 + np.cumsum([np.pi / FAST, np.pi, np.pi / FAST])
    crossings = np.concatenate([[np.pi / 2], crossings[crossings < 6]])
    assert len(cuts) >= len(crossings)
    for c in crossings:  # a slab ends within 1e-9 of every crossing (CUT_RESOLUTION)
        ends = np.cumsum(r.slab_lengths)
        assert np.abs(ends - c).min() <= 1e-8 * max(r.slab_lengths), c


@pytest.mark.mpi
def test_fixed_slabs_are_cut_at_the_kink_too():
    r = run(RunConfig.create("force", {"F": KINKED}, x0="-1", v0="0", T=2, slabs=1, cells=40,
                             degree=3))
    assert r.status == "ok" and len(r.slab_lengths) >= 2
    assert np.cumsum(r.slab_lengths)[0] == pytest.approx(np.pi / 2, abs=1e-8)
    assert _error(r) <= r.error_estimate, (_error(r), r.error_estimate)


def test_reference_stops_at_the_kinks():
    from fem_dual.inputs import scene_of

    scene = scene_of("force", {"F": KINKED})
    flow = scene.reference(np.array([-1.0]), np.array([0.0]))
    t = np.linspace(0.05, 6, 40)
    x, v = flow(t)
    ex, ev = exact(t)
    assert np.abs(x[:, 0] - ex).max() < 1e-11 and np.abs(v[:, 0] - ev).max() < 1e-11


def test_a_cut_ends_the_slab_before_the_time_and_keeps_exact_positions():
    schedule = SlabSchedule(T=6.0, slabs=4)
    t0, dt = schedule.current()
    assert schedule.cut(t0 + 0.3 * dt)
    t0_cut, dt_cut = schedule.current()
    assert t0_cut == t0 and 0.3 * dt * (1 - 1e-8) <= dt_cut <= 0.3 * dt
    state = schedule.state
    assert len(state) == SlabSchedule.STATE_SIZE == 7
    schedule.accept(1.0)
    total = dt_cut
    while not schedule.done():
        total += schedule.current()[1]
        schedule.accept(1.0)
    assert total == pytest.approx(6.0, rel=1e-15)
    restored = SlabSchedule(T=6.0, slabs=4)
    restored.state = state
    assert restored.state == state
    assert not SlabSchedule(T=6.0, slabs=4).cut(0.0)  # (a kink at the slab's start: no cut)


def test_a_start_on_the_kink():
    """From x = 0: moving, the reference stops at the next crossings as the exact motion does;
    at rest in the equilibrium on the kink it stays there (scipy counts a zero as a crossing:
    a motion sitting on a kink stopped the reference at every step)."""
    from fem_dual.inputs import scene_of

    scene = scene_of("force", {"F": KINKED})
    flow = scene.reference(np.array([0.0]), np.array([1.0]))
    t = np.linspace(0.01, 3, 50)
    x, v = flow(t)
    shifted = exact(t + np.pi / 2)  # (x = 0, v = 1 is where the motion from -1 first crosses)
    assert np.abs(x[:, 0] - shifted[0]).max() < 1e-11
    assert np.abs(v[:, 0] - shifted[1]).max() < 1e-11
    r = run(RunConfig.create("force", {"F": "-x - abs(x)"}, x0="0", v0="0", T=10, rtol=1e-8))
    assert r.status == "ok" and not np.any(r.x) and r.error["x_max"] == 0.0


def test_two_kinks_in_two_dimensions_and_no_slab_at_a_kink_found_again():
    """After a cut the next slab starts a hair before the kink and finds it again: it is not
    cut again (KINK_AT_START), and it takes up the length the cut slab had (a cut at the first
    slab once left slabs of 1e-12 growing 4x a slab, and the cost prediction refused the run)."""
    F = "-x - 3*abs(y) + 0.5*y, -y - 2*abs(x)"
    r = run(RunConfig.create("force", {"F": F}, x0="0.5,-0.3", T=5, rtol=1e-8))
    assert r.status == "ok" and min(r.slab_lengths) > 1e-3, r.slab_lengths
    assert max(r.error["x_max"], r.error["v_max"]) <= r.error_estimate
