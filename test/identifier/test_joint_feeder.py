"""The identifier's joint_state mode without ROS: names, the feeder, and the parameters."""

import array
import types

import numpy as np
import pytest

from bcid_ros.estimators import make_estimator
from bcid_ros.estimators import make_batched_estimator
from bcid_ros.identifier.feeder import SampleFeeder
from bcid_ros.identifier.joint_feeder import (check_joint_names, joint_feeder_from_parameters,
                                              joint_topic, JointFeeder)
from bcid_ros.identifier.parameters import check_identifier_parameters, check_simulator_parameters
from bcid_ros.simulation import make_scenario
from equivalence import assert_paths_agree, rounding_spread


def joint_state(names, velocity, effort, position=()):
    """Return a duck-typed JointState, with the arrays as rclpy delivers them."""
    return types.SimpleNamespace(name=list(names), position=array.array('d', position),
                                 velocity=array.array('d', velocity),
                                 effort=array.array('d', effort))


def messages(scenario, samples, seed):
    """Return JointState-like messages: joints shuffled, some left out, some NaN; and y, u."""
    y, u = scenario.simulate(samples, seed)
    return messages_of(scenario.joint_names, y, u, seed), y, u


def messages_of(joint_names, y, u, seed):
    """Return the messages of :func:`messages` for samples y, u ``(N, K)``."""
    rng = np.random.default_rng(seed + 1)
    names = np.array(joint_names)
    result = []
    for t in range(y.shape[0]):
        order = rng.permutation(len(names))
        order = order[rng.random(len(order)) >= 0.02]
        velocity, effort = y[t, order].copy(), u[t, order].copy()
        velocity[rng.random(len(order)) < 0.01] = np.nan
        result.append(joint_state(names[order], velocity, effort))
    return result


@pytest.mark.parametrize('names', [['joint_1'], ['shoulder_pan', 'elbow', '_wrist', 'J2']])
def test_names_that_make_topic_tokens_are_taken(names):
    assert check_joint_names(names) == tuple(names)


@pytest.mark.parametrize('names,match', [
    ([], r"'joints' must list at least one joint name .* got \[\]"),
    (['a', '1b'], r"'joints' must hold names made of letters.* got \['1b'\]"),
    (['arm/elbow', 'wrist 1', '', 'knee-2', 'ä'],
     r"got \['arm/elbow', 'wrist 1', '', 'knee-2', 'ä'\]"),
    (['a', 'b', 'a'], r"'joints' must hold unique names, got a more than once"),
])
def test_bad_names_are_refused(names, match):
    with pytest.raises(ValueError, match=match):
        check_joint_names(names)


def test_the_name_rule_agrees_with_ros():
    rclpy = pytest.importorskip('rclpy')
    from rclpy.expand_topic_name import expand_topic_name
    from rclpy.validate_full_topic_name import validate_full_topic_name

    for name in ['joint_1', '_a', 'A9', 'a_', '1a', 'a-b', 'a b', 'ä', '~', '{a}', 'a.b']:
        try:
            validate_full_topic_name(expand_topic_name(joint_topic(name, '~/valid'), 'n', '/'))
            ros_accepts = True
        except (ValueError, rclpy.exceptions.InvalidTopicNameException):
            ros_accepts = False
        try:
            check_joint_names([name])
            accepted = True
        except ValueError:
            accepted = False
        assert accepted == ros_accepts, name


def single_feeders(name, joints, messages, publish_period):
    """
    Feed each joint's samples to its own single-plant SampleFeeder.

    Return the feeders, the joints due per message, each joint's published
    parameters and noise as float arrays, and the validity after each message.
    """
    # each starts as its joint of a new batched estimator (its validity decisions' phase)
    start = make_batched_estimator(name, len(joints), order=2)
    singles = []
    for k in range(len(joints)):
        estimator = make_estimator(name, order=2)
        estimator.set_state(start.plant_state(k))
        singles.append(SampleFeeder(estimator, 0, publish_period))
    due, theta, noise = [], [[] for _ in joints], [[] for _ in joints]
    valid = []
    for message in messages:
        samples = message_samples(message, joints)
        due.append([])
        for k, single in enumerate(singles):
            if k not in samples:
                single.gap()
                continue
            estimates = single.take_rows(np.array([samples[k]])).estimates
            if estimates is not None:
                due[-1].append(k)
                theta[k].append(estimates[0])
                noise[k].append(estimates[2])
        valid.append([single.estimator.valid for single in singles])
    figures = {(k, 'theta'): np.array(theta[k]) for k in range(len(joints))}
    figures.update(((k, 'noise'), np.array(noise[k])) for k in range(len(joints)))
    return singles, due, figures, valid


