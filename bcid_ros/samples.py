"""
The ``samples`` message format of SPEC sections 3 and 4 (pure Python, no ROS).

Everything here works on duck-typed messages: anything with ``data`` and
``layout.dim[i].label/size/stride`` (and ``layout.data_offset``) will do, so
the same code decodes live rclpy messages and the objects that
``mcap_ros2`` decodes from bags.

:class:`SampleFeeder` feeds decoded samples to an estimator with the
identifier node's policy for bad samples. The node and the offline replay
both use it, so they give the same estimates on the same messages.
"""

from __future__ import annotations

import time
from typing import Any, Iterable, Sequence

import numpy as np

#: ``layout.dim[0].label`` of a frame (a message holding k samples).
FRAME_LABEL = 'samples'


def sample_label(num_inputs: int) -> str:
    """Return the label of one sample row, ``'y,u1,...,ur'``."""
    return ','.join(['y'] + [f'u{i}' for i in range(1, num_inputs + 1)])


def names_label(names: Iterable[str]) -> str:
    """Return the comma-separated label of the estimate topics (SPEC section 4)."""
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
        k > 1 is a SPEC section 3 frame with two.
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
      estimators guard their covariance against wind-up).

    :meth:`take_message`, :meth:`take_rows` and :meth:`due_estimates` are the
    identifier's whole per-message rule (what is dropped, what restarts the
    regressor, when estimates are published). identifier_node and
    ``bcid replay`` both go through them, which is why they agree bit for bit.

    Parameters
    ----------
    estimator : RecursiveEstimator
        The estimator to feed.
    excitation_window : int
        Samples of unchanged input before a sample counts as unexcited;
        0 turns the check off.
    publish_period : int
        Samples between published estimates (see :meth:`due_estimates`).

    """

    def __init__(self, estimator: Any, excitation_window: int = 0,
                 publish_period: int = 1) -> None:
        self.estimator = estimator
        self.excitation_window = int(excitation_window)
        self.publish_period = int(publish_period)
        self.since_publish = 0
        self.nonfinite_estimates = 0
        #: What went wrong with the last message or rows that were refused.
        self.problem = ''
        self.used = 0
        self.nonfinite = 0
        self.unexcited = 0
        self.gaps = 0
        self.update_count = 0
        self.update_ns_total = 0
        self.update_ns_max = 0
        self._last_u: list[float] | None = None
        self._constant_run = 0
        self._restart_pending = False

    def feed(self, rows: np.ndarray) -> int:
        """
        Feed rows ``[y, u1, ..., ur]`` (shape ``(k, 1 + r)``); return how many were used.

        Raises
        ------
        ValueError
            If a row does not have 1 + r values (nothing is fed then).

        """
        estimator = self.estimator
        rows = np.asarray(rows, dtype=float)
        if rows.ndim != 2 or rows.shape[1] != 1 + estimator.num_inputs:
            raise ValueError(f'rows must have 1 + num_inputs = {1 + estimator.num_inputs} '
                             f'columns, got shape {rows.shape}')
        used = 0
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
                self.nonfinite += 1
                self.gap(count=False)
                continue
            if window:
                u = input_lists[k]
                if u == self._last_u:
                    self._constant_run += 1
                    if self._constant_run >= window:
                        self.unexcited += 1
                else:
                    self._constant_run = 0
                    self._last_u = u
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
        return used

    def take_message(self, message: Any) -> str | None:
        """
        Decode and feed one samples message; return what was wrong with it, or None.

        An empty message is dropped; a malformed one is dropped and restarts
        the regressor (a sample may be missing); see :meth:`take_rows` for the
        rest. The reason is left in :attr:`problem`.

        Returns
        -------
        str or None
            ``'empty'``, ``'bad_layout'``, ``'estimator_errors'`` or None.

        """
        try:
            rows = decode_samples(message, self.estimator.num_inputs)
        except ValueError as error:
            self.problem = str(error)
            if self.problem.startswith('empty'):
                return 'empty'
            self.gap(count=False)
            return 'bad_layout'
        return self.take_rows(rows)

    def take_rows(self, rows: np.ndarray) -> str | None:
        """Feed rows; return ``'estimator_errors'`` if the estimator raised, else None."""
        try:
            self.since_publish += self.feed(rows)
        except Exception as error:  # an estimator failure must not stop the stream
            self.gap(count=False)
            self.problem = repr(error)
            return 'estimator_errors'
        return None

    def due_estimates(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """
        Return ``(theta, theta_uncompensated, noise)`` if it is time to publish them.

        It is time once ``publish_period`` samples were used since the last
        publication and the estimate is valid. A non-finite estimate is never
        returned: it is counted in :attr:`nonfinite_estimates` instead.
        """
        estimator = self.estimator
        if self.since_publish < self.publish_period or not estimator.valid:
            return None
        theta = estimator.theta
        uncompensated = estimator.theta_uncompensated
        if not (np.isfinite(theta).all() and np.isfinite(uncompensated).all()):
            self.nonfinite_estimates += 1
            return None
        self.since_publish = 0
        return theta, uncompensated, estimator.noise

    def gap(self, count: bool = True) -> None:
        """
        Note that samples are missing here: restart the regressor before the next update.

        Parameters
        ----------
        count : bool
            Count it in ``gaps`` (the caller counts the reason otherwise).

        """
        if count:
            self.gaps += 1
        self._restart_pending = True

    def reset(self) -> None:
        """Reset the estimator and forget the input history (counters are kept)."""
        self.estimator.reset()
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


__all__ = ['FRAME_LABEL', 'SampleFeeder', 'decode_samples', 'estimate_layout', 'names_label',
           'parse_names_label', 'sample_label', 'samples_data', 'samples_layout']
