"""
identifier_node publishes ~/parameter_std and ~/parameter_covariance, and replay's std is the same.

The samples of a simulated bag are published to an in-process identifier;
its last std must equal the std that ``bcid replay`` computes on the bag,
bit for bit (same machine, same run), and the messages must carry the
documented layout.
"""

from pathlib import Path

import numpy as np
import pytest

from conftest import spin_until

rclpy = pytest.importorskip('rclpy')

from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from std_msgs.msg import Float64MultiArray  # noqa: E402

from bcid_ros.bag.reader import BagReader  # noqa: E402
from bcid_ros.bag.replay import replay, SAMPLES_TOPIC  # noqa: E402
from bcid_ros.bag.simulate import simulate_bag  # noqa: E402
from bcid_ros.estimators.lagged import BLOCK as HAC_BLOCK  # noqa: E402
from bcid_ros.estimators.rules import GATE_WARMUP  # noqa: E402
from bcid_ros.identifier.layouts import decode_samples  # noqa: E402
from bcid_ros.identifier.parameters import load_yaml_parameters  # noqa: E402
from bcid_ros.nodes.common import LATCHED_QOS, SAMPLES_QOS  # noqa: E402
from bcid_ros.nodes.identifier_node import IdentifierNode  # noqa: E402
from bcid_ros.nodes.messages import samples_message  # noqa: E402

pytestmark = pytest.mark.ros

CONFIG = Path(__file__).resolve().parents[2] / 'config' / 'ding_miso.yaml'
DEEP = QoSProfile(depth=10000, reliability=ReliabilityPolicy.RELIABLE,
                  durability=DurabilityPolicy.TRANSIENT_LOCAL)
SAMPLES = 600


@pytest.mark.parametrize('estimator', ['rls', 'bcrls'])
def test_node_publishes_std_and_covariance_equal_to_replay(estimator, ros_context, executor,
                                                           tmp_path):
    bag = simulate_bag('ding_miso', SAMPLES, 7, 1000.0, tmp_path / 'bag')
    parameters = dict(load_yaml_parameters(CONFIG, 'bcid_identifier'), estimator=estimator)
    offline = replay(bag, parameters)
    identifier = IdentifierNode(context=ros_context, parameter_overrides=[
        Parameter(name, value=value) for name, value in parameters.items()])
    feeder = rclpy.create_node('feeder', context=ros_context)
    executor.add_node(identifier)
    executor.add_node(feeder)
    received = {'parameters': [], 'parameter_std': [], 'parameter_covariance': []}
    for topic, store in received.items():
        feeder.create_subscription(Float64MultiArray, f'/bcid_identifier/{topic}',
                                   store.append, DEEP)
    publisher = feeder.create_publisher(Float64MultiArray, '/samples', SAMPLES_QOS)
    assert spin_until(executor, lambda: publisher.get_subscription_count() >= 1 and all(
        feeder.count_publishers(f'/bcid_identifier/{topic}') for topic in received) and all(
        identifier.count_subscribers(f'/bcid_identifier/{topic}') for topic in received))

    rows = [decode_samples(message, 2)
            for _, message in BagReader(bag).float64_multi_arrays(SAMPLES_TOPIC)]
    for start in range(0, len(rows), 100):
        for row in rows[start:start + 100]:
            publisher.publish(samples_message(row))
        target = min(start + 100, len(rows))
        assert spin_until(executor, lambda: identifier.feeder.used >= target)
    published = identifier.estimates_published
    # the last std is the replay's (rls has none at its first estimate, bcrls none before
    # its first block of moments: the counts of std and covariance are checked below)
    assert spin_until(executor, lambda: len(received['parameters']) >= published and (
        received['parameter_std'] and np.array_equal(received['parameter_std'][-1].data,
                                                     offline.std))), (
        published, {topic: len(store) for topic, store in received.items()})
    assert spin_until(executor, lambda: len(received['parameter_covariance']) == len(
        received['parameter_std']))

    names = identifier.estimator.parameter_names
    label, p = ','.join(names), len(names)
    std, covariance = received['parameter_std'][-1], received['parameter_covariance'][-1]
    assert [(d.label, d.size, d.stride) for d in std.layout.dim] == [(label, p, p)]
    assert [(d.label, d.size, d.stride) for d in covariance.layout.dim] == [
        (label, p, p * p), (label, p, p)]
    matrix = np.array(covariance.data).reshape(p, p)
    np.testing.assert_array_equal(matrix, matrix.T)
    np.testing.assert_array_equal(np.array(std.data), np.sqrt(np.diag(matrix)))
    # published with every estimate, and the last one is the replay's, bit for bit
    # the first update with a covariance: rls's HAC after a block of scores recorded from
    # the gate's warm-up (10 p updates) on; bcrls's sandwich after its first moment block
    first = {'rls': GATE_WARMUP * 6 + HAC_BLOCK - 1, 'bcrls': 64}[estimator]
    assert len(received['parameters']) == published == SAMPLES - 2 - 6 + 1
    assert len(received['parameter_std']) == published - (first - 6)
    np.testing.assert_array_equal(np.array(received['parameters'][-1].data), offline.theta)
    np.testing.assert_array_equal(np.array(std.data), offline.std)
    assert offline.summary()['std'] == dict(zip(names, offline.std.tolist()))

    # a late joiner gets the latest std and covariance at once (transient_local, depth 1)
    late = {}
    for topic in ('parameter_std', 'parameter_covariance'):
        feeder.create_subscription(Float64MultiArray, f'/bcid_identifier/{topic}',
                                   lambda message, topic=topic: late.setdefault(topic, message),
                                   LATCHED_QOS)
    assert spin_until(executor, lambda: len(late) == 2)
    np.testing.assert_array_equal(np.array(late['parameter_std'].data), offline.std)
    np.testing.assert_array_equal(np.array(late['parameter_covariance'].data), matrix.ravel())


