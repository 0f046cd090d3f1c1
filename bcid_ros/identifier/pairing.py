"""
Pairing of the separate ``input`` and ``output`` topics into samples (pure Python, no ROS).

:class:`Pairing` turns the two streams into rows ``[y, u1, ..., ur]`` with
the identifier's rule (docs/nodes.md, "Pairing"):

* ``sync: arrival`` pairs first-in first-out. A message lost in transport
  leaves a *hole* at its place in the queue, so that its partner is dropped
  instead of being paired with the next message.
* ``sync: stamp`` pairs two stamps within the tolerance. A head that the
  other topic has passed can never be paired and is dropped; duplicated or
  out-of-order stamps are dropped; an interval between pairs longer than
  :data:`GAP_FACTOR` sample periods is a gap. The sample period is given or
  learnt as the median of the first :data:`PERIOD_LEARNING_INTERVALS`
  intervals. A stamp more than :func:`jump_threshold_ns` before the last one
  of its side is not out of order but a *time jump* (a looped bag, a plant
  clock restarted): the pairing starts over from it (queues, last stamps and
  last pair forgotten, a gap), so that the identifier is not deaf from then on.

Each call returns a :class:`Paired`: the rows to feed in order, with
:data:`GAP` where the regressor must restart, and the problems to count.
:class:`SequenceTracker` finds messages lost in transport from the
publication sequence numbers.
"""

from __future__ import annotations

import collections
import dataclasses
import statistics
from typing import Any

#: Intervals used to learn the sample period in stamp mode when it is not given.
PERIOD_LEARNING_INTERVALS = 20
#: An interval longer than this many sample periods is a gap (stamp mode).
GAP_FACTOR = 1.5
#: In :attr:`Paired.samples`: samples are missing here, restart the regressor.
GAP = None
#: A stamp this far (s) or further before its side's last one is a time jump, not out of order.
TIME_JUMP_S = 1.0
#: The two sides, as named in messages and counters.
SIDES = ('input', 'output')

_HOLE = (None, None)


@dataclasses.dataclass
class Paired:
    """
    What one message did to the pairing.

    Attributes
    ----------
    samples : list
        In order: rows ``[y, u1, ..., ur]`` to feed, and :data:`GAP` where
        samples are missing (restart the regressor before the next row).
    problems : list of tuple of str
        ``(counter, text)`` of every message dropped or gap found; the
        counter is a key of :data:`bcid_ros.identifier.interface.COUNTERS`.
    notes : list of str
        Things worth logging that are not problems (the learnt period).

    """

    samples: list[list[float] | None] = dataclasses.field(default_factory=list)
    problems: list[tuple[str, str]] = dataclasses.field(default_factory=list)
    notes: list[str] = dataclasses.field(default_factory=list)

    def gap(self) -> None:
        """Mark missing samples here (consecutive marks are one)."""
        if not self.samples or self.samples[-1] is not GAP:
            self.samples.append(GAP)

    def problem(self, counter: str, text: str, gap: bool = True) -> None:
        """Add a problem, and a gap unless ``gap`` is False."""
        self.problems.append((counter, text))
        if gap:
            self.gap()


