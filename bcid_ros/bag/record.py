"""
``bcid record``: a minimal rosbag2 MCAP recorder over rclpy.

Each requested topic is subscribed as soon as a publisher of it appears (the
graph is polled every 0.1 s), with a QoS that every publisher can serve
(:func:`bcid_ros.bag.rosqos.subscriber_profile`): latched topics are
received from their history, volatile ones with KEEP_ALL so that a reliable
publisher is slowed down rather than a message dropped. Messages are stored
as received (serialised CDR, never decoded) with rmw's reception time stamp,
and the publishers' offered QoS goes into the bag.

SIGINT or SIGTERM stops the recording: the messages already received (also
those still queued in the subscriptions) are written, then the bag is
closed, so nothing received is lost. Against SIGKILL and crashes, the open
chunk is closed and handed to the operating system every :data:`FLUSH_PERIOD`
s, so a killed recording keeps what was received until then; ``bcid replay``
and ``info`` read it without its footer, ``bcid reindex`` repairs it
(docs/guarantees.md).
"""

from __future__ import annotations

import functools
import os
from pathlib import Path
import signal
import sys
import time
from typing import Any, Sequence

import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

from bcid_ros.bag.rosqos import message_class, subscriber_profile, to_bag_qos
from bcid_ros.bag.writer import BagWriter
from bcid_ros.errors import BcidError

#: Seconds between looks at the ROS graph for the topics not yet subscribed.
DISCOVERY_PERIOD = 0.1

#: Seconds between chunk flushes: a kill loses at most about this much (plus what is queued).
FLUSH_PERIOD = 0.5

#: Longest time (s) spent writing queued messages after the stop request.
DRAIN_LIMIT = 5.0


def absolute_topic(name: str) -> str:
    """Return ``name`` resolved in the root namespace (``samples`` -> ``/samples``)."""
    name = name.strip()
    if not name or name.startswith('~'):
        raise BcidError(f'cannot record topic {name!r}: give a name such as /samples')
    return name if name.startswith('/') else '/' + name


class Recorder:
    """
    Subscribe to topics when they appear and write what arrives to a bag.

    Parameters
    ----------
    node : rclpy.node.Node
        The node that owns the subscriptions.
    writer : BagWriter
        The open bag.
    topics : sequence of str
        Absolute topic names.

    """

    def __init__(self, node: Node, writer: BagWriter, topics: Sequence[str]) -> None:
        self.node = node
        self.writer = writer
        self.pending = list(dict.fromkeys(topics))
        self.subscriptions: dict[str, Any] = {}
        self.counts = {topic: 0 for topic in self.pending}
        self.discovery_timer = node.create_timer(DISCOVERY_PERIOD, self.discover)
        self.flush_timer = node.create_timer(FLUSH_PERIOD, writer.flush)
        self.discover()

    def discover(self) -> None:
        """Subscribe to every pending topic that now has a publisher."""
        for topic in list(self.pending):
            publishers = self.node.get_publishers_info_by_topic(topic)
            if not publishers:
                continue
            self.pending.remove(topic)
            types = sorted({info.topic_type for info in publishers})
            if len(types) > 1:
                print(f'bcid record: {topic} is published with types {", ".join(types)}; '
                      f'recording {types[0]}', file=sys.stderr)
            offered = [to_bag_qos(info.qos_profile) for info in publishers
                       if info.topic_type == types[0]]
            try:
                cls = message_class(types[0])
                self.writer.add_topic(topic, types[0], offered)
            except BcidError as error:
                print(f'bcid record: skipping {topic}: {error}', file=sys.stderr)
                continue
            self.subscriptions[topic] = self.node.create_subscription(
                cls, topic, functools.partial(self.on_message, topic),
                subscriber_profile(offered), raw=True)
        if not self.pending:
            self.discovery_timer.cancel()

    def on_message(self, topic: str, data: bytes, info: Any) -> None:
        """Write one serialised message with its reception time."""
        stamp = int(info.get('received_timestamp', 0)) if isinstance(info, dict) else 0
        if stamp <= 0:
            stamp = time.time_ns()
        self.writer.write(topic, stamp, data)
        self.counts[topic] += 1

    @property
    def total(self) -> int:
        """Return the number of messages written so far."""
        return sum(self.counts.values())


def record_bag(out: str | Path, topics: Sequence[str], duration: float = 0.0,
               ros_args: Sequence[str] | None = None) -> dict[str, int]:
    """
    Record ``topics`` into a new bag at ``out`` until SIGINT/SIGTERM or ``duration``.

    Parameters
    ----------
    out : str or pathlib.Path
        The bag directory to create.
    topics : sequence of str
        Topic names (relative names are taken in the root namespace).
    duration : float
        Seconds to record; 0 records until SIGINT or SIGTERM.
    ros_args : sequence of str, optional
        Extra ``--ros-args`` for the recorder node.

    Returns
    -------
    dict
        Messages written per topic.

    Raises
    ------
    BcidError
        If ``out`` exists or a topic name is not usable.

    """
    if duration < 0:
        raise BcidError(f'--duration must be >= 0, got {duration}')
    names = [absolute_topic(t) for t in topics]
    stop = {'requested': False}

    def request_stop(signum: int, frame: Any) -> None:
        stop['requested'] = True

    previous = {sig: signal.signal(sig, request_stop) for sig in (signal.SIGINT, signal.SIGTERM)}
    writer = BagWriter(out)
    context = Context()
    try:
        rclpy.init(args=['--ros-args', *(ros_args or [])], context=context,
                   signal_handler_options=SignalHandlerOptions.NO)
        node = Node(f'bcid_recorder_{os.getpid()}', context=context)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        try:
            recorder = Recorder(node, writer, names)
            deadline = time.monotonic() + duration if duration > 0 else float('inf')
            while not stop['requested'] and time.monotonic() < deadline:
                executor.spin_once(timeout_sec=0.05)
            # Write what has arrived but not been taken yet: spin until three
            # consecutive rounds bring nothing new (or DRAIN_LIMIT seconds, if
            # publishers keep sending).
            quiet = 0
            drain_end = time.monotonic() + DRAIN_LIMIT
            while quiet < 3 and time.monotonic() < drain_end:
                before = recorder.total
                executor.spin_once(timeout_sec=0.01)
                quiet = quiet + 1 if recorder.total == before else 0
            counts = dict(recorder.counts)
        finally:
            executor.shutdown()
            node.destroy_node()
    finally:
        writer.close()
        context.try_shutdown()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return counts


__all__ = ['Recorder', 'absolute_topic', 'record_bag']
