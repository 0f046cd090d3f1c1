"""
Large frames fed in slices, so that a node's other callbacks wait at most 20 ms (no ROS).

A frame of 300,000 samples takes seconds to feed; fed in one callback, it
holds up the node's timers (``/diagnostics``, state saves), services
(``~/reset``) and parameter changes for as long. :class:`SlicedFeeder` takes
such messages, and every message after them while any is pending (the
order of the samples is kept), and feeds them a slice at a time: each call of
:meth:`SlicedFeeder.step` works for about :data:`STEP_BUDGET_S` and returns the
results of the messages it finished. The node calls it from a timer until it
is idle (docs/guarantees.md).

The result of a message fed in slices is that of
:meth:`~bcid_ros.identifier.feeder.SampleFeeder.take_rows` on the whole
message: the same samples go to :meth:`~bcid_ros.identifier.feeder.SampleFeeder.feed`
in the same order (its counts add up over slices), an estimator error drops
the rest of the message and restarts the regressor, and the estimates due are
collected once, after the last slice (as ``bcid replay`` publishes them).
"""

from __future__ import annotations

import collections
import time
from typing import Any

from bcid_ros.identifier.feeder import FeedResult, SampleFeeder
from bcid_ros.identifier.layouts import decode_samples

#: Messages with more values than this are fed in slices (a frame of ~300 samples of 1 + 2).
LARGE_VALUES = 1024
#: Seconds of feeding per :meth:`SlicedFeeder.step` (the other callbacks then run).
STEP_BUDGET_S = 0.005
#: Rows of the first slice of a step; later slices are sized from the measured time per row.
FIRST_SLICE = 64
#: Most rows of one slice.
LARGEST_SLICE = 65536


class SlicedFeeder:
    """
    Feed large messages (and those queued behind them) a slice at a time.

    Parameters
    ----------
    feeder : SampleFeeder
        The node's feeder.
    budget_s : float
        Seconds of work per :meth:`step`.

    """

    def __init__(self, feeder: SampleFeeder, budget_s: float = STEP_BUDGET_S) -> None:
        self.feeder = feeder
        self.budget_s = budget_s
        self._queue: collections.deque[tuple[Any, bool]] = collections.deque()
        self._current: list[Any] | None = None   # [rows, next row, FeedResult]
        self._row_s = 0.0

    @property
    def busy(self) -> bool:
        """Whether messages are waiting or part fed."""
        return bool(self._queue) or self._current is not None

    def takes(self, message: Any) -> bool:
        """Whether ``message`` must go through :meth:`push`: it is large, or others wait."""
        return self.busy or len(message.data) > LARGE_VALUES

    def push(self, message: Any, gap: bool = False) -> None:
        """Queue a message; ``gap``: samples were lost just before it (restart first)."""
        self._queue.append((message, gap))

    def clear(self) -> None:
        """Drop what waits (``~/reset``: the samples before a reset are not wanted)."""
        self._queue.clear()
        self._current = None

    def step(self) -> list[FeedResult]:
        """Feed for about the budget; return the results of the messages finished, in order."""
        clock = time.perf_counter
        deadline = clock() + self.budget_s
        finished: list[FeedResult] = []
        while self.busy and clock() < deadline:
            if self._current is None:
                result = self._begin()
                if result is not None:
                    finished.append(result)
                continue
            result = self._feed_slice(deadline)
            if result is not None:
                finished.append(result)
        return finished

    def _begin(self) -> FeedResult | None:
        """Decode the next message; return its result at once if it is dropped."""
        message, gap = self._queue.popleft()
        if gap:
            self.feeder.gap()
        try:
            rows = decode_samples(message, self.feeder.estimator.num_inputs)
        except ValueError:
            return self.feeder.take_message(message)  # the feeder's rule for a bad message
        self._current = [rows, 0, FeedResult()]
        return None

    def _uncount(self, result: FeedResult) -> None:
        """Take back the counts of the slices fed: take_rows counts none of a failed message."""
        feeder = self.feeder
        feeder.used -= result.used
        feeder.since_publish -= result.used
        feeder.nonfinite -= result.nonfinite
        feeder.unexcited -= result.unexcited

    def _feed_slice(self, deadline: float) -> FeedResult | None:
        """Feed one slice of the current message; return its result once it is done."""
        rows, start, result = self._current
        left = deadline - time.perf_counter()
        size = FIRST_SLICE if not self._row_s else int(max(left, 0.0) / self._row_s)
        end = min(rows.shape[0], start + max(16, min(size, LARGEST_SLICE)))
        began = time.perf_counter()
        try:
            self.feeder.feed(rows[start:end], result)
        except Exception as error:  # as take_rows: drop the rest of the message, restart
            self._uncount(result)
            self.feeder.gap()
            self._current = None
            return FeedResult(dropped='estimator_errors', reason=repr(error))
        self._row_s = (time.perf_counter() - began) / (end - start)
        if end < rows.shape[0]:
            self._current[1] = end
            return None
        self._current = None
        feeder = self.feeder
        result.estimates = feeder.due_estimates()
        result.withheld = (result.estimates is None and feeder.estimator.ready
                           and feeder.since_publish >= feeder.publish_period)
        return result


__all__ = ['LARGE_VALUES', 'STEP_BUDGET_S', 'SlicedFeeder']
