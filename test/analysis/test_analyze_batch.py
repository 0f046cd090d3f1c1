"""``bcid analyze`` parts: residual tests, batch structure search, LM solver, BLAS threads."""

import numpy as np
import pytest
from scipy import signal

from bcid_ros.analysis import metrics
from bcid_ros.analysis.batch import (Candidate, fit_candidate, FULL_GRID_INPUTS, Record,
                                     redundancy, search_structures)
from bcid_ros.analysis.pem import fit_oe, Structure
from bcid_ros.analysis.search import FIT_MARGIN, recommend
from bcid_ros.blas_threads import _controls, openblas_libraries, single_threaded_blas


def _held_binary(rng, count, hold):
    """Return a random binary signal (+-1) held ``hold`` samples, shape ``(count,)``."""
    levels = rng.choice([-1.0, 1.0], size=-(-count // hold))
    return np.repeat(levels, hold)[:count]


def _hidden_plant(seed, count):
    """Return (y, u) of order 3, dead time 2, held binary input, 5 % output noise."""
    rng = np.random.default_rng(seed)
    a = np.real(np.poly([0.9, 0.7 * np.exp(0.5j), 0.7 * np.exp(-0.5j)]))
    u = _held_binary(rng, count, 5)
    x = signal.lfilter([0.0, 0.0, 0.0, 0.5, 0.3, -0.2], a, u)
    return x + 0.05 * x.std() * rng.standard_normal(count), u[:, None]


def test_cross_correlation_test_holds_its_level_under_coloured_noise_and_a_held_input():
    # the residual is AR(1) noise at pole 0.9, independent of a held binary input: a test
    # that ignored the colour would reject nearly always; 200 runs at the 1 % level reject
    # 2 on average, binomial standard error 1.4, so at most 2 + 3 x 1.4
    rejected = 0
    for seed in range(200):
        rng = np.random.default_rng(seed)
        u = _held_binary(rng, 1300, 4)[:, None]
        residual = signal.lfilter([1.0], [1.0, -0.9], rng.standard_normal(1000))
        rejected += metrics.cross_correlation_test(residual, u, 20)[1] < 0.01
    assert rejected <= 6


def test_cross_correlation_test_finds_an_input_left_in_the_residual():
    rng = np.random.default_rng(5)
    u = _held_binary(rng, 1300, 4)[:, None]
    noise = signal.lfilter([1.0], [1.0, -0.9], rng.standard_normal(1300))
    # a missed slow mode: 0.3 of the input through a pole at 0.8, beside a noise of std ~2.3
    missed = signal.lfilter([0.0, 0.3], [1.0, -0.8], u[:, 0])
    residual = (noise + missed)[300:]
    assert metrics.cross_correlation_test(residual, u, 20)[1] < 1e-6


def test_the_estimate_uncertainty_keeps_a_consistent_oe_fit_from_failing_the_test():
    # OE under strongly coloured noise at a high SNR is consistent but not efficient: its
    # residual on new data carries the estimate's own error, correlated with u; with
    # cov(theta) in the test's covariance the true structure passes, without it it fails
    rng = np.random.default_rng(2)
    count = 4000
    u = _held_binary(rng, count, 3)[:, None]
    a = np.poly([0.95, 0.6])
    x = signal.lfilter([0.0, 1.0, -0.5], a, u[:, 0])
    v = signal.lfilter([1.0], np.poly([0.98, 0.95]), rng.standard_normal(count))
    y = x + 0.02 * x.std() / v.std() * v
    record = Record(y, u, 2800)
    candidate = fit_candidate(record, 2, (0,))
    y_c, u_c = record.centred()
    without = metrics.cross_correlation_test(candidate.residual, u_c, record.test_lags)[1]
    assert candidate.cross_correlation_p >= 0.01
    assert without < 1e-4


def test_accuracy_test_tells_a_better_model_from_an_equal_one():
    rng = np.random.default_rng(1)
    noise = rng.standard_normal(1000)
    misfit = 0.5 * np.sin(np.arange(1000) / 7.0)
    assert metrics.accuracy_test(noise + misfit, noise, 20)[1] < 1e-6
    # the same errors in the other order: b is worse, so p is near 1
    assert metrics.accuracy_test(noise, noise + misfit, 20)[1] > 0.99
    z, p = metrics.accuracy_test(noise, rng.standard_normal(1000), 20)
    assert abs(z) < 4.0 and 1e-4 < p < 1 - 1e-4


def test_levenberg_marquardt_reaches_the_trust_region_minimum():
    y, u = _hidden_plant(3, 3000)
    y, u = y - y.mean(), u - u.mean(axis=0)
    structure = Structure(3, 1, 2)
    trf = fit_oe(y, u, structure, solver='trf')
    lm = fit_oe(y, u, structure, solver='lm')
    # both stop when a step lowers the cost by < 1e-8 of it; near the minimum that is
    # (dtheta/std)^2 / N < 1e-8, |dtheta| < sqrt(3000e-8) std = 0.0055 std: 0.05 std is ten times
    assert np.all(np.abs(lm.theta - trf.theta) <= 0.05 * trf.std)
    assert lm.loss <= trf.loss * (1 + 1e-6)
    # one sample moved by 50 noise std moves the estimate by far more than the bound
    moved = y.copy()
    moved[1500] += 50 * 0.05 * y.std()
    other = fit_oe(moved, u, structure, solver='lm')
    assert np.any(np.abs(other.theta - trf.theta) > 0.05 * trf.std)
    with pytest.raises(ValueError, match='solver'):
        fit_oe(y, u, structure, solver='newton')


def test_single_threaded_blas_sets_one_thread_and_restores_the_count():
    controls = [found for found in map(_controls, openblas_libraries()) if found is not None]
    if not controls:
        pytest.skip('no OpenBLAS loaded in this process')
    before = [getter() for _, getter in controls]
    with single_threaded_blas() as count:
        assert count == len(controls)
        assert [getter() for _, getter in controls] == [1] * len(controls)
    assert [getter() for _, getter in controls] == before


def test_the_hidden_plant_structure_is_found():
    # the plant (order 3, dead time 2, held input, 5 % noise), 3000 samples
    y, u = _hidden_plant(0, 3000)
    with single_threaded_blas():
        candidates = search_structures(Record(y, u, 2100), (1, 4), (0, 3))
    chosen, adequate = recommend(candidates)
    assert (chosen.order, chosen.delays, adequate) == (3, (2,), True)
    # orders 1 and 2 are outside the margin: their RMS error is over 1.3 times the best
    best = max(c.fit for c in candidates)
    assert all(100 - c.fit > (1 + FIT_MARGIN) * (100 - best)
               for c in candidates if c.order < 3)


def test_dead_time_per_input_of_a_two_input_plant():
    rng = np.random.default_rng(4)
    count = 2000
    u = rng.standard_normal((count, 2))
    a = np.poly([0.8, 0.5])
    x = signal.lfilter([0.0, 0.0, 0.0, 1.0, 0.5], a, u[:, 0]) + \
        signal.lfilter([0.0, 0.7, -0.4], a, u[:, 1])
    y = x + 0.1 * x.std() * rng.standard_normal(count)
    with single_threaded_blas():
        candidates = search_structures(Record(y, u, 1400), (1, 3), (0, 2))
    assert len(candidates) == 3 * 9  # the full grid for two inputs
    chosen, adequate = recommend(candidates)
    assert (chosen.order, chosen.delays, adequate) == (2, (2, 0), True)


def test_coordinate_search_of_the_dead_times_beyond_two_inputs():
    rng = np.random.default_rng(6)
    count = 1500
    u = rng.standard_normal((count, 3))
    delays = (0, 2, 1)
    gains = (1.0, -0.8, 0.6)
    x = sum(signal.lfilter(np.concatenate([np.zeros(d + 1), [g]]), [1.0, -0.7], u[:, i])
            for i, (d, g) in enumerate(zip(delays, gains)))
    y = x + 0.1 * x.std() * rng.standard_normal(count)
    fits = []
    with single_threaded_blas():
        candidates = search_structures(Record(y, u, 1050), (1, 1), (0, 2),
                                       progress=fits.append)
    assert FULL_GRID_INPUTS < 3
    assert len(candidates) < 27 and len(fits) == len(candidates)  # fewer than 3^3
    chosen, _ = recommend(candidates)
    assert chosen.delays == delays


def test_redundancy_finds_a_cancelled_pole_and_a_negligible_first_coefficient():
    structure = Structure(2, 1, 0)
    covariance = np.diag([1e-4, 1e-4, 1e-4, 1e-4])
    # pole 0.5 and zero 0.5: (q - 0.5)(...) cancels
    theta = np.concatenate([np.poly([0.5, 0.8])[1:], [1.0, -0.5]])
    assert any('cancelled' in reason for reason in redundancy(structure, theta, covariance))
    # b1_1 = 0.01 is within 2.58 standard deviations (0.01 each) of zero
    theta = np.concatenate([np.poly([0.5, 0.8])[1:], [0.01, 1.0]])
    assert any('dead time of u1 is longer' in r for r in redundancy(structure, theta, covariance))
    theta = np.concatenate([np.poly([0.5, 0.8])[1:], [1.0, 0.3]])
    assert redundancy(structure, theta, covariance) == ()
    infinite = np.full((4, 4), np.inf)
    assert 'not finite' in redundancy(structure, theta, infinite)[0]


def _candidate(order, fit, uncorrelated=True, redundant=False, mdl=0.0, delays=(0,)):
    return Candidate(order, delays, fit=fit, stable=True, mdl=mdl,
                     cross_correlation_p=0.5 if uncorrelated else 1e-5,
                     redundancy=('cancelled',) if redundant else ())


def test_the_rule_prefers_the_smallest_adequate_order_within_the_margin():
    candidates = [_candidate(1, 80.0), _candidate(2, 90.3, uncorrelated=False),
                  _candidate(3, 90.5), _candidate(4, 91.0)]

    def chosen():
        found, adequate = recommend(candidates)
        return candidates.index(found), adequate

    # the margin is 100 - 1.1 x (100 - 91) = 90.1: order 1 is outside, order 2 fails the test
    assert chosen() == (2, True)
    # a redundant order 3 is skipped
    candidates[2] = _candidate(3, 90.5, redundant=True)
    assert chosen() == (3, True)
    # nothing adequate: the smallest order within the margin that is not redundant
    candidates[3] = _candidate(4, 91.0, uncorrelated=False)
    assert chosen() == (1, False)


def test_at_the_chosen_order_the_lowest_mdl_picks_the_dead_time():
    candidates = [_candidate(2, 90.0, mdl=-10.0, delays=(1,)),
                  _candidate(2, 90.2, mdl=-30.0, delays=(2,)),
                  _candidate(2, 90.3, mdl=-20.0, delays=(3,))]
    assert recommend(candidates)[0] is candidates[1]
    assert recommend([]) == (None, False)
