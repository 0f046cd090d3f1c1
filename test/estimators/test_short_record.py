"""
A short record is judged on what it has (issue 34: 148 samples never became valid or not).

The residual tests wait for a window of 20 samples a lag (200 for M = 10); before that, once
the samples come to SHORT_MINIMUM, they run with N // 20 lags (AdequacyMonitor.short_reasons).
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import signal

from bcid_ros.estimators import make_estimator
from bcid_ros.estimators.adequacy import SHORT_MINIMUM

#: Samples of each record (issue 34's heated plate had 148).
SAMPLES = 150
#: Records of the false-alarm count.
RUNS = 40
#: The residual tests' stated false-alarm rate.
FALSE_ALARM = 0.01


def record(seed, equation_noise, poles=(0.8, 0.5), count=SAMPLES):
    """Return y, u of a second-order plant (or ``poles``) under white input."""
    rng = np.random.default_rng(seed)
    u = rng.standard_normal(count)
    a = np.poly(poles)
    noise = 0.1 * rng.standard_normal(count)
    y = signal.lfilter([0.0, 1.0, 0.5], a, u)
    return y + (signal.lfilter([1.0], a, noise) if equation_noise else noise), u


@pytest.mark.parametrize('name', ['rls', 'rpem'])
def test_a_short_record_of_the_model_is_valid(name):
    # rls on ARX data, rpem on output-error data: not valid no more often than the tests'
    # rate allows (3 binomial standard deviations over the runs)
    invalid = 0
    for seed in range(RUNS):
        y, u = record(seed, equation_noise=name == 'rls')
        estimator = make_estimator(name, order=2)
        estimator.run(y, u)
        assert not any('not ready' in reason for reason in estimator.validity_reasons)
        invalid += not estimator.valid
    assert invalid <= RUNS * FALSE_ALARM + 3.0 * np.sqrt(RUNS * FALSE_ALARM * (1 - FALSE_ALARM))


@pytest.mark.parametrize('name', ['rls', 'bcrls', 'rpem'])
@pytest.mark.parametrize('seed', range(3))
def test_a_short_record_of_another_plant_gets_a_named_reason(name, seed):
    # order 1 for a third-order plant with a resonance
    y, u = record(seed, equation_noise=name == 'rls', poles=(0.9, 0.6 + 0.6j, 0.6 - 0.6j))
    estimator = make_estimator(name, order=1)
    estimator.run(y, u)
    assert not estimator.valid
    assert any(reason.startswith('residual') and 'not ready' not in reason
               for reason in estimator.validity_reasons), estimator.validity_reasons


def test_bcrls_gives_a_verdict_on_a_short_record():
    # bcrls's own output error carries its settling estimates (the tracking issue's part):
    # a verdict, not 'not ready'
    y, u = record(0, equation_noise=False)
    estimator = make_estimator('bcrls', order=2)
    estimator.run(y, u)
    assert not any('not ready' in reason for reason in estimator.validity_reasons)


def test_fewer_samples_than_the_minimum_are_not_judged():
    y, u = record(0, equation_noise=True, count=SHORT_MINIMUM + 20)
    estimator = make_estimator('rls', order=2)
    estimator.run(y, u)
    assert any('not ready' in reason for reason in estimator.validity_reasons)
