"""
``bcid play``: a minimal rosbag2 MCAP player over rclpy.

Every topic is published with the QoS its recorded publishers offered
(:func:`bcid_ros.bag.rosqos.publisher_profile`), so latched topics such as
the simulator's truth are transient_local again and reach subscribers that
join later. Messages go out as stored (serialised CDR, never decoded).

Timing: message k is published at ``t0 + (t_k - t_first) / rate`` on the
monotonic clock; absolute targets keep errors from accumulating. The
player sleeps until ``SPIN_NS`` before the target and then polls the clock,
which brings the lateness down to microseconds at a small CPU cost. Before
exiting, the player waits until reliable subscribers have acknowledged every
message.

A rate of 0 publishes as fast as possible, and never loses a sample
silently: it waits for a subscriber on every volatile topic, publishes the
reliable ones with KEEP_ALL (so the writer waits for a subscriber that keeps
all, as the identifier does, instead of overwriting what it has not taken),
and reads the identifiers' own counts on ``/diagnostics`` before and after
(:class:`IdentifierCounts`): messages one of them lost make a shortfall,
which the summary names and ``bcid play`` exits 1 on.

``clock`` publishes ``/clock`` (rosgraph_msgs/Clock) from the bag's time,
for nodes with ``use_sim_time``.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
import time
from typing import Any, Sequence

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray
import numpy as np
import rclpy
from rclpy.context import Context
from rclpy.duration import Duration
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from rosgraph_msgs.msg import Clock

from bcid_ros.bag.reader import BagReader
from bcid_ros.bag.rosqos import message_class, publisher_profile
from bcid_ros.errors import BcidError
from bcid_ros.identifier.interface import COUNTERS, DiagnosticKey, DIAGNOSTICS

#: Nanoseconds before a message's time at which the player stops sleeping and polls.
SPIN_NS = 200_000

#: Seconds to wait at the end for reliable subscribers to acknowledge everything.
ACK_TIMEOUT = 10.0

#: Playing as fast as possible: seconds to wait for subscribers (unless given), for the
#: identifiers' first counts on /diagnostics (published every second), and at the end for
#: their counts to settle.
FAST_SUBSCRIBER_WAIT = 10.0
FIRST_COUNTS_WAIT = 1.5
SETTLE_TIMEOUT = 15.0

#: /clock: best effort, depth 1 (what rclpy's time source subscribes with).
CLOCK_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT)


@dataclasses.dataclass
class PlayStats:
    """
    What a play did, and how punctual it was.

    ``lateness_ns`` holds, per message, the publish call's start minus its
    target time (empty when played as fast as possible).
    """

    messages: int
    wall_s: float
    bag_s: float
    rate: float
    lateness_ns: np.ndarray
    unacknowledged: tuple[str, ...] = ()
    #: Per identifier seen on /diagnostics: (status name, messages taken, messages lost).
    subscribers: tuple[tuple[str, int, int], ...] = ()
    clock_messages: int = 0

    @property
    def shortfall(self) -> tuple[str, ...]:
        """Return what was not delivered: unacknowledged topics, identifiers that lost some."""
        lost = tuple(f'{name} lost {count}' for name, _, count in self.subscribers if count > 0)
        return tuple(f'{topic} not acknowledged' for topic in self.unacknowledged) + lost

    def describe(self) -> str:
        """Return a one-paragraph summary with the timing statistics."""
        text = (f'played {self.messages} messages ({self.bag_s:.3f} s of bag time) in '
                f'{self.wall_s:.3f} s')
        if self.rate > 0 and self.lateness_ns.size:
            late = self.lateness_ns / 1e3
            text += (f' at rate {self.rate:g}; lateness (µs): mean {late.mean():.1f}, '
                     f'median {np.median(late):.1f}, p99 {np.percentile(late, 99):.1f}, '
                     f'max {late.max():.1f}')
        elif self.rate == 0:
            text += ' (as fast as possible)'
        for name, taken, lost in self.subscribers:
            node = name.split(': ')[0]
            if taken < 0 or lost < 0:
                text += (f'; the counts of {node} went back (it restarted, or two nodes share '
                         'its name): not checked')
            else:
                text += f'; {node} took {taken} messages, lost {lost}'
        if self.clock_messages:
            text += f'; {self.clock_messages} /clock messages'
        if self.unacknowledged:
            text += ('; not acknowledged by every reliable subscriber: '
                     + ', '.join(self.unacknowledged))
        if self.shortfall:
            text += ('. SHORTFALL: samples were lost (play slower with --rate, or let the '
                     'subscriber keep all: qos_overrides./<topic>.subscription.history: '
                     'keep_all)')
        return text


def _wait_until(target_ns: int) -> None:
    """Sleep, then poll, until ``time.monotonic_ns()`` reaches ``target_ns``."""
    remaining = target_ns - time.monotonic_ns()
    if remaining > SPIN_NS:
        time.sleep((remaining - SPIN_NS) / 1e9)
    while time.monotonic_ns() < target_ns:
        pass


class IdentifierCounts:
    """
    The identifiers' own message counts, as their ``/diagnostics`` statuses say.

    Every status with the keys ``messages received`` and ``lost in
    transport`` is an identifier's; :meth:`since` returns what each took and
    lost between the first status seen and the last.
    """

    def __init__(self, node: Node) -> None:
        self.first: dict[str, tuple[int, int]] = {}
        self.last: dict[str, tuple[int, int, float]] = {}
        self._previous: dict[str, tuple[int, int]] = {}
        self._lost_key = COUNTERS['lost']
        node.create_subscription(DiagnosticArray, DIAGNOSTICS, self.on_diagnostics, 100)

    def on_diagnostics(self, message: DiagnosticArray) -> None:
        """Note each identifier's counts."""
        for status in message.status:
            values = {pair.key: pair.value for pair in status.values}
            try:
                counts = (int(values[DiagnosticKey.MESSAGES]), int(values[self._lost_key]))
            except (KeyError, ValueError):
                continue
            self.first.setdefault(status.name, counts)
            self.last[status.name] = (*counts, time.monotonic())

    def settled(self, after: float) -> bool:
        """Return whether every identifier reported twice since ``after`` without a change."""
        return all(seen > after and self._previous.get(name) == (taken, lost)
                   for name, (taken, lost, seen) in self.last.items()) if self.last else True

    def remember(self) -> None:
        """Keep the latest counts, to tell whether the next ones changed."""
        self._previous = {name: (taken, lost) for name, (taken, lost, _) in self.last.items()}

    def since(self) -> tuple[tuple[str, int, int], ...]:
        """Return ``(status name, messages taken, messages lost)`` since the first status."""
        return tuple((name, taken - self.first[name][0], lost - self.first[name][1])
                     for name, (taken, lost, _) in sorted(self.last.items()))


