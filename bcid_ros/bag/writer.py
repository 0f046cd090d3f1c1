"""
Write rosbag2 MCAP bags with rosbags (no rclpy).

:class:`BagWriter` is a thin layer over ``rosbags.rosbag2.Writer`` with the
MCAP storage plugin: rosbags writes ``metadata.yaml``, the ``ros2`` profile,
``ros2msg`` schemas, full type names and each channel's
``offered_qos_profiles``, and compresses the chunks with zstd. Added here:

* the file name: rosbag2 names the first file of a bag ``<bag>_0.mcap``
  (docs/bags.md), rosbags ``<bag>.mcap``;
* the CRCs that ``ros2 bag record`` (mcap's C++ writer) writes and rosbags
  leaves at 0: each chunk's CRC-32 of its uncompressed records, the data
  section's CRC-32 in the Data End record and the summary's in the footer
  (docs/guarantees.md); a reader detects any changed byte;
* :meth:`BagWriter.flush`: close the open chunk and hand it to the operating
  system, so that a recording killed at any moment keeps every chunk
  flushed before (``bcid record`` flushes every :data:`FLUSH_PERIOD` s;
  ``bcid reindex`` rebuilds the summary of such a file).

Messages are serialised to CDR with the rosbags type store of ROS 2 Jazzy, so
``bcid simulate`` and ``bcid replay --output`` need no ROS installation.
"""

from __future__ import annotations

import os
from pathlib import Path
import shutil
import struct
import zlib
from typing import Any, Iterable, Sequence

import numpy as np
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer
from rosbags.rosbag2.errors import WriterError
from rosbags.rosbag2.storage_mcap import McapWriter
from rosbags.typesys import get_typestore, Stores

from bcid_ros.bag.qos import Qos
from bcid_ros.bag.summary import file_crc
from bcid_ros.errors import BcidError
from bcid_ros.identifier.interface import FLOAT64_MULTI_ARRAY

#: The message definitions of ROS 2 Jazzy (std_msgs, diagnostic_msgs, sensor_msgs, ...).
TYPESTORE = get_typestore(Stores.ROS2_JAZZY)

#: rosbag2 metadata version written (9: Jazzy's, offered_qos_profiles as a YAML list).
METADATA_VERSION = 9


#: Offset of the CRC field in a Chunk record: opcode, length, start, end, uncompressed size.
CHUNK_CRC_AT = 1 + 8 + 8 + 8 + 8
#: Offset of the summary CRC in the footer record: opcode, length, summary start and offset.
FOOTER_CRC_AT = 1 + 8 + 8 + 8
#: The Data End record: opcode, length (4), data section CRC.
DATA_END_SIZE = 1 + 8 + 4
#: Bytes of the closing magic.
MAGIC_SIZE = 8


class _Rosbag2McapWriter(McapWriter):
    """rosbags' MCAP storage, named ``<bag>_0.mcap`` as rosbag2 does, with CRCs."""

    def __init__(self, path: Path, compression: CompressionMode) -> None:
        super().__init__(path, compression)
        # rosbags has written the magic and header to <bag>.mcap; move them.
        self.bio.close()
        wanted = path / f'{path.name}_0.mcap'
        self.path.rename(wanted)
        self.path = wanted
        self.bio = wanted.open('r+b')
        self.bio.seek(0, os.SEEK_END)

    def close_chunk(self) -> None:
        """Write the pending chunk as rosbags does, then its CRC (rosbags writes 0)."""
        crc = zlib.crc32(self.chunk.bio.getbuffer())
        start = self.bio.tell()
        super().close_chunk()
        end = self.bio.tell()
        self.bio.seek(start + CHUNK_CRC_AT)
        self.bio.write(struct.pack('<I', crc))
        self.bio.seek(end)

    def close(self, version: int, metadata: str) -> None:
        """Finish the file as rosbags does, then fill in the data and summary CRCs."""
        super().close(version, metadata)
        with self.path.open('r+b') as stream:
            write_section_crcs(stream)


def write_section_crcs(stream: Any) -> None:
    """
    Fill in the data section CRC (Data End) and the summary CRC (footer) of a finished MCAP.

    The summary starts right after the Data End record (as rosbags and
    :mod:`bcid_ros.bag.recovery` write it); the data CRC covers every byte
    before Data End, the summary CRC the summary and the footer up to its CRC.
    """
    stream.seek(0, os.SEEK_END)
    size = stream.tell()
    footer_at = size - MAGIC_SIZE - (FOOTER_CRC_AT + 4)
    stream.seek(footer_at + 9)
    summary_start = struct.unpack('<Q', stream.read(8))[0]
    data_end_at = (summary_start or footer_at) - DATA_END_SIZE
    data_crc = file_crc(stream, 0, data_end_at)
    stream.seek(data_end_at + 9)
    stream.write(struct.pack('<I', data_crc))
    summary_crc = file_crc(stream, summary_start or footer_at, footer_at + FOOTER_CRC_AT)
    stream.seek(footer_at + FOOTER_CRC_AT)
    stream.write(struct.pack('<I', summary_crc))
    stream.flush()
    os.fsync(stream.fileno())