class Pairing:
    """
    Pair input values with output values, by arrival or by stamp.

    Parameters
    ----------
    stamped : bool
        Pair by stamp (``sync: stamp``) instead of by arrival.
    tolerance_ns : int
        Stamp mode: largest stamp difference of a pair.
    queue_size : int
        Most unpaired values kept per side; the oldest is dropped beyond it.
    period_ns : float
        Stamp mode: the sample period, for the gap detection; 0 learns it.

    """

    def __init__(self, stamped: bool, tolerance_ns: int, queue_size: int,
                 period_ns: float = 0.0) -> None:
        self.stamped = stamped
        self.tolerance_ns = int(tolerance_ns)
        self.queue_size = int(queue_size)
        self.period_ns = period_ns
        self._queues = {side: collections.deque() for side in SIDES}
        self._last_stamp: dict[str, int | None] = dict.fromkeys(SIDES)
        self._last_pair_ns: int | None = None
        self._intervals: list[int] = []

    @classmethod
    def from_settings(cls, settings: dict[str, Any]) -> Pairing:
        """Return the pairing of the identifier parameters ``settings``."""
        return cls(settings['sync'] == 'stamp', int(round(settings['sync_tolerance'] * 1e9)),
                   settings['queue_size'], settings['sample_period'] * 1e9)

    def add(self, side: str, value: Any, stamp_ns: int | None = None,
            lost: int = 0) -> Paired:
        """
        Take one message's value and pair what can be paired.

        Parameters
        ----------
        side : str
            ``'input'`` (value: the list ``[u1, ..., ur]``) or ``'output'`` (y).
        value : list of float or float
            The decoded value.
        stamp_ns : int, optional
            The header stamp (stamp mode).
        lost : int
            Messages of this side lost in transport just before this one.

        Returns
        -------
        Paired

        """
        paired = Paired()
        self._lose(side, lost, paired)
        queue = self._queues[side]
        if self.stamped:
            last = self._last_stamp[side]
            if last is not None and last - stamp_ns >= self.jump_threshold_ns:
                self._start_over(side, stamp_ns, last, paired)
            elif last is not None and stamp_ns <= last:
                kind = 'duplicate' if stamp_ns == last else 'out_of_order'
                paired.problem(kind, f'{side} message with a {kind.replace("_", " ")} stamp '
                               f'dropped ({stamp_ns * 1e-9:.9f} s after {last * 1e-9:.9f} s)',
                               gap=False)
                return paired
            self._last_stamp[side] = stamp_ns
        else:
            stamp_ns = None
        queue.append((stamp_ns, value))
        if len(queue) > self.queue_size:
            queue.popleft()
            paired.problem('unpaired', f'{side} queue over queue_size={self.queue_size}: '
                           f'oldest {side} sample dropped (is the other topic published?)')
        self._pair(paired)
        return paired

    def refuse(self, side: str, lost: int = 0) -> Paired:
        """Take a message of ``side`` that could not be decoded: a missing sample."""
        paired = Paired()
        self._lose(side, lost, paired)
        self._lose(side, 1, paired)
        paired.gap()
        return paired

    @property
    def jump_threshold_ns(self) -> int:
        """Return how far back a stamp must go to be a time jump: TIME_JUMP_S, 2 tolerances."""
        return max(int(TIME_JUMP_S * 1e9), 2 * self.tolerance_ns)

    def _start_over(self, side: str, stamp_ns: int, last: int, paired: Paired) -> None:
        """Pair afresh from a stamp that jumped back: forget the queues and the stamps."""
        self.reset()
        paired.problem('time_jumps', f'{side} stamps jumped back by '
                       f'{(last - stamp_ns) * 1e-9:.6g} s (to {stamp_ns * 1e-9:.9f} s): '
                       'a looped bag or a restarted clock? pairing started over')

    def reset(self) -> None:
        """Forget the queued values, the last stamps and the last pair (the period is kept)."""
        for queue in self._queues.values():
            queue.clear()
        self._last_stamp = dict.fromkeys(SIDES)
        self._last_pair_ns = None

    def _lose(self, side: str, count: int, paired: Paired) -> None:
        # In arrival mode a lost message leaves a hole at its place in the FIFO,
        # so that its partner is dropped instead of being paired with the next one.
        if count and not self.stamped:
            self._queues[side].extend([_HOLE] * min(count, self.queue_size))
        elif count:
            paired.gap()

    def _pair(self, paired: Paired) -> None:
        inputs, outputs = self._queues['input'], self._queues['output']
        while inputs and outputs:
            if self.stamped:
                t_in, t_out = inputs[0][0], outputs[0][0]
                if abs(t_in - t_out) > self.tolerance_ns:
                    # The older head can never be paired: the other topic has moved past it.
                    side, queue = (('input', inputs) if t_in < t_out else ('output', outputs))
                    queue.popleft()
                    paired.problem('unpaired', f'{side} sample without a partner within '
                                   'sync_tolerance dropped')
                    continue
                self._check_interval(t_out, paired)
            u = inputs.popleft()[1]
            y = outputs.popleft()[1]
            if u is None or y is None:
                paired.gap()
                continue
            paired.samples.append([y, *u])

    def _check_interval(self, stamp: int, paired: Paired) -> None:
        last = self._last_pair_ns
        self._last_pair_ns = stamp
        if last is None:
            return
        interval = stamp - last
        if not self.period_ns:
            self._intervals.append(interval)
            if len(self._intervals) >= PERIOD_LEARNING_INTERVALS:
                self.period_ns = statistics.median(self._intervals)
                paired.notes.append(f'sample period learnt from the stamps: '
                                    f'{self.period_ns * 1e-9:.6g} s')
            return
        if interval > GAP_FACTOR * self.period_ns:
            paired.problem('gaps', f'gap of {interval * 1e-9:.6g} s in the stamps (period '
                           f'{self.period_ns * 1e-9:.6g} s): regressor restarted')


class SequenceTracker:
    """
    Count messages lost in transport from the publication sequence numbers.

    One publisher per topic is assumed; a smaller number than the last one
    is a new publisher and counts nothing.
    """

    def __init__(self) -> None:
        self._last: dict[str, int] = {}

    def lost(self, topic: str, sequence: int | None) -> int:
        """Return how many messages of ``topic`` were lost before the one numbered ``sequence``."""
        if not sequence:
            return 0
        last = self._last.get(topic)
        self._last[topic] = sequence
        if last is None or sequence <= last + 1:
            return 0
        return sequence - last - 1

    def reset(self) -> None:
        """Forget the last numbers."""
        self._last.clear()


__all__ = ['GAP', 'GAP_FACTOR', 'PERIOD_LEARNING_INTERVALS', 'Paired', 'Pairing',
           'SIDES', 'SequenceTracker', 'TIME_JUMP_S']
