"""
An instability is named before the residual tests' reasons.

On a record of 150 samples (issue 34's heated plate had 148) bcrls's compensation diverged and
was reset, and its reasons began with 'residual tests not ready', or had only that.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import signal

from bcid_ros.estimators import make_estimator


@pytest.mark.parametrize('seed', [0, 2])
def test_bcrls_names_a_diverged_compensation_before_the_tests(seed):
    # a 150-sample staircase record (issue 34's heated plate was 148): the compensation
    # diverged and was reset, and 'residual tests not ready' came first (or alone)
    rng = np.random.default_rng(seed)
    u = np.repeat(rng.uniform(0.0, 1.0, 13), 100)[:1200]
    y = signal.lfilter([0.0, 0.02, 0.01, -0.005], np.poly([0.97, 0.9, 0.6]), u)
    y += 0.02 * signal.lfilter([1.0], [1.0, -0.95], rng.standard_normal(1200))
    estimator = make_estimator('bcrls', order=3, detrend='mean')
    for k in range(150):
        estimator.update(y[k], [u[k]])
    reasons = estimator.validity_reasons
    assert estimator.flags.get('compensation_reset', 0) >= 1
    tests = [k for k, reason in enumerate(reasons) if reason.startswith('residual')]
    named = ('residual', 'simulated')
    others = [k for k, reason in enumerate(reasons) if not reason.startswith(named)]
    assert others and tests and max(others) < min(tests), reasons
