"""
A fast CDR decoder for ``std_msgs/msg/Float64MultiArray``, the samples topic of every bag.

``mcap_ros2`` decodes any type from its schema, at about 21 µs per one-sample message,
which is most of a replay's time. This decoder reads the one type the replay needs in a few
µs, with numpy viewing the data in place. It returns objects with the same fields
(``layout.dim[i].label/size/stride``, ``layout.data_offset``, ``data``), so
:func:`bcid_ros.samples.decode_samples` takes either. Anything it does not recognise raises
ValueError, and the reader then falls back to ``mcap_ros2``.

CDR (OMG DDS-XTypes, encapsulation CDR_LE or CDR_BE): a 4-byte encapsulation header, then
the fields, each aligned to its own size counted from the end of the header; strings are a
uint32 length that counts the terminating NUL, then the bytes.
"""

from __future__ import annotations

import struct
from typing import NamedTuple

import numpy as np


class Dimension(NamedTuple):
    """std_msgs/msg/MultiArrayDimension."""

    label: str
    size: int
    stride: int


class Layout(NamedTuple):
    """std_msgs/msg/MultiArrayLayout."""

    dim: tuple[Dimension, ...]
    data_offset: int


class Float64MultiArray(NamedTuple):
    """std_msgs/msg/Float64MultiArray with ``data`` as a read-only float64 array."""

    layout: Layout
    data: np.ndarray


_UINT32 = {'<': struct.Struct('<I'), '>': struct.Struct('>I')}
_UINT32_PAIR = {'<': struct.Struct('<II'), '>': struct.Struct('>II')}
_DOUBLE = {'<': np.dtype('<f8'), '>': np.dtype('>f8')}


def decode_float64_multi_array(raw: bytes) -> Float64MultiArray:
    """
    Decode one CDR-serialised Float64MultiArray.

    Parameters
    ----------
    raw : bytes
        The serialised message, encapsulation header included.

    Returns
    -------
    Float64MultiArray
        With ``data`` a float64 array viewing ``raw``.

    Raises
    ------
    ValueError
        If the encapsulation is not plain CDR or the bytes do not hold a whole message.

    """
    layout, start, length, dtype = decode_head(raw)
    return Float64MultiArray(layout, np.frombuffer(raw, dtype=dtype, count=length,
                                                   offset=start))


def decode_head(raw: bytes) -> tuple[Layout, int, int, np.dtype]:
    """
    Decode the layout of a CDR Float64MultiArray and find its data.

    Everything before the data (the layout, the data length, the padding)
    is the message's *head*: two messages with the same head bytes have the
    same layout and the same number of values at the same place, which is
    what lets a reader decode a whole run of such messages at once.

    Parameters
    ----------
    raw : bytes
        The serialised message, encapsulation header included.

    Returns
    -------
    layout : Layout
        The decoded layout.
    start : int
        Byte offset of the first value in ``raw`` (the length of the head).
    length : int
        Number of values.
    dtype : numpy.dtype
        Their float64 byte order.

    Raises
    ------
    ValueError
        If the encapsulation is not plain CDR or the bytes do not hold a whole message.

    """
    if len(raw) < 4 or raw[0] != 0 or raw[1] not in (0, 1):
        raise ValueError('not a plain CDR encapsulation')
    order = '<' if raw[1] == 1 else '>'
    uint32, pair = _UINT32[order], _UINT32_PAIR[order]
    base = 4  # alignment counts from the end of the encapsulation header
    pos = base
    try:
        (count,) = uint32.unpack_from(raw, pos)
        pos += 4
        if count > len(raw):
            raise ValueError('dimension count beyond the message')
        dims = []
        for _ in range(count):
            pos += -(pos - base) % 4
            (length,) = uint32.unpack_from(raw, pos)
            pos += 4
            end = pos + length
            if length == 0 or end > len(raw) or raw[end - 1] != 0:
                raise ValueError('bad string in the layout')
            label = bytes(raw[pos:end - 1]).decode('utf-8')
            pos = end + (-(end - base) % 4)
            size, stride = pair.unpack_from(raw, pos)
            pos += 8
            dims.append(Dimension(label, size, stride))
        pos += -(pos - base) % 4
        data_offset, length = pair.unpack_from(raw, pos)
    except struct.error as error:
        raise ValueError(f'message ends inside the layout ({error})') from None
    pos += 8
    if length:
        pos += -(pos - base) % 8
    if pos + 8 * length > len(raw):
        raise ValueError('data beyond the message')
    return Layout(tuple(dims), data_offset), pos, length, _DOUBLE[order]
