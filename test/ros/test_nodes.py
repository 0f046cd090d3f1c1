"""
Node tests with in-process executors: end to end, frames, separate topics, reset, late joiners.

Every test gets its own rclpy Context on its own domain (conftest.py). The
identifier's estimates are compared with the estimator run offline over the
same samples: the node must do no numerics of its own, so they are equal to
1e-12.
"""

from pathlib import Path
import time

import numpy as np
import pytest

from conftest import spin_until

rclpy = pytest.importorskip('rclpy')

from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from std_msgs.msg import Bool, Float64MultiArray  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from bcid_ros.identifier.parameters import (  # noqa: E402
    estimator_from_parameters, load_yaml_parameters, SIMULATOR_PARAMETERS)
from bcid_ros.nodes.common import LATCHED_QOS  # noqa: E402
from bcid_ros.nodes.identifier_node import IdentifierNode  # noqa: E402
from bcid_ros.nodes.simulator_node import SimulatorNode  # noqa: E402
from bcid_ros.simulation import make_scenario  # noqa: E402

pytestmark = pytest.mark.ros

CONFIG = Path(__file__).resolve().parents[2] / 'config'


def overrides(values):
    """Return ROS parameter overrides from a dict."""
    return [Parameter(name, value=value) for name, value in values.items()]


def config(scenario, node='bcid_identifier'):
    """Return the parameters of one node from the scenario's config file."""
    declared = ({spec.name for spec in SIMULATOR_PARAMETERS} if node == 'bcid_simulator'
                else None)
    return load_yaml_parameters(CONFIG / f'{scenario}.yaml', node, declared)


#: Like the estimates' latched QoS, but deep enough to keep every message.
RECORDER_QOS = QoSProfile(depth=10000, reliability=ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.TRANSIENT_LOCAL)


class Recorder:
    """Records every message of the identifier's estimate topics on a node of its own."""

    def __init__(self, context, prefix='/bcid_identifier', qos=RECORDER_QOS):
        self.node = rclpy.create_node('recorder', context=context)
        self.parameters = []
        self.uncompensated = []
        self.noise = []
        self.labels = {}
        self.valid = []
        self.node.create_subscription(Bool, f'{prefix}/valid',
                                      lambda message: self.valid.append(message.data), qos)
        for topic, store in (('parameters', self.parameters),
                             ('parameters_uncompensated', self.uncompensated),
                             ('noise_variance', self.noise)):
            self.node.create_subscription(
                Float64MultiArray, f'{prefix}/{topic}',
                lambda message, store=store, topic=topic: self._record(topic, store, message),
                qos)

    def _record(self, topic, store, message):
        self.labels[topic] = message.layout.dim[0].label
        store.append(np.array(message.data))


def run_pair(executor, context, scenario, samples, identifier_values=None, simulator_values=None):
    """Run simulator -> identifier in one executor until all samples are used; return both."""
    identifier_settings = dict(config(scenario), **(identifier_values or {}))
    identifier = IdentifierNode(context=context,
                                parameter_overrides=overrides(identifier_settings))
    simulator_settings = dict(config(scenario, 'bcid_simulator'), num_samples=samples,
                              rate_hz=1000.0, start_delay=0.0, wait_for_subscribers=1)
    simulator_settings.update(simulator_values or {})
    simulator = SimulatorNode(context=context, parameter_overrides=overrides(simulator_settings))
    executor.add_node(identifier)
    executor.add_node(simulator)
    duration = samples / simulator_settings['rate_hz']
    assert spin_until(executor, lambda: simulator.done, timeout=duration + 20)
    assert spin_until(executor, lambda: identifier.feeder.used + identifier.counters['lost']
                      >= samples, timeout=10)
    assert identifier.counters['lost'] == 0, 'messages lost in transport; the machine is slow'
    return identifier, simulator


def offline(scenario, samples, values=None):
    """Return the estimator run offline over the simulator's samples (seed from the config)."""
    settings = dict(config(scenario), **(values or {}))
    seed = config(scenario, 'bcid_simulator').get('seed', 0)
    y, u = make_scenario(scenario).simulate(samples, seed)
    estimator = estimator_from_parameters(settings)
    estimator.run(y, u)
    return estimator


