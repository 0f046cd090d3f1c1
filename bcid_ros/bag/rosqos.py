"""
Convert QoS between rclpy and the bag's (rosbags) form, and pick a profile per topic.

This module imports rclpy; only ``bcid record`` and ``bcid play`` use it.
The policies follow rosbag2: a player offers transient_local only if every
recorded publisher offered it, and reliable only if every one did; a
recorder requests what all current publishers can serve.
"""

from __future__ import annotations

import importlib
from typing import Any, Sequence

from rclpy.duration import Duration
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, LivelinessPolicy, QoSProfile,
                       ReliabilityPolicy)
from rosbags.interfaces import (Qos, QosDurability, QosHistory, QosLiveliness, QosReliability,
                                QosTime)

from bcid_ros.bag.qos import is_reliable, is_transient_local
from bcid_ros.errors import BcidError

#: rmw's infinite duration (INT64_MAX ns); rosbag2 writes it as sec/nsec.
INFINITE_NS = 2 ** 63 - 1

#: Smallest history depth the player gives a volatile topic (the simulator's samples depth).
MIN_VOLATILE_DEPTH = 1000


def _time(duration: Duration) -> QosTime:
    nanoseconds = min(int(duration.nanoseconds), INFINITE_NS)
    return QosTime(nanoseconds // 10 ** 9, nanoseconds % 10 ** 9)


def to_bag_qos(profile: QoSProfile) -> Qos:
    """Return the bag form of an rclpy profile (as offered by a publisher)."""
    return Qos(QosHistory[profile.history.name], int(profile.depth),
               QosReliability[profile.reliability.name],
               QosDurability[profile.durability.name],
               _time(profile.deadline), _time(profile.lifespan),
               QosLiveliness[profile.liveliness.name],
               _time(profile.liveliness_lease_duration),
               bool(profile.avoid_ros_namespace_conventions))


def publisher_profile(offered: Sequence[Qos], keep_all: bool = False) -> QoSProfile:
    """
    Return the profile to publish a recorded topic with.

    Reliability and durability follow the offers (rosbag2 play's rule);
    the depth is the largest offered KEEP_LAST depth, for volatile topics at
    least :data:`MIN_VOLATILE_DEPTH`, so that a burst played as fast as
    possible is not overwritten before a reliable subscriber has it.
    ``keep_all`` (playing as fast as possible) gives a reliable volatile
    topic KEEP_ALL: the writer then waits for a reliable subscriber that
    keeps all too, instead of overwriting what it has not yet taken.
    Deadline, lifespan and liveliness are left at their defaults.
    """
    depths = [q.depth for q in offered if q.history == QosHistory.KEEP_LAST]
    latched = is_transient_local(offered)
    depth = max(depths, default=1) if latched else max(depths + [MIN_VOLATILE_DEPTH])
    keep_all = keep_all and not latched and is_reliable(offered)
    return QoSProfile(
        history=HistoryPolicy.KEEP_ALL if keep_all else HistoryPolicy.KEEP_LAST,
        depth=max(depth, 1),
        reliability=(ReliabilityPolicy.RELIABLE if is_reliable(offered)
                     else ReliabilityPolicy.BEST_EFFORT),
        durability=(DurabilityPolicy.TRANSIENT_LOCAL if latched
                    else DurabilityPolicy.VOLATILE),
        liveliness=LivelinessPolicy.AUTOMATIC)


def subscriber_profile(offered: Sequence[Qos]) -> QoSProfile:
    """
    Return the profile to record a topic with, compatible with every offer.

    Reliable and transient_local only where every publisher offers them;
    KEEP_ALL for volatile topics, so that a reliable publisher is slowed
    down rather than a message dropped; KEEP_LAST with the largest offered
    depth for latched topics (all their history is then received).
    """
    latched = is_transient_local(offered)
    reliability = (ReliabilityPolicy.RELIABLE if is_reliable(offered)
                   else ReliabilityPolicy.BEST_EFFORT)
    if latched:
        depth = max([q.depth for q in offered if q.history == QosHistory.KEEP_LAST] + [1])
        return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=reliability,
                          durability=DurabilityPolicy.TRANSIENT_LOCAL)
    return QoSProfile(history=HistoryPolicy.KEEP_ALL, depth=1000, reliability=reliability,
                      durability=DurabilityPolicy.VOLATILE)


def message_class(msgtype: str) -> Any:
    """
    Return the Python class of ``pkg/msg/Name`` (or ``pkg/Name``).

    Raises
    ------
    BcidError
        If the package is not installed or has no such message.

    """
    parts = msgtype.split('/')
    if len(parts) not in (2, 3):
        raise BcidError(f'{msgtype!r} is not a message type name (pkg/msg/Name)')
    package, name = parts[0], parts[-1]
    try:
        return getattr(importlib.import_module(f'{package}.msg'), name)
    except (ImportError, AttributeError):
        raise BcidError(f'message type {msgtype} is not installed '
                        f'(no Python module {package}.msg with {name})') from None


__all__ = ['message_class', 'publisher_profile', 'subscriber_profile', 'to_bag_qos']