class _Rosbag2Writer(Writer):
    STORAGE_PLUGINS = {**Writer.STORAGE_PLUGINS, StoragePlugin.MCAP: _Rosbag2McapWriter}


def full_type_name(msgtype: str) -> str:
    """Return ``pkg/msg/Name`` for ``pkg/Name`` or ``pkg/msg/Name``."""
    parts = msgtype.split('/')
    if len(parts) == 2:
        return f'{parts[0]}/msg/{parts[1]}'
    return msgtype


def float64_multi_array(dims: Iterable[tuple[str, int, int]], data: Any) -> Any:
    """
    Return a ``std_msgs/msg/Float64MultiArray`` of the rosbags type store.

    Parameters
    ----------
    dims : iterable of (label, size, stride)
        ``layout.dim``, outermost first.
    data : array_like
        The values.

    """
    types = TYPESTORE.types
    dim = types['std_msgs/msg/MultiArrayDimension']
    layout = types['std_msgs/msg/MultiArrayLayout'](
        dim=[dim(label=label, size=int(size), stride=int(stride)) for label, size, stride in dims],
        data_offset=0)
    return types[FLOAT64_MULTI_ARRAY](layout=layout,
                                      data=np.ascontiguousarray(data, dtype=np.float64))


class BagWriter:
    """
    Write a new rosbag2 MCAP bag directory.

    Use as a context manager; on an exception inside the ``with`` block the
    partly written directory is removed. :meth:`close` finishes the bag
    (chunk index, summary, ``metadata.yaml``).

    Parameters
    ----------
    path : str or pathlib.Path
        The bag directory; it must not exist.
    compress : bool
        zstd-compress the MCAP chunks (rosbag2's ``zstd_fast`` preset does
        the same: compression inside the storage, not of the whole file).

    Raises
    ------
    BcidError
        If ``path`` exists.

    """

    def __init__(self, path: str | Path, *, compress: bool = True) -> None:
        self.path = Path(path)
        if self.path.exists():
            raise BcidError(f'{self.path} exists already; give a new bag directory')
        self._writer = _Rosbag2Writer(self.path, version=METADATA_VERSION,
                                      storage_plugin=StoragePlugin.MCAP)
        if compress:
            self._writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        self._writer.open()
        self._connections: dict[str, Any] = {}
        self._types: dict[str, str] = {}
        self.counts: dict[str, int] = {}

    def add_topic(self, topic: str, msgtype: str, qos: Sequence[Qos] = ()) -> None:
        """
        Add a topic (an MCAP channel) with its type and offered QoS profiles.

        Raises
        ------
        BcidError
            If the type is not a ROS 2 Jazzy message known to rosbags, or
            the topic was added before.

        """
        msgtype = full_type_name(msgtype)
        if msgtype not in TYPESTORE.types:
            raise BcidError(f'cannot record {topic}: message type {msgtype} is not a ROS 2 '
                            'Jazzy message known to rosbags')
        if topic in self._connections:
            raise BcidError(f'topic {topic} added twice')
        self._connections[topic] = self._writer.add_connection(
            topic, msgtype, typestore=TYPESTORE, offered_qos_profiles=list(qos))
        self._types[topic] = msgtype
        self.counts[topic] = 0

    def write(self, topic: str, time_ns: int, data: bytes | memoryview) -> None:
        """Write one CDR-serialised message received (or stamped) at ``time_ns``."""
        self._writer.write(self._connections[topic], int(time_ns), data)
        self.counts[topic] += 1

    def write_message(self, topic: str, time_ns: int, message: Any) -> None:
        """Serialise a rosbags message object to CDR and write it."""
        self.write(topic, time_ns, TYPESTORE.serialize_cdr(message, self._types[topic]))

    def flush(self) -> None:
        """
        Close the open chunk (with its message indexes) and hand the file to the OS.

        Everything written before a flush survives a kill of the process
        (``bcid reindex`` then restores the summary); no fsync, so not a
        power loss.
        """
        storage = self._writer.storage
        if storage is not None and storage.chunk.bio.tell():
            storage.close_chunk()
        if storage is not None:
            storage.bio.flush()

    def close(self) -> None:
        """Finish the bag: last chunk, summary and ``metadata.yaml``."""
        if self._writer.storage is not None:
            self._writer.close()

    def abort(self) -> None:
        """Stop writing and remove the unfinished bag directory."""
        try:
            self._writer.abort()
        except WriterError:
            pass
        shutil.rmtree(self.path, ignore_errors=True)

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(self, exc_type: Any, exc: Any, traceback: Any) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


__all__ = ['BagWriter', 'TYPESTORE', 'float64_multi_array', 'full_type_name']
