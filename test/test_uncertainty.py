"""
The parameter covariance of the estimators: its formulas, its bookkeeping and its calibration.

Calibration is the test that matters: over Monte Carlo runs, the share of
true parameters inside the estimate +- 2 std must be close to the 95.4 % of
a Gaussian. The N = 1000 cases run in the default suite, N = 10000 is
``slow``; docs/estimators.md ("Uncertainty") has the full table.
"""

import math

import numpy as np
import pytest
from scipy.signal import lfilter

from bcid_ros.estimators import make_estimator
from bcid_ros.estimators.base import standard_deviations, weighted_square_ratio
from bcid_ros.estimators.rls import ls_batch
from bcid_ros.simulation import make_scenario

#: Ding's plant, used with ARX noise for rls and with output-error noise for bcrls.
ALPHA = [1.0, -0.84, 0.16]
B1 = [0.0, 0.12, 0.324]
B2 = [0.0, 0.25, 0.186]
TRUTH = np.array([ALPHA[1], ALPHA[2], B1[1], B1[2], B2[1], B2[2]])
#: P(|z| <= 2) for a standard normal z.
NOMINAL = math.erf(2.0 / math.sqrt(2.0))


def arx_data(rng, count, noise_std=0.1):
    """Return (y, u) of Ding's plant with white equation error: A y = B1 u1 + B2 u2 + e."""
    u = rng.standard_normal((count, 2))
    e = noise_std * rng.standard_normal(count)
    y = lfilter(B1, ALPHA, u[:, 0]) + lfilter(B2, ALPHA, u[:, 1]) + lfilter([1.0], ALPHA, e)
    return y, u


def ding_data(rng, count):
    """Return (y, u) of Ding's output-error scenario."""
    return make_scenario('ding_miso').stream(rng).take(count)


def run(name, y, u, **settings):
    """Return the estimator ``name`` (n = 2, r = 2) after the samples."""
    estimator = make_estimator(name, order=2, num_inputs=2, **settings)
    update = estimator.update
    for k in range(y.shape[0]):
        update(y[k], u[k])
    return estimator


def coverage(name, data, count, runs, seed, **settings):
    """Return the per-run, per-parameter indicator of |theta_hat - theta| <= 2 std."""
    inside = np.empty((runs, TRUTH.shape[0]), dtype=bool)
    for r in range(runs):
        y, u = data(np.random.default_rng(seed + r), count)
        estimator = run(name, y, u, **settings)
        inside[r] = np.abs(estimator.theta - TRUTH) <= 2.0 * estimator.parameter_std
    return inside


def check_calibrated(inside):
    """Assert the pooled share in [90 %, 98 %] and each parameter's within 4 MC std errors."""
    runs = inside.shape[0]
    pooled = inside.mean()
    per_parameter = inside.mean(axis=0)
    assert 0.90 <= pooled <= 0.98, f'pooled coverage {pooled:.3f}'
    # one parameter's share over `runs` runs has the binomial standard error
    # sqrt(q (1 - q) / runs), 1.5 % at 200 runs; 4 of them bound a chance miss
    bound = 4.0 * math.sqrt(NOMINAL * (1.0 - NOMINAL) / runs)
    assert np.all(np.abs(per_parameter - NOMINAL) <= bound), per_parameter


# ------------------------------------------------------------------ formulas
def test_rls_covariance_is_residual_variance_times_p():
    y, u = arx_data(np.random.default_rng(1), 800)
    estimator = run('rls', y, u)
    theta, p, loss, _ = ls_batch(y, u, order=2, num_inputs=2,
                                 initial_covariance=estimator.initial_covariance_diagonal)
    updates = y.shape[0] - 2
    expected = loss / (updates - 6) * p
    np.testing.assert_allclose(estimator.parameter_covariance, expected, rtol=1e-7)
    np.testing.assert_allclose(estimator.parameter_std, np.sqrt(np.diag(expected)), rtol=1e-7)


