"""
Beside a real robot: namespaces, sensor QoS, dated and stale estimates, the managed node.

Each test runs the identifier in-process on a domain of its own (conftest.py)
and drives it as a robot integrator would: a shipped config under two
namespaces, a best-effort sensor publisher, a plant that stops, and the
lifecycle services.
"""

from pathlib import Path

import numpy as np
import pytest

from conftest import spin_until

rclpy = pytest.importorskip('rclpy')

from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from lifecycle_msgs.msg import State, Transition  # noqa: E402
from lifecycle_msgs.srv import ChangeState, GetState  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import qos_profile_sensor_data  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from std_msgs.msg import Bool, Float64MultiArray  # noqa: E402

from bcid_ros.identifier.parameters import (  # noqa: E402
    estimator_from_parameters, load_yaml_parameters)
from bcid_ros.nodes.common import LATCHED_QOS, SAMPLES_QOS  # noqa: E402
from bcid_ros.nodes.identifier_lifecycle_node import IdentifierLifecycleNode  # noqa: E402
from bcid_ros.nodes.identifier_node import IdentifierNode  # noqa: E402
from bcid_ros.nodes.messages import samples_message  # noqa: E402
from bcid_ros.simulation import make_scenario  # noqa: E402

pytestmark = pytest.mark.ros

CONFIG = Path(__file__).resolve().parents[2] / 'config' / 'ding_miso.yaml'


def ding_rows(count, seed=3):
    """Return ``count`` samples [y, u1, u2] of the Ding scenario."""
    y, u = make_scenario('ding_miso').simulate(count, seed)
    return np.column_stack([y, u])


def offline_theta(rows, values=None):
    """Return the estimate of the config's estimator run offline over ``rows``."""
    estimator = estimator_from_parameters(dict(load_yaml_parameters(CONFIG), **(values or {})))
    estimator.run(rows[:, 0], rows[:, 1:])
    return estimator.theta


def feed(executor, publisher, rows, node, used_before=0, batch=50):
    """Publish ``rows`` one sample per message; spin until the node has used them all."""
    for start in range(0, len(rows), batch):
        for row in rows[start:start + batch]:
            publisher.publish(samples_message(row[None, :]))
        assert spin_until(executor, lambda: node.feeder.used >= used_before + min(
            start + batch, len(rows)), timeout=10)


def test_one_shipped_config_two_namespaces_distinct_statuses_and_a_typo_warned(
        ros_context, executor, capfd):
    nodes = {ns: IdentifierNode(context=ros_context, cli_args=[
        '--ros-args', '--params-file', str(CONFIG), '-r', f'__ns:={ns}',
        '-p', 'forgeting_factor:=0.99'])
        for ns in ('/robot1', '/robot2')}
    warnings = capfd.readouterr().err
    for ns, node in nodes.items():
        executor.add_node(node)
        # the file applies under the namespace: r = 2 and n = 2 (the defaults are 1 and 2)
        assert node.settings['num_inputs'] == 2 and node.estimator.parameter_names[-1] == 'b2_2'
        assert node.get_fully_qualified_name() == f'{ns}/bcid_identifier'
        # the typo is warned once per node, with the name it meant
        assert warnings.count(f'[{ns[1:]}.bcid_identifier]: parameter \'forgeting_factor\' is '
                              'not a parameter of this node and is ignored; did you mean '
                              '\'forgetting_factor\'?') == 1
    listener = rclpy.create_node('listener', context=ros_context)
    executor.add_node(listener)
    names = set()
    listener.create_subscription(DiagnosticArray, '/diagnostics',
                                 lambda m: names.update(s.name for s in m.status), 10)
    expected = {'/robot1/bcid_identifier: identifier', '/robot2/bcid_identifier: identifier'}
    assert spin_until(executor, lambda: expected <= names, timeout=10), names
    # each one's samples reach it alone
    sender = rclpy.create_node('sender', context=ros_context)
    executor.add_node(sender)
    publisher = sender.create_publisher(Float64MultiArray, '/robot1/samples', SAMPLES_QOS)
    assert spin_until(executor, lambda: publisher.get_subscription_count() == 1, timeout=10)
    rows = ding_rows(40)
    feed(executor, publisher, rows, nodes['/robot1'])
    assert nodes['/robot2'].feeder.used == 0


