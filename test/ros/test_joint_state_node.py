"""
The identifier in input_mode joint_state, and the simulator's joints scenario, on a ROS graph.

Every test gets its own rclpy Context on its own domain (conftest.py). A
driver node publishes JointState messages in small bursts and waits until
the identifier has taken them, so nothing is lost; the estimates the node
publishes per joint are compared with the same messages replayed through
the ROS-free JointFeeder in the test (equal bit for bit: same machine, same
run, same code path) and with one single-plant estimator per joint (the batched
step is another arithmetic path: within the rounding spread of the single
plant, test/equivalence.py).
"""

import numpy as np
import pytest

from conftest import spin_until

rclpy = pytest.importorskip('rclpy')

from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from std_msgs.msg import Bool, Float64MultiArray  # noqa: E402

from bcid_ros.estimators import make_estimator  # noqa: E402
from bcid_ros.estimators import make_batched_estimator  # noqa: E402
from bcid_ros.identifier.feeder import SampleFeeder  # noqa: E402
from bcid_ros.identifier.joint_feeder import JointFeeder  # noqa: E402
from bcid_ros.nodes.common import SAMPLES_QOS  # noqa: E402
from bcid_ros.nodes.identifier_node import IdentifierNode  # noqa: E402
from bcid_ros.nodes.messages import as_doubles  # noqa: E402
from bcid_ros.nodes.simulator_node import SimulatorNode  # noqa: E402
from bcid_ros.simulation import make_scenario  # noqa: E402
from equivalence import assert_paths_agree, rounding_spread  # noqa: E402

pytestmark = pytest.mark.ros

#: Keeps every message of a topic, late joiners included.
RECORDER_QOS = QoSProfile(depth=10000, reliability=ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.TRANSIENT_LOCAL)
JOINTS = ['joint_1', 'joint_2', 'joint_3', 'joint_4', 'joint_5']


def overrides(values):
    """Return ROS parameter overrides from a dict."""
    return [Parameter(name, value=value) for name, value in values.items()]


def identifier(executor, context, joints=JOINTS, **values):
    """Start an identifier in joint_state mode on the executor."""
    settings = dict(input_mode='joint_state', joints=list(joints), estimator='bcrls', order=2,
                    **values)
    node = IdentifierNode(context=context, parameter_overrides=overrides(settings))
    executor.add_node(node)
    return node


class Recorder:
    """Records every estimate and validity message of each joint."""

    def __init__(self, context, joints, prefix='/bcid_identifier'):
        self.node = rclpy.create_node('recorder', context=context)
        self.parameters = {joint: [] for joint in joints}
        self.noise = {joint: [] for joint in joints}
        self.std = {joint: [] for joint in joints}
        self.valid = {joint: [] for joint in joints}
        self.labels = {}
        self.diagnostics = []
        for joint in joints:
            for topic, store in (('parameters', self.parameters), ('noise_variance', self.noise),
                                 ('parameter_std', self.std)):
                self.node.create_subscription(
                    Float64MultiArray, f'{prefix}/{joint}/{topic}',
                    lambda message, store=store[joint], topic=topic: self._record(
                        topic, store, message), RECORDER_QOS)
            self.node.create_subscription(
                Bool, f'{prefix}/{joint}/valid',
                lambda message, store=self.valid[joint]: store.append(message.data),
                RECORDER_QOS)
        self.node.create_subscription(DiagnosticArray, '/diagnostics',
                                      self.diagnostics.append, 10)

    def _record(self, topic, store, message):
        self.labels[topic] = message.layout.dim[0].label
        store.append(np.array(message.data))

    def count(self):
        """Return the estimate messages recorded, all joints."""
        return sum(len(messages) for messages in self.parameters.values())


def joint_messages(samples, seed, leave_out=(), nan_at=None, extra=True):
    """
    Return JointState messages of the joints scenario and the clean (y, u).

    The joints come in a new random order in every message, with a joint
    that is not configured (``gripper``) among them; ``leave_out`` is
    ``(joint index, period)``: that joint is absent from every period-th
    message; ``nan_at`` is ``(joint index, t)``: a NaN velocity there.
    """
    scenario = make_scenario('joints', num_joints=len(JOINTS), seed=seed)
    y, u = scenario.simulate(samples, seed)
    rng = np.random.default_rng(seed)
    messages = []
    for t in range(samples):
        velocity, effort = y[t].copy(), u[t].copy()
        if nan_at is not None and nan_at[1] == t:
            velocity[nan_at[0]] = np.nan
        keep = [k for k in range(len(JOINTS))
                if not (leave_out and leave_out[0] == k and t % leave_out[1] == 0)]
        names = [JOINTS[k] for k in keep] + (['gripper'] if extra else [])
        velocity = np.append(velocity[keep], 0.5) if extra else velocity[keep]
        effort = np.append(effort[keep], -0.5) if extra else effort[keep]
        order = rng.permutation(len(names))
        message = JointState(name=[names[k] for k in order])
        message.velocity = as_doubles(velocity[order])
        message.effort = as_doubles(effort[order])
        message.header.stamp.sec, message.header.stamp.nanosec = divmod(t * 10_000_000, 10 ** 9)
        messages.append(message)
    return messages, y, u


