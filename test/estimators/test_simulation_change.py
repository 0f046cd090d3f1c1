"""
A plant change found by the simulation check (SimulationWindow.contradicted_twice).

A model that passed the check on a full window, then contradicted on two disjoint windows with
no check passing in between, is taken as a plant change (rpem: the change path, from the
samples of the last window); a model that never passed is never restarted by it
(docs/tracking.md, "What a detection does").
"""

import numpy as np
import pytest
from scipy import signal

from benchmarks.tracking import TrackingCase
from bcid_ros.estimators import make_estimator, rules, simulation_check
from bcid_ros.estimators.change_detection import BLOCK_LENGTH, FALSE_ALARM
from bcid_ros.estimators.rpem.online import SIMULATION_NOTE
from bcid_ros.estimators.simulation_check import (change_rate, SimulationWindow, tail_looks,
                                                  WINDOW)

FALSE_ALARM_CHECK = simulation_check.FALSE_ALARM

PERIOD = 100


def judged_windows(y, u, a, b, looks_at_tail=True):
    """Yield (recorded samples, window) after each check of a window every PERIOD samples."""
    window = SimulationWindow(a.size, 1, False, [0], period=PERIOD, looks_at_tail=looks_at_tail)
    for t in range(y.size):
        window.record(float(y[t]), [u[t]])
        if (t + 1) % PERIOD == 0:
            window.reasons(a, b)
            window.vouch()  # an estimator whose other checks pass
            yield t + 1, window


def first_order(pole_before, pole_after, change, samples=6000, seed=3):
    """Return (y, u): y = q^-1/(1 - pole q^-1) u + 0.3 e, the pole changing at ``change``."""
    rng = np.random.default_rng(seed)
    u = rng.standard_normal(samples)
    before = signal.lfilter([0.0, 1.0], [1.0, -pole_before], u)
    after = signal.lfilter([0.0, 1.0], [1.0, -pole_after], u)
    y = np.where(np.arange(samples) < change, before, after)
    return y + 0.3 * rng.standard_normal(samples), u


def second_order(samples=6000, seed=4):
    """Return (y, u): y = q^-1/((1 - 0.9 q^-1)(1 - 0.5 q^-1)) u + 0.3 e, beyond a first order."""
    rng = np.random.default_rng(seed)
    u = rng.standard_normal(samples)
    y = signal.lfilter([0.0, 1.0], np.poly([0.9, 0.5]), u)
    return y + 0.3 * rng.standard_normal(samples), u


def test_a_model_that_passed_is_judged_changed_on_the_samples_since_its_first_contradiction():
    """
    Pole 0.8 -> 0.7 at 3000: the change is reported on the samples after c alone.

    A model at the old plant (10 dB SNR) passes on full windows before; the first
    contradicted check is at c (after 3000). The samples recorded since c, disjoint from c's
    window, contradict it at the first look (their first PERIOD, at least ``minimum``):
    reported there, with their count as the age, long before c + WINDOW.
    """
    y, u = first_order(0.8, 0.7, 3000)
    first, found = None, None
    for recorded, window in judged_windows(y, u, np.array([-0.8]), np.array([1.0])):
        if recorded <= 3000:
            assert window.contradicted_twice() == 0
            assert not window.reason, recorded
        elif window.reason and first is None:
            first = recorded
        if window.contradicted_twice():
            found = (recorded, window.contradicted_twice())
            break
    assert window.passed
    assert first is not None and 3000 < first <= 3000 + WINDOW
    assert window.minimum <= PERIOD
    assert found == (first + PERIOD, PERIOD)
    # a window that does not look at a run's tail (rls, bcrls: they take no change from
    # it) reports at the first check whose window starts after c
    for recorded, window in judged_windows(y, u, np.array([-0.8]), np.array([1.0]),
                                           looks_at_tail=False):
        if window.contradicted_twice():
            break
    assert (recorded, window.contradicted_twice()) == (first + WINDOW, WINDOW)


@pytest.fixture
def tails_pass(monkeypatch):
    """Make every look at a run's tail pass; return the looks' (samples, alpha)."""
    real_judge = simulation_check.judge
    looks = []

    def judge(y, u, a, b, lags, false_alarm=FALSE_ALARM_CHECK, **settings):
        verdict = real_judge(y, u, a, b, lags, false_alarm=false_alarm, **settings)
        if false_alarm == FALSE_ALARM_CHECK:  # the check of the window
            return verdict
        looks.append((y.shape[1], false_alarm))
        return verdict[:3] + (np.zeros(1, dtype=bool),) + verdict[4:]

    monkeypatch.setattr(simulation_check, 'judge', judge)
    return looks


