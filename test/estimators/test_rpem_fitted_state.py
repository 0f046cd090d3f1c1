"""
rpem's std after its batch fits counts the initial state each fit chose (rpem/uncertainty.py).

The fits hand the recursion the information of their samples with each segment's initial
state held; on a slow plant the held state's free response claims information about the
poles that the fitted state absorbs, and the std was up to 100 times below the batch fit's.
"""

import warnings

import numpy as np
import pytest
from scipy import signal

from bcid_ros.analysis.pem import fit_oe, Structure
from bcid_ros.estimators import make_estimator
from bcid_ros.estimators.hac import HacCovariance
from bcid_ros.estimators.rpem.uncertainty import fitted_state_excess, normalised_covariance


@pytest.mark.parametrize('seed', range(4))
def test_rpem_std_on_a_slow_plant_agrees_with_the_batch_fit(seed):
    """
    Poles 0.98, 0.97 and 0.83, white input and noise at 20 dB, 1200 samples (eight fits).

    rpem's std of each parameter against the batch OE fit's of the same samples (its
    initial state fitted): both estimate one asymptotic covariance, each within some
    10-25 % (the HAC's and the batch fit's sampling error at ~1000 samples), so a factor of
    2 either way is gross. With the state held the b's std was 0.01-0.5 times the batch
    fit's (errors up to 23 std); with the excess 0.94-1.24.
    """
    rng = np.random.default_rng(seed)
    a = np.real(np.poly([0.98, 0.97, 0.83]))
    b = np.array([1.0, -0.5, 0.2]) * 1e-3
    u = rng.standard_normal(1200)
    x = signal.lfilter(np.r_[0.0, b], a, u)
    y = x + 0.1 * x.std() * rng.standard_normal(1200)
    estimator = make_estimator('rpem', order=3)
    for t in range(1200):
        estimator.update(y[t], u[t])
    std = np.sqrt(np.diag(estimator.parameter_covariance))
    with warnings.catch_warnings():
        warnings.simplefilter('ignore')
        batch = fit_oe(y - y.mean(), u - u.mean(), Structure(3), offset=True)
    ratio = std / batch.std[:6]
    assert np.all((ratio > 0.5) & (ratio < 2.0)), ratio


def test_the_excess_is_zero_where_the_state_carries_no_information():
    """Profiled information equal to the held one: no excess (and a PSD E otherwise)."""
    rng = np.random.default_rng(3)
    scores = rng.standard_normal((2000, 3))
    information = scores.T @ scores
    held_information = np.zeros((4, 4))
    held_information[:3, :3] = information
    held_information[3, 3] = 2000.0
    hac = HacCovariance(dimension=4, forgetting_factor=1.0)
    hac.record_all(np.column_stack((scores, rng.standard_normal(2000))))
    held = normalised_covariance(hac, np.linalg.inv(held_information + 1e-6 * np.eye(4)),
                                 2000.0, 1.0)
    same = fitted_state_excess(held, held_information, information, scores, 1e-6, 2000.0,
                               1.0)
    # the two HAC estimates of one long-run covariance differ by their sampling error only
    assert np.abs(same).max() <= 0.1 * np.abs(held_information @ held @ held_information).max()
    less = fitted_state_excess(held, held_information, 0.25 * information, 0.5 * scores,
                               1e-6, 2000.0, 1.0)
    assert np.linalg.eigvalsh(less).min() >= -1e-9 * np.abs(less).max()
    assert np.abs(less).max() > 0.0
