"""
The CDR codec of the two messages the package reads or writes without rclpy (no ROS).

CDR (OMG DDS-XTypes; encapsulation CDR_LE ``00 01 00 00`` or CDR_BE
``00 00 00 00``): a 4-byte encapsulation header, then the fields, each
aligned to its own size counted from the end of the header; a string is a
uint32 length that counts the terminating NUL, then the UTF-8 bytes and the
NUL; a sequence is a uint32 count, then the elements.

**Decoding** ``std_msgs/msg/Float64MultiArray``, the samples topic of every
bag. ``mcap_ros2`` decodes any type from its schema, at about 21 µs per
one-sample message, which is most of a replay's time. :func:`decode_head`
reads the one type the replay needs in a few µs, with numpy viewing the
data in place. It returns objects with the same fields
(``layout.dim[i].label/size/stride``, ``layout.data_offset``, ``data``), so
:func:`bcid_ros.identifier.layouts.decode_samples` takes either. Anything it
does not recognise raises ValueError, and the bag reader then falls back to
``mcap_ros2``.

**Encoding** ``diagnostic_msgs/msg/DiagnosticArray`` for many statuses.
rclpy publishes a message by converting every Python field into its C
structure; for a thousand per-joint statuses of a few key-value pairs each,
that conversion costs more per second than the identification itself. The
statuses of :class:`DiagnosticArrayEncoder` are plain tuples written
straight into the CDR bytes that ``Publisher.publish`` takes as they are
(``publish_raw``), with the encoded form of the strings that do not change
(names, hardware id, keys) kept. The joint diagnostics tests check the bytes
against rclpy's own serialisation.
"""

from __future__ import annotations

import struct
from typing import NamedTuple, Sequence

import numpy as np

_UINT32 = {'<': struct.Struct('<I'), '>': struct.Struct('>I')}
_UINT32_LE = _UINT32['<']
_UINT32_PAIR = {'<': struct.Struct('<II'), '>': struct.Struct('>II')}
_DOUBLE = {'<': np.dtype('<f8'), '>': np.dtype('>f8')}


# ------------------------------------------------------------ decoding Float64MultiArray
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
        One serialised message whose head to read (from its encapsulation header on).

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


# ------------------------------------------------------------- encoding DiagnosticArray
#: Encapsulation header: CDR, little endian.
CDR_LE = b'\x00\x01\x00\x00'

_STAMP = struct.Struct('<iI')
_PADDING = (b'', b'\x00\x00\x00', b'\x00\x00', b'\x00')

#: One status: ``(level, name, message, hardware_id, [(key, value), ...])``.
StatusTuple = tuple[int, str, str, str, Sequence[tuple[str, str]]]


class DiagnosticArrayEncoder:
    """
    Serialise DiagnosticArray messages to CDR, keeping the encoded names, hardware ids and keys.

    Messages and values change from one period to the next and are encoded
    each time; the kept strings are bounded by :attr:`CACHE_SIZE`.
    """

    #: Most strings kept encoded.
    CACHE_SIZE = 100_000

    def __init__(self) -> None:
        self._strings: dict[str, bytes] = {}

    def _kept(self, text: str) -> bytes:
        encoded = self._strings.get(text)
        if encoded is None:
            encoded = _encoded(text)
            if len(self._strings) < self.CACHE_SIZE:
                self._strings[text] = encoded
        return encoded

    def encode(self, stamp: tuple[int, int], statuses: Sequence[StatusTuple],
               frame_id: str = '') -> bytes:
        """
        Return the CDR bytes of a DiagnosticArray.

        Parameters
        ----------
        stamp : tuple of int
            ``(sec, nanosec)`` of the header.
        statuses : sequence of tuple
            ``(level, name, message, hardware_id, [(key, value), ...])``;
            ``level`` 0 to 255, the rest text.
        frame_id : str
            The header's frame id.

        Returns
        -------
        bytes
            The serialised message, encapsulation header included.

        """
        kept = self._kept
        out = bytearray(CDR_LE)
        out += _STAMP.pack(*stamp)
        out += _encoded(frame_id)
        # offsets count from the end of the 4-byte header, so len(out) % 4 is the alignment
        out += _PADDING[len(out) % 4]
        out += _UINT32_LE.pack(len(statuses))
        for level, name, message, hardware_id, values in statuses:
            out.append(level)
            out += _PADDING[len(out) % 4]
            out += kept(name)
            out += _PADDING[len(out) % 4]
            out += _encoded(message)
            out += _PADDING[len(out) % 4]
            out += kept(hardware_id)
            out += _PADDING[len(out) % 4]
            out += _UINT32_LE.pack(len(values))
            for key, value in values:
                out += _PADDING[len(out) % 4]
                out += kept(key)
                out += _PADDING[len(out) % 4]
                out += _encoded(value)
        return bytes(out)


def _encoded(text: str) -> bytes:
    """Return a CDR string: uint32 length with the NUL, the UTF-8 bytes, the NUL."""
    data = text.encode()
    return _UINT32_LE.pack(len(data) + 1) + data + b'\x00'


__all__ = ['CDR_LE', 'DiagnosticArrayEncoder', 'Dimension', 'Float64MultiArray', 'Layout',
           'StatusTuple', 'decode_float64_multi_array', 'decode_head']