def test_uncertainty_is_computed_only_while_subscribed(ros_context, executor, tmp_path):
    bag = simulate_bag('ding_miso', 400, 8, 1000.0, tmp_path / 'bag')
    parameters = dict(load_yaml_parameters(CONFIG, 'bcid_identifier'), estimator='bcrls')
    identifier = IdentifierNode(context=ros_context, parameter_overrides=[
        Parameter(name, value=value) for name, value in parameters.items()])
    estimator = identifier.estimator
    # the node's reads of the covariance; within an update the estimator reads it itself
    # (bcrls's residual tests every block of 128 samples, the simulation check when it runs:
    # docs/trust.md), which is its own cost, not the node's
    reads, updating = [], []
    computed = estimator._parameter_covariance

    def counted_covariance():
        if not updating:
            reads.append(1)
        return computed()

    def marked(update):
        def marked_update(*args, **kwargs):
            updating.append(1)
            try:
                return update(*args, **kwargs)
            finally:
                updating.pop()
        return marked_update

    estimator._parameter_covariance = counted_covariance
    estimator.update = marked(estimator.update)
    estimator.update_block = marked(estimator.update_block)
    feeder = rclpy.create_node('feeder', context=ros_context)
    executor.add_node(identifier)
    executor.add_node(feeder)
    estimates, std = [], []
    feeder.create_subscription(Float64MultiArray, '/bcid_identifier/parameters',
                               estimates.append, DEEP)
    publisher = feeder.create_publisher(Float64MultiArray, '/samples', SAMPLES_QOS)
    assert spin_until(executor, lambda: publisher.get_subscription_count() >= 1
                      and identifier.count_subscribers('/bcid_identifier/parameters'))
    rows = [decode_samples(message, 2)
            for _, message in BagReader(bag).float64_multi_arrays(SAMPLES_TOPIC)]

    def feed(part):
        for row in part:
            publisher.publish(samples_message(row))
        target = identifier.feeder.used + len(part)
        assert spin_until(executor, lambda: identifier.feeder.used >= target)

    feed(rows[:200])
    # estimates went out, past bcrls's first block of moments, and no one asked for a std
    assert spin_until(executor, lambda: len(estimates) >= 100)
    assert estimator.parameter_covariance is not None and len(reads) == 1
    feeder.create_subscription(Float64MultiArray, '/bcid_identifier/parameter_std',
                               std.append, DEEP)
    assert spin_until(executor, lambda: identifier.count_subscribers(
        '/bcid_identifier/parameter_std') >= 1)
    feed(rows[200:])
    assert spin_until(executor, lambda: len(std) >= 150)
    assert len(reads) > 150