# Reduced sizes. The bounds on delta guard the configs (a wrong order or
# estimator gives delta of the order of the LS bias: 7.5 % for Ding, see
# docs/reproduction_ding.md); the node's own correctness is the exact equality to the
# offline run, which is the strong check.
SCENARIOS = [
    ('ding_miso', 2000, 0.03),
    ('ding_miso_nonstationary', 2000, 0.03),
    ('ikenoue_colored', 6000, 0.15),
    ('ikenoue_white_input', 6000, 0.15),
    # cl_bcls: over six seeds at N = 3000 the offline delta was 0.02 to 0.24
    # (seed 0, the config's, is the 0.24), so 0.3 only guards the config.
    ('ikeda_closed_loop', 3000, 0.3),
]


@pytest.mark.slow
@pytest.mark.parametrize('scenario,samples,bound', SCENARIOS, ids=[s[0] for s in SCENARIOS])
def test_end_to_end_equals_offline(ros_context, executor, scenario, samples, bound):
    # Frames of 10 at 3 kHz for the slower, longer bciv runs.
    frame, rate = (10, 3000.0) if scenario.startswith('ikenoue') else (1, 1000.0)
    # Both nodes share one Python thread here; publishing every 10th estimate (five latched
    # topics each) keeps them within 1 kHz on a busy 2-core machine. The check is the final
    # estimate, which the publish period does not change.
    identifier, _ = run_pair(executor, ros_context, scenario, samples,
                             identifier_values={'publish_period': 10},
                             simulator_values={'frame_size': frame, 'rate_hz': rate})
    reference = offline(scenario, samples)
    np.testing.assert_allclose(identifier.estimator.theta, reference.theta, rtol=0, atol=1e-12)
    truth = make_scenario(scenario).truth().parameters
    delta = np.linalg.norm(identifier.estimator.theta - truth) / np.linalg.norm(truth)
    assert delta < bound


def test_frames_late_joiner_and_reset(ros_context, executor):
    samples = 1500
    recorder = Recorder(ros_context)
    executor.add_node(recorder.node)
    identifier, simulator = run_pair(executor, ros_context, 'ding_miso', samples,
                                     simulator_values={'frame_size': 7})
    reference = offline('ding_miso', samples)
    # Frames of 7 give the same estimate as the offline run (and so as single samples).
    np.testing.assert_allclose(identifier.estimator.theta, reference.theta, rtol=0, atol=1e-12)
    assert spin_until(executor, lambda: recorder.parameters
                      and np.array_equal(recorder.parameters[-1], reference.theta), timeout=5)
    assert recorder.labels['parameters'] == 'a1,a2,b1_1,b1_2,b2_1,b2_2'
    assert recorder.labels['noise_variance'] == 'sigma2'
    assert all(np.isfinite(p).all() for p in recorder.parameters + recorder.noise)
    # At most one publication per frame (215 frames), every one received.
    assert len(recorder.parameters) == identifier.estimates_published
    assert samples // 7 - 2 <= identifier.estimates_published <= -(-samples // 7)

    # A late joiner gets the latest estimate at once (transient_local, depth 1).
    late = Recorder(ros_context, qos=LATCHED_QOS)
    executor.add_node(late.node)
    assert spin_until(executor, lambda: late.parameters and late.noise and late.valid,
                      timeout=5)
    # ~/valid went false -> true once, before the first estimate, and is latched.
    assert recorder.valid == [False, True] and late.valid == [True]
    assert len(late.parameters) == 1
    np.testing.assert_array_equal(late.parameters[0], identifier.estimator.theta)
    np.testing.assert_array_equal(late.noise[0], identifier.estimator.noise)

    # ~/reset restarts the estimator from its initial state.
    client = late.node.create_client(Trigger, '/bcid_identifier/reset')
    assert spin_until(executor, client.service_is_ready, timeout=5)
    future = client.call_async(Trigger.Request())
    assert spin_until(executor, future.done, timeout=5)
    assert future.result().success
    assert identifier.estimator.samples == 0 and not identifier.estimator.valid
    assert spin_until(executor, lambda: late.valid[-1:] == [False], timeout=5)


