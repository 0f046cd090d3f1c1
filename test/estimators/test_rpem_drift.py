"""
rpem through a drift with its defaults (lambda = 1, change detection on).

Issue 31 asks every drift to be tracked. A change found part of the way through a drift
restarts the fits from a change point inside it; the fits of all samples since then kept
the rest of the drift for good (its weight falling as 1/N). After a change rpem now
compares each fit with the last one of the same window start, and a move beyond what
their nested windows explain keeps the newest half of the window (rpem/window.py;
docs/tracking_log.md, "Limits and what is left", 2026-11-28, session 7).
"""

import numpy as np
import pytest

from benchmarks.tracking import TrackingCase
from bcid_ros.estimators import make_estimator

#: The first-order plant y = b (1 - a) / (1 - a q^-1) u + v whose gain drifts.
POLE = 0.9


def drifting_plant(seed, start=4000, drift=2000, after=4000, gain=1.8, snr_db=25.0):
    """Return (y, u, theta at the end) of a plant whose gain grows by ``gain`` over ``drift``."""
    rng = np.random.default_rng(seed)
    count = start + drift + after
    u = np.repeat(np.sign(rng.standard_normal(count // 8 + 1)), 8)[:count]  # PRBS held 8
    b = np.concatenate((np.ones(start), np.linspace(1.0, gain, drift), np.full(after, gain)))
    x = np.zeros(count)
    for t in range(1, count):
        x[t] = POLE * x[t - 1] + b[t] * (1.0 - POLE) * u[t - 1]
    y = x + x[:start].std() * 10.0 ** (-snr_db / 20.0) * rng.standard_normal(count)
    return y, u, np.array([-POLE, gain * (1.0 - POLE)])


@pytest.mark.parametrize('seed', [0, 2, 3])
def test_a_drift_is_tracked_to_within_the_estimates_own_uncertainty_by_the_end(seed):
    # 4000 samples after the drift's end, where the squared norm of the error has the
    # expectation |std|^2 for an estimate of the final plant alone. Before the window's
    # move (b305845) the final error was 5.5, 5.7 and 4.5 times the std on these seeds
    # (3.0-6.0 on seeds 0-7); with it 1.1, 2.5 and 2.8 (0.1-2.8)
    y, u, final = drifting_plant(seed)
    estimator = make_estimator('rpem', order=1)
    for t in range(y.shape[0]):
        estimator.update(y[t], u[t])
    assert np.linalg.norm(estimator.theta - final) < 3.0 * np.linalg.norm(
        estimator.parameter_std)


@pytest.mark.parametrize('seed', [0, 1, 2, 3])
def test_after_an_abrupt_change_the_fits_window_stays(seed):
    # the same plant's gain stepped at once: the fits after the change are of one plant,
    # nested windows whose moves the chi-square at 1e-3 explains (about 5 comparisons a
    # run: P(a move) about 0.5 % a seed if the fits' covariance is honest)
    y, u, final = drifting_plant(seed, drift=1)
    estimator = make_estimator('rpem', order=1)
    for t in range(y.shape[0]):
        estimator.update(y[t], u[t])
    assert estimator.flags.get('plant_change', 0) >= 1
    assert estimator.flags.get('window_moved', 0) == 0
    assert np.linalg.norm(estimator.theta - final) < 3.0 * np.linalg.norm(
        estimator.parameter_std)


def test_the_fit_a_move_is_judged_against_is_state():
    # saved once a fit after the change waits to be compared, a run goes on bit for bit
    # through the window's moves
    y, u, _ = drifting_plant(0)
    estimator = make_estimator('rpem', order=1)
    for t in range(y.shape[0]):
        estimator.update(y[t], u[t])
        if estimator.get_state().scalars['window_weight'] > 0.0:
            break
    assert estimator.flags.get('plant_change', 0) == 1 and 'window_moved' not in estimator.flags
    restored = make_estimator('rpem', order=1)
    restored.set_state(estimator.get_state())
    for each in (estimator, restored):
        for k in range(t + 1, y.shape[0]):
            each.update(y[k], u[k])
    assert estimator.flags['window_moved'] >= 1 and estimator.flags == restored.flags
    np.testing.assert_array_equal(estimator.theta, restored.theta)
    np.testing.assert_array_equal(estimator.parameter_std, restored.parameter_std)


@pytest.mark.parametrize('seed, accuracy', [((5, 22), 0.01), ((2, 19), 0.02)])
def test_a_drift_still_going_after_its_detection_leaves_the_fits_once_the_check_says_so(
        seed, accuracy):
    # tracking plants whose change was detected early in a drift of a slow third-order plant
    # (poles 0.99): the fits of every sample since the change point blended the rest of the
    # drift and ended 17.8 % and 45 % off (not valid); the nested-window test never moved
    # the window. The simulation check contradicted the new model on two disjoint windows:
    # the fits now keep the last window's samples (window_moved), and the estimate ends
    # within 1 % (0.43 %; the band of the benchmark is 1 %) and 2 % (0.66 %)
    case = TrackingCase(seed, 'family')
    estimator = make_estimator('rpem', order=case.order, num_inputs=case.num_inputs)
    for t in range(case.samples):
        estimator.update(float(case.y[t]), case.u[t])
    assert estimator.flags.get('window_moved', 0) >= 1
    truth = case.theta[-1]
    assert np.linalg.norm(estimator.theta - truth) < accuracy * np.linalg.norm(truth)


def test_the_contradictions_a_window_move_counts_are_state():
    # (5, 22) saved while its pending change's run of contradictions is under way (a
    # thousand samples before the move): the restored run moves the window at the same
    # sample and goes on bit for bit
    case = TrackingCase((5, 22), 'family')
    estimator = make_estimator('rpem', order=case.order, num_inputs=case.num_inputs)
    saved_at = 8000
    for t in range(saved_at):
        estimator.update(float(case.y[t]), case.u[t])
    state = estimator.get_state()
    assert state.scalars['simulation_run_start'] >= 0 and 'window_moved' not in estimator.flags
    restored = make_estimator('rpem', order=case.order, num_inputs=case.num_inputs)
    restored.set_state(state)
    for each in (estimator, restored):
        for t in range(saved_at, case.samples):
            each.update(float(case.y[t]), case.u[t])
    assert estimator.flags['window_moved'] >= 1 and estimator.flags == restored.flags
    np.testing.assert_array_equal(estimator.theta, restored.theta)
    np.testing.assert_array_equal(estimator.parameter_std, restored.parameter_std)
