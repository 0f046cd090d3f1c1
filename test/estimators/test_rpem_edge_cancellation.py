"""
rpem's fits and a mode on the stability region's edge that a zero cancels (rpem/stability.py).

With each segment's initial state free (the fits after a plant change), a mode on the edge
whose zero cancels it in the input's response can lower a fit's loss: its initial state is a
slow exponential that fits the slow part of the disturbance. Tracking plant (8, 22) (a pole
0.975 -> 0.985 over 2490 samples, n = 3, multisine, coloured noise) took such a fit part way
through its drift and stayed 180 % off to the end (docs/tracking_log.md, session 19).
"""

import numpy as np
import pytest

from benchmarks.tracking import delta, TrackingCase
from bcid_ros.estimators import make_estimator
from bcid_ros.estimators.rpem.fit import BatchFit
from bcid_ros.estimators.rpem.stability import (CANCELLING_DISTANCE, edge_mode_cancelled,
                                                EDGE_MARGIN)

EDGE = 1.0 - EDGE_MARGIN / 2.0  # a root on the edge
#: The end rpem took at sample 6887 of tracking plant (8, 22) before the rule, in the
#: plant's units: poles 0.999, 0.999, 0.973, zeros 0.9986 +- 0.014j.
CANCELLED_END = np.array([-2.9734, 2.9471, -0.9737, 0.1101, -0.2197, 0.1096])


def _tail(roots):
    return np.real(np.poly(roots))[1:]


@pytest.mark.parametrize('poles, zeros, cancelled', [
    ([EDGE, 0.6], [[EDGE - 0.5 * CANCELLING_DISTANCE]], True),
    # an integrator's pole: no zero near it
    ([EDGE, 0.6], [[0.3]], False),
    ([EDGE, 0.6], [[EDGE - 2.0 * CANCELLING_DISTANCE]], False),
    # cancelled inside the region: not the initial state's free mode
    ([0.95, 0.6], [[0.95]], False),
    # one input of two still sees the mode
    ([EDGE, 0.6], [[EDGE], [0.2]], False),
    ([EDGE, 0.6], [[EDGE], [EDGE + 0.001]], True),
    # an input with no response at all does not see it either
    ([EDGE, 0.6], [[EDGE], None], True),
])
def test_a_mode_is_cancelled_only_on_the_edge_and_in_every_input(poles, zeros, cancelled):
    numerators = [np.zeros(3) if z is None else np.concatenate(([0.5], 0.5 * _tail(z)))
                  for z in zeros]
    assert edge_mode_cancelled(_tail(poles), numerators) is cancelled


def test_a_fit_takes_the_end_whose_edge_mode_is_not_cancelled_and_keeps_the_other():
    """
    The fit of (8, 22)'s samples 5135-6887 (mid-drift), started from the cancelled end.

    The cancelled end has the lower loss (the alternative's loss ratio is below 1): the
    loss alone took it, 180 % off. The fit now takes the other end, and the cancelled one
    stays its alternative (the covariance counts it where the data do not tell them apart).
    """
    case = TrackingCase((8, 22))
    y, u = case.y[5135:6887], case.u[5135:6887]
    y_scale, u_scale = y.std(), u.std(axis=0)
    start = CANCELLED_END.copy()
    start[3:] *= u_scale[0] / y_scale  # the fit's normalised units
    segment = ((y - y.mean()) / y_scale, (u - u.mean(axis=0)) / u_scale, np.ones(y.shape[0]))
    prior = 1.0 / make_estimator('rpem', order=3, num_inputs=1).initial_covariance
    fit = BatchFit(3, 1, False, (0,), False, True)
    result = fit.fit([segment], [start], prior, after_change=True)

    def in_plant_units(theta):
        return np.concatenate((theta[:3], theta[3:] * y_scale / u_scale[0]))

    assert not edge_mode_cancelled(result.theta[:3], [result.theta[3:]])
    other, ratio = result.alternative
    assert edge_mode_cancelled(other[:3], [other[3:]]) and ratio < 1.0
    truth = case.theta[6886]
    assert delta(in_plant_units(result.theta), truth) < 0.3
    assert delta(in_plant_units(other), truth) > 1.0


def test_rpem_follows_the_drift_of_tracking_plant_8_22_to_its_end():
    """With its defaults: 1.8 (180 %) off at the end before the rule, 1.1 % after."""
    case = TrackingCase((8, 22))
    estimator = make_estimator('rpem', order=case.order, num_inputs=case.num_inputs)
    for t in range(case.samples):
        estimator.update(float(case.y[t]), case.u[t])
    assert delta(estimator.theta, case.theta[-1]) < 0.1