def wait_for(executor, node, recorder):
    """Spin until the recorder is matched on every joint topic and has the first validity."""
    adapter = node.joint_state
    publishers = adapter._parameters + adapter._noise + adapter._std + adapter._valid
    assert spin_until(executor, lambda: all(p.get_subscription_count() for p in publishers)
                      and all(recorder.valid.values()))


def drive(executor, context, node, messages, burst=50):
    """Publish the messages in bursts, each taken by the node before the next."""
    driver = rclpy.create_node('joint_driver', context=context)
    executor.add_node(driver)
    publisher = driver.create_publisher(JointState, 'joint_states', SAMPLES_QOS)
    assert spin_until(executor, lambda: publisher.get_subscription_count() >= 1)
    adapter = node.joint_state
    for start in range(0, len(messages), burst):
        for message in messages[start:start + burst]:
            publisher.publish(message)
        taken = start + len(messages[start:start + burst])
        assert spin_until(executor, lambda: adapter.messages >= taken, timeout=30)
    assert adapter.counters['lost'] == 0


def replay(messages, name='bcrls', publish_period=1):
    """Return each joint's published estimates when the messages go through a JointFeeder."""
    feeder = JointFeeder(JOINTS, make_batched_estimator(name, len(JOINTS), order=2),
                         publish_period=publish_period)
    published = {joint: [] for joint in JOINTS}
    published_std = {joint: [] for joint in JOINTS}
    for message in messages:
        result = feeder.take(message)
        for row, k in enumerate(result.due):
            published[JOINTS[k]].append(result.theta[row])
            if np.isfinite(result.std[row]).all():
                published_std[JOINTS[k]].append(result.std[row])
    feeder.published_std = published_std
    return feeder, published


def single_plant(y, u, k, present=None, publish_period=1):
    """Return joint k's single-plant feeder (absent samples as gaps) and its estimates."""
    feeder = SampleFeeder(make_estimator('bcrls', order=2), 0, publish_period)
    published = []
    for t in range(len(y)):
        if present is not None and not present[t]:
            feeder.gap()
            continue
        estimates = feeder.take_rows(np.array([[y[t, k], u[t, k]]])).estimates
        if estimates is not None:
            published.append(estimates)
    return feeder, published


def single_plant_figures(y, u, k, present=None, publish_period=1):
    """Return joint k's single-plant published estimates and final state, as float arrays."""
    feeder, published = single_plant(y, u, k, present, publish_period)
    return {'parameters': np.array([theta for theta, _, _ in published]),
            'noise': np.array([noise for _, _, noise in published]),
            'final theta': feeder.estimator.theta}


def assert_joint_follows_its_single_plant(figures, y, u, k, present=None, publish_period=1):
    """
    Assert that joint k's ``figures`` are its single-plant run's, within the rounding spread.

    The batched estimator is another arithmetic path than the single plant's
    (test/equivalence.py); their counts of estimates must agree exactly.
    """
    def compute(y, u):
        return single_plant_figures(y, u, k, present, publish_period)

    expected = compute(y, u)
    assert {key: np.shape(value) for key, value in figures.items()} == {
        key: np.shape(expected[key]) for key in figures}
    spread = rounding_spread(compute, y, u)
    assert_paths_agree(figures, {key: expected[key] for key in figures}, spread, len(y),
                       JOINTS[k])