@pytest.mark.parametrize('input_type,output_type,sync', [
    ('float64_multi_array', 'float64', 'arrival'),
    ('joint_state', 'joint_state', 'arrival'),
    ('joint_state', 'joint_state', 'stamp'),
])
def test_separate_topics_equal_combined(ros_context, executor, input_type, output_type, sync):
    samples = 1000
    identifier, _ = run_pair(
        executor, ros_context, 'ding_miso', samples,
        identifier_values={'input_mode': 'separate', 'sync': sync, 'input_type': input_type,
                           'output_type': output_type, 'queue_size': 1000},
        simulator_values={'output_mode': 'separate', 'input_type': input_type,
                          'output_type': output_type})
    assert identifier.feeder.used == samples
    assert sum(identifier.counters.values()) == 0
    np.testing.assert_allclose(identifier.estimator.theta, offline('ding_miso', samples).theta,
                               rtol=0, atol=1e-12)


def test_same_seed_same_data_at_any_rate_and_frame(ros_context, executor):
    # Two simulators, different rates and frame sizes, same seed: identical estimates.
    first, _ = run_pair(executor, ros_context, 'ding_miso', 600,
                        simulator_values={'frame_size': 1})
    for node in list(executor.get_nodes()):
        executor.remove_node(node)
        node.destroy_node()
    second, _ = run_pair(executor, ros_context, 'ding_miso', 600,
                         simulator_values={'frame_size': 13, 'rate_hz': 3000.0})
    np.testing.assert_array_equal(first.estimator.theta, second.estimator.theta)


def test_a_backlog_is_taken_in_one_callback_in_order(ros_context, executor):
    # A node that falls behind pays rclpy's wait set once per backlog, not once per message
    # (nodes/common.py, create_draining_subscription): messages already queued when the
    # samples callback runs are taken in that callback, in order, with their sequence numbers.
    from bcid_ros.nodes.common import SAMPLES_QOS
    from bcid_ros.nodes.messages import samples_message

    identifier = IdentifierNode(context=ros_context,
                                parameter_overrides=overrides(config('ding_miso')))
    executor.add_node(identifier)
    sender = rclpy.create_node('sender', context=ros_context)
    executor.add_node(sender)
    publisher = sender.create_publisher(Float64MultiArray, '/samples', SAMPLES_QOS)
    assert spin_until(executor, lambda: publisher.get_subscription_count() > 0, timeout=10)
    spin_until(executor, lambda: False, timeout=0.3)  # whatever start-up callbacks are ready
    y, u = make_scenario('ding_miso').simulate(200, 5)
    rows = np.column_stack([y, u])
    frames = 40
    for k in range(frames):
        publisher.publish(samples_message(rows[5 * k:5 * (k + 1)]))
    time.sleep(1.0)  # all of them arrive in the subscription's queue
    while identifier.messages == 0:
        executor.spin_once(timeout_sec=1.0)
    # the first callback took more than its own message: all of the backlog within
    # DRAIN_SECONDS (40 frames of bcrls take about that on a slow 2-core machine, where one
    # CI run saw 39 of 40 in the first callback), the rest in the next
    assert identifier.messages > 1
    assert spin_until(executor, lambda: identifier.messages == frames, timeout=10)
    assert identifier.counters['lost'] == 0
    reference = estimator_from_parameters(config('ding_miso'))
    reference.run(y, u)
    np.testing.assert_array_equal(identifier.estimator.theta, reference.theta)


@pytest.mark.parametrize('count', [0, 1, 2, 6, 7, 36])
def test_serialized_estimates_are_rclpy_serialization(count):
    from rclpy.serialization import deserialize_message, serialize_message

    from bcid_ros.nodes.messages import (as_doubles, covariance_message, estimate_message,
                                         SerializedArray)

    names = [f'p{k}' for k in range(max(count, 1))]
    values = np.random.default_rng(count).standard_normal(count) * 1e3
    for message in (estimate_message(names), estimate_message(names[:1] * 3),
                    covariance_message(names[:2])):
        serialized = SerializedArray(message).serialize(values)
        expected = type(message)()
        expected.layout = message.layout
        expected.data = as_doubles(values)
        # the same bytes but the alignment padding, which the serialiser leaves as it finds
        assert len(serialized) == len(serialize_message(expected))
        assert serialized.endswith(values.tobytes())
        decoded = deserialize_message(serialized, type(message))
        assert decoded.layout == message.layout and list(decoded.data) == values.tolist()
