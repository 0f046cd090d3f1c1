"""
analyze's search across orders: warm starts, near-cancelling pairs, the estimator recommended.

A staircase input (the steps of a heated plate's set point) with strongly coloured output
noise: from the cold starts (ARX, refined IV) the fits of orders 3 to 6 fell into minima far
worse than the order-2 fit (validation fit 24-29 % against 98.5 %, and a worse fit of the
estimation part), as on a measured plate in issue 34. An order-(n + 1) fit started from the
order-n fit with a pole and a zero added cannot end worse on the estimation part.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import signal

from bcid_ros.analysis.batch import near_pairs, NEAR_PAIR, Record, search_structures
from bcid_ros.analysis.online import OnlineResult, recommend_estimator
from bcid_ros.analysis.pem import Structure
from bcid_ros.analysis.search import FIT_POINTS, recommend

#: The staircase's hold (samples) and the record's length.
HOLD, SAMPLES = 100, 1200


def staircase_record(seed: int) -> Record:
    """Return a third-order plant (poles 0.97, 0.9, 0.6) under a staircase, AR(1) noise."""
    rng = np.random.default_rng(seed)
    u = np.repeat(rng.uniform(0.0, 1.0, SAMPLES // HOLD + 1), HOLD)[:SAMPLES]
    y = signal.lfilter([0.0, 0.02, 0.01, -0.005], np.poly([0.97, 0.9, 0.6]), u)
    y += 0.02 * signal.lfilter([1.0], [1.0, -0.95], rng.standard_normal(SAMPLES))
    return Record(y, u[:, None], SAMPLES * 7 // 10)


@pytest.mark.parametrize('seed', [0, 1, 2])
def test_the_estimation_fit_never_falls_with_the_order(seed):
    candidates = search_structures(staircase_record(seed), (1, 6), (0, 0))
    fits = [c.estimation_fit for c in candidates]
    assert [c.order for c in candidates] == list(range(1, 7))
    # each order's fit is at least the one before (rounding of the fit's own arithmetic)
    assert all(later >= earlier - 1e-9 for earlier, later in zip(fits, fits[1:])), fits


#: How far an order above the right one may fall below its validation fit (points): its extra
#: parameters fitted to coloured noise cost up to 2.3 (seeds 0-3, orders 3-5: 96.2-98.5 where
#: the order-2 fits are 97.9-98.5, on a machine whose BLAS ends seed 1's order 4 in another
#: minimum than the development machine's), where the failure this guards against, cold
#: starts in far minima, costs 70
OVERFIT_POINTS = 5.0


def test_orders_above_the_right_one_keep_its_validation_fit():
    # seed 1: the cold starts gave 23.7, 27.9, 29.3, 24.7 % for orders 3-6, against 98.5 %
    candidates = search_structures(staircase_record(1), (1, 5), (0, 0))
    second = candidates[1].fit
    assert second > 95.0
    for candidate in candidates[2:]:
        assert candidate.fit >= second - OVERFIT_POINTS, (candidate.order, candidate.fit)


def noisy_plate(seed: int) -> Record:
    """Return a heated plate's record at a low signal-to-noise ratio (validation fits ~60 %)."""
    rng = np.random.default_rng(seed)
    u = np.repeat(rng.uniform(0.0, 1.0, SAMPLES // 170 + 2), 170)[:SAMPLES]
    a = np.poly([0.977, 0.85, 0.3])
    b = np.array([0.0, 1.0, 0.5, -0.3]) * a.sum() / 1.2
    y = signal.lfilter(b, a, u)
    v = signal.lfilter([1.0], [1.0, -0.95], rng.standard_normal(SAMPLES))
    return Record(y + 0.3 * np.std(y) / np.std(v) * v, u[:, None], SAMPLES * 7 // 10)


def test_the_recommended_structure_is_within_two_points_of_the_best():
    # with the margin relative to the RMS error alone (10 %), a best fit of 59.0 % let
    # order 1 at 55.3 % be chosen: 3.7 points below the best on the grid
    candidates = search_structures(noisy_plate(3), (1, 3), (0, 0))
    chosen, _ = recommend(candidates)
    best = max(c.fit for c in candidates if c.usable)
    assert chosen.fit >= best - FIT_POINTS, [(c.order, c.fit) for c in candidates]


def test_near_cancelling_pairs_are_reported():
    structure = Structure(3, 1, (0,))
    # F = (1 - 0.9 q^-1)(1 - 0.5 q^-1)(1 - 0.2 q^-1); B = q^-1 (1 - 0.88 q^-1)(1 + 0.3 q^-1)
    denominator = np.poly([0.9, 0.5, 0.2])
    numerator = np.convolve([1.0, -0.88], [1.0, 0.3])
    theta = np.concatenate([denominator[1:], numerator])
    pairs = near_pairs(structure, theta)
    assert len(pairs) == 1
    assert pairs[0]['input'] == 1
    assert pairs[0]['pole'] == pytest.approx([0.9, 0.0])
    assert pairs[0]['zero'] == pytest.approx([0.88, 0.0])
    assert pairs[0]['distance'] == pytest.approx(0.02)
    # a zero just beyond the distance is no pair
    far = np.concatenate([denominator[1:], np.convolve([1.0, -(0.9 - 1.01 * NEAR_PAIR)],
                                                       [1.0, 0.3])])
    assert near_pairs(structure, far) == ()


def result(name, fit, valid):
    return OnlineResult(name, valid=valid, stable=True, fit=fit)


def test_a_close_estimate_is_preferred_to_a_valid_far_one():
    # the glass furnace of issue 34: rls valid at 64.7 %, rpem not valid at 72.0 %, batch 72.8 %
    results = [result('rls', 64.7, True), result('rpem', 72.0, False)]
    assert recommend_estimator(results, 72.8, 0.10) == ('rpem', True, False)


def test_a_valid_close_estimate_comes_first():
    results = [result('rls', 71.0, True), result('rpem', 72.5, False)]
    assert recommend_estimator(results, 72.8, 0.10) == ('rls', True, True)


def test_a_valid_far_estimate_is_named_not_close():
    results = [result('rls', 40.0, True), result('rpem', 30.0, False)]
    assert recommend_estimator(results, 72.8, 0.10) == ('rls', False, True)
    unstable = OnlineResult('bcrls', valid=True, stable=False, fit=99.0)
    assert recommend_estimator([unstable], 72.8, 0.10) == (None, False, False)