def test_the_looks_at_the_tail_double_share_alpha_and_leave_the_disjoint_window(tails_pass):
    """
    Where no look at the samples since c contradicts, the whole window does at c + WINDOW.

    The same change, with every look at the tail passing (judge's verdict replaced): the
    looks come at tails of 100, 200, 400 and 800 samples (from ``minimum`` = 80, each at
    least twice the last, below WINDOW), each at alpha / tail_looks = alpha / 4, and the
    change is reported as before the looks, at the first check whose window starts after c.
    """
    y, u = first_order(0.8, 0.7, 3000)
    first, found = None, None
    for recorded, window in judged_windows(y, u, np.array([-0.8]), np.array([1.0])):
        if recorded > 3000 and window.reason and first is None:
            first = recorded
        if window.contradicted_twice():
            found = (recorded, window.contradicted_twice())
            break
    assert tail_looks(window.minimum, WINDOW) == 4
    assert tails_pass == [(tail, FALSE_ALARM_CHECK / 4) for tail in (100, 200, 400, 800)]
    assert found == (first + WINDOW, WINDOW)


def test_a_model_that_never_passed_is_never_judged_changed():
    """
    A model that is contradicted at every full window and never passed reports no change.

    A first-order model of a second-order plant (poles 0.9 and 0.5): however long the
    contradiction, no change.
    """
    y, u = second_order()
    contradicted = 0
    for recorded, window in judged_windows(y, u, np.array([-0.9]), np.array([1.0])):
        contradicted += bool(window.reason) and recorded >= WINDOW
        assert window.contradicted_twice() == 0
        assert not window.passed
    assert contradicted == (6000 - WINDOW) // PERIOD + 1


def test_across_disjoint_windows_a_model_that_never_passed_is_reported_and_new_run_recounts():
    """
    contradicted_across needs no pass, takes no look at the tail; new_run() counts afresh.

    It is rpem's evidence that a pending change's fits blend another plant. The first-order
    model of a second-order plant, contradicted from its first check c, is reported at the
    first check whose window starts after c, c + WINDOW (the samples since c alone
    contradict it from c + PERIOD, but a model that never passed takes no look at them);
    after each new_run() the run starts at the next check, so the next report is
    WINDOW + PERIOD later.
    """
    y, u = second_order()
    first, reported = None, []
    for recorded, window in judged_windows(y, u, np.array([-0.9]), np.array([1.0])):
        if window.reason and first is None:
            first = recorded
        if window.contradicted_across():
            assert window.contradicted_across() == WINDOW
            reported.append(recorded)
            window.new_run()
            assert window.contradicted_across() == 0
    assert first is not None
    # the run starts at the first contradiction, again at the check after each new_run
    assert reported[0] == first + WINDOW
    assert np.all(np.diff(reported) == WINDOW + PERIOD)


def test_a_gap_in_a_run_waits_for_a_verdict_on_the_samples_after_it():
    """
    After a gap (a sample not recorded) the run's one verdict is not a second window.

    Pole 0.8 -> 0.7 at 3000, the old model: at the first contradicted check c a gap. The
    verdict before the gap holds, but no change is reported on it: only once a check judged
    the samples after the gap (disjoint from c's window), with their count as the age, as
    a look at the run's tail (alpha / J); contradicted_across, which takes no looks, waits
    for a whole window of them.
    """
    y, u = first_order(0.8, 0.7, 3000)
    window = SimulationWindow(1, 1, False, [0], period=PERIOD, looks_at_tail=True)
    a, b = np.array([-0.8]), np.array([1.0])
    gap_at = None
    for t in range(y.size):
        window.record(float(y[t]), [u[t]])
        if gap_at is None and (t + 1) % PERIOD == 0:
            window.reasons(a, b)
            window.vouch()
            if window.reason:
                gap_at = t + 1
                window.gap()
        elif gap_at is not None:
            assert window.contradicted_twice() == 0 and window.contradicted_across() == 0
            if (t + 1 - gap_at) % PERIOD == 0:
                window.reasons(a, b)
                window.vouch()
                break
    assert gap_at is not None and window.reason
    assert window.contradicted_twice() == PERIOD
    assert window.contradicted_across() == 0


def test_after_a_gap_the_pending_path_waits_for_a_whole_window_after_it():
    """
    contradicted_across after a gap: a whole window of the samples after it, not their first.

    The first-order model of a second-order plant, contradicted from its first check c, a
    gap there. The samples after the gap contradict it at every check while the window
    refills; each such verdict at alpha, a look the alpha^2 bound does not allow (the code
    before reported at c + PERIOD with their PERIOD samples). Reported at c + WINDOW, with
    the whole window; never by contradicted_twice (the model never passed).
    """
    y, u = second_order()
    window = SimulationWindow(1, 1, False, [0], period=PERIOD, looks_at_tail=True)
    a, b = np.array([-0.9]), np.array([1.0])
    gap_at = reported = None
    for t in range(y.size):
        window.record(float(y[t]), [u[t]])
        if (t + 1) % PERIOD:
            continue
        window.reasons(a, b)
        window.vouch()
        if gap_at is None and window.reason:
            gap_at = t + 1
            window.gap()
        elif gap_at is not None:
            assert window.reason and window.contradicted_twice() == 0
            if window.contradicted_across():
                reported = (t + 1, window.contradicted_across())
                break
    assert gap_at is not None
    assert reported == (gap_at + WINDOW, WINDOW)


