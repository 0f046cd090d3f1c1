"""A live forgetting_factor reaches every part whose memory is the estimator's (HAC, window)."""

import numpy as np
import pytest
from registry_cases import BATCHED_NAMES, data, make, NAMES

from bcid_ros.estimators import make_batched_estimator
from bcid_ros.estimators.adequacy import AdequacyMonitor, default_window


def parts(est):
    return getattr(est, '_monitor', None), getattr(est, '_hac', None)


def forgetting_names():
    """Yield the estimators that forget and keep residual tests or a HAC covariance."""
    for name in NAMES:
        try:
            est = make(name, forgetting_factor=0.99)
        except ValueError:  # cl_bcls with a window forgets through the window only
            continue
        if any(part is not None for part in parts(est)):
            yield name


@pytest.mark.parametrize('name', list(forgetting_names()))
def test_a_live_forgetting_factor_reaches_the_residual_tests_and_the_hac(name):
    y, u = data(name)
    est = make(name)
    half = len(y) // 2
    est.run(y[:half], u[:half])
    est.forgetting_factor = 0.99
    monitor, hac = parts(est)
    if monitor is not None:
        assert monitor.window == default_window(0.99) < default_window(1.0)
    if hac is not None:
        assert hac.forgetting_factor == 0.99
        assert hac._products.decay == 0.99 ** 2
    # a state round trip keeps the new factor in every part
    restored = make(name)
    restored.set_state(est.get_state())
    assert restored.forgetting_factor == 0.99
    for mine, theirs in zip(parts(est), parts(restored)):
        if mine is not None:
            assert theirs.forgetting_factor == 0.99 if hasattr(mine, 'dimension') \
                else theirs.window == mine.window
    # changed before the first sample: the very run of one built with it (one code path)
    changed, built = make(name), make(name, forgetting_factor=0.99)
    changed.forgetting_factor = 0.99
    first, second = changed.run(y, u), built.run(y, u)
    np.testing.assert_array_equal(first.theta, second.theta)
    np.testing.assert_array_equal(first.valid, second.valid)
    assert changed.validity_reasons == built.validity_reasons
    if hac is not None:
        np.testing.assert_array_equal(changed.parameter_std, built.parameter_std)


@pytest.mark.parametrize('name', BATCHED_NAMES)
def test_the_batched_forms_follow_too(name):
    batched = make_batched_estimator(name, 3, order=2)
    batched.forgetting_factor = 0.995
    assert batched._monitor.window == default_window(0.995)
    assert batched._hac is None or batched._hac.forgetting_factor == 0.995


def test_a_window_given_to_the_monitor_stays():
    monitor = AdequacyMonitor(num_inputs=1, window=500.0, forgetting_factor=1.0)
    monitor.follow_forgetting_factor(0.9)
    assert monitor.window == 500.0
    following = AdequacyMonitor(num_inputs=1, forgetting_factor=1.0)
    lam = 1.0 - 2.0 ** -9  # a memory of 512 samples, exactly
    following.follow_forgetting_factor(lam)
    assert following.window == default_window(lam) == 512.0
    assert following.check_period == AdequacyMonitor(num_inputs=1, window=512.0).check_period
    assert following.check_period != AdequacyMonitor(num_inputs=1).check_period
