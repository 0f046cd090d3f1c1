"""
The demos' monitors take the samples only once they know the identifier (AfterDiscovery).

The simulator starts publishing once its samples have two subscribers, the identifier and
the demo's monitor. A CI run of the payload-change demo saw the monitor discover the
identifier 1-2 s after the samples began, after the plant change: ``~/valid``, latched,
reached it with its last value only, and its turn to false at the change was never seen.
The monitor now subscribes to the samples once the identifier's ``~/valid`` publisher is
discovered, so the simulator cannot start before.
"""

import pytest

from bcid_ros.identifier import interface
from bcid_ros.nodes.demo import Monitor
from bcid_ros.nodes.demo_graph import AfterDiscovery
from bcid_ros.nodes.demo_loop import LoopMonitor


class FakeNode:
    """Records the topics subscribed; its graph knows the publishers in ``publishers``."""

    def __init__(self):
        self.publishers = set()
        self.topics = []

    def count_publishers(self, topic):
        return int(topic in self.publishers)

    def create_subscription(self, message_type, topic, callback, qos):
        self.topics.append(topic)
        return topic


def test_after_discovery_subscribes_once_the_publisher_is_known():
    node = FakeNode()
    later = AfterDiscovery(node, '/a/valid',
                           lambda: node.create_subscription(None, '/samples', None, None))
    assert not later.poll() and node.topics == []
    assert '/a/valid' in later.note()
    node.publishers.add('/a/valid')
    assert later.poll() and later.poll() and node.topics == ['/samples']  # created once
    assert later.note() == ''


@pytest.mark.parametrize('make', [
    lambda node: Monitor(node, interface.IDENTIFIER_NODE, interface.SIMULATOR_NODE),
    lambda node: LoopMonitor(node, None),  # (the record is only written to)
], ids=['demo', 'adaptive_loop'])
def test_the_monitors_take_the_samples_only_after_the_identifiers_valid(make):
    node = FakeNode()
    monitor = make(node)
    valid = interface.resolve(interface.VALID, interface.IDENTIFIER_NODE)
    assert valid in node.topics  # latched: subscribed at once
    assert not any(topic.endswith('/' + interface.SAMPLES) for topic in node.topics)
    monitor.samples_subscription.poll()
    assert not any(topic.endswith('/' + interface.SAMPLES) for topic in node.topics)
    node.publishers.add(valid)
    monitor.samples_subscription.poll()
    assert [topic for topic in node.topics if topic.endswith('/' + interface.SAMPLES)]
