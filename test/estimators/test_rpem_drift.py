"""
rpem through a drift with its defaults (lambda = 1, change detection on): an open goal.

Issue 31 asks every drift to be tracked; docs/tracking.md ("Limits and what is left")
says why rpem's defaults miss some: a change found part of the way through a drift
leaves the rest of the drift in every later fit (a fit spans all samples since the last
change). The test below is the goal, marked as not met (strict: it fails once it passes).
"""

import numpy as np
import pytest

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


@pytest.mark.xfail(strict=True, reason='issue 31: the fits after a change found part of the '
                   'way through a drift keep the rest of it (docs/tracking.md)')
@pytest.mark.parametrize('seed', [0, 2, 3])
def test_a_drift_is_tracked_to_within_the_estimates_own_uncertainty_by_the_end(seed):
    # 4000 samples after the drift's end: the final error 4.5-5.8 times the estimate's std
    # on these seeds (2026-11-27), where the squared norm of the error has the expectation
    # |std|^2 for an estimate of the final plant alone
    y, u, final = drifting_plant(seed)
    estimator = make_estimator('rpem', order=1)
    for t in range(y.shape[0]):
        estimator.update(y[t], u[t])
    assert np.linalg.norm(estimator.theta - final) < 3.0 * np.linalg.norm(
        estimator.parameter_std)
