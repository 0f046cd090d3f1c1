"""``bcid info``: a bag's topics, counts, duration, QoS and truth, as text."""

from __future__ import annotations

from datetime import datetime, timezone
from pathlib import Path

from bcid_ros.bag.qos import describe
from bcid_ros.bag.reader import BagReader


def describe_bag(path: str | Path) -> str:
    """
    Return a human-readable description of the bag at ``path``.

    Raises
    ------
    BcidError
        If the bag cannot be read.

    """
    bag = BagReader(path)
    size = sum(f.stat().st_size for f in bag.files)
    lines = [f'bag:       {bag.path}',
             f'files:     {", ".join(f.name for f in bag.files)} ({size / 1024:.1f} KiB)',
             f'messages:  {bag.message_count}',
             f'duration:  {bag.duration_s:.3f} s']
    if bag.start_ns is not None:
        start = datetime.fromtimestamp(bag.start_ns / 1e9, tz=timezone.utc)
        lines.append(f'start:     {start.isoformat()} ({bag.start_ns / 1e9:.9f} s)')
    lines.append('topics:')
    width = max((len(name) for name in bag.topics), default=0)
    for name in sorted(bag.topics):
        topic = bag.topics[name]
        lines.append(f'  {name:{width}}  {topic.type}  {topic.count} msgs  '
                     f'[{describe(topic.qos)}]')
    truth = bag.truth()
    if truth is not None:
        lines.append('truth:')
        for names, values in ((truth.parameter_names, truth.parameters),
                              (truth.noise_names, truth.noise)):
            if names:
                lines.append('  ' + ', '.join(f'{n} = {v:.6g}' for n, v in zip(names, values)))
    return '\n'.join(lines)


__all__ = ['describe_bag']