def test_a_sensor_data_publisher_needs_one_override_and_is_named_on_diagnostics(
        ros_context, executor):
    sender = rclpy.create_node('sensor', context=ros_context)
    executor.add_node(sender)
    publisher = sender.create_publisher(Float64MultiArray, '/samples', qos_profile_sensor_data)
    values = load_yaml_parameters(CONFIG)
    strict = IdentifierNode(context=ros_context,
                            parameter_overrides=[Parameter(k, value=v)
                                                 for k, v in values.items()])
    executor.add_node(strict)
    # reliable (the default) cannot take a best-effort publisher: named on /diagnostics
    assert spin_until(executor, lambda: '/samples' in strict.qos_events.refused, timeout=10)
    status = strict.diagnostics.status()
    assert 'incompatible QoS on /samples (reliability)' in status.message
    assert status.as_dict()['incompatible QoS /samples'].endswith('reliability')
    assert publisher.get_subscription_count() == 0
    executor.remove_node(strict)
    strict.destroy_node()

    override = 'qos_overrides./samples.subscription.reliability'
    node = IdentifierNode(context=ros_context, parameter_overrides=[
        *(Parameter(k, value=v) for k, v in values.items()),
        Parameter(override, value='best_effort')])
    executor.add_node(node)
    assert node.get_parameter(override).value == 'best_effort'
    assert spin_until(executor, lambda: publisher.get_subscription_count() == 1, timeout=10)
    spin_until(executor, lambda: False, timeout=0.3)
    rows = ding_rows(300)
    for start in range(0, len(rows), 20):  # best effort: paced, so that none is dropped
        for row in rows[start:start + 20]:
            publisher.publish(samples_message(row[None, :]))
        spin_until(executor, lambda: node.feeder.used >= start + 20, timeout=2)
    assert node.feeder.used + node.counters['lost'] == len(rows)
    assert not node.qos_events.refused
    if node.counters['lost'] == 0:
        np.testing.assert_allclose(node.estimator.theta, offline_theta(rows), rtol=0,
                                   atol=1e-12)


def test_estimates_carry_the_stamp_of_the_last_sample_and_go_stale(ros_context, executor):
    values = dict(load_yaml_parameters(CONFIG), stale_after=1.0)
    node = IdentifierNode(context=ros_context, parameter_overrides=[
        Parameter(k, value=v) for k, v in values.items()])
    executor.add_node(node)
    listener = rclpy.create_node('controller', context=ros_context)
    executor.add_node(listener)
    stamped, valid = [], []
    listener.create_subscription(JointState, '/bcid_identifier/parameters_stamped',
                                 stamped.append, LATCHED_QOS)
    listener.create_subscription(Bool, '/bcid_identifier/valid',
                                 lambda m: valid.append(m.data), LATCHED_QOS)
    publisher = listener.create_publisher(Float64MultiArray, '/samples', SAMPLES_QOS)
    assert spin_until(executor, lambda: publisher.get_subscription_count() == 1, timeout=10)
    rows = ding_rows(605, seed=0)  # the estimator finds it valid after 600 and 605 samples
    before = node.get_clock().now().nanoseconds
    feed(executor, publisher, rows[:600], node)
    after = node.get_clock().now().nanoseconds
    assert spin_until(executor, lambda: stamped and np.array_equal(
        stamped[-1].position, node.estimator.theta), timeout=5)
    last = stamped[-1]
    assert list(last.name) == list(node.estimator.parameter_names)
    # unstamped samples: the node clock's receive time of the last one
    stamp = last.header.stamp.sec * 10 ** 9 + last.header.stamp.nanosec
    assert before <= stamp <= after
    assert stamp == max(s.header.stamp.sec * 10 ** 9 + s.header.stamp.nanosec for s in stamped)
    assert spin_until(executor, lambda: valid[-1:] == [True], timeout=0.5)
    # the plant stops: ~/valid turns false after stale_after, with the reason
    assert spin_until(executor, lambda: valid[-1] is False, timeout=3)
    assert node.get_clock().now().nanoseconds - stamp >= 1e9
    status = node.diagnostics.status()
    assert 'estimate not valid: no samples for' in status.message
    # samples resume: valid again
    feed(executor, publisher, rows[600:], node, used_before=600)
    assert spin_until(executor, lambda: valid[-1] is True, timeout=3)
    assert 'no samples for' not in node.diagnostics.status().message