def test_rls_covariance_with_forgetting_uses_the_effective_sample_size():
    lam = 0.99
    y, u = arx_data(np.random.default_rng(2), 1500)
    estimator = run('rls', y, u, forgetting_factor=lam)
    tau = estimator.weighted_count
    updates = y.shape[0] - 2
    weights = lam ** np.arange(updates)
    # the closed form equals sum(w^2) / sum(w) over the weights of the updates
    assert weighted_square_ratio(tau, lam) == pytest.approx(
        (weights ** 2).sum() / weights.sum(), rel=1e-9)
    ratio = weighted_square_ratio(tau, lam)
    expected = estimator.loss / (tau - 6 * ratio) * ratio * estimator.covariance
    np.testing.assert_allclose(estimator.parameter_covariance, expected, rtol=1e-12)
    assert weighted_square_ratio(10.0, 1.0) == 1.0
    assert weighted_square_ratio(1e9, 0.5) == pytest.approx(1.0 / 1.5)


def test_not_ready_and_uncalibrated_estimators_have_no_covariance():
    for name in ('rls', 'bcrls'):
        estimator = make_estimator(name, order=2, num_inputs=2)
        assert estimator.parameter_covariance is None and estimator.parameter_std is None
    assert standard_deviations(None) is None
    y, u = make_scenario('ikenoue_colored').simulate(600, 0)
    bciv = make_estimator('bciv', order=2, iv_lag=4, idle_samples=100)
    bciv.run(y, u)
    assert bciv.ready and bciv.parameter_covariance is None and bciv.parameter_std is None
    # cl_bcls has none either (docs/estimators.md, "Uncertainty"): the base's None
    cl_bcls = make_estimator('cl_bcls', order=2, controller_numerator=[0.2289],
                             controller_denominator=[1.0, -0.09004])
    assert cl_bcls.parameter_covariance is None and cl_bcls.parameter_std is None


def test_bcrls_lagged_moments_equal_the_batch_sums_and_survive_a_state_round_trip():
    y, u = ding_data(np.random.default_rng(3), 1000)
    estimator = run('bcrls', y, u)
    sums, weight = estimator._new_moments(estimator._pending_moments())
    phi = np.column_stack([-y[1:-1], -y[:-2], u[1:-1, 0], u[:-2, 0], u[1:-1, 1], u[:-2, 1]])
    z = np.column_stack([phi, y[2:]])
    assert weight == z.shape[0]
    for k in range(3):
        np.testing.assert_allclose(sums[k], z[k:].T @ z[:z.shape[0] - k], rtol=1e-12,
                                   atol=1e-10)
    # a snapshot in the middle of a block continues to the same covariance, bit for bit
    first = run('bcrls', y[:537], u[:537])
    second = make_estimator('bcrls', order=2, num_inputs=2)
    second.set_state(first.get_state())
    for k in range(537, 1000):
        first.update(y[k], u[k])
        second.update(y[k], u[k])
    np.testing.assert_array_equal(first.parameter_covariance, second.parameter_covariance)
    np.testing.assert_array_equal(first.parameter_covariance, estimator.parameter_covariance)


def test_bcrls_covariance_is_unit_free():
    y, u = ding_data(np.random.default_rng(4), 1500)
    base = run('bcrls', y, u)
    scaled = run('bcrls', y * 1e-3, u * 1e4)
    # theta: a -> a, b -> b s_y / s_u; so std of b scales by 1e-7
    factor = np.array([1.0, 1.0, 1e-7, 1e-7, 1e-7, 1e-7])
    np.testing.assert_allclose(scaled.parameter_std, base.parameter_std * factor, rtol=1e-6)
    covariance = base.parameter_covariance
    np.testing.assert_allclose(covariance, covariance.T, rtol=0, atol=0)
    assert np.linalg.eigvalsh(covariance).min() > 0


# --------------------------------------------------------------- calibration
RUNS = 200


def test_rls_calibrated_on_an_arx_plant():
    check_calibrated(coverage('rls', arx_data, 1000, RUNS, seed=10_000))


def test_bcrls_calibrated_on_ding():
    check_calibrated(coverage('bcrls', ding_data, 1000, RUNS, seed=20_000))


@pytest.mark.slow
@pytest.mark.parametrize('name, data', [('rls', arx_data), ('bcrls', ding_data)],
                         ids=['rls-arx', 'bcrls-ding'])
def test_calibrated_at_10000_samples(name, data):
    check_calibrated(coverage(name, data, 10_000, RUNS, seed=30_000))


@pytest.mark.slow
@pytest.mark.parametrize('name, data', [('rls', arx_data), ('bcrls', ding_data)],
                         ids=['rls-arx', 'bcrls-ding'])
def test_calibrated_with_forgetting(name, data):
    check_calibrated(coverage(name, data, 3000, RUNS, seed=40_000, forgetting_factor=0.995))
