"""
When an estimate goes stale: the rule of the identifier's ``stale_after`` (no ROS).

A plant that stops sending leaves the last estimate latched, and a consumer
cannot tell a still plant from a dead link. :class:`Staleness` says when no
sample has come for too long, so that ``~/valid`` turns false with the
reason ``no samples for T s``:

- ``stale_after > 0``: after that many seconds;
- ``stale_after == 0`` (automatic): after ten times the median interval
  between the arrivals of the recent samples, and at least
  :data:`MIN_AUTOMATIC` seconds (a frame's samples arrive together, so the
  intervals are those between messages that brought samples); never before
  two samples have given an interval (a restored estimate at start-up stays
  valid until samples come and stop);
- ``stale_after < 0``: never.

Times are seconds on the node's clock (so ``use_sim_time`` works); the
clock going backwards (a replayed bag looping) restarts the intervals.
"""

from __future__ import annotations

import collections
import math

#: Arrivals whose intervals the automatic limit takes the median of.
RECENT_ARRIVALS = 50
#: The automatic limit: this many median intervals ...
AUTOMATIC_FACTOR = 10.0
#: ... and at least this many seconds.
MIN_AUTOMATIC = 1.0


class Staleness:
    """
    The arrivals of samples, and whether the latest is older than the limit.

    Parameters
    ----------
    stale_after : float
        Seconds; 0 automatic, negative never (see the module docstring).

    Raises
    ------
    ValueError
        If ``stale_after`` is not a finite number.

    """

    def __init__(self, stale_after: float) -> None:
        if not math.isfinite(stale_after):
            raise ValueError(f"parameter 'stale_after' must be a finite number of seconds, "
                             f'got {stale_after!r}')
        self.stale_after = float(stale_after)
        self._intervals: collections.deque[float] = collections.deque(
            maxlen=RECENT_ARRIVALS - 1)
        self.last: float | None = None
        self._skip_interval = False

    def restart(self, now: float) -> None:
        """
        Count the age from ``now`` (the node starts or resumes taking samples).

        The wait until the first sample after it is not an interval between samples.
        """
        self.last = now
        self._skip_interval = True

    def arrived(self, now: float) -> None:
        """Record that samples arrived at ``now``."""
        if self.last is not None and not self._skip_interval:
            interval = now - self.last
            if interval < 0:  # the clock went back: the old intervals mean nothing now
                self._intervals.clear()
            elif interval > 0:
                self._intervals.append(interval)
        self.last = now
        self._skip_interval = False

    def limit(self) -> float | None:
        """Return the seconds without samples after which the estimate is stale (None: not now)."""
        if self.stale_after < 0:
            return None
        if self.stale_after > 0:
            return self.stale_after
        if not self._intervals:  # no rate known yet (a restored estimate, before samples)
            return None
        intervals = sorted(self._intervals)
        middle = len(intervals) // 2
        median = (intervals[middle] if len(intervals) % 2
                  else 0.5 * (intervals[middle - 1] + intervals[middle]))
        return max(MIN_AUTOMATIC, AUTOMATIC_FACTOR * median)

    def age(self, now: float) -> float | None:
        """Return the seconds since the last arrival (None before the first)."""
        return None if self.last is None else max(0.0, now - self.last)

    def reason(self, now: float) -> str:
        """Return ``'no samples for T s'`` if stale at ``now``, else ``''``."""
        limit, age = self.limit(), self.age(now)
        if limit is None or age is None or age < limit:
            return ''
        return f'no samples for {age:.3g} s'


__all__ = ['AUTOMATIC_FACTOR', 'MIN_AUTOMATIC', 'RECENT_ARRIVALS', 'Staleness']
