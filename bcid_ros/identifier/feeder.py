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
import time
from typing import Any, Callable

import numpy as np

from bcid_ros.estimators.base import all_finite
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
        self.update_count = 0
        self.update_ns_total = 0
        self.update_ns_max = 0
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

        """
        if result is None:
            result = FeedResult()
        estimator = self.estimator
        rows = np.asarray(rows, dtype=float)
        if rows.ndim != 2 or rows.shape[1] != 1 + estimator.num_inputs:
            raise ValueError(f'rows must have 1 + num_inputs = {1 + estimator.num_inputs} '
                             f'columns, got shape {rows.shape}')
        # The checks of estimator.update, done once for the block: the shape
        # above, finiteness here; then each sample goes in unchecked.
        short = self.excitation_window and rows.shape[0] < VECTOR_CHECK_MIN
        # freeze_unexcited sets the hold sample by sample: only the checked loop does that
        if not short and not self.freeze_unexcited and block_is_finite(rows):
            (used, unexcited), nonfinite = self._feed_finite(rows), 0
        else:
            finite = np.isfinite(rows).all(axis=1).tolist()
            used, nonfinite, unexcited = self._feed_checked(rows, finite)
        self.used += used
        self.nonfinite += nonfinite
        self.unexcited += unexcited
        self.since_publish += used
        result.used += used
        result.nonfinite += nonfinite
        result.unexcited += unexcited
        return result

    def _feed_finite(self, rows: np.ndarray) -> tuple[int, int]:
        """Feed rows known to be finite; return (used, unexcited)."""
        total_rows = rows.shape[0]
        if not total_rows:
            return 0, 0
        inputs = rows[:, 1:]
        runs = self._constant_runs(inputs)
        estimator = self.estimator
        clock = time.perf_counter_ns
        count = total = 0
        largest = self.update_ns_max
        try:
            if self._restart_pending:
                estimator.restart_regressor()
                self._restart_pending = False
            update = estimator.trusted_block_update(rows)
            for y, u in zip(rows[:, 0].tolist(), inputs):
                start = clock()
                update(y, u)
                elapsed = clock() - start
                count += 1
                total += elapsed
                if elapsed > largest:
                    largest = elapsed
        finally:
            self.update_count += count
            self.update_ns_total += total
            self.update_ns_max = largest
            if runs is not None:  # the check of a failing sample came before its update
                self._keep_run(runs, inputs, min(count, total_rows - 1))
        unexcited = 0 if runs is None else int(np.count_nonzero(runs >= self.excitation_window))
        return count, unexcited

    def _constant_runs(self, inputs: np.ndarray) -> np.ndarray | None:
        """
        Return the unchanged-input run after each of these finite samples (None without a window).

        The excitation check of :meth:`_feed_checked` for a whole block: the
        run grows by one for a sample whose input equals the previous one and
        is 0 otherwise; a sample is unexcited when its run reaches the window.
        """
        if not self.excitation_window:
            return None
        count = inputs.shape[0]
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

    def _feed_checked(self, rows: np.ndarray, finite: list[bool]) -> tuple[int, int, int]:
        """Feed rows with NaN/Inf skipping and the excitation check; return the counts."""
        estimator = self.estimator
        used = nonfinite = unexcited = 0
        clock = time.perf_counter_ns
        window = self.excitation_window
        outputs = rows[:, 0].tolist()
        inputs = rows[:, 1:]
        input_lists = inputs.tolist() if window else None
        update = estimator.update_trusted
        for k, y in enumerate(outputs):
            if not finite[k]:
                nonfinite += 1
                self._restart_pending = True
                continue
            if window:
                u = input_lists[k]
                if u == self._last_u:
                    self._constant_run += 1
                    if self._constant_run >= window:
                        unexcited += 1
                else:
                    self._constant_run = 0
                    self._last_u = u
                # --- freeze_unexcited: hold the adaptation while the input is constant
                if self.freeze_unexcited:
                    estimator.excitation_hold = self._constant_run >= window
            if self._restart_pending:
                estimator.restart_regressor()
                self._restart_pending = False
            start = clock()
            update(y, inputs[k])
            elapsed = clock() - start
            self.update_count += 1
            self.update_ns_total += elapsed
            if elapsed > self.update_ns_max:
                self.update_ns_max = elapsed
            used += 1
        return used, nonfinite, unexcited

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
        if not self.freeze_unexcited and block_is_finite(rows):
            self._take_finite(rows, count, publish, result, timed)
        else:
            self._take_each(rows, count, publish, result)
        return result

    def _take_each(self, rows: np.ndarray, count: int, publish: bool,
                   result: BlockResult) -> None:
        """Feed message by message through :meth:`feed` (for blocks with samples to skip)."""
        for index in range(rows.shape[0] // count):
            fed = FeedResult()
            try:
                self.feed(rows[index * count:(index + 1) * count], fed)
            except Exception as error:  # as in take_rows
                self.gap()
                result.failures.append((index, repr(error)))
                continue
            result.used += fed.used
            result.nonfinite += fed.nonfinite
            result.unexcited += fed.unexcited
            if publish and self._due():
                self._collect(result, index)

    def _take_finite(self, rows: np.ndarray, count: int, publish: bool,
                     result: BlockResult, timed: bool = True) -> None:
        """Feed finite samples: one loop over the samples, the excitation check vectorised."""
        messages = rows.shape[0] // count
        updates = total = 0
        largest = self.update_ns_max
        first = 0
        try:
            while first < messages:
                # Until an update fails, from message ``first`` on; then again after it.
                first, done, elapsed = self._take_finite_from(rows, count, first, publish,
                                                              result, largest, timed)
                updates += done
                total += elapsed[0]
                largest = elapsed[1]
        finally:
            self.update_count += updates
            self.update_ns_total += total
            self.update_ns_max = largest

    def _take_finite_from(self, rows: np.ndarray, count: int, first: int, publish: bool,
                          result: BlockResult, largest: int, timed: bool = True
                          ) -> tuple[int, int, tuple[int, int]]:
        """
        Feed messages from ``first`` on until one fails or all are done.

        Without ``publish`` nothing happens between messages, so the samples
        of all go through one loop. Returns the message to go on from, the
        updates made and their ``(total, largest)`` time in ns.
        """
        estimator = self.estimator
        period = self.publish_period
        window = self.excitation_window
        inputs = rows[first * count:, 1:]
        runs = self._constant_runs(inputs)
        unexcited = (None if runs is None else
                     np.count_nonzero((runs >= window).reshape(-1, count), axis=1).tolist())
        outputs = rows[first * count:, 0].tolist()
        input_rows = list(inputs)
        messages = len(outputs) // count
        if self._restart_pending:  # only a failure sets it, and a failure ends this call
            estimator.restart_regressor()
            self._restart_pending = False
        update = estimator.trusted_block_update(rows[first * count:])
        updates = total = sample = 0
        failed = None
        for index in range(messages if publish else 1):
            stop = sample + count if publish else len(outputs)
            done, elapsed, largest, error = self._run_updates(update, outputs, input_rows, sample,
                                                              stop, timed, largest)
            updates += done
            total += elapsed
            sample += done
            if publish:
                whole, start = (1 if error is None else 0), index
            else:
                whole, start = (messages if error is None else sample // count), 0
            self._count_messages(whole, count, unexcited, start, result)
            if error is not None:  # as in take_rows: drop the rest, restart
                failed = sample // count
                self._restart_pending = True
                result.failures.append((first + failed, repr(error)))
                break
            if publish and self.since_publish >= period and estimator.ready:
                self._collect(result, first + index)
        if runs is not None:
            self._keep_run(runs, inputs, min(sample, len(outputs) - 1))
        following = first + messages if failed is None else first + failed + 1
        return following, updates, (total, largest)

    def _count_messages(self, messages: int, count: int, unexcited: list[int] | None,
                        start: int, result: BlockResult) -> None:
        """Count ``messages`` whole messages of ``count`` samples from ``start`` on as used."""
        if messages <= 0:
            return
        used = messages * count
        self.used += used
        self.since_publish += used
        result.used += used
        if unexcited is not None:
            quiet = sum(unexcited[start:start + messages])
            self.unexcited += quiet
            result.unexcited += quiet

    @staticmethod
    def _run_updates(update: Callable[[float, np.ndarray], None], outputs: list[float],
                     inputs: list[np.ndarray], begin: int, end: int, timed: bool,
                     largest: int) -> tuple[int, int, int, Exception | None]:
        """
        Update on samples ``begin`` to ``end - 1`` with ``update``; stop at the first that raises.

        ``update`` is the estimator's ``trusted_block_update`` of the block.
        Returns the updates made, their total and largest time in ns (0 and
        ``largest`` unless ``timed``), and the exception (None if none).
        """
        sample, total = begin, 0
        try:
            if timed:
                clock = time.perf_counter_ns
                while sample < end:
                    start = clock()
                    update(outputs[sample], inputs[sample])
                    elapsed = clock() - start
                    total += elapsed
                    if elapsed > largest:
                        largest = elapsed
                    sample += 1
            else:
                for sample in range(begin, end):
                    update(outputs[sample], inputs[sample])
                sample = end
        except Exception as error:  # the caller drops the rest and restarts
            return sample - begin, total, largest, error
        return sample - begin, total, largest, None

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
        count = self.update_count
        mean = self.update_ns_total / count / 1e3 if count else 0.0
        largest = self.update_ns_max / 1e3
        self.update_count = 0
        self.update_ns_total = 0
        self.update_ns_max = 0
        return count, mean, largest

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
