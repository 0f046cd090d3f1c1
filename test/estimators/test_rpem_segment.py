"""rpem's segment predictor: the impulse response of 1/F behind the free responses."""

import numpy as np
import pytest
from scipy import signal

from bcid_ros.estimators.rpem import segment
from bcid_ros.estimators.rpem.segment import impulse_response, NEGLIGIBLE, SegmentPredictor

#: Fast, slow, oscillatory and unstable F (monic, normalised units).
POLYNOMIALS = ([1.0, -0.585], [1.0, -1.5, 0.7], [1.0, -0.999], [1.0, 0.1, 0.2, 0.05],
               [1.0, -2.5, 2.1, -0.6], [1.0, -1.01])


def full_response(f_poly: np.ndarray, count: int) -> np.ndarray:
    """Return the impulse response of 1/F, one filter call over every sample."""
    impulse = np.zeros(count)
    impulse[0] = 1.0
    return signal.lfilter([1.0], f_poly, impulse)


@pytest.mark.parametrize('f_poly', POLYNOMIALS)
@pytest.mark.parametrize('count', [7, 300, 8192])
def test_impulse_response_is_the_filters_bits_down_to_negligible(f_poly, count):
    f_poly = np.array(f_poly)
    h = impulse_response(signal.lfilter, f_poly, count)
    full = full_response(f_poly, count)
    kept = np.abs(full) >= NEGLIGIBLE
    np.testing.assert_array_equal(h[kept], full[kept])
    assert not h[~kept].any()


def test_no_subnormal_number_in_a_fast_poles_free_responses():
    # why the response stops at NEGLIGIBLE: a pole at 0.585 reaches the subnormal numbers
    # (below 2.2e-308) after about 1300 samples, and arithmetic on them is tens of times
    # slower on x86; the filter's full response holds them, the free responses must not
    predictor = SegmentPredictor(3, 1, False, (0,), armax=False, offset=False)
    f_poly = np.real(np.poly([0.585, 0.3, -0.2]))
    tiny = np.finfo(float).tiny
    assert ((full_response(f_poly, 8192) != 0.0)
            & (np.abs(full_response(f_poly, 8192)) < tiny)).any()
    free = predictor._free_responses(f_poly, 8192)
    assert np.all((free == 0.0) | (np.abs(free) >= tiny))


def test_the_predictors_errors_are_those_of_the_full_response(monkeypatch):
    # the values left out are below what they would be added to: the same bits
    rng = np.random.default_rng(3)
    count = 6000
    u = rng.standard_normal((count, 1))
    theta = np.concatenate([np.real(np.poly([0.585, 0.3, -0.2]))[1:], [1.0, 0.5, -0.3]])
    y = signal.lfilter(np.concatenate(([0.0], theta[3:])),
                       np.concatenate(([1.0], theta[:3])), u[:, 0])
    y += 0.1 * rng.standard_normal(count)
    weights = np.ones(count)
    predictor = SegmentPredictor(3, 1, False, (0,), armax=False, offset=True)
    short = predictor.predict(theta, y, u, weights)
    monkeypatch.setattr(segment, 'impulse_response',
                        lambda lfilter, f_poly, n: full_response(f_poly, n))
    full = predictor.predict(theta, y, u, weights)
    np.testing.assert_array_equal(short.eps, full.eps)
    np.testing.assert_array_equal(short.psi, full.psi)
