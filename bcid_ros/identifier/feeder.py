"""
The identifier's sample feeder: decoded samples into an estimator, with the node's policy (no ROS).

:class:`SampleFeeder` feeds decoded samples to an estimator with the
identifier node's policy for bad samples. The node and the offline replay
both use it, so they give the same estimates on the same messages. The
message layouts and :func:`~bcid_ros.identifier.layouts.decode_samples` are
:mod:`bcid_ros.identifier.layouts`'s.
"""

from __future__ import annotations

import dataclasses
import itertools
from typing import Any

import numpy as np

from bcid_ros.estimators.blocks import BlockStopped, checked_rows, UpdateTimes
from bcid_ros.estimators.plants import usable_samples
from bcid_ros.estimators.transaction import all_finite
from bcid_ros.identifier.layouts import decode_samples

#: Fewest samples for which the vectorised excitation check beats the sample loop (measured:
#: for one sample it costs about 5 µs more; for a frame of 50 it is cheaper).
VECTOR_CHECK_MIN = 16


@dataclasses.dataclass(slots=True)
class FeedResult:
    """
    What :class:`SampleFeeder` did with one message or block of rows.

    The counts add up over a block, so that a caller feeding many messages
    at once can sum them; the node counts and warns from them directly.

    Attributes
    ----------
    used : int
        Samples that went into the estimator.
    nonfinite : int
        Samples skipped for a NaN or Inf (each restarts the regressor).
    unexcited : int
        Samples used although the input had not changed for
        ``excitation_window`` samples.
    dropped : str
        Why the whole message was dropped: ``'empty'``, ``'bad_layout'``
        (wrong length or layout; restarts the regressor) or
        ``'estimator_errors'`` (the estimator raised; restarts the
        regressor); empty if it was not.
    reason : str
        The decoding error or the estimator's exception, for the log.
    estimates : tuple of numpy.ndarray or None
        ``(theta, theta_uncompensated, noise)`` when they are due for
        publication (see :meth:`SampleFeeder.due_estimates`), else None.
    withheld : bool
        Whether a due estimate was not finite and so not returned.

    """

    used: int = 0
    nonfinite: int = 0
    unexcited: int = 0
    dropped: str = ''
    reason: str = ''
    estimates: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
    withheld: bool = False


@dataclasses.dataclass(slots=True)
class BlockResult:
    """
    What :meth:`SampleFeeder.take_messages` did with a block of messages.

    Attributes
    ----------
    used, nonfinite, unexcited : int
        Sums over the block, as in :class:`FeedResult` (the samples of a
        message dropped for an estimator error are not counted).
    failures : list of tuple
        ``(message index, repr of the exception)`` of each message dropped
        because the estimator raised.
    withheld : int
        Messages after which a due estimate was not finite and so not returned.
    published : list of int
        Index of each message after which estimates were due.
    used_totals : list of int
        :attr:`SampleFeeder.used` right after each of those messages.
    estimates : list of tuple
        ``(theta, theta_uncompensated, noise)`` for each of those messages.
    valid : list of bool
        ``~/valid`` right after each of those messages.
    flags : list of dict
        The estimator's flag counts right after each of those messages (copies).

    """

    used: int = 0
    nonfinite: int = 0
    unexcited: int = 0
    failures: list[tuple[int, str]] = dataclasses.field(default_factory=list)
    withheld: int = 0
    published: list[int] = dataclasses.field(default_factory=list)
    used_totals: list[int] = dataclasses.field(default_factory=list)
    estimates: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = dataclasses.field(
        default_factory=list)
    valid: list[bool] = dataclasses.field(default_factory=list)
    flags: list[dict[str, int]] = dataclasses.field(default_factory=list)


def block_is_finite(rows: np.ndarray) -> bool:
    """
    Return whether every value of ``rows`` is finite.

    One sum in Python floats, exact if that overflows; numpy's sum would warn
    about the overflow of huge finite samples, which the estimators handle.
    """
    return all_finite(rows.reshape(-1))


