"""The joints scenario: random stable plants drawn from the seed, with truth per joint."""

import numpy as np
import pytest
from scipy import signal

from bcid_ros.simulation import make_scenario
from bcid_ros.simulation.joints import JointsScenario, POLE_RADIUS


def test_registered_with_its_settings():
    scenario = make_scenario('joints', num_joints=4, seed=3)
    assert isinstance(scenario, JointsScenario)
    assert scenario.joint_names == ('joint_1', 'joint_2', 'joint_3', 'joint_4')
    assert scenario.num_inputs == 4
    assert (scenario.joint_order, scenario.inputs_per_joint) == (2, 1)


def test_same_seed_same_plants_other_seed_other_plants():
    first = JointsScenario(num_joints=20, seed=5)
    again = JointsScenario(num_joints=20, seed=5)
    other = JointsScenario(num_joints=20, seed=6)
    np.testing.assert_array_equal(first.parameters, again.parameters)
    np.testing.assert_array_equal(first.sigma2, again.sigma2)
    assert not np.array_equal(first.parameters, other.parameters)
    np.testing.assert_array_equal(first.simulate(300, 1)[0], again.simulate(300, 1)[0])
    assert not np.array_equal(first.simulate(300, 1)[0], first.simulate(300, 2)[0])
    # more joints: the first ones are drawn first, so they stay the same plants
    np.testing.assert_array_equal(JointsScenario(num_joints=30, seed=5).parameters[:20],
                                  first.parameters)


def test_every_plant_is_stable_with_its_zero_off_the_poles():
    scenario = JointsScenario(num_joints=500, seed=11)
    a = np.column_stack([np.ones(500), scenario.parameters[:, :2]])
    radii = np.array([np.abs(np.roots(row)).max() for row in a])
    # np.roots of these quadratics (simple roots): within 4 eps sum|a_k r^k| / |A'(r)| of
    # the drawn poles, at most 6e-13 here; 1e-12 holds that
    assert radii.max() <= POLE_RADIUS[1] + 1e-12
    assert radii.min() >= POLE_RADIUS[0] - 1e-12
    zeros = -scenario.parameters[:, 3] / scenario.parameters[:, 2]
    gaps = [np.abs(np.roots(row) - zero).min() for row, zero in zip(a, zeros)]
    assert min(gaps) >= 0.2 - 1e-12
    assert np.all(scenario.parameters[:, 2] != 0.0)
    # both kinds of pole pairs are drawn
    complex_pairs = np.array([np.iscomplex(np.roots(row)).any() for row in a])
    assert 0 < complex_pairs.sum() < 500


def test_truth_per_joint_and_in_one():
    scenario = JointsScenario(num_joints=3, seed=2)
    truths = scenario.joint_truths()
    assert list(truths) == ['joint_1', 'joint_2', 'joint_3']
    for k, truth in enumerate(truths.values()):
        assert truth.parameter_names == ('a1', 'a2', 'b1_1', 'b1_2')
        assert truth.parameters.shape == (4,)
        np.testing.assert_array_equal(truth.parameters, scenario.parameters[k])
        assert truth.noise_names == ('sigma2',)
        assert truth.noise.shape == (1,)
        assert 0.05 ** 2 <= truth.noise[0] <= 0.2 ** 2
    whole = scenario.truth()
    assert whole.parameter_names[:5] == ('joint_1/a1', 'joint_1/a2', 'joint_1/b1_1',
                                         'joint_1/b1_2', 'joint_2/a1')
    assert whole.parameters.shape == (12,)
    assert whole.noise_names == ('joint_1/sigma2', 'joint_2/sigma2', 'joint_3/sigma2')


def test_samples_follow_each_joints_truth_in_any_blocks():
    scenario = JointsScenario(num_joints=4, seed=8)
    y, u = scenario.simulate(2000, 9)
    assert y.shape == u.shape == (2000, 4)
    stream = scenario.stream(np.random.default_rng(9))
    blocks = [stream.take(k) for k in (1, 0, 3, 996, 1000)]
    np.testing.assert_array_equal(np.concatenate([b[0] for b in blocks]), y)
    np.testing.assert_array_equal(np.concatenate([b[1] for b in blocks]), u)
    # y - B/A u is the joint's white noise, with the joint's variance
    for k, truth in enumerate(scenario.joint_truths().values()):
        a1, a2, b1, b2 = truth.parameters
        noise = y[:, k] - signal.lfilter([0.0, b1, b2], [1.0, a1, a2], u[:, k])
        # variance of 2000 Gaussian draws: relative standard error sqrt(2/2000) = 3.2 %;
        # 5 standard errors = 16 %
        assert np.var(noise) == pytest.approx(truth.noise[0], rel=0.16)
        assert np.var(u[:, k]) == pytest.approx(1.0, rel=0.16)


def test_bad_settings_are_refused():
    with pytest.raises(ValueError, match='num_joints must be an integer >= 1, got 0'):
        make_scenario('joints', num_joints=0)
    with pytest.raises(ValueError, match='seed must be an integer >= 0, got -1'):
        JointsScenario(seed=-1)
