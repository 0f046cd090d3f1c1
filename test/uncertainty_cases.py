"""
The plants and runs that the uncertainty tests share (test/estimators, test/statistical).

Ding's MISO plant with white equation error (for rls) or output error (for
bcrls), and the papers' single-input scenarios for bciv and cl_bcls.
"""

import math

import numpy as np
from scipy.signal import lfilter

from bcid_ros.estimators import make_estimator
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


IKENOUE_COLORED = dict(order=2, iv_lag=5, input_noise='colored')
IKENOUE_WHITE = dict(order=2, iv_lag=4, input_noise='white')
IKEDA = dict(order=1, controller_numerator=[0.2289], controller_denominator=[1.0, -0.09004])


def ikenoue(count, seed):
    """Return (y, u) of Ikenoue's section 5.1 (colored input noise)."""
    return make_scenario('ikenoue_colored').simulate(count, seed)


def ikenoue_white(count, seed):
    """Return (y, u) of Ikenoue's section 5.2 (white input noise)."""
    return make_scenario('ikenoue_white_input').simulate(count, seed)


def ikeda(count, seed):
    """Return (y, u) of Ikeda's closed loop."""
    return make_scenario('ikeda_closed_loop').simulate(count, seed)


def run_single(name, y, u, **settings):
    """Return the single-input estimator ``name`` after the samples."""
    estimator = make_estimator(name, **settings)
    estimator.run(y, u)
    return estimator
