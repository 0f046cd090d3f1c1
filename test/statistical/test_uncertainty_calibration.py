"""
The calibration of the estimators' parameter covariance, over Monte Carlo runs.

Over the runs, the share of true parameters inside the estimate +- 2 std must
be close to the 95.4 % of a Gaussian. The N = 1000 cases run in the default
suite, N = 10000 is ``slow``; docs/estimators.md ("Uncertainty") has the full
table. The formulas and the bookkeeping are test/estimators/test_uncertainty.py.
"""

import math

import numpy as np
import pytest
from uncertainty_cases import (arx_data, ding_data, IKEDA, ikeda, IKENOUE_COLORED,
                               IKENOUE_WHITE, ikenoue, ikenoue_white, NOMINAL, run, run_single,
                               TRUTH)

from bcid_ros.simulation import make_scenario


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


def single_coverage(name, data, count, runs, seed, settings):
    """Return the per-run, per-parameter indicator of |theta_hat - theta| <= 2 std (None: out)."""
    scenario = {ikenoue: 'ikenoue_colored', ikenoue_white: 'ikenoue_white_input',
                ikeda: 'ikeda_closed_loop'}[data]
    truth = make_scenario(scenario).truth().parameters
    inside = np.zeros((runs, truth.shape[0]), dtype=bool)
    for r in range(runs):
        y, u = data(count, seed + r)
        estimator = run_single(name, y, u, **settings)
        std = estimator.parameter_std
        if std is not None:
            inside[r] = np.abs(estimator.theta - truth) <= 2.0 * std
    return inside


REDUCED_RUNS = 60


@pytest.mark.parametrize('name, data, settings', [
    ('bciv', ikenoue, IKENOUE_COLORED), ('cl_bcls', ikeda, IKEDA)], ids=['bciv', 'cl_bcls'])
def test_block_covariance_calibrated_at_reduced_size(name, data, settings):
    inside = single_coverage(name, data, 1000, REDUCED_RUNS, 60_000, settings)
    # a share over R runs has the binomial standard error sqrt(q (1 - q) / R), 2.7 % at 60
    # runs (the parameters of one run counted as one draw); 4 of them bound a chance miss
    bound = 4.0 * math.sqrt(NOMINAL * (1.0 - NOMINAL) / REDUCED_RUNS)
    assert abs(inside.mean() - NOMINAL) <= bound, inside.mean(axis=0)
    assert np.all(np.abs(inside.mean(axis=0) - NOMINAL) <= bound), inside.mean(axis=0)


#: Runs of the slow checks at N = 10000 (bciv takes about 1 s a run).
SLOW_RUNS = 100
#: The pooled shares at N = 10000 that docs/estimators.md ("Measured coverage") documents.
DOCUMENTED_10000 = {'bciv-colored': 0.909, 'bciv-white': 0.952, 'cl_bcls': 0.930}


@pytest.mark.slow
@pytest.mark.parametrize('case, name, data, settings', [
    ('bciv-colored', 'bciv', ikenoue, IKENOUE_COLORED),
    ('bciv-white', 'bciv', ikenoue_white, IKENOUE_WHITE),
    ('cl_bcls', 'cl_bcls', ikeda, IKEDA)], ids=['bciv-colored', 'bciv-white', 'cl_bcls'])
def test_block_covariance_coverage_at_10000_samples_as_documented(case, name, data, settings):
    inside = single_coverage(name, data, 10_000, SLOW_RUNS, 70_000, settings)
    # the documented pooled share, within 4 binomial standard errors of 100 runs (2.1 % each);
    # a std 1.5 times too small moves the share under 82 %, 1.5 times too large over 99 %
    bound = 4.0 * math.sqrt(NOMINAL * (1.0 - NOMINAL) / SLOW_RUNS)
    assert abs(inside.mean() - DOCUMENTED_10000[case]) <= bound, inside.mean(axis=0)
    assert 0.88 <= inside.mean() <= 0.98
