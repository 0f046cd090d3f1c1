"""
The identifier's sample subscriptions on rclpy: QoS overrides, incompatible QoS, staleness.

Every sample subscription (``samples``, ``input``, ``output``,
``joint_states``) is made by :func:`subscribe_samples`: reliable, volatile,
depth 1000 by default, with ROS 2's standard override parameters
``qos_overrides./<topic>.subscription.{reliability,durability,history,depth}``
(read-only, read at start-up), so that a best-effort sensor publisher can
connect. A publisher whose QoS does not match is reported by
:class:`IncompatibleQoS` in the log and on ``/diagnostics`` by topic name.
:class:`StalenessWatch` turns ``~/valid`` false when no sample has come for
``stale_after`` seconds (the rule is :class:`bcid_ros.identifier.staleness.Staleness`).
"""

from __future__ import annotations

from typing import Any, Callable

from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.node import Node
from rclpy.qos import qos_policy_name_from_kind

from bcid_ros.identifier.interface import DiagnosticKey as Key
from bcid_ros.identifier.staleness import Staleness
from bcid_ros.nodes.common import (create_draining_subscription, samples_qos,
                                   samples_qos_overrides)
from bcid_ros.nodes.diagnostics import Status, WARN

#: Seconds between two looks at the age of the last sample.
STALENESS_CHECK_PERIOD = 0.1


class IncompatibleQoS:
    """
    Publishers that could not connect to a sample subscription for their QoS.

    A diagnostics task: while such a publisher was seen and no message came
    since, the status warns with the topic, the policy and the parameter
    that fixes it.

    Parameters
    ----------
    node : rclpy.node.Node
        The identifier node (its logger).
    messages : callable
        Returns the messages taken so far (the node's total).

    """

    def __init__(self, node: Node, messages: Callable[[], int]) -> None:
        self._node = node
        self._messages = messages
        #: topic -> (publishers refused so far, last policy, messages when last refused)
        self.refused: dict[str, tuple[int, str, int]] = {}

    def callbacks(self, topic: str) -> SubscriptionEventCallbacks:
        """Return the event callbacks of the subscription to ``topic`` (resolved name)."""
        return SubscriptionEventCallbacks(
            incompatible_qos=lambda info: self.on_incompatible(topic, info))

    def on_incompatible(self, topic: str, info: Any) -> None:
        """Count a refused publisher and say how to let it in."""
        policy = qos_policy_name_from_kind(info.last_policy_kind).lower()
        self.refused[topic] = (info.total_count, policy, self._messages())
        self._node.get_logger().warning(
            f'a publisher on {topic} offers a QoS incompatible with this subscription '
            f'({policy}) and cannot connect; set the parameter '
            f'qos_overrides.{topic}.subscription.{policy} to match it (e.g. best_effort '
            'for a sensor-data publisher)')

    def __call__(self, status: Status) -> None:
        """Add the refused publishers per topic; warn while no message came since."""
        for topic, (count, policy, messages) in sorted(self.refused.items()):
            status.add(Key.INCOMPATIBLE_QOS + topic, f'{count} publisher(s), {policy}')
            if self._messages() == messages:
                status.merge_summary(WARN, f'incompatible QoS on {topic} ({policy}): set '
                                     f'qos_overrides.{topic}.subscription.{policy}')


def subscribe_samples(node: Node, message_type: type, topic: str,
                      callback: Callable[[Any, Any], None], qos_events: IncompatibleQoS,
                      draining: bool = True) -> Any:
    """
    Subscribe to a sample topic with the QoS override parameters and the QoS events.

    ``draining`` takes the queued messages in one callback
    (:func:`~bcid_ros.nodes.common.create_draining_subscription`);
    otherwise ``callback(message, info)`` is called per message.
    """
    resolved = node.resolve_topic_name(topic)
    options = {'event_callbacks': qos_events.callbacks(resolved),
               'qos_overriding_options': samples_qos_overrides()}
    if draining:
        return create_draining_subscription(node, message_type, topic, callback,
                                            samples_qos(), **options)
    return node.create_subscription(message_type, topic, callback, samples_qos(), **options)


class StalenessWatch:
    """
    Turn the estimate stale when no sample came for ``stale_after`` seconds; a diagnostics task.

    Parameters
    ----------
    node : rclpy.node.Node
        The identifier node: its clock and timers.
    stale_after : float
        The parameter (0 automatic, negative never).
    on_change : callable
        Called when the estimate turns stale or fresh again (publish ``~/valid``).

    Attributes
    ----------
    reason : str
        ``'no samples for T s'`` while stale, else ``''``.

    """

    def __init__(self, node: Node, stale_after: float, on_change: Callable[[], None]) -> None:
        self._node = node
        self._rule = Staleness(stale_after)
        self._on_change = on_change
        self.reason = ''
        self.timer = None

    def now(self) -> float:
        """Return the node clock's time in seconds."""
        return self._node.get_clock().now().nanoseconds * 1e-9

    def start(self) -> None:
        """Start looking at the age of the last sample (on the node's clock), counted from now."""
        self._rule.restart(self.now())
        if self.timer is None:
            self.timer = self._node.create_timer(STALENESS_CHECK_PERIOD, self.check)
        else:
            self.timer.reset()

    def stop(self) -> None:
        """Stop looking (a deactivated node takes no samples)."""
        if self.timer is not None:
            self.timer.cancel()

    def arrived(self, now: float) -> None:
        """Record samples at ``now`` (node clock, s); an estimate that was stale is fresh again."""
        self._rule.arrived(now)
        if self.reason:
            self.reason = ''
            self._on_change()

    def check(self) -> None:
        """Turn the estimate stale if the last sample is older than the limit."""
        reason = self._rule.reason(self.now())
        if bool(reason) != bool(self.reason):
            self.reason = reason
            self._on_change()
        elif reason:
            self.reason = reason  # the age keeps growing

    def __call__(self, status: Status) -> None:
        """Add the age of the last sample and the limit; warn while stale."""
        now = self.now()
        age, limit = self._rule.age(now), self._rule.limit()
        status.add(Key.LAST_SAMPLE_AGE, 'n/a' if age is None else age)
        status.add(Key.STALE_AFTER, 'never' if limit is None else limit)
        if self.reason:
            status.merge_summary(WARN, f'estimate not valid: {self.reason}')


__all__ = ['IncompatibleQoS', 'STALENESS_CHECK_PERIOD', 'StalenessWatch', 'subscribe_samples']
