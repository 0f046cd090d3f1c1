"""
The CUSUM change detector: its false-alarm rate against the bound, its delays, its change point.

Many plants run at once through the detector's plant axis. A count of false alarms over N
samples of no change is compared with the bound's expectation N / ARL plus four Poisson
standard errors; detection shares with four binomial standard errors.
"""

import math

import numpy as np
import pytest
from scipy import signal

from bcid_ros.estimators.change_detection import (ChangeDetector, FALSE_ALARM, threshold,
                                                  VARIANCE_RATIO, WARMUP)

PLANTS = 400


def run(errors):
    """Feed (N, K) errors to a K-plant detector; return the (N, K) ages."""
    detector = ChangeDetector(errors.shape[1])
    return np.array([detector.record(row) for row in errors])


def test_threshold_is_lordens_bound_for_the_stated_rate():
    assert threshold() == pytest.approx(math.log(1.0 / FALSE_ALARM))
    with pytest.raises(ValueError, match='false_alarm'):
        threshold(0.0)


@pytest.mark.parametrize('pole', [0.0, 0.9])
def test_false_alarms_on_errors_that_do_not_change_stay_within_the_bound(pole):
    rng = np.random.default_rng(7 + int(10 * pole))
    samples = 25000
    errors = signal.lfilter([1.0], [1.0, -pole], rng.standard_normal((samples, PLANTS)), axis=0)
    alarms = int((run(errors) > 0).sum())
    tested = (samples - WARMUP) * PLANTS
    expected = tested * FALSE_ALARM  # the bound: at most one per 1 / FALSE_ALARM samples
    assert alarms <= expected + 4.0 * math.sqrt(expected)


def first_detection(ages, start):
    """Return per plant the first sample with a detection at or after ``start`` (-1: none)."""
    hit = ages[start:] > 0
    first = np.where(hit.any(axis=0), hit.argmax(axis=0) + start, -1)
    return first


@pytest.mark.parametrize('size', [3.0, 1.8])
def test_a_shift_is_detected_about_when_its_evidence_reaches_the_threshold(size):
    rng = np.random.default_rng(11)
    before, after = 2000, 1500
    errors = rng.standard_normal((before + after, PLANTS))
    errors[before:] *= math.sqrt(size)
    drift = 0.5 * (1.0 - 1.0 / VARIANCE_RATIO) * size - 0.5 * math.log(VARIANCE_RATIO)
    ages = run(errors)
    early = (ages[:before] > 0).any(axis=0)
    first = first_detection(ages, before)
    found = (first >= 0) & ~early
    assert found.mean() >= 0.95
    delay = first[found] - before + 1
    # Wald: the mean delay is about h over the mean increment (plus an overshoot < 1 step)
    design = threshold() / drift
    assert 0.7 * design <= np.median(delay) <= 1.5 * design
    # the change point (the GLR's within the detecting run) lies near the true one
    start = first[found] - ages[first[found], np.flatnonzero(found)] + 1
    assert abs(np.median(start - before)) <= 0.2 * design


def test_a_step_of_the_mean_is_seen_while_the_centring_catches_up():
    rng = np.random.default_rng(12)
    errors = rng.standard_normal((3000, PLANTS))
    errors[2000:] += 2.0
    ages = run(errors)
    found = first_detection(ages, 2000)
    assert ((found >= 2000) & (found < 2100)).mean() >= 0.95


def test_one_plant_on_floats_takes_the_decisions_of_the_plant_axis():
    rng = np.random.default_rng(3)
    errors = rng.standard_normal(6000)
    errors[3000:] *= 2.5
    single, batched = ChangeDetector(), ChangeDetector(1)
    ages = [single.record(float(e)) for e in errors]
    batch_ages = [int(batched.record(np.array([e]))[0]) for e in errors]
    assert ages == batch_ages and any(ages)
    for key, value in single.get_state().items():
        # the same element-wise operations in the same order: equal within a few ulp
        np.testing.assert_allclose(value, batched.get_state()[key], rtol=1e-12, atol=1e-300)


def test_state_round_trip_continues_bit_for_bit():
    rng = np.random.default_rng(5)
    errors = rng.standard_normal(4000)
    errors[2500:] += 1.0
    first = ChangeDetector()
    for e in errors[:2600]:
        first.record(e)
    second = ChangeDetector()
    second.set_state(first.get_state())
    rest = errors[2600:]
    assert [first.record(e) for e in rest] == [second.record(e) for e in rest]
    fresh = ChangeDetector()
    fresh.set_state({})  # an old snapshot without the detector starts afresh
    assert not fresh.state.armed.any()
