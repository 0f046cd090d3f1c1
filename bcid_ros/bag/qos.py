"""
QoS profiles as stored in rosbag2 bags (rosbags' ``Qos``), without rclpy.

A bag keeps, per topic, the QoS profiles its publishers offered
(``offered_qos_profiles``), so that a player can offer the same: above all
``transient_local`` for latched topics such as the simulator's truth. The
rclpy side of the conversion is in :mod:`bcid_ros.bag.rosqos`.
"""

from __future__ import annotations

from typing import Sequence

from rosbags.interfaces import (Qos, QosDurability, QosHistory, QosLiveliness,
                                QosReliability, QosTime)
from rosbags.rosbag2.metadata import parse_qos

#: A zero duration: rmw's "unspecified", i.e. the default (infinite) deadline etc.
UNSPECIFIED = QosTime(0, 0)


def make_qos(*, reliable: bool = True, transient_local: bool = False, depth: int = 10,
             keep_all: bool = False) -> Qos:
    """
    Return a rosbags ``Qos`` with the given policies and default times.

    Parameters
    ----------
    reliable : bool
        RELIABLE, else BEST_EFFORT.
    transient_local : bool
        TRANSIENT_LOCAL (late joiners get the last ``depth`` messages), else VOLATILE.
    depth : int
        History depth of KEEP_LAST.
    keep_all : bool
        KEEP_ALL history instead of KEEP_LAST.

    """
    return Qos(QosHistory.KEEP_ALL if keep_all else QosHistory.KEEP_LAST, int(depth),
               QosReliability.RELIABLE if reliable else QosReliability.BEST_EFFORT,
               QosDurability.TRANSIENT_LOCAL if transient_local else QosDurability.VOLATILE,
               UNSPECIFIED, UNSPECIFIED, QosLiveliness.AUTOMATIC, UNSPECIFIED, False)


#: The estimate and truth topics: reliable, transient_local, depth 1 (docs/nodes.md).
LATCHED = make_qos(reliable=True, transient_local=True, depth=1)


def parse_offered(text: str) -> list[Qos]:
    """
    Return the profiles of an ``offered_qos_profiles`` value (YAML, v8 or v9 style).

    Raises
    ------
    ValueError
        If the YAML cannot be parsed.

    """
    try:
        return parse_qos(text)
    except Exception as error:  # rosbags raises its ReaderError; keep our callers simple
        raise ValueError(f'bad offered_qos_profiles: {error}') from None


def is_transient_local(profiles: Sequence[Qos]) -> bool:
    """Return whether every offered profile is transient_local (what rosbag2 play offers)."""
    return bool(profiles) and all(p.durability == QosDurability.TRANSIENT_LOCAL
                                  for p in profiles)


def is_reliable(profiles: Sequence[Qos]) -> bool:
    """Return whether every offered profile is reliable (an empty list counts as reliable)."""
    return all(p.reliability == QosReliability.RELIABLE for p in profiles)


def describe(profiles: Sequence[Qos]) -> str:
    """Return a short text such as ``reliable, transient_local, keep_last 1``."""
    if not profiles:
        return 'no QoS recorded'
    texts = []
    for p in profiles:
        history = (f'keep_last {p.depth}' if p.history == QosHistory.KEEP_LAST
                   else p.history.name.lower())
        texts.append(f'{p.reliability.name.lower()}, {p.durability.name.lower()}, {history}')
    unique = list(dict.fromkeys(texts))
    return '; '.join(unique)


__all__ = ['LATCHED', 'Qos', 'describe', 'is_reliable', 'is_transient_local', 'make_qos',
           'parse_offered']