def joint_figures(feeder, messages):
    """Feed the messages to a JointFeeder; return the joints due per message and the figures."""
    count = len(feeder.estimator.theta)
    due, theta, noise = [], [[] for _ in range(count)], [[] for _ in range(count)]
    valid = []
    for message in messages:
        result = feeder.take(message)
        due.append(result.due.tolist())
        for row, k in enumerate(result.due):
            theta[k].append(result.theta[row])
            noise[k].append(result.noise[row])
        valid.append(feeder.valid.tolist())
    figures = {(k, 'theta'): np.array(theta[k]) for k in range(count)}
    figures.update(((k, 'noise'), np.array(noise[k])) for k in range(count))
    return due, figures, valid


def assert_joints_follow_their_singles(name, scenario, y, u, seed, publish_period, figures):
    """
    Assert each joint's published figures equal its single-plant feeder's on the same samples.

    The batched estimator is another arithmetic path than the single plant's:
    within the rounding spread of the singles (test/equivalence.py).
    """
    def compute(y, u):
        messages = messages_of(scenario.joint_names, y, u, seed)
        return single_feeders(name, scenario.joint_names, messages, publish_period)[2]

    spread = rounding_spread(compute, y, u)
    expected = compute(y, u)
    for k in range(len(scenario.joint_names)):
        keys = [(k, 'theta'), (k, 'noise')]
        assert_paths_agree({key[1]: figures[key] for key in keys},
                           {key[1]: expected[key] for key in keys},
                           {key[1]: spread[key] for key in keys}, len(y), f'joint {k}')


@pytest.mark.parametrize('name', ['rls', 'bcrls'])
@pytest.mark.parametrize('publish_period', [1, 7])
def test_each_joint_is_published_as_the_single_plant_feeder_would(name, publish_period):
    scenario = make_scenario('joints', num_joints=5, seed=2)
    feeder = JointFeeder(scenario.joint_names, make_batched_estimator(name, 5, order=2),
                         publish_period=publish_period)
    messages_in, y, u = messages(scenario, 1200, 3)
    due, figures, valid = joint_figures(feeder, messages_in)
    singles, single_due, _, single_valid = single_feeders(name, scenario.joint_names,
                                                          messages_in, publish_period)
    assert due == single_due
    assert valid == single_valid
    assert_joints_follow_their_singles(name, scenario, y, u, 3, publish_period, figures)
    np.testing.assert_array_equal(feeder.valid, [s.estimator.valid for s in singles])
    assert min(len(figures[k, 'theta']) for k in range(5)) > 1000 // publish_period // 2
    assert feeder.used == sum(single.used for single in singles)
    np.testing.assert_array_equal(feeder.demux.nonfinite, [s.nonfinite for s in singles])
    assert feeder.demux.missing.min() > 0 and feeder.demux.nonfinite.min() > 0


def test_the_joint_bound_catches_one_changed_sample():
    scenario = make_scenario('joints', num_joints=5, seed=2)
    feeder = JointFeeder(scenario.joint_names, make_batched_estimator('bcrls', 5, order=2))
    messages_in, y, u = messages(scenario, 1200, 3)
    # joint 3's effort in one message changed by a ten-thousandth
    message = next(m for m in messages_in[600:] if scenario.joint_names[3] in m.name)
    message.effort[list(message.name).index(scenario.joint_names[3])] *= 1.0 + 1e-4
    _, figures, _ = joint_figures(feeder, messages_in)
    with pytest.raises(AssertionError, match='joint 3 .*the paths differ by'):
        assert_joints_follow_their_singles('bcrls', scenario, y, u, 3, 1, figures)


def message_samples(message, joints):
    """Return ``{joint index: [y, u]}`` of the joints a message carries (NaN included)."""
    index = {name: k for k, name in enumerate(message.name)}
    return {k: [message.velocity[index[joint]], message.effort[index[joint]]]
            for k, joint in enumerate(joints) if joint in index}


def test_validity_changes_and_reset():
    feeder = JointFeeder(['a', 'b'], make_batched_estimator('rls', 2, order=1))
    # a: an ARX plant y_t = 0.5 y_t-1 + u_t-1 + e_t, long enough for its residual tests;
    # b: two samples only (never its p = 2 updates)
    rng = np.random.default_rng(4)
    u = rng.standard_normal(1200)
    e = 0.1 * rng.standard_normal(1200)
    y = np.zeros(1200)
    for t in range(1, 1200):
        y[t] = 0.5 * y[t - 1] + u[t - 1] + e[t]
    changed, valid = [], []
    for t in range(1200):
        names = ['a', 'b'] if t < 2 else ['a']
        result = feeder.take(joint_state(names, [y[t], 0.2 * t][:len(names)],
                                         [u[t], 1.0 + t][:len(names)]))
        changed.append(result.valid_changed.tolist())
        valid.append(feeder.valid.tolist())
    # the changes reported are exactly the flips of a's validity, and b never changes
    flips = [t for t in range(1, 1200) if valid[t][0] != valid[t - 1][0]]
    assert [t for t, joints in enumerate(changed) if joints] == flips
    assert all(joints in ([], [0]) for joints in changed)
    assert feeder.valid.tolist() == [True, False]
    assert feeder.reset().valid_changed.tolist() == [0]
    assert not feeder.valid.any()


