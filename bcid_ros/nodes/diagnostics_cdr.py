"""
A ``diagnostic_msgs/msg/DiagnosticArray`` serialised directly to CDR, for many statuses (no ROS).

rclpy publishes a message by converting every Python field into its C
structure; for a thousand per-joint statuses of a few key-value pairs each,
that conversion costs more per second than the identification itself. The
statuses here are plain tuples written straight into the CDR bytes that
``Publisher.publish`` takes as they are (``publish_raw``), with the encoded
form of the strings that do not change (names, hardware id, keys) kept.
``test/test_joint_diagnostics.py`` checks the bytes against rclpy's own
serialisation.

CDR (little endian, the encapsulation header ``00 01 00 00``): each field is
aligned to its size counted from the end of the header; a string is a uint32
length that counts the terminating NUL, then the UTF-8 bytes and the NUL; a
sequence is a uint32 count, then the elements.
"""

from __future__ import annotations

import struct
from typing import Sequence

#: Encapsulation header: CDR, little endian.
CDR_LE = b'\x00\x01\x00\x00'

_UINT32 = struct.Struct('<I')
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
        out += _UINT32.pack(len(statuses))
        for level, name, message, hardware_id, values in statuses:
            out.append(level)
            out += _PADDING[len(out) % 4]
            out += kept(name)
            out += _PADDING[len(out) % 4]
            out += _encoded(message)
            out += _PADDING[len(out) % 4]
            out += kept(hardware_id)
            out += _PADDING[len(out) % 4]
            out += _UINT32.pack(len(values))
            for key, value in values:
                out += _PADDING[len(out) % 4]
                out += kept(key)
                out += _PADDING[len(out) % 4]
                out += _encoded(value)
        return bytes(out)


def _encoded(text: str) -> bytes:
    """Return a CDR string: uint32 length with the NUL, the UTF-8 bytes, the NUL."""
    data = text.encode()
    return _UINT32.pack(len(data) + 1) + data + b'\x00'


__all__ = ['CDR_LE', 'DiagnosticArrayEncoder', 'StatusTuple']