def test_stamped_samples_date_the_estimate_with_their_header(ros_context, executor):
    values = dict(load_yaml_parameters(CONFIG), input_mode='separate', num_inputs=1, order=1,
                  input_type='joint_state', output_type='joint_state', sync='stamp',
                  sample_period=0.01)
    node = IdentifierNode(context=ros_context, parameter_overrides=[
        Parameter(k, value=v) for k, v in values.items()])
    executor.add_node(node)
    plant = rclpy.create_node('plant', context=ros_context)
    executor.add_node(plant)
    stamped = []
    plant.create_subscription(JointState, '/bcid_identifier/parameters_stamped',
                              stamped.append, LATCHED_QOS)
    inputs = plant.create_publisher(JointState, '/input', SAMPLES_QOS)
    outputs = plant.create_publisher(JointState, '/output', SAMPLES_QOS)
    assert spin_until(executor, lambda: inputs.get_subscription_count() == 1
                      and outputs.get_subscription_count() == 1, timeout=10)
    rng = np.random.default_rng(0)
    y = 0.0
    base = 1_700_000_000 * 10 ** 9
    for k in range(60):
        u = float(rng.standard_normal())
        stamp = base + k * 10_000_000
        for publisher, field, value in ((inputs, 'effort', u), (outputs, 'position', y)):
            message = JointState(name=['j'])
            setattr(message, field, [value])
            message.header.stamp.sec, message.header.stamp.nanosec = divmod(stamp, 10 ** 9)
            publisher.publish(message)
        y = 0.8 * y + 0.5 * u
    assert spin_until(executor, lambda: node.feeder.used == 60, timeout=10)

    def stamps():
        return [m.header.stamp.sec * 10 ** 9 + m.header.stamp.nanosec for m in stamped]

    last = base + 59 * 10_000_000
    assert spin_until(executor, lambda: stamps()[-1:] == [last], timeout=5), stamps()[-3:]
    # every estimate is dated by a sample's header stamp, in order
    assert set(stamps()) <= {base + k * 10_000_000 for k in range(60)}
    assert stamps() == sorted(stamps())


def lifecycle_call(executor, client, request):
    """Call a lifecycle service and return its response."""
    assert spin_until(executor, client.service_is_ready, timeout=10)
    future = client.call_async(request)
    assert spin_until(executor, future.done, timeout=10)
    return future.result()


def test_lifecycle_keeps_the_state_across_deactivate_and_cleanup(
        ros_context, executor, tmp_path):
    state_file = tmp_path / 'state.json'
    values = dict(load_yaml_parameters(CONFIG), state_file=str(state_file))
    node = IdentifierLifecycleNode(context=ros_context, parameter_overrides=[
        Parameter(k, value=v) for k, v in values.items()])
    executor.add_node(node)
    driver = rclpy.create_node('driver', context=ros_context)
    executor.add_node(driver)
    change = driver.create_client(ChangeState, '/bcid_identifier/change_state')
    get = driver.create_client(GetState, '/bcid_identifier/get_state')
    publisher = driver.create_publisher(Float64MultiArray, '/samples', SAMPLES_QOS)

    def transition(kind, expected):
        assert lifecycle_call(executor, change, ChangeState.Request(
            transition=Transition(id=kind))).success
        assert lifecycle_call(executor, get, GetState.Request()).current_state.id == expected

    assert lifecycle_call(executor, get, GetState.Request()).current_state.id == \
        State.PRIMARY_STATE_UNCONFIGURED
    transition(Transition.TRANSITION_CONFIGURE, State.PRIMARY_STATE_INACTIVE)
    assert publisher.get_subscription_count() == 0  # configured, not yet subscribed
    transition(Transition.TRANSITION_ACTIVATE, State.PRIMARY_STATE_ACTIVE)
    assert spin_until(executor, lambda: publisher.get_subscription_count() == 1, timeout=10)
    rows = ding_rows(400)
    feed(executor, publisher, rows[:250], node)
    transition(Transition.TRANSITION_DEACTIVATE, State.PRIMARY_STATE_INACTIVE)
    assert spin_until(executor, lambda: publisher.get_subscription_count() == 0, timeout=10)
    transition(Transition.TRANSITION_ACTIVATE, State.PRIMARY_STATE_ACTIVE)
    assert spin_until(executor, lambda: publisher.get_subscription_count() == 1, timeout=10)
    feed(executor, publisher, rows[250:], node, used_before=250)
    theta = node.estimator.theta.copy()
    # the same estimate as one uninterrupted run over the same samples
    np.testing.assert_allclose(theta, offline_theta(rows), rtol=0, atol=1e-12)
    # cleanup goes from inactive (the lifecycle state machine has no active -> cleanup)
    transition(Transition.TRANSITION_DEACTIVATE, State.PRIMARY_STATE_INACTIVE)
    transition(Transition.TRANSITION_CLEANUP, State.PRIMARY_STATE_UNCONFIGURED)
    assert node.estimator is None and state_file.is_file()
    # configuring again restores what cleanup saved, bit for bit
    transition(Transition.TRANSITION_CONFIGURE, State.PRIMARY_STATE_INACTIVE)
    assert node.feeder.used == 400
    np.testing.assert_array_equal(node.estimator.theta, theta)
    transition(Transition.TRANSITION_ACTIVATE, State.PRIMARY_STATE_ACTIVE)
    assert spin_until(executor, lambda: publisher.get_subscription_count() == 1, timeout=10)

    # samples published while inactive are not taken, and not lost in transport: the
    # regressor restarts at the jump in the sequence numbers, nothing is counted
    transition(Transition.TRANSITION_DEACTIVATE, State.PRIMARY_STATE_INACTIVE)
    assert spin_until(executor, lambda: publisher.get_subscription_count() == 0, timeout=10)
    more = ding_rows(60, seed=9)
    for row in more[:30]:
        publisher.publish(samples_message(row[None, :]))
    spin_until(executor, lambda: False, timeout=0.3)
    assert node.feeder.used == 400
    transition(Transition.TRANSITION_ACTIVATE, State.PRIMARY_STATE_ACTIVE)
    assert spin_until(executor, lambda: publisher.get_subscription_count() == 1, timeout=10)
    feed(executor, publisher, more[30:], node, used_before=400)
    assert node.counters['lost'] == 0
    assert node.estimator.samples == 430 - 2  # the regressor refilled: n = 2 samples