def test_each_joint_equals_its_single_plant_estimate_in_any_order(executor, ros_context):
    messages, y, u = joint_messages(800, seed=3)
    node = identifier(executor, ros_context, publish_period=5)
    recorder = Recorder(ros_context, JOINTS)
    executor.add_node(recorder.node)
    wait_for(executor, node, recorder)
    drive(executor, ros_context, node, messages)
    replayed, expected = replay(messages, publish_period=5)
    total = sum(len(estimates) for estimates in expected.values())
    assert spin_until(executor, lambda: recorder.count() >= total)
    # each topic arrives on its own: wait for every one of them
    assert spin_until(executor, lambda: sum(map(len, recorder.noise.values())) >= total)
    std_total = sum(len(std) for std in replayed.published_std.values())
    assert spin_until(executor, lambda: sum(map(len, recorder.std.values())) >= std_total)
    assert node.joint_state.estimates_published == total
    assert recorder.labels['parameters'] == 'a1,a2,b1_1,b1_2'
    assert recorder.labels['noise_variance'] == 'sigma2'
    assert recorder.labels['parameter_std'] == 'a1,a2,b1_1,b1_2'
    for k, joint in enumerate(JOINTS):
        # the node is the replay, bit for bit (same machine, same run)
        np.testing.assert_array_equal(np.array(recorder.parameters[joint]),
                                      np.array(expected[joint]))
        # a standard deviation from the first block of 64 steps on, with the parameters' names
        assert len(recorder.std[joint]) > 100
        np.testing.assert_array_equal(np.array(recorder.std[joint]),
                                      np.array(replayed.published_std[joint]))
        # latched changes only: starts False, alternates, ends as the estimator ends
        flags = recorder.valid[joint]
        assert flags[0] is False and all(a != b for a, b in zip(flags, flags[1:]))
        assert flags[-1] == bool(node.feeder.valid[k])
        assert len(recorder.parameters[joint]) > 100
        assert_joint_follows_its_single_plant(
            {'parameters': np.array(recorder.parameters[joint]),
             'noise': np.array(recorder.noise[joint])}, y, u, k, publish_period=5)
    assert not any(counts.any() for counts in node.feeder.counters().values())


def test_the_joint_bound_catches_one_changed_sample():
    # the offline JointFeeder path of the test above, with one velocity of joint 2 changed
    # by a ten-thousandth: the comparison with joint 2's single-plant run must fail
    messages, y, u = joint_messages(800, seed=3)
    changed = list(messages[400].name).index(JOINTS[2])
    messages[400].velocity[changed] *= 1.0 + 1e-4
    _, published = replay(messages, publish_period=5)
    assert_joint_follows_its_single_plant({'parameters': np.array(published[JOINTS[1]])},
                                          y, u, 1, publish_period=5)
    with pytest.raises(AssertionError, match='joint_3 parameters: the paths differ by'):
        assert_joint_follows_its_single_plant({'parameters': np.array(published[JOINTS[2]])},
                                              y, u, 2, publish_period=5)


def test_a_missing_joint_and_a_nan_touch_only_their_joint(executor, ros_context):
    # joint_3 is absent from every 40th message, joint_2 has one NaN velocity
    messages, y, u = joint_messages(600, seed=4, leave_out=(2, 40), nan_at=(1, 300))
    node = identifier(executor, ros_context, publish_period=10)
    node.joint_state.diagnostics.timer.cancel()  # one period: from start-up to the end
    recorder = Recorder(ros_context, JOINTS)
    executor.add_node(recorder.node)
    wait_for(executor, node, recorder)
    drive(executor, ros_context, node, messages)
    counts = node.feeder.counters()
    np.testing.assert_array_equal(counts['missing'], [0, 0, 15, 0, 0])
    np.testing.assert_array_equal(counts['nonfinite'], [0, 1, 0, 0, 0])
    estimator = node.feeder.estimator
    # every joint is its own single-plant run: the others as if nothing had happened
    with_nan = y.copy()
    with_nan[300, 1] = np.nan
    present = np.arange(600) % 40 != 0
    singles = {}
    for k in range(len(JOINTS)):
        single, _ = single_plant(with_nan, u, k, present if k == 2 else None)
        singles[JOINTS[k]] = single
        assert_joint_follows_its_single_plant({'final theta': estimator.theta[k]}, with_nan, u, k,
                                              present if k == 2 else None)
        assert estimator.samples[k] == single.estimator.samples
    assert estimator.samples.tolist()[:2] == [598, 595]  # the NaN, then n = 2 to refill
    # the period's statuses: the two joints warn, the others do not
    node.joint_state.diagnostics.publish()
    assert spin_until(executor, lambda: recorder.diagnostics)
    statuses = {status.name: status for status in recorder.diagnostics[-1].status}
    assert len(statuses) == 1 + len(JOINTS)
    node_status = statuses['/bcid_identifier: identifier']
    values = {pair.key: pair.value for pair in node_status.values}
    assert values['joints'] == '5' and values['joint samples missing'] == '15'
    assert values['bad samples: NaN or Inf'] == '1'
    assert node_status.level == b'\x01' and 'joint_3' in node_status.message
    for joint in JOINTS:
        status = statuses[f'/bcid_identifier: joint {joint}']
        values = {pair.key: pair.value for pair in status.values}
        if joint == 'joint_2':
            assert status.level == b'\x01' and 'NaN or Inf' in status.message
            assert values['bad samples: NaN or Inf'] == '1'
        elif joint == 'joint_3':
            assert status.level == b'\x01' and 'missing from the message' in status.message
            assert values['missing from the message'] == '15'
        else:
            # an estimator flag of the start-up may warn, never what happened elsewhere
            assert 'missing' not in status.message and 'NaN' not in status.message
            assert status.level != b'\x02', status.message
            # valid as the joint's own single-plant run (its residual tests need their window)
            assert values['valid'] == str(singles[joint].estimator.valid).lower()
            assert values['samples used'] == '600'
            assert 'missing from the message' not in values  # a counter shows once not zero


