"""
rpem has a std from its first fit on, and is never valid without one (rpem/store.py, _recorded).

A fit of fewer samples than a block of the HAC (lagged.BLOCK, 256) once left the HAC no
estimate, and the fitted state's share unknown: no std until the recursion's first block after
a fit of a block or more (312-389 samples into the tracking family's runs), while the model's
checks made rpem valid from its first fit (120-160 samples) on. Over the first 600 samples of
seeds 0-10 of that family, 42 runs with the defaults were valid more than 30 % off, up to 114 %
(docs/tracking_log.md, session 19). The fit's scores now complete their block.
"""

import numpy as np
import pytest

from benchmarks.tracking import CONFIGS, TrackingCase
from bcid_ros.estimators import make_estimator
from bcid_ros.estimators.lagged import BLOCK
from test_short_record import record

#: Tracking plants valid without a std on the code before: (0, 5) at 159 samples 84 % off,
#: (0, 2) at 141 92 % off, (1, 4) at 143 63 % off, (0, 1) at 119 (accurate).
PLANTS = [(0, 5), (0, 2), (1, 4), (0, 1)]


def test_a_record_shorter_than_a_block_has_a_std():
    y, u = record(0, equation_noise=False)
    assert y.shape[0] < BLOCK
    estimator = make_estimator('rpem', order=2)
    estimator.run(y, u)
    covariance = estimator.parameter_covariance
    assert covariance is not None
    assert np.isfinite(covariance).all() and (np.diagonal(covariance) > 0.0).all()


@pytest.mark.parametrize('config', ['rpem', 'rpem_0.999'])
@pytest.mark.parametrize('plant', PLANTS)
def test_rpem_is_never_valid_without_a_std(plant, config):
    case = TrackingCase(plant)
    name, settings = CONFIGS[config]
    estimator = make_estimator(name, order=case.order, num_inputs=case.num_inputs, **settings)
    for t in range(2 * BLOCK):
        valid = estimator.update(float(case.y[t]), case.u[t])
        assert not valid or estimator.parameter_covariance is not None, t
    covariance = estimator.parameter_covariance
    assert covariance is not None and np.isfinite(covariance).all()