@dataclasses.dataclass(slots=True)
class _Plan:
    """
    The per-sample rule's decisions for a block of rows, made at once, and how far it is fed.

    :meth:`SampleFeeder._plan` makes it; :meth:`SampleFeeder._feed` feeds it
    up to a row, as often as the caller needs to stop (to publish).
    """

    #: The finite rows of the block, which go to the estimator.
    kept: np.ndarray
    #: Index of each finite row in the block (None: all are).
    positions: np.ndarray | None
    #: The unchanged-input run after each finite row (None: no excitation check).
    runs: np.ndarray | list[int] | None
    #: Unexcited finite rows before each finite row, and in all: ``[0, ..., total]``.
    quiet_before: list[int] | None
    #: Whether each finite row is taken with the adaptation held (None: never).
    held: np.ndarray | None
    #: ``(first, stop, gap)`` over the finite rows: see :func:`_stretches`.
    stretches: list[tuple[int, int, bool]]
    #: The next stretch to feed, and the finite rows the estimator took.
    stretch: int = 0
    taken: int = 0
    #: What the estimator raised (None: nothing; the rows after it were not fed).
    error: Exception | None = None

    def kept_before(self, end: int) -> int:
        """Return how many of the finite rows come before row ``end`` of the block."""
        return end if self.positions is None else int(np.searchsorted(self.positions, end))

    def counts(self, begin: int, end: int) -> tuple[int, int, int]:
        """Return ``(used, nonfinite, unexcited)`` of rows ``begin`` to ``end - 1``."""
        first, stop = self.kept_before(begin), self.kept_before(end)
        quiet = 0 if self.quiet_before is None else (self.quiet_before[stop]
                                                     - self.quiet_before[first])
        return stop - first, end - begin - (stop - first), quiet

    def failed_row(self) -> int:
        """Return the index in the block of the row whose update raised."""
        return self.taken if self.positions is None else int(self.positions[self.taken])


def _stretches(count: int, positions: np.ndarray | None,
               held: np.ndarray | None) -> list[tuple[int, int, bool]]:
    """
    Return the stretches of the finite rows that go to the estimator in one block each.

    ``count`` rows, of which those at ``positions`` are finite (None: all);
    ``held``: whether each finite row is taken with the adaptation held (None:
    never). A stretch ends before a skipped row and where ``held`` changes.
    Each is ``(first, stop, gap)`` over the finite rows; ``gap``: rows were
    skipped right before it.
    """
    kept = count if positions is None else positions.shape[0]
    if not kept:
        return []
    if positions is None and held is None:
        return [(0, kept, False)]
    gaps = (np.zeros(kept, dtype=bool) if positions is None
            else np.diff(positions, prepend=-1) > 1)
    starts = gaps.copy()
    starts[0] = True
    if held is not None:
        starts[1:] |= held[1:] != held[:-1]
    firsts = np.flatnonzero(starts).tolist()
    return [(first, stop, bool(gaps[first]))
            for first, stop in zip(firsts, firsts[1:] + [kept])]


