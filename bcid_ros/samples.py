"""
The ``samples`` message format of docs/nodes.md (pure Python, no ROS).

Everything here works on duck-typed messages: anything with ``data`` and
``layout.dim[i].label/size/stride`` (and ``layout.data_offset``) will do, so
the same code decodes live rclpy messages and the objects that
``mcap_ros2`` decodes from bags.

:class:`SampleFeeder` feeds decoded samples to an estimator with the
identifier node's policy for bad samples. The node and the offline replay
both use it, so they give the same estimates on the same messages.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any, Iterable, Sequence

import numpy as np

#: ``layout.dim[0].label`` of a frame (a message holding k samples).
FRAME_LABEL = 'samples'


def sample_label(num_inputs: int) -> str:
    """Return the label of one sample row, ``'y,u1,...,ur'``."""
    return ','.join(['y'] + [f'u{i}' for i in range(1, num_inputs + 1)])


def names_label(names: Iterable[str]) -> str:
    """Return the comma-separated label of the estimate topics (docs/nodes.md)."""
    return ','.join(names)


def parse_names_label(label: str) -> tuple[str, ...]:
    """Return the names of a comma-separated label (the inverse of :func:`names_label`)."""
    return tuple(name.strip() for name in label.split(',')) if label else ()


def samples_layout(count: int, num_inputs: int) -> list[tuple[str, int, int]]:
    """
    Return the ``(label, size, stride)`` dimensions of a samples message.

    Parameters
    ----------
    count : int
        Samples in the message, k >= 1. One sample has a single dimension;
        k > 1 is a frame (docs/nodes.md) with two.
    num_inputs : int
        r.

    Returns
    -------
    list of tuple
        The ``layout.dim`` entries, outermost first.

    """
    width = 1 + num_inputs
    row = (sample_label(num_inputs), width, width)
    if count == 1:
        return [row]
    return [(FRAME_LABEL, count, count * width), row]


def samples_data(y: Any, u: Any) -> np.ndarray:
    """
    Return the row-major data ``[y(t), u1(t), ..., ur(t), y(t+1), ...]``.

    Parameters
    ----------
    y : array_like, shape ``(k,)``
        Outputs.
    u : array_like, shape ``(k,)`` or ``(k, r)``
        Inputs.

    Returns
    -------
    numpy.ndarray, shape ``(k (1 + r),)``

    """
    y = np.asarray(y, dtype=float).reshape(-1)
    u = np.asarray(u, dtype=float).reshape(y.shape[0], -1)
    return np.column_stack([y, u]).reshape(-1)


def estimate_layout(names: Sequence[str]) -> tuple[str, int, int]:
    """Return the single ``(label, size, stride)`` dimension of an estimate message."""
    return names_label(names), len(names), len(names)


def decode_samples(message: Any, num_inputs: int | None = None) -> np.ndarray:
    """
    Decode a ``samples`` message into rows ``[y, u1, ..., ur]``.

    Accepts one sample (no layout, or one dimension of size 1 + r) and
    frames (two dimensions: ``samples`` of size k, then the row of size
    1 + r). Values are not checked for NaN/Inf here; that is per sample, in
    :class:`SampleFeeder`.

    Parameters
    ----------
    message : std_msgs/msg/Float64MultiArray or alike
        Needs ``data`` and ``layout.dim``; ``layout.data_offset`` is honoured.
    num_inputs : int, optional
        r; when given the row width must be 1 + r.

    Returns
    -------
    numpy.ndarray, shape ``(k, 1 + r)``
        A fresh float array.

    Raises
    ------
    ValueError
        If the message is empty or its length or layout is wrong; the
        message says what was expected.

    """
    layout = getattr(message, 'layout', None)
    dims = list(getattr(layout, 'dim', None) or [])
    offset = int(getattr(layout, 'data_offset', 0) or 0)
    data = np.asarray(message.data, dtype=float).reshape(-1)
    if offset:
        if offset < 0 or offset > data.shape[0]:
            raise ValueError(f'layout.data_offset {offset} is outside the {data.shape[0]} '
                             'values')
        data = data[offset:]
    length = data.shape[0]
    if length == 0:
        raise ValueError('empty message (no values)')
    expected = None if num_inputs is None else 1 + num_inputs
    if len(dims) > 2:
        raise ValueError(f'layout has {len(dims)} dimensions; expected 1 (one sample) '
                         f'or 2 (a frame: {FRAME_LABEL!r} x row)')
    if len(dims) == 2:
        frame, row = dims
        if frame.label != FRAME_LABEL:
            raise ValueError(f'a two-dimensional layout must have dim[0].label '
                             f'{FRAME_LABEL!r}, got {frame.label!r}')
        count, width = int(frame.size), int(row.size)
        if count == 0:
            raise ValueError('empty frame (dim[0].size is 0)')
        if expected is not None and width != expected:
            raise ValueError(f'frame rows have {width} values; expected 1 + num_inputs = '
                             f'{expected} (y,u1,...,ur)')
        if width < 2:
            raise ValueError(f'frame rows have {width} values; expected at least 2 (y, u1)')
        if count * width != length:
            raise ValueError(f'frame of {count} x {width} needs {count * width} values, got '
                             f'{length}')
        if row.stride not in (0, width) or frame.stride not in (0, count * width):
            raise ValueError(f'frame strides ({frame.stride}, {row.stride}) do not match a '
                             f'row-major {count} x {width} frame')
        return data.reshape(count, width).copy()
    if dims:
        dim = dims[0]
        if dim.label == FRAME_LABEL:
            raise ValueError(f'a frame (dim[0].label {FRAME_LABEL!r}) needs a second '
                             'dimension for the row')
        if dim.size not in (0, length):
            raise ValueError(f'dim[0].size is {dim.size} but the message has {length} values')
    if expected is not None and length != expected:
        raise ValueError(f'a sample has {length} values; expected 1 + num_inputs = '
                         f'{expected} (y,u1,...,ur)')
    if length < 2:
        raise ValueError(f'a sample has {length} value; expected at least 2 (y, u1)')
    return data.reshape(1, length).copy()


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
    :class:`FeedResult`. identifier_node and ``bcid replay`` both go through
    them, which is why they agree bit for bit.

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
        used = nonfinite = unexcited = 0
        clock = time.perf_counter_ns
        window = self.excitation_window
        # The checks of estimator.update, done once for the block: the shape
        # above, finiteness here; then each sample goes in unchecked.
        finite = np.isfinite(rows).all(axis=1).tolist()
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
        self.used += used
        self.nonfinite += nonfinite
        self.unexcited += unexcited
        self.since_publish += used
        result.used += used
        result.nonfinite += nonfinite
        result.unexcited += unexcited
        return result

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
        if not (np.isfinite(theta).all() and np.isfinite(uncompensated).all()):
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


__all__ = ['FRAME_LABEL', 'FeedResult', 'SampleFeeder', 'decode_samples', 'estimate_layout',
           'names_label', 'parse_names_label', 'sample_label', 'samples_data', 'samples_layout']