def test_what_keeps_a_sample_out_is_counted():
    feeder = JointFeeder(['a', 'b', 'c'], make_batched_estimator('rls', 3, order=1),
                         excitation_window=2)
    results = [feeder.take(joint_state(['c', 'a'], [1.0, np.nan], [2.0, 3.0])),
               feeder.take(joint_state(['a', 'b', 'c'], [1.0, 2.0], [1.0, 1.0, 1.0])),
               feeder.take(joint_state(['a', 'b', 'c'], [1.0, 2.0, 3.0], [1.0, 1.0, 2.0]))]
    assert [(r.missing, r.nonfinite, r.used, r.length_mismatch) for r in results] == [
        (1, 1, 1, False), (3, 0, 0, True), (0, 0, 3, False)]
    counts = feeder.counters()
    np.testing.assert_array_equal(counts['missing'], [0, 1, 0])
    np.testing.assert_array_equal(counts['length_mismatch'], [1, 1, 1])
    np.testing.assert_array_equal(counts['nonfinite'], [1, 0, 0])
    # runs of unchanged u (window 2): a 1, 1, 1 and c 2, 2, 2, 2 count 1 and 2; b changed
    for _ in range(2):
        feeder.take(joint_state(['a', 'b', 'c'], [1.0, 2.0, 3.0], [1.0, 5.0, 2.0]))
    np.testing.assert_array_equal(feeder.unexcited, [1, 0, 2])
    assert feeder.excitation_lost


def test_parameters_of_the_joint_state_mode():
    values = {'input_mode': 'joint_state', 'joints': ['a', 'b']}
    checked = check_identifier_parameters(values)
    assert (checked['input_field'], checked['output_field']) == ('effort', 'velocity')
    assert check_identifier_parameters({})['output_field'] == 'position'
    feeder = joint_feeder_from_parameters(dict(checked, estimator='rls', order=3))
    assert feeder.estimator.name == 'rls' and feeder.estimator.order == 3
    assert feeder.demux.output_field == 'velocity'
    for change, match in [
            ({'joints': []}, r"'joints' must list at least one joint name"),
            ({'joints': ['a', 'b c']}, r"'joints' must hold names made of letters"),
            ({'estimator': 'bciv'}, r"'estimator' must be one of rls, bcrls with input_mode: "
                                    r"joint_state .* got 'bciv'"),
            ({'estimator': 'cl_bcls'}, r"got 'cl_bcls'"),
            ({'num_inputs': 2}, r"'num_inputs' must be 1 with input_mode: joint_state"),
            ({'input_field': 'velocity'}, r"'input_field' and 'output_field' must differ")]:
        with pytest.raises(ValueError, match=match):
            check_identifier_parameters(dict(values, **change))


def test_simulator_parameters_of_the_joints_scenario():
    checked = check_simulator_parameters({'scenario': 'joints', 'num_joints': 3})
    assert checked['num_joints'] == 3 and checked['joints'] == []
    check_simulator_parameters({'scenario': 'joints', 'num_joints': 2, 'joints': ['l', 'r']})
    with pytest.raises(ValueError, match=r"'joints' must have num_joints = 3 names \(or none\)"):
        check_simulator_parameters({'scenario': 'joints', 'num_joints': 3, 'joints': ['a']})
    with pytest.raises(ValueError, match=r"'joints' must hold names made of letters"):
        check_simulator_parameters({'scenario': 'joints', 'num_joints': 1, 'joints': ['1']})
    with pytest.raises(ValueError, match=r"'frame_size' must be 1 with scenario joints"):
        check_simulator_parameters({'scenario': 'joints', 'frame_size': 10})


def test_the_joints_config_builds_what_it_says():
    from pathlib import Path

    from bcid_ros.identifier.parameters import load_yaml_parameters, SIMULATOR_PARAMETERS

    path = Path(__file__).resolve().parents[2] / 'config' / 'joints.yaml'
    simulator = check_simulator_parameters(load_yaml_parameters(
        path, 'bcid_simulator', {spec.name for spec in SIMULATOR_PARAMETERS}))
    feeder = joint_feeder_from_parameters(
        check_identifier_parameters(load_yaml_parameters(path)))
    scenario = make_scenario('joints', num_joints=simulator['num_joints'])
    assert feeder.joints == scenario.joint_names and len(feeder.joints) == 12
    assert (feeder.demux.input_field, feeder.demux.output_field) == ('effort', 'velocity')
    assert feeder.estimator.name == 'bcrls' and feeder.publish_period == 10
