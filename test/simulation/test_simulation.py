"""The scenarios: block-size independence, determinism and truth."""

import numpy as np
import pytest
from scipy import signal

from bcid_ros.simulation import make_scenario, SCENARIOS, StreamingFilter

PAPER_SCENARIOS = [name for name in SCENARIOS if name != 'custom']


@pytest.mark.parametrize('name', PAPER_SCENARIOS)
def test_samples_do_not_depend_on_the_block_sizes(name):
    scenario = make_scenario(name)
    y, u = scenario.simulate(700, 42)
    stream = scenario.stream(np.random.default_rng(42))
    blocks = [stream.take(k) for k in (1, 0, 2, 97, 0, 100, 500)]
    np.testing.assert_array_equal(np.concatenate([b[0] for b in blocks]), y)
    np.testing.assert_array_equal(np.concatenate([b[1] for b in blocks]), u)
    assert u.shape == (700, scenario.num_inputs)


@pytest.mark.parametrize('name', PAPER_SCENARIOS)
def test_same_seed_same_data_other_seed_other_data(name):
    scenario = make_scenario(name)
    first = scenario.simulate(200, 1)
    again = make_scenario(name).simulate(200, 1)
    other = scenario.simulate(200, 2)
    np.testing.assert_array_equal(first[0], again[0])
    assert not np.array_equal(first[0], other[0])


@pytest.mark.parametrize('name', PAPER_SCENARIOS)
def test_truth_names_match_the_parameters(name):
    truth = make_scenario(name).truth()
    assert len(truth.parameter_names) == truth.parameters.size
    assert len(truth.noise_names) == truth.noise.size
    assert np.isfinite(truth.parameters).all()


@pytest.mark.parametrize('b, a', [([0.0, 0.5, 0.2], [1.0, -0.9, 0.2]),
                                  ([1.0, -0.3, 0.5, -0.7, 0.9], [1.0]),
                                  ([2.0], [1.0])])
def test_streaming_filter_is_bit_exact_across_block_boundaries(b, a):
    x = np.random.default_rng(1).standard_normal(500)
    whole = StreamingFilter(b, a)(x)
    filt = StreamingFilter(b, a)
    parts = np.concatenate([filt(x[k:k + size]) for k, size in
                            ((0, 1), (1, 2), (3, 0), (3, 97), (100, 400))])
    np.testing.assert_array_equal(parts, whole)


def test_streaming_filter_equals_lfilter_across_blocks_and_empty_ones():
    x = np.random.default_rng(0).standard_normal(300)
    filt = StreamingFilter([0.0, 0.5, 0.2], [1.0, -0.9, 0.2])
    out = np.concatenate([filt(x[:100]), filt(x[100:100]), filt(x[100:])])
    # lfilter with a carried zero initial state runs the same recursion as without one (the
    # same bits here); 1e-12 would still hold a few eps of |y| < 4 if it did not
    np.testing.assert_allclose(out, signal.lfilter([0.0, 0.5, 0.2], [1.0, -0.9, 0.2], x),
                               rtol=0, atol=1e-12)


def test_ding_noise_matches_the_paper():
    scenario = make_scenario('ding_miso')
    y, u = scenario.simulate(200000, 5)
    # u is white with unit variance; the residual y - x has variance 0.01
    assert u.var(axis=0) == pytest.approx([1.0, 1.0], rel=0.02)
    plant = signal.lfilter([0, 0.12, 0.324], [1, -0.84, 0.16], u[:, 0]) + signal.lfilter(
        [0, 0.25, 0.186], [1, -0.84, 0.16], u[:, 1])
    assert (y - plant).var() == pytest.approx(0.01, rel=0.02)


def test_unknown_scenario_is_refused():
    with pytest.raises(ValueError, match="scenario must be one of ding_miso.*got 'nope'"):
        make_scenario('nope')