def test_lifecycle_refuses_a_bad_parameter_at_configure(ros_context, executor):
    node = IdentifierLifecycleNode(context=ros_context, parameter_overrides=[
        Parameter('estimator', value='cl_bcls')])  # needs its controller
    executor.add_node(node)
    driver = rclpy.create_node('driver', context=ros_context)
    executor.add_node(driver)
    change = driver.create_client(ChangeState, '/bcid_identifier/change_state')
    result = lifecycle_call(executor, change, ChangeState.Request(
        transition=Transition(id=Transition.TRANSITION_CONFIGURE)))
    assert not result.success
    get = driver.create_client(GetState, '/bcid_identifier/get_state')
    assert lifecycle_call(executor, get, GetState.Request()).current_state.id == \
        State.PRIMARY_STATE_UNCONFIGURED


def test_joint_state_estimates_go_stale_too(ros_context, executor):
    joints = ['j1', 'j2']
    node = IdentifierNode(context=ros_context, parameter_overrides=[
        Parameter('input_mode', value='joint_state'), Parameter('joints', value=joints),
        Parameter('order', value=1), Parameter('stale_after', value=0.5),
        Parameter('estimator', value='rls')])  # equation-error data below: LS is consistent
    executor.add_node(node)
    robot = rclpy.create_node('robot', context=ros_context)
    executor.add_node(robot)
    valid = {joint: [] for joint in joints}
    for joint in joints:
        robot.create_subscription(Bool, f'/bcid_identifier/{joint}/valid',
                                  lambda m, joint=joint: valid[joint].append(m.data),
                                  LATCHED_QOS)
    publisher = robot.create_publisher(JointState, '/joint_states', SAMPLES_QOS)
    assert spin_until(executor, lambda: publisher.get_subscription_count() == 1, timeout=10)
    rng = np.random.default_rng(1)
    y = np.zeros(2)

    def send(count):
        nonlocal y
        for _ in range(count):
            u = rng.standard_normal(2)
            publisher.publish(JointState(name=joints, effort=u.tolist(),
                                         velocity=y.tolist(), position=[0.0, 0.0]))
            y = 0.8 * y + 0.5 * u + 0.05 * rng.standard_normal(2)

    for _ in range(12):
        send(50)
        spin_until(executor, lambda: False, timeout=0.02)
    assert spin_until(executor, lambda: all(v[-1:] == [True] for v in valid.values()),
                      timeout=5), valid
    # the robot stops publishing: every joint's ~/valid turns false, and the node says why
    assert spin_until(executor, lambda: all(v[-1:] == [False] for v in valid.values()),
                      timeout=3)
    assert 'estimate not valid: no samples for' in node.joint_state.diagnostics.status().message
    send(1)
    assert spin_until(executor, lambda: all(v[-1:] == [True] for v in valid.values()),
                      timeout=3)