def _spin_until(executor: SingleThreadedExecutor, done: Any, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if done():
            return True
        executor.spin_once(timeout_sec=0.05)
    return done()


def _settle(executor: SingleThreadedExecutor, counts: IdentifierCounts) -> None:
    """Spin until the identifiers' counts stop changing (they may still take their queues)."""
    deadline = time.monotonic() + SETTLE_TIMEOUT
    while time.monotonic() < deadline:
        mark = time.monotonic()
        counts.remember()
        if _spin_until(executor, lambda: counts.settled(mark), 2.5):
            return


def play_bag(bag: str | Path, rate: float = 1.0, topics: Sequence[str] | None = None,
             wait_for_subscribers: float | None = None, delay: float = 0.0,
             ros_args: Sequence[str] | None = None, clock: float = 0.0) -> PlayStats:
    """
    Publish the messages of a bag with their recorded timing and QoS.

    Parameters
    ----------
    bag : str or pathlib.Path
        The bag directory or ``.mcap`` file.
    rate : float
        Time scale (2 plays twice as fast); 0 plays as fast as possible.
    topics : sequence of str, optional
        Play only these topics (default: all).
    wait_for_subscribers : float, optional
        If > 0, wait up to this many seconds, before playing, until every
        volatile topic has a subscriber (volatile messages published before
        a subscriber is matched are lost for it). Default: 0, or
        :data:`FAST_SUBSCRIBER_WAIT` with rate 0.
    delay : float
        Seconds to wait after creating the publishers, before playing.
    ros_args : sequence of str, optional
        Extra ``--ros-args`` for the player node.
    clock : float
        If > 0, publish ``/clock`` from the bag's time, at most this many
        times per second of bag time (and with the last message).

    Returns
    -------
    PlayStats

    Raises
    ------
    BcidError
        If the bag cannot be read, a topic is missing or a type is not
        installed, or no subscriber came within ``wait_for_subscribers``.

    """
    if not rate >= 0 or rate == float('inf'):
        raise BcidError(f'--rate must be >= 0 (0: as fast as possible), got {rate}')
    if not clock >= 0 or clock == float('inf'):
        raise BcidError(f'--clock must be >= 0 messages per second, got {clock}')
    fast = rate == 0
    if wait_for_subscribers is None:
        wait_for_subscribers = FAST_SUBSCRIBER_WAIT if fast else 0.0
    reader = BagReader(bag)
    selected = list(reader.topics) if not topics else list(dict.fromkeys(topics))
    missing = [t for t in selected if t not in reader.topics]
    if missing:
        raise BcidError(f'{reader.path}: no topic {", ".join(missing)} in the bag '
                        f'(topics: {", ".join(sorted(reader.topics))})')
    classes = {t: message_class(reader.topics[t].type) for t in selected}
    context = Context()
    rclpy.init(args=['--ros-args', *(ros_args or [])], context=context,
               signal_handler_options=SignalHandlerOptions.NO)
    try:
        node = Node(f'bcid_player_{os.getpid()}', context=context)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        try:
            publishers = {t: node.create_publisher(
                classes[t], t, publisher_profile(reader.topics[t].qos, keep_all=fast))
                for t in selected}
            clock_publisher = node.create_publisher(Clock, '/clock', CLOCK_QOS) if clock else None
            counts = IdentifierCounts(node) if fast else None
            _wait_for_subscribers(publishers, wait_for_subscribers)
            if counts is not None:  # the identifiers' counts before: published every second
                _spin_until(executor, lambda: bool(counts.last), FIRST_COUNTS_WAIT)
            if delay > 0:
                time.sleep(delay)
            stats = _play(reader, publishers, rate, clock_publisher, clock)
            if counts is not None and counts.last:
                _settle(executor, counts)
                stats.subscribers = counts.since()
            return stats
        finally:
            executor.remove_node(node)
            node.destroy_node()
            executor.shutdown()
    finally:
        context.try_shutdown()


def _wait_for_subscribers(publishers: dict[str, Any], timeout: float) -> None:
    if timeout <= 0:
        return
    volatile = [t for t, p in publishers.items()
                if p.qos_profile.durability != DurabilityPolicy.TRANSIENT_LOCAL]
    deadline = time.monotonic() + timeout
    while True:
        waiting = [t for t in volatile if publishers[t].get_subscription_count() == 0]
        if not waiting:
            return
        if time.monotonic() > deadline:
            raise BcidError(f'no subscriber on {", ".join(waiting)} within {timeout:g} s')
        time.sleep(0.01)


def _clock_message(log_time: int) -> Clock:
    sec, nanosec = divmod(log_time, 1_000_000_000)
    return Clock(clock=Time(sec=sec, nanosec=nanosec))


def _play(reader: BagReader, publishers: dict[str, Any], rate: float,
          clock_publisher: Any = None, clock_rate: float = 0.0) -> PlayStats:
    stream = reader.messages(list(publishers))
    lateness: list[int] = []
    count = clocks = 0
    first_ns = last_ns = clock_ns = None
    clock_step = round(1e9 / clock_rate) if clock_rate else 0
    start = time.monotonic_ns()
    for topic, log_time, data in stream:
        if first_ns is None:
            first_ns = log_time
            start = time.monotonic_ns()
        last_ns = log_time
        if rate > 0:
            target = start + round((log_time - first_ns) / rate)
            _wait_until(target)
            lateness.append(time.monotonic_ns() - target)
        if clock_publisher is not None and (clock_ns is None
                                            or log_time - clock_ns >= clock_step):
            clock_publisher.publish(_clock_message(log_time))  # the time before the message
            clock_ns = log_time
            clocks += 1
        publishers[topic].publish(data)
        count += 1
    if clock_publisher is not None and last_ns is not None and clock_ns != last_ns:
        clock_publisher.publish(_clock_message(last_ns))
        clocks += 1
    wall = (time.monotonic_ns() - start) / 1e9
    unacknowledged = tuple(
        t for t, p in publishers.items()
        if p.qos_profile.reliability == ReliabilityPolicy.RELIABLE
        and p.get_subscription_count() > 0
        and not p.wait_for_all_acked(Duration(seconds=ACK_TIMEOUT)))
    bag_s = 0.0 if first_ns is None else (last_ns - first_ns) / 1e9
    return PlayStats(count, wall, bag_s, rate, np.array(lateness, dtype=np.int64),
                     unacknowledged, clock_messages=clocks)


__all__ = ['IdentifierCounts', 'PlayStats', 'play_bag']
