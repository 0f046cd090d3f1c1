"""
rpem's change warning: not valid while the change detector's CUSUM is past half its threshold.

Until a detection the old model is valid; the warning (``CHANGE_WARNING`` w of the threshold
h) makes ``valid`` false part of the way. Its cost where nothing changes is derived from the
detector's design: S(t) is the largest sum of its last k increments, whose exponentials,
taken backwards from t, are a supermartingale from 1 under the null (the log-likelihood-ratio
increments have E exp = 1, less with the clip), so by Ville's inequality S >= w h on at most
exp(-w h) = FALSE_ALARM^w of the samples (docs/tracking.md).
"""

import math

import numpy as np
import pytest
from scipy import signal
from test_tracking import changing_plant, run

from bcid_ros.estimators import make_estimator
from bcid_ros.estimators.change_detection import ChangeDetector, FALSE_ALARM, WARMUP
from bcid_ros.estimators.rpem.online import CHANGE_WARNING

#: Plants of the rate test, and its samples after the detector's warm-up.
PLANTS, SAMPLES = 400, 5000
#: A change half the size of test_tracking.py's (its CUSUM needs tens of samples).
SMALLER = ([1.0, -1.45, 0.68], [0.0, 1.1, 0.55])


@pytest.mark.parametrize('pole', [0.0, 0.9])
def test_the_share_of_samples_past_the_warning_is_within_its_bound(pole):
    # white and AR(1) errors of no change through the detector's plant axis; the share of
    # each plant's samples with S >= w h, averaged over the plants, against exp(-w h) plus
    # three standard errors of that mean (the plants are independent; the samples of one
    # are not, so the spread is the plants')
    rng = np.random.default_rng(11 + int(10 * pole))
    errors = signal.lfilter([1.0], [1.0, -pole],
                            rng.standard_normal((WARMUP + SAMPLES, PLANTS)), axis=0)
    detector = ChangeDetector(PLANTS)
    level = CHANGE_WARNING * detector.threshold
    past = np.zeros(PLANTS)
    for t, row in enumerate(errors):
        detector.record(row)
        if t >= WARMUP:
            past += detector.state.statistic >= level
    share = past / SAMPLES
    bound = math.exp(-level)
    assert bound == pytest.approx(FALSE_ALARM ** CHANGE_WARNING)
    assert share.mean() <= bound + 3.0 * share.std(ddof=1) / math.sqrt(PLANTS)
    # one plant reads the same statistic without writing its numbers back
    single = ChangeDetector()
    for value in errors[:WARMUP + 200, 0]:
        single.record(value)
        assert single.statistic_of() == single.state.statistic[0]


@pytest.mark.parametrize('seed', [0, 1, 2, 3])
def test_rpem_is_not_valid_once_a_change_is_suspected_before_its_detection(seed):
    # valid was true up to the detection sample; now false from the sample the CUSUM passes
    # w h, some samples before (about w of the delay: the evidence grows linearly)
    y, u, _ = changing_plant(seed, after=SMALLER)
    estimator = make_estimator('rpem', order=2)
    valid, reasons = run(estimator, y, u)
    flagged = [t for t, why in enumerate(reasons) if why and why[0].startswith('plant changed')]
    assert estimator.flags['plant_change'] == 1
    first = 3000 + int(np.argmin(valid[3000:]))
    assert valid[2999] and first < flagged[0]
    assert reasons[first][0].startswith('change suspected'), reasons[first]