def test_a_passing_check_ends_the_run_and_a_clear_forgets_the_pass(tails_pass):
    """
    A check that passes between two contradicted ones restarts the run; clear() resets.

    The looks at the run's tail pass (else they report the change before the pass).
    """
    y, u = first_order(0.8, 0.7, 3000)
    window = SimulationWindow(1, 1, False, [0], period=PERIOD, looks_at_tail=True)
    a, b = np.array([-0.8]), np.array([1.0])
    for t in range(y.size):
        window.record(float(y[t]), [u[t]])
        if (t + 1) % PERIOD == 0:
            # a model of the new plant judged once on a window of its samples alone, a
            # check before the old model's run would be reported: it passes, and the run of
            # the old model's contradictions starts again after it
            passing = t + 1 == 3000 + WINDOW
            window.reasons(np.array([-0.7]) if passing else a, b)
            window.vouch()
            if passing:
                assert not window.reason
                resumed = t + 1 + PERIOD
            if window.contradicted_twice():
                break
    assert t + 1 == resumed + WINDOW
    window.clear()
    assert not window.passed and window.contradicted_twice() == 0


def test_the_run_survives_a_snapshot(tails_pass):
    """
    The run's start, its looks, the pass and the recorded count go through state_items/load.

    Taken in a run whose looks at its tail pass (its next look due at 800 samples).
    """
    y, u = first_order(0.8, 0.7, 3000)
    for recorded, window in judged_windows(y, u, np.array([-0.8]), np.array([1.0])):
        if recorded == 3600:
            break
    copy = SimulationWindow(1, 1, False, [0], period=PERIOD, looks_at_tail=True)
    copy.load(*window.state_items())
    assert copy.state_items()[1] == window.state_items()[1]
    assert window.state_items()[1]['simulation_next_look'] == 800
    for t in range(3600, 5000):
        for each in (window, copy):
            each.record(float(y[t]), [u[t]])
            if (t + 1) % PERIOD == 0:
                each.reasons(np.array([-0.8]), np.array([1.0]))
                each.vouch()
        assert copy.contradicted_twice() == window.contradicted_twice()
        assert copy.passed == window.passed
    # three looks before the snapshot, then both the fourth
    assert [tail for tail, _ in tails_pass] == [100, 200, 400, 800, 800]


def test_rpem_takes_a_change_its_detector_misses_from_the_simulation_check():
    """
    Tracking plant (4, 5): pole 0.188 -> 0.078 at 3553 (theta 11 % off), 13 dB, white input.

    The detector never fires on it; before this path the recursion crept (5 % off 4000
    samples later) while the check contradicted it from about 500 samples after the change.
    Now: flag ``plant_change`` after the change only, within WINDOW samples of it (the
    samples since the check's first contradiction alone contradict the model), the change's
    reason names the check, and the estimate ends within 2 % (its pre-change error is 0.3 %).
    """
    case = TrackingCase((4, 5), 'family')
    estimator = make_estimator('rpem', order=case.order, num_inputs=case.num_inputs)
    reasons = None
    for t in range(case.samples):
        before = estimator.flags.get('plant_change', 0)
        estimator.update(float(case.y[t]), case.u[t])
        if estimator.flags.get('plant_change', 0) != before:
            assert t >= case.change_at, t
            # on the samples since the check's first contradiction, about 600 samples
            # after the change (the whole disjoint window came 1000 later: 1601)
            assert t < case.change_at + WINDOW, t
            reasons = reasons or estimator.validity_reasons
    assert estimator.flags.get('plant_change', 0) == 1
    assert reasons[0].startswith('plant changed') and reasons[0].endswith(SIMULATION_NOTE)
    truth = case.theta[-1]
    assert np.linalg.norm(estimator.theta - truth) < 0.02 * np.linalg.norm(truth)
    assert estimator.valid


def test_a_model_the_estimator_does_not_vouch_for_never_passes():
    """The check's pass alone is not enough: without vouch() no change is ever reported."""
    y, u = first_order(0.8, 0.7, 3000)
    window = SimulationWindow(1, 1, False, [0], period=PERIOD, looks_at_tail=True)
    for t in range(y.size):
        window.record(float(y[t]), [u[t]])
        if (t + 1) % PERIOD == 0:
            window.reasons(np.array([-0.8]), np.array([1.0]))
            assert window.contradicted_twice() == 0
    assert not window.passed and window.reason


def test_rpem_plant_change_sources_stay_within_the_stated_rate():
    """The whitened test, the block test and this evidence share FALSE_ALARM (per sample)."""
    rpem = make_estimator('rpem', order=2, num_inputs=1)
    # Lorden: a CUSUM of threshold h alarms at most e^-h a sample (the block test a block)
    rates = (np.exp(-rpem._detector.threshold), np.exp(-rpem._block_test.threshold) / BLOCK_LENGTH,
             change_rate(rules.VALIDITY_PERIOD))
    assert sum(rates) <= FALSE_ALARM * (1 + 1e-12)
    assert min(rates) > 0.0
