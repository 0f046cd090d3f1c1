"""The custom plant's dead time and operating point."""

import numpy as np
import pytest

from bcid_ros.simulation import make_scenario

PLANT = {'plant_denominator': [1.0, -1.2, 0.5], 'plant_numerator': [0.0, 1.0, 0.4]}


def test_an_input_delay_shifts_the_plant_response():
    plain = make_scenario('custom', **PLANT, noise_variance=0.0)
    delayed = make_scenario('custom', **PLANT, noise_variance=0.0, input_delay=3)
    y0, u0 = plain.simulate(300, 5)
    y3, u3 = delayed.simulate(300, 5)
    np.testing.assert_array_equal(u3, u0)
    np.testing.assert_array_equal(y3[:3], 0.0)
    # lfilter with three leading zeros in b adds its terms in another order: a few eps of
    # |y| < 7 (measured 1.8e-15); 1e-12 is far above that, far below a wrong shift
    np.testing.assert_allclose(y3[3:], y0[:-3], rtol=1e-12, atol=1e-12)


def test_delays_per_input_and_the_true_lags_in_the_names():
    scenario = make_scenario('custom', plant_denominator=[1.0, -0.5],
                             plant_numerator=[0.0, 1.0, 0.0, 2.0], input_delay=[0, 2])
    truth = scenario.truth()
    assert truth.parameter_names == ('a1', 'b1_1', 'b2_3')
    np.testing.assert_array_equal(truth.parameters, [-0.5, 1.0, 2.0])
    y, u = make_scenario('custom', plant_denominator=[1.0, -0.5],
                         plant_numerator=[0.0, 1.0, 0.0, 2.0], input_delay=[0, 2],
                         noise_variance=0.0).simulate(50, 1)
    expected = np.zeros(50)
    for t in range(50):
        previous = expected[t - 1] if t else 0.0
        expected[t] = (0.5 * previous + (u[t - 1, 0] if t >= 1 else 0.0)
                       + (2.0 * u[t - 3, 1] if t >= 3 else 0.0))
    # the same first-order recursion, summed in another order by lfilter: a few eps of
    # |y| < 7 carried with weight 0.5^k (measured 9e-16); 1e-12 is far above that
    np.testing.assert_allclose(y, expected, rtol=1e-12, atol=1e-12)


def test_operating_point_adds_offsets_around_the_same_deviations():
    plain = make_scenario('custom', **PLANT)
    shifted = make_scenario('custom', **PLANT, input_offset=2.5, output_offset=-7.0)
    y0, u0 = plain.simulate(400, 9)
    y1, u1 = shifted.simulate(400, 9)
    # adding and removing an offset rounds twice, by eps of |u| + 2.5 and |y| + 7 (< 16):
    # measured 4e-16 and 1.3e-15; 1e-12 is far above that
    np.testing.assert_allclose(u1 - 2.5, u0, rtol=0, atol=1e-12)
    np.testing.assert_allclose(y1 + 7.0, y0, rtol=0, atol=1e-12)


def test_delay_and_offsets_do_not_depend_on_the_block_sizes():
    scenario = make_scenario('custom', **PLANT, input_delay=4, input_offset=1.0,
                             output_offset=3.0, equation_error=True)
    y, u = scenario.simulate(300, 3)
    stream = scenario.stream(np.random.default_rng(3))
    blocks = [stream.take(k) for k in (1, 2, 0, 3, 94, 200)]
    np.testing.assert_array_equal(np.concatenate([b[0] for b in blocks]), y)
    np.testing.assert_array_equal(np.concatenate([b[1] for b in blocks]), u)


@pytest.mark.parametrize('settings, word', [
    ({'input_delay': -1}, 'input_delay'),
    ({'input_delay': 1.5}, 'input_delay'),
    ({'input_delay': [1, 2]}, 'input_delay'),
    ({'input_offset': [1.0, 2.0]}, 'input_offset'),
    ({'output_offset': float('nan')}, 'output_offset'),
    ({'output_offset': 'high'}, 'output_offset'),
])
def test_bad_delay_or_offset_is_refused_by_name(settings, word):
    with pytest.raises(ValueError, match=word):
        make_scenario('custom', **PLANT, **settings)
