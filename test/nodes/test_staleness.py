"""The rule of ``stale_after``: when an estimate is stale (bcid_ros.identifier.staleness)."""

import pytest

from bcid_ros.identifier.staleness import MIN_AUTOMATIC, RECENT_ARRIVALS, Staleness


def test_a_fixed_limit_counts_from_the_start_and_from_each_sample():
    rule = Staleness(0.5)
    assert rule.reason(100.0) == ''  # nothing to measure from yet
    rule.restart(100.0)
    assert rule.reason(100.49) == ''
    assert rule.reason(100.5) == 'no samples for 0.5 s'
    rule.arrived(100.6)
    assert rule.reason(101.0) == '' and rule.reason(101.2) == 'no samples for 0.6 s'


def test_automatic_is_ten_median_intervals_at_least_one_second():
    rule = Staleness(0.0)
    rule.restart(0.0)
    rule.arrived(5.0)  # the wait for the first sample is no interval
    assert rule.limit() is None and rule.reason(1e6) == ''
    for k in range(1, 30):
        rule.arrived(5.0 + 0.5 * k)  # 2 Hz
    assert rule.limit() == pytest.approx(5.0)
    fast = Staleness(0.0)
    for k in range(200):
        fast.arrived(k * 0.001)  # 1 kHz: ten intervals are 10 ms, below the floor
    assert fast.limit() == MIN_AUTOMATIC


def test_automatic_follows_recent_arrivals_and_a_clock_that_goes_back():
    rule = Staleness(0.0)
    for k in range(RECENT_ARRIVALS):
        rule.arrived(k * 1.0)
    assert rule.limit() == pytest.approx(10.0)
    for k in range(RECENT_ARRIVALS):  # the plant speeds up to 0.2 s: only recent ones count
        rule.arrived(RECENT_ARRIVALS + k * 0.2)
    assert rule.limit() == pytest.approx(2.0)
    rule.arrived(3.0)  # a looped bag: the clock went back
    assert rule.limit() is None
    rule.arrived(3.3)
    assert rule.limit() == pytest.approx(3.0)


def test_negative_is_never_and_a_non_finite_limit_is_refused():
    rule = Staleness(-1.0)
    rule.arrived(0.0)
    assert rule.limit() is None and rule.reason(1e9) == ''
    with pytest.raises(ValueError, match="'stale_after'"):
        Staleness(float('nan'))
