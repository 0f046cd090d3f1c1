"""
The layouts of the identifier's messages (docs/nodes.md), and decoding a samples message (no ROS).

A samples message holds one row ``[y, u1, ..., ur]`` or a frame of k rows;
an estimate message one labelled vector; ``~/parameter_covariance`` a
labelled p x p matrix. Everything here works on duck-typed messages:
anything with ``data`` and ``layout.dim[i].label/size/stride`` (and
``layout.data_offset``) will do, so the same code decodes live rclpy
messages and the objects that ``mcap_ros2`` or :mod:`bcid_ros.identifier.cdr`
decode from bags.
"""

from __future__ import annotations

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

    The row's label is honoured (:func:`row_order`): a row labelled
    ``u1,u2,y`` is reordered to ``y,u1,u2``; a label that names other columns
    (``temp,heater,fan``) is refused. A label without a comma names no columns
    and is ignored, as an empty one.

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
        return in_row_order(data.reshape(count, width), row_order(row.label, width))
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
    order = row_order(dims[0].label, length) if dims else None
    return in_row_order(data.reshape(1, length), order)


def row_order(label: str, width: int) -> list[int] | None:
    """
    Return where each of ``y, u1, ..., ur`` is in a row labelled ``label`` (None: in order).

    Parameters
    ----------
    label : str
        The row dimension's label: empty or one word (names no columns: taken
        in order), or the comma-separated column names in any order.
    width : int
        1 + r.

    Raises
    ------
    ValueError
        If the label names columns that are not ``y, u1, ..., ur`` each once.

    """
    if not label or ',' not in label:
        return None
    names = parse_names_label(label)
    expected = sample_label(width - 1).split(',')
    if sorted(names) != sorted(expected) or len(set(names)) != len(names):
        raise ValueError(f'the row label {label!r} names other columns than '
                         f'{",".join(expected)} (relabel them, or leave the label empty for '
                         'that order)')
    order = [names.index(name) for name in expected]
    return None if order == list(range(width)) else order


def in_row_order(rows: np.ndarray, order: list[int] | None) -> np.ndarray:
    """Return a fresh copy of ``rows`` with its columns in ``y, u1, ..., ur`` order."""
    return rows.copy() if order is None else rows[:, order]


def covariance_layout(names: Sequence[str]) -> list[tuple[str, int, int]]:
    """
    Return the ``(label, size, stride)`` dimensions of ``~/parameter_covariance``.

    A row-major p x p matrix: both dimensions carry the comma-separated
    parameter names of ``~/parameters``.

    >>> covariance_layout(('a1', 'b1_1'))
    [('a1,b1_1', 2, 4), ('a1,b1_1', 2, 2)]
    """
    label, size = names_label(names), len(names)
    return [(label, size, size * size), (label, size, size)]


__all__ = ['FRAME_LABEL', 'covariance_layout', 'decode_samples', 'estimate_layout',
           'in_row_order', 'row_order',
           'names_label', 'parse_names_label', 'sample_label', 'samples_data', 'samples_layout']