@pytest.mark.parametrize('values,match', [
    ({'joints': ['joint_1', '2nd']}, r"'joints' must hold names made of letters, digits and "
                                     r"underscores.*got \['2nd'\]"),
    ({'joints': ['arm/elbow']}, r"got \['arm/elbow'\]"),
    ({'joints': ['a', 'a']}, r"'joints' must hold unique names"),
    ({'joints': None}, r"'joints' must list at least one joint name"),  # not set
    ({'estimator': 'bciv'}, r"'estimator' must be one of rls, bcrls with input_mode: joint_state"),
])
def test_bad_joint_state_parameters_are_refused_at_start_up(ros_context, values, match):
    settings = dict({'input_mode': 'joint_state', 'joints': JOINTS}, **values)
    settings = {name: value for name, value in settings.items() if value is not None}
    with pytest.raises(ValueError, match=match):
        IdentifierNode(context=ros_context, parameter_overrides=overrides(settings))


def test_simulator_joints_feed_the_identifier(executor, ros_context):
    joints, samples, seed = ['hip', 'knee', 'ankle'], 1500, 6
    node = identifier(executor, ros_context, joints=joints, publish_period=10)
    simulator = SimulatorNode(context=ros_context, parameter_overrides=overrides({
        'scenario': 'joints', 'num_joints': 3, 'joints': joints, 'seed': seed,
        'num_samples': samples, 'rate_hz': 250.0, 'start_delay': 0.0,
        'wait_for_subscribers': 1}))
    truths = {}
    listener = rclpy.create_node('truth_listener', context=ros_context)
    for joint in joints:
        listener.create_subscription(
            Float64MultiArray, f'/bcid_simulator/{joint}/true_parameters',
            lambda message, joint=joint: truths.__setitem__(joint, np.array(message.data)),
            RECORDER_QOS)
    for each in (simulator, listener):
        executor.add_node(each)
    assert spin_until(executor, lambda: simulator.done, timeout=samples / 250 + 30)
    adapter = node.joint_state
    assert spin_until(executor, lambda: adapter.messages + adapter.counters['lost'] >= samples
                      and len(truths) == 3, timeout=20)
    assert adapter.counters['lost'] == 0, 'messages lost in transport; the machine is slow'
    scenario = make_scenario('joints', num_joints=3, seed=seed)
    y, u = scenario.simulate(samples, seed)
    batched = make_batched_estimator('bcrls', 3, order=2)
    for t in range(samples):
        batched.update(y[t], u[t])
    # one code path: every message holds every joint (a full present mask is the default
    # path) and the same samples, in the same order: the same bits
    np.testing.assert_array_equal(node.feeder.estimator.theta, batched.theta)
    for k, joint in enumerate(joints):
        np.testing.assert_array_equal(truths[joint], scenario.parameters[k])
        # a guard on the data path, not on the estimator: 1500 samples at noise std
        # <= 0.2 leave delta of a few per cent; a wrong field or joint gives about 1
        delta = np.linalg.norm(batched.theta[k] - truths[joint]) / np.linalg.norm(truths[joint])
        assert delta < 0.2, (joint, delta)


def test_live_parameters_and_reset_apply_to_every_joint(executor, ros_context):
    from std_srvs.srv import Trigger

    node = identifier(executor, ros_context, publish_period=5)
    messages, _, _ = joint_messages(40, seed=7)
    for message in messages[:20]:
        node.joint_state.on_joint_state(message, {})  # the callback, without transport
    assert node.feeder.estimator.ready.all()
    results = node.set_parameters([Parameter('publish_period', value=3),
                                   Parameter('forgetting_factor', value=0.99)])
    assert all(result.successful for result in results)
    assert node.feeder.publish_period == 3
    assert node.feeder.estimator.forgetting_factor == 0.99
    refused = node.set_parameters([Parameter('forgetting_factor', value=1.5)])[0]
    assert not refused.successful and node.feeder.estimator.forgetting_factor == 0.99
    published = node.joint_state.estimates_published
    for message in messages[20:23]:
        node.joint_state.on_joint_state(message, {})
    assert node.joint_state.estimates_published == published + len(JOINTS)
    response = node.joint_state.on_reset(Trigger.Request(), Trigger.Response())
    assert response.success and 'estimators of 5 joints reset' in response.message
    assert not node.feeder.valid.any()
    assert node.feeder.estimator.samples.sum() == 0
