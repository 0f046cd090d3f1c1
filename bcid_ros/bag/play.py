"""
``bcid play``: a minimal rosbag2 MCAP player over rclpy.

Every topic is published with the QoS its recorded publishers offered
(:func:`bcid_ros.bag.rosqos.publisher_profile`), so latched topics such as
the simulator's truth are transient_local again and reach subscribers that
join later. Messages go out as stored (serialised CDR, never decoded).

Timing: message k is published at ``t0 + (t_k - t_first) / rate`` on the
monotonic clock; absolute targets keep errors from accumulating. The
player sleeps until ``SPIN_NS`` before the target and then polls the clock,
which brings the lateness down to microseconds at a small CPU cost. A rate
of 0 publishes as fast as possible. Before exiting, the player waits until
reliable subscribers have acknowledged every message.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
import time
from typing import Any, Sequence

import numpy as np
import rclpy
from rclpy.context import Context
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions

from bcid_ros.bag.reader import BagReader
from bcid_ros.bag.rosqos import message_class, publisher_profile
from bcid_ros.errors import BcidError

#: Nanoseconds before a message's time at which the player stops sleeping and polls.
SPIN_NS = 200_000

#: Seconds to wait at the end for reliable subscribers to acknowledge everything.
ACK_TIMEOUT = 10.0


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
        if self.unacknowledged:
            text += ('; not acknowledged by every reliable subscriber: '
                     + ', '.join(self.unacknowledged))
        return text


def _wait_until(target_ns: int) -> None:
    """Sleep, then poll, until ``time.monotonic_ns()`` reaches ``target_ns``."""
    remaining = target_ns - time.monotonic_ns()
    if remaining > SPIN_NS:
        time.sleep((remaining - SPIN_NS) / 1e9)
    while time.monotonic_ns() < target_ns:
        pass


def play_bag(bag: str | Path, rate: float = 1.0, topics: Sequence[str] | None = None,
             wait_for_subscribers: float = 0.0, delay: float = 0.0,
             ros_args: Sequence[str] | None = None) -> PlayStats:
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
    wait_for_subscribers : float
        If > 0, wait up to this many seconds, before playing, until every
        volatile topic has a subscriber (volatile messages published before
        a subscriber is matched are lost for it).
    delay : float
        Seconds to wait after creating the publishers, before playing.
    ros_args : sequence of str, optional
        Extra ``--ros-args`` for the player node.

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
        try:
            publishers = {t: node.create_publisher(classes[t], t,
                                                   publisher_profile(reader.topics[t].qos))
                          for t in selected}
            _wait_for_subscribers(publishers, wait_for_subscribers)
            if delay > 0:
                time.sleep(delay)
            return _play(reader, publishers, rate)
        finally:
            node.destroy_node()
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


def _play(reader: BagReader, publishers: dict[str, Any], rate: float) -> PlayStats:
    stream = reader.messages(list(publishers))
    lateness: list[int] = []
    count = 0
    first_ns = last_ns = None
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
        publishers[topic].publish(data)
        count += 1
    wall = (time.monotonic_ns() - start) / 1e9
    unacknowledged = tuple(
        t for t, p in publishers.items()
        if p.qos_profile.reliability == ReliabilityPolicy.RELIABLE
        and p.get_subscription_count() > 0
        and not p.wait_for_all_acked(Duration(seconds=ACK_TIMEOUT)))
    bag_s = 0.0 if first_ns is None else (last_ns - first_ns) / 1e9
    return PlayStats(count, wall, bag_s, rate, np.array(lateness, dtype=np.int64),
                     unacknowledged)


__all__ = ['PlayStats', 'play_bag']