class SampleFeeder:
    """
    Feed samples to an estimator with the identifier node's bad-sample policy.

    * A sample with NaN or Inf is not used; it is counted in ``nonfinite``
      and the estimator's regressor is restarted, so that no update
      regresses across the missing sample.
    * :meth:`gap` restarts the regressor for samples lost elsewhere (a
      malformed message, an unpaired or out-of-order sample, a stamp gap).
    * A run of more than ``excitation_window`` samples with an unchanged
      input is counted in ``unexcited`` (the samples are still used; the
      estimators guard their covariance against wind-up), or, with
      ``freeze_unexcited``, taken with the adaptation held.

    :meth:`take_message` and :meth:`take_rows` are the identifier's whole
    per-message rule (what is dropped, what restarts the regressor, when
    estimates are published); they say what happened in a
    :class:`FeedResult`. identifier_node goes through them, and ``bcid
    replay`` through :meth:`take_messages`, the same rule for a block of
    messages at once, which is why they agree bit for bit.

    Parameters
    ----------
    estimator : RecursiveEstimator
        The estimator to feed.
    excitation_window : int
        Samples of unchanged input before a sample counts as unexcited;
        0 turns the check off.
    publish_period : int
        Samples between published estimates (see :meth:`due_estimates`).
    freeze_unexcited : bool
        Hold the estimator's adaptation (``excitation_hold``) while the
        input is unexcited, instead of using the samples.

    """

    def __init__(self, estimator: Any, excitation_window: int = 0,
                 publish_period: int = 1, freeze_unexcited: bool = False) -> None:
        self.estimator = estimator
        self.freeze_unexcited = bool(freeze_unexcited)
        self.excitation_window = int(excitation_window)
        self.publish_period = int(publish_period)
        self.since_publish = 0
        #: Totals since construction (a reset keeps them).
        self.used = 0
        self.nonfinite = 0
        self.unexcited = 0
        #: The estimator's update times since the diagnostics last took them.
        self.times = UpdateTimes()
        self._last_u: list[float] | None = None
        self._constant_run = 0
        self._restart_pending = False

    def feed(self, rows: np.ndarray, result: FeedResult | None = None) -> FeedResult:
        """
        Feed rows ``[y, u1, ..., ur]`` (shape ``(k, 1 + r)``) to the estimator.

        Parameters
        ----------
        rows : numpy.ndarray, shape ``(k, 1 + r)``
            The samples, oldest first.
        result : FeedResult, optional
            Add the counts to this one (a fresh one by default).

        Returns
        -------
        FeedResult
            ``used``, ``nonfinite`` and ``unexcited`` counted; the rest untouched.

        Raises
        ------
        ValueError
            If a row does not have 1 + r values (nothing is fed then).
        Exception
            What the estimator raised (the rows after it are not fed, nothing is counted).

        """
        if result is None:
            result = FeedResult()
        rows = checked_rows(rows, self.estimator.num_inputs)
        plan = self._plan(rows)
        self._feed(plan, rows.shape[0], self.times)
        self._end(plan, rows.shape[0])
        if plan.error is not None:
            raise plan.error
        self._count(plan.counts(0, rows.shape[0]), result)
        return result

    def _count(self, counts: tuple[int, int, int], result: FeedResult | BlockResult) -> None:
        """Add ``(used, nonfinite, unexcited)`` to the totals and to ``result``."""
        used, nonfinite, unexcited = counts
        self.used += used
        self.nonfinite += nonfinite
        self.unexcited += unexcited
        self.since_publish += used
        result.used += used
        result.nonfinite += nonfinite
        result.unexcited += unexcited

    def _plan(self, rows: np.ndarray) -> _Plan:
        """
        Decide the per-sample rule for a block of rows at once (vectorised).

        A row with NaN or Inf is skipped and restarts the regressor before the
        next one; the excitation check runs on the rows used and, with
        ``freeze_unexcited``, holds the adaptation from the row whose run
        reaches the window. The rows between those events are stretches,
        each one :meth:`update_block` of the estimator (see :meth:`_feed`).
        """
        finite = None if block_is_finite(rows) else usable_samples(rows[:, 0], rows[:, 1:])
        kept = rows if finite is None else rows[finite]
        positions = None if finite is None else np.flatnonzero(finite)
        runs = self._constant_runs(kept[:, 1:])
        quiet = held = quiet_before = None
        if runs is not None:
            window = self.excitation_window
            if isinstance(runs, list):  # a few rows: in Python, cheaper than numpy's calls
                quiet = [run >= window for run in runs]
                quiet_before = list(itertools.accumulate(quiet, initial=0))
            else:
                quiet = runs >= window
                quiet_before = [0, *np.cumsum(quiet).tolist()]
            held = np.asarray(quiet) if self.freeze_unexcited else None
        return _Plan(kept, positions, runs, quiet_before, held,
                     _stretches(rows.shape[0], positions, held))

    def _feed(self, plan: _Plan, end: int, times: UpdateTimes | None) -> bool:
        """
        Feed the planned rows before row ``end`` of the block; return False if one raised.

        The one loop of the feeder: each stretch (or the part of one before
        ``end``) is one :meth:`update_block` of the estimator, whose estimate
        is that of the rows one by one. It stops at the first row whose
        update raises (``plan.error``). ``times``: time the updates (None:
        count them only).
        """
        estimator, kept, stretches = self.estimator, plan.kept, plan.stretches
        stop_kept = plan.kept_before(end)
        try:
            while plan.stretch < len(stretches) and plan.taken < stop_kept:
                first, stop, gap = stretches[plan.stretch]
                if plan.taken == first:
                    if gap:
                        self._restart_pending = True
                    if plan.held is not None:
                        estimator.excitation_hold = bool(plan.held[first])
                if self._restart_pending:
                    estimator.restart_regressor()
                    self._restart_pending = False
                last = min(stop, stop_kept)
                taken = estimator.update_block(kept[plan.taken:last], times)
                if times is None:
                    self.times.add(taken)
                plan.taken += taken
                if plan.taken == stop:
                    plan.stretch += 1
        except BlockStopped as stopped:
            plan.taken += stopped.taken
            if times is None:
                self.times.add(stopped.taken)
            plan.error = stopped.error
            return False
        return True

    def _end(self, plan: _Plan, rows: int) -> None:
        """Keep the excitation state and a pending restart after a plan of ``rows`` rows."""
        kept, positions = plan.kept.shape[0], plan.positions
        if plan.error is None and positions is not None and (
                not kept or positions[-1] < rows - 1):
            self._restart_pending = True  # rows skipped at the end
        if plan.runs is not None and kept:  # a failing row's check came before its update
            self._keep_run(plan.runs, plan.kept[:, 1:], min(plan.taken, kept - 1))

    def _constant_runs(self, inputs: np.ndarray) -> np.ndarray | list[int] | None:
        """
        Return the unchanged-input run after each of these samples (None without a window).

        The run grows by one for a sample whose input equals the previous one
        and is 0 otherwise; a sample is unexcited when its run reaches the
        window. Sample by sample for a few samples (a list: cheaper than the
        vectorised form under ``VECTOR_CHECK_MIN``), vectorised for more.
        """
        if not self.excitation_window:
            return None
        count = inputs.shape[0]
        if count < VECTOR_CHECK_MIN:
            last, run, runs = self._last_u, self._constant_run, []
            for u in inputs.tolist():
                run, last = (run + 1, last) if u == last else (0, u)
                runs.append(run)
            return runs
        first_same = self._last_u is not None and inputs[0].tolist() == self._last_u
        changes = inputs[1:] != inputs[:-1]
        if changes.all():  # every input differs from the one before: no run past sample 0
            runs = np.zeros(count, dtype=np.int64)
            runs[0] = self._constant_run + 1 if first_same else 0
            return runs
        same = np.empty(count, dtype=bool)
        same[0] = first_same
        same[1:] = ~changes.any(axis=1)
        steps = np.arange(count)
        reset = np.maximum.accumulate(np.where(same, -1, steps))
        return np.where(reset >= 0, steps - reset, self._constant_run + steps + 1)

    def _keep_run(self, runs: np.ndarray, inputs: np.ndarray, last: int) -> None:
        """Keep the excitation state after sample ``last`` of a block (see _constant_runs)."""
        self._constant_run = int(runs[last])
        self._last_u = inputs[last].tolist()

    def take_message(self, message: Any) -> FeedResult:
        """
        Decode and feed one samples message; return what happened, with the due estimates.

        An empty message is dropped; a malformed one is dropped and restarts
        the regressor (a sample may be missing); see :meth:`take_rows` for the
        rest.
        """
        try:
            rows = decode_samples(message, self.estimator.num_inputs)
        except ValueError as error:
            reason = str(error)
            if reason.startswith('empty'):
                return FeedResult(dropped='empty', reason=reason)
            self.gap()
            return FeedResult(dropped='bad_layout', reason=reason)
        return self.take_rows(rows)

    def take_rows(self, rows: np.ndarray) -> FeedResult:
        """
        Feed the rows of one message; return what happened, with the due estimates.

        If the estimator raises, the rest of the rows are dropped, the
        regressor restarts and the result says ``'estimator_errors'``.
        """
        result = FeedResult()
        try:
            self.feed(rows, result)
        except Exception as error:  # an estimator failure must not stop the stream
            self.gap()
            result.dropped = 'estimator_errors'
            result.reason = repr(error)
            return result
        self._add_estimates(result)
        return result

    def take_messages(self, rows: np.ndarray, count: int, publish: bool = True,
                      timed: bool = True) -> BlockResult:
        """
        Feed consecutive messages of ``count`` samples each, with the rule of :meth:`take_rows`.

        The result is what calling :meth:`take_rows` on each message in turn
        would give, estimator state and counts alike, but without a call per
        message: this is how ``bcid replay`` feeds a bag's blocks.

        Parameters
        ----------
        rows : numpy.ndarray, shape ``(m count, 1 + r)``
            The samples of m messages, oldest first.
        count : int
            Samples per message, >= 1.
        publish : bool
            Whether to collect the due estimates; without, nothing is
            checked for publication (for a caller that publishes nothing).
        timed : bool
            Whether to time each update for :meth:`take_update_times`; without,
            the updates of a finite block are counted but not timed (for a caller
            that reports no update times: two clock readings cost a few per cent
            of an update).

        Returns
        -------
        BlockResult

        Raises
        ------
        ValueError
            If the rows are not m whole messages of 1 + r values (nothing is fed then).

        """
        estimator = self.estimator
        rows = np.asarray(rows, dtype=float)
        width = 1 + estimator.num_inputs
        if count < 1 or rows.ndim != 2 or rows.shape[1] != width or rows.shape[0] % count:
            raise ValueError(f'rows must be whole messages of count = {count} samples of '
                             f'1 + num_inputs = {width} values, got shape {rows.shape}')
        result = BlockResult()
        messages = rows.shape[0] // count
        times = self.times if timed else None
        first = 0
        while first < messages:
            # the rule for the messages from ``first`` on, decided at once (again after a
            # failure: the rows it drops are not checked either)
            plan = self._plan(rows[first * count:])
            span = messages - first
            done = 0
            while done < span:
                # up to the first message after which estimates may be due (samples
                # skipped for NaN only put that later: the check then says not yet)
                stop = span if not publish else min(span, done + max(
                    1, -(-(self.publish_period - self.since_publish) // count)))
                if not self._feed(plan, stop * count, times):
                    break
                self._count(plan.counts(done * count, stop * count), result)
                if publish and self._due():
                    self._collect(result, first + stop - 1)
                done = stop
            self._end(plan, span * count)
            if plan.error is None:
                break
            # as in take_rows: the failing message is dropped, the regressor restarts
            failed = plan.failed_row() // count
            self._count(plan.counts(done * count, failed * count), result)
            self.gap()
            result.failures.append((first + failed, repr(plan.error)))
            first += failed + 1
        return result

    def _collect(self, result: BlockResult, index: int) -> None:
        """Add the estimates due after message ``index`` to ``result`` (or count them withheld)."""
        estimates = self.due_estimates()
        if estimates is None:
            result.withheld += 1
            return
        result.published.append(index)
        result.used_totals.append(self.used)
        result.estimates.append(estimates)
        result.valid.append(bool(self.estimator.valid))
        result.flags.append(dict(self.estimator.flags))

    def _add_estimates(self, result: FeedResult) -> None:
        estimates = self.due_estimates()
        if estimates is None and self._due():
            result.withheld = True
        result.estimates = estimates

    def _due(self) -> bool:
        return self.since_publish >= self.publish_period and bool(self.estimator.ready)

    def due_estimates(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """
        Return ``(theta, theta_uncompensated, noise)`` if it is time to publish them.

        It is time once ``publish_period`` samples were used since the last
        publication and the estimator is ready (``~/valid`` says whether to trust
        it). A non-finite estimate is never
        returned (and the count since the last publication goes on).
        """
        if not self._due():
            return None
        estimator = self.estimator
        theta = estimator.theta
        uncompensated = estimator.theta_uncompensated
        if not all_finite(theta, uncompensated):
            return None
        self.since_publish = 0
        return theta, uncompensated, estimator.noise

    def gap(self) -> None:
        """Note that samples are missing here: restart the regressor before the next update."""
        self._restart_pending = True

    def reset(self) -> None:
        """Reset the estimator and forget the input history (the totals are kept)."""
        self.estimator.reset()
        self.estimator.excitation_hold = False  # freeze_unexcited starts over too
        self.since_publish = 0
        self._last_u = None
        self._constant_run = 0
        self._restart_pending = False

    def take_update_times(self) -> tuple[int, float, float]:
        """Return ``(updates, mean µs, max µs)`` since the last call, and start over."""
        return self.times.take()

    @property
    def excitation_lost(self) -> bool:
        """Whether the input is constant right now (for longer than the window)."""
        return bool(self.excitation_window) and self._constant_run >= self.excitation_window

    def get_state(self) -> dict[str, Any]:
        """
        Return the feeder's own state as plain values (the estimator's is its own).

        With the estimator's snapshot it is all that the next results depend
        on: the count towards the next publication, the input history of the
        excitation check, a pending regressor restart, and the totals.
        """
        return {'since_publish': self.since_publish, 'used': self.used,
                'nonfinite': self.nonfinite, 'unexcited': self.unexcited,
                'last_u': None if self._last_u is None else list(self._last_u),
                'constant_run': self._constant_run, 'restart_pending': self._restart_pending}

    def set_state(self, state: dict[str, Any]) -> None:
        """Restore a state made by :meth:`get_state` (KeyError if one is missing)."""
        last_u = state['last_u']
        values = (int(state['since_publish']), int(state['used']), int(state['nonfinite']),
                  int(state['unexcited']), None if last_u is None else [float(v) for v in last_u],
                  int(state['constant_run']), bool(state['restart_pending']))
        (self.since_publish, self.used, self.nonfinite, self.unexcited, self._last_u,
         self._constant_run, self._restart_pending) = values


__all__ = ['BlockResult', 'FeedResult', 'SampleFeeder', 'block_is_finite']
