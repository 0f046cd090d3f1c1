"""
The residual adequacy monitor: its null distribution, false alarms, power, reasons and recovery.

The Monte Carlo tests run many plants at once through the monitor's plant axis. A share
measured over K independent plants has the binomial standard error sqrt(p (1 - p) / K); the
tolerances are four of them (a correct monitor fails one such check with probability 6e-5).
"""

import math

import numpy as np
import pytest
from scipy import signal, stats

from bcid_ros.estimators.adequacy import (AdequacyMonitor, BLOCK, chi2_quantile, chi2_survival,
                                          default_window, levinson, MAX_WINDOW, MIN_WINDOW)
from bcid_ros.estimators.lagged import effective_size
from bcid_ros.estimators.residual_statistics import quadratic_forms

PLANTS = 600
SAMPLES = 3000
WINDOW = 500  # N = (1 + mu) / (1 - mu) = 999 effective samples in the steady state


def low_pass(white, pole=0.9):
    """Return white noise through 1 / (1 - pole q^-1), unit variance."""
    return signal.lfilter([1.0], [1.0, -pole], white, axis=0) * math.sqrt(1.0 - pole * pole)


def held_prbs(rng, samples, plants, inputs, hold=8):
    """Return a +-1 signal held for ``hold`` samples, shape (samples, plants, inputs)."""
    levels = np.sign(rng.standard_normal((samples // hold + 1, plants, inputs)))
    return np.repeat(levels, hold, axis=0)[:samples]


def monitor_run(residual, inputs, **settings):
    """Feed (N, K) residuals and (N, K, r) inputs to a K-plant monitor; return it."""
    monitor = AdequacyMonitor(num_inputs=inputs.shape[-1], plants=residual.shape[1],
                              window=WINDOW, **settings)
    for t in range(residual.shape[0]):
        monitor.record(residual[t], inputs[t])
    return monitor


def within(share, expected, count):
    """Whether ``share`` over ``count`` plants is within 4 binomial standard errors of it."""
    return abs(share - expected) <= 4.0 * math.sqrt(expected * (1.0 - expected) / count)


# ------------------------------------------------------------------ chi-square
@pytest.mark.parametrize('dof', [1, 2, 3, 10, 11, 25])
def test_chi2_survival_is_scipys(dof):
    x = np.array([0.01, 0.5, 3.0, 10.0, 23.2, 40.0, 80.0])
    ours = np.array([chi2_survival(value, dof) for value in x])
    # finite sums of positive terms: a few ulp of each term, relative
    np.testing.assert_allclose(ours, stats.chi2.sf(x, dof), rtol=1e-12, atol=1e-300)


@pytest.mark.parametrize('dof', [1, 10, 25])
@pytest.mark.parametrize('tail', [0.5, 0.01, 1e-4])
def test_chi2_quantile_inverts_the_survival(dof, tail):
    # the bisection stops at a relative width of 1e-12
    assert chi2_quantile(tail, dof) == pytest.approx(stats.chi2.isf(tail, dof), rel=1e-10)


# ------------------------------------------------------------------ the null
@pytest.mark.parametrize('excitation', ['low_pass', 'held_prbs'])
def test_the_statistics_are_chi_square_under_the_null_with_coloured_inputs(excitation):
    rng = np.random.default_rng(11)
    residual = rng.standard_normal((SAMPLES, PLANTS))
    if excitation == 'low_pass':
        inputs = low_pass(rng.standard_normal((SAMPLES, PLANTS, 2)))
    else:
        inputs = held_prbs(rng, SAMPLES, PLANTS, 2)
    monitor = monitor_run(residual, inputs)
    statistics = monitor.statistics  # (K, 3): whiteness, u1, u2
    lags = monitor.lags
    # the mean of chi2(M) is M with standard error sqrt(2M / K)
    assert np.abs(statistics.mean(axis=0) - lags).max() < 4.0 * math.sqrt(2.0 * lags / PLANTS)
    for share in (0.5, 0.9):
        above = (statistics > stats.chi2.ppf(share, lags)).mean(axis=0)
        assert all(within(value, 1.0 - share, PLANTS) for value in above), above


def test_the_naive_cross_test_of_white_inputs_would_fail_here():
    """The same held-PRBS data with R_u taken as diagonal (white u): its tail is far too heavy."""
    rng = np.random.default_rng(11)
    residual = rng.standard_normal((SAMPLES, PLANTS))
    inputs = held_prbs(rng, SAMPLES, PLANTS, 1)
    monitor = monitor_run(residual, inputs)
    # the sums of e(t) [e(t) ... e(t - E), u(t - 1) ... u(t - U)] and of u(t - a) u(t - b)
    first = 1 + monitor._residual_lags
    weight = monitor._weight  # one per plant
    r = monitor._residual_sums[:, 0, first:first + monitor.lags] / weight[:, None]
    power = monitor._residual_sums[:, 0, 0] * monitor._input_sums[:, 0, 0, 0] / weight ** 2
    naive = monitor.effective_samples * (r * r).sum(axis=-1) / power
    threshold = stats.chi2.ppf(0.99, monitor.lags)
    assert (naive > threshold).mean() > 0.01 + 4.0 * math.sqrt(0.01 * 0.99 / PLANTS)
    assert within((monitor.statistics[:, 1] > threshold).mean(), 0.01, PLANTS)


def test_the_false_alarm_rate_at_a_moment_is_within_its_bound():
    rng = np.random.default_rng(12)
    residual = rng.standard_normal((SAMPLES, PLANTS))
    inputs = low_pass(rng.standard_normal((SAMPLES, PLANTS, 2)))
    monitor = monitor_run(residual, inputs, false_alarm=0.05)
    # the stated rate is an upper bound at any moment: in alarm only with Q above the low
    # threshold, which each of the T tests exceeds with 1 - (1 - alpha)^(1/T)
    alarm = monitor.alarm.mean()
    assert alarm <= 0.05 + 4.0 * math.sqrt(0.05 * 0.95 / PLANTS)
    low = monitor.thresholds[0]
    assert np.all(monitor.alarm <= (monitor.statistics > low).any(axis=1))


@pytest.mark.parametrize('colour', ['ar0.9', 'oversampled'])
def test_the_oe_cross_test_holds_its_null_with_coloured_residual_and_inputs(colour):
    rng = np.random.default_rng(13)
    white = rng.standard_normal((SAMPLES + 1000, PLANTS))
    if colour == 'ar0.9':
        residual = low_pass(white)[1000:]
    else:  # a second-order, oversampled noise: poles 0.9 +- 0.1j
        residual = signal.lfilter([1.0], [1.0, -1.8, 0.82], white, axis=0)[1000:]
    inputs = low_pass(rng.standard_normal((SAMPLES, PLANTS, 2)))
    monitor = monitor_run(residual, inputs, model='oe')
    statistics = monitor.statistics  # (K, 2): u1, u2 (no whiteness test for 'oe')
    assert statistics.shape == (PLANTS, 2)
    lags = monitor.lags
    assert np.abs(statistics.mean(axis=0) - lags).max() < 4.0 * math.sqrt(2.0 * lags / PLANTS)
    above = (statistics > stats.chi2.ppf(0.9, lags)).mean(axis=0)
    assert all(within(value, 0.1, PLANTS) for value in above), above
    # the 'arx' test of the same data: not white, every plant
    assert monitor_run(residual[:, :50], inputs[:, :50]).alarm.all()


# ------------------------------------------------------------------ power
def assert_power(alarms, monitor, noncentrality):
    """Check the share in alarm against Q ~ noncentral chi2(M, noncentrality) at the thresholds."""
    # the alarm goes on above the high threshold and stays on above the low one: its share
    # lies between the two powers, within 4 binomial standard errors (at most 0.5 each)
    low, high = monitor.thresholds
    power_high = stats.ncx2.sf(high, monitor.lags, noncentrality)
    power_low = stats.ncx2.sf(low, monitor.lags, noncentrality)
    error = 4.0 * math.sqrt(0.25 / alarms.size)
    assert power_high - error <= alarms.mean() <= power_low + error, (
        alarms.mean(), power_high, power_low)


def test_a_coloured_residual_is_found_with_the_power_of_its_noncentral_chi_square():
    rng = np.random.default_rng(21)
    rho = 0.15
    residual = low_pass(rng.standard_normal((SAMPLES + 500, PLANTS)), rho)[500:]
    inputs = low_pass(rng.standard_normal((SAMPLES, PLANTS, 1)))
    monitor = monitor_run(residual, inputs)
    # Q_0 ~ noncentral chi2(M, N sum_k rho^2k) at N = 999 effective samples
    noncentrality = monitor.effective_samples[0] * sum(
        rho ** (2 * k) for k in range(1, monitor.lags + 1))
    whiteness = np.array([any(reason.startswith('residual not white (lag ') for reason in plant)
                          for plant in monitor.reasons])
    assert_power(whiteness, monitor, noncentrality)
    assert whiteness.mean() > 0.5
    found = [reason for plant in monitor.reasons for reason in plant if 'not white' in reason]
    assert sum('(lag 1: 0.1' in reason for reason in found) > 0.9 * len(found)


def test_a_residual_correlated_with_an_input_at_lag_3_is_named():
    rng = np.random.default_rng(22)
    inputs = held_prbs(rng, SAMPLES, PLANTS, 2)
    correlation = 0.2
    residual = rng.standard_normal((SAMPLES, PLANTS))
    residual[3:] += correlation / math.sqrt(1.0 - correlation ** 2) * inputs[:-3, :, 1]
    monitor = monitor_run(residual, inputs)
    # r = c R_u e_3, so N r' (sigma^2 R_u)^-1 r = N c^2 R_u(0) / sigma^2 = N correlation^2
    found = np.array([any(reason.startswith('residual correlated with u2 at lag ')
                          for reason in plant) for plant in monitor.reasons])
    assert_power(found, monitor, monitor.effective_samples[0] * correlation ** 2)
    assert found.mean() > 0.5
    # the input is held for 8 samples, so lags 2 and 4 carry 7/8 of lag 3's correlation:
    # r_3 - r_2 has mean c / 8 = 0.025 and standard deviation sqrt(2 (1/8) / N) = 0.016, so
    # lag 3 beats each neighbour with probability 0.94 and both with about 0.88
    named = [reason for plant in monitor.reasons for reason in plant if 'with u2' in reason]
    prefix = 'residual correlated with u2 at lag '
    lag3 = [reason for reason in named if reason.startswith(prefix + '3 (')]
    near = sum(reason.startswith(tuple(f'{prefix}{k} ' for k in (2, 3, 4))) for reason in named)
    assert len(lag3) > 0.75 * len(named) and near > 0.95 * len(named)
    # the value is the correlation coefficient: one plant's has a standard deviation of
    # 1 / sqrt(N) = 0.032, the median of ~500 a tenth of that (0.02 leaves room for the
    # selection of the plants in alarm)
    values = [float(reason.split('(')[1].rstrip(')')) for reason in lag3]
    assert abs(np.median(values) - correlation) < 0.02
    # u1 is independent of the residual: its test is in alarm at most at the stated rate
    wrong = sum(any('with u1' in reason for reason in plant) for plant in monitor.reasons)
    assert wrong <= PLANTS * 0.01 + 4.0 * math.sqrt(PLANTS * 0.01)


def test_the_oe_cross_test_finds_the_lag_under_coloured_noise():
    rng = np.random.default_rng(23)
    inputs = low_pass(rng.standard_normal((SAMPLES, PLANTS, 1)))
    residual = low_pass(rng.standard_normal((SAMPLES + 1000, PLANTS)))[1000:]
    residual[3:] += 0.3 * inputs[:-3, :, 0]
    monitor = monitor_run(residual, inputs, model='oe')
    assert monitor.alarm.mean() > 0.95
    lag3 = sum(any(' at lag 3 ' in reason for reason in plant) for plant in monitor.reasons)
    assert lag3 > 0.8 * PLANTS


# ------------------------------------------------------------------ hysteresis and recovery
def test_the_alarm_clears_once_the_window_forgot_the_bad_data():
    rng = np.random.default_rng(31)
    switch, samples, plants = 3000, 6000, 200
    residual = np.concatenate((low_pass(rng.standard_normal((switch, plants)), 0.3),
                               rng.standard_normal((samples - switch, plants))))
    inputs = low_pass(rng.standard_normal((samples, plants, 1)))
    monitor = AdequacyMonitor(num_inputs=1, plants=plants, window=WINDOW)
    cleared = np.full(plants, -1)
    for t in range(samples):
        monitor.record(residual[t], inputs[t])
        if t + 1 == switch:
            assert monitor.alarm.all()
        if t >= switch:
            cleared[(cleared < 0) & ~monitor.alarm] = t - switch
    # the bad data's share of the moments falls as mu^s, of Q as mu^(2s): from N sum rho^2k
    # = 99 it is under the low threshold (26) after s = W ln(99 / 26) / 2 = 330 samples;
    # 3 W leaves room for the noise of Q. At the first check after the switch, all still on.
    assert (cleared >= 0).all() and cleared.max() < 3 * WINDOW
    assert cleared.min() >= BLOCK


def test_hysteresis_goes_on_above_the_high_threshold_and_off_below_the_low_one(monkeypatch):
    monitor = AdequacyMonitor(num_inputs=0, window=WINDOW)
    low, high = monitor.thresholds
    sequence = iter([0.5 * (low + high), high + 1, 0.5 * (low + high), low - 1,
                     0.5 * (low + high)])
    monkeypatch.setattr(monitor, '_statistics_now', lambda plants, sizes: (
        np.array([[next(sequence)]]), np.array([[1]]), np.array([[0.5]])))
    states = []
    rng = np.random.default_rng(0)
    for _ in range(5):
        while True:  # until a check
            checks = monitor.checks
            monitor.record(float(rng.standard_normal()), np.zeros(0))
            if monitor.checks > checks:
                break
        states.append(monitor.alarm)
    assert states == [False, True, True, False, False]
    assert monitor.reasons == ()
    assert monitor.checks == 5


def test_not_ready_before_the_window_holds_enough_samples():
    monitor = AdequacyMonitor(num_inputs=1, lags=10, window=WINDOW)
    rng = np.random.default_rng(1)
    for _ in range(190):
        monitor.record(float(rng.standard_normal()), rng.standard_normal(1))
    # N = 128 after one block, under 20 per lag
    assert not monitor.ready and monitor.checks == 0
    for _ in range(100):
        monitor.record(float(rng.standard_normal()), rng.standard_normal(1))
    assert monitor.ready and monitor.checks == 1


# ------------------------------------------------------------------ plants, state, settings
def test_one_plant_and_a_batch_agree():
    rng = np.random.default_rng(41)
    residual = rng.standard_normal((2000, 3))
    inputs = low_pass(rng.standard_normal((2000, 3, 2)))
    batch = monitor_run(residual, inputs)
    single = AdequacyMonitor(num_inputs=2, window=WINDOW)
    changed = AdequacyMonitor(num_inputs=2, window=WINDOW)
    for t in range(2000):
        single.record(float(residual[t, 1]), inputs[t, 1])
        changed.record(float(residual[t, 1]) + (0.5 if t == 1900 else 0.0), inputs[t, 1])
    # two summation orders of ~2000 products each: relative rounding below 1e-12 of Q,
    # whose conditioning (the Toeplitz solve, cond < 1e3) leaves it below 1e-9
    np.testing.assert_allclose(single.statistics, batch.statistics[1], rtol=1e-9)
    assert np.abs(changed.statistics - single.statistics).max() > 1e-6 * single.statistics.max()


def test_a_restored_monitor_continues_bit_for_bit():
    rng = np.random.default_rng(42)
    residual = low_pass(rng.standard_normal((3000, 2)), 0.2)
    inputs = rng.standard_normal((3000, 2, 1))
    first = AdequacyMonitor(num_inputs=1, plants=2, window=WINDOW)
    for t in range(1000 + BLOCK // 2):
        first.record(residual[t], inputs[t])
    second = AdequacyMonitor(num_inputs=1, plants=2, window=WINDOW)
    second.set_state(first.get_state())
    for t in range(1000 + BLOCK // 2, 3000):
        first.record(residual[t], inputs[t])
        second.record(residual[t], inputs[t])
    np.testing.assert_array_equal(first.statistics, second.statistics)
    assert first.reasons == second.reasons
    np.testing.assert_array_equal(first.checks, second.checks)


def test_the_default_window_follows_the_forgetting_memory():
    assert default_window(1.0) == MAX_WINDOW
    assert default_window(0.995) == pytest.approx(200.0)
    assert default_window(0.998) == pytest.approx(500.0)
    assert default_window(0.9) == MIN_WINDOW


def test_levinson_whitens_an_ar2():
    # R(k) of the AR(2) 1 - 1.8 q^-1 + 0.82 q^-2 (its Yule-Walker equations hold exactly)
    a = np.array([1.0, -1.8, 0.82])
    r0 = 1.0
    r1 = -a[1] / (1 + a[2]) * r0
    r2 = -a[1] * r1 - a[2] * r0
    np.testing.assert_allclose(levinson(np.array([r0, r1, r2])), a, rtol=1e-12)
    assert levinson(np.array([1.0, 1.0, 1.0])) is None


@pytest.mark.parametrize('settings, message', [
    ({'model': 'bj'}, 'model must be one of'),
    ({'num_inputs': -1}, 'num_inputs must be an integer >= 0'),
    ({'lags': 0}, 'lags must be an integer >= 1'),
    ({'window': 50.0}, 'window must be at least 100 samples'),
    ({'false_alarm': 0.5}, r'false_alarm must be in \(0, 0.5\)'),
    ({'forgetting_factor': 1.5}, r'forgetting_factor must be in \(0, 1\]'),
    ({'plants': 0}, 'plants must be None or an integer >= 1'),
    ({'input_names': ['a', 'b', 'c']}, 'input_names must have num_inputs = 2 names'),
])
def test_settings_are_validated(settings, message):
    with pytest.raises(ValueError, match=message):
        AdequacyMonitor(**{'num_inputs': 2, **settings})


def test_repr_is_one_line():
    text = repr(AdequacyMonitor(num_inputs=2, model='oe'))
    assert '\n' not in text and "model='oe'" in text and 'window=1000' in text


def test_many_plants_statistics_are_each_plants_alone_bit_for_bit():
    # the batched estimators test K plants in one call: the quadratic forms (one stacked
    # eigendecomposition) and the effective sizes are each plant's of a call of its own
    rng = np.random.default_rng(5)
    count, lags = 9, 6
    factors = rng.standard_normal((count, lags, lags + 2))
    variance = factors @ np.swapaxes(factors, -1, -2) / (lags + 2)
    variance[2, 0, :] = variance[2, :, 0] = 1e-12 * variance[2, 0, 0]  # one direction dropped
    variance[4, 1, 1] = np.nan  # one plant without a test
    extra = 0.01 * np.einsum('kia,kja->kij', *(2 * [rng.standard_normal((count, lags, 2))]))
    r = 0.1 * rng.standard_normal((count, lags))
    sizes = rng.uniform(50.0, 2000.0, count)
    for more in (None, extra):
        statistics, standardised = quadratic_forms(variance, r, sizes, more)
        for k in range(count):
            alone = quadratic_forms(variance[k:k + 1], r[k:k + 1], sizes[k:k + 1],
                                    None if more is None else more[k:k + 1])
            assert alone[0][0] == statistics[k]
            np.testing.assert_array_equal(alone[1][0], standardised[k])
        assert statistics[4] == 0.0 and np.isfinite(statistics).all()
    weight, squared = rng.uniform(0.0, 900.0, 500), rng.uniform(0.0, 900.0, 500)
    squared[::7] = 0.0
    sizes = effective_size(weight, squared)
    assert [effective_size(w, q) for w, q in zip(weight.tolist(), squared.tolist())] == (
        sizes.tolist())
