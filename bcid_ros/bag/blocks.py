"""
Read one Float64MultiArray topic of an MCAP file in blocks, decoded with numpy.

``mcap``'s own reader parses every record of a chunk in Python and, for
log-time order, passes every message through a heap (about 23 µs a message
in all). Here the chunks are read in file order, the topic's messages are
found through each chunk's message index, and runs of messages that share a
CDR *head* (the same layout and number of values: every sample message of a
recording) become one float64 matrix each, a :class:`MessageBlock`.

**Order.** A rosbag2 recorder writes in log-time order, so file order is the
order the messages were received in. That is checked, not assumed: the
chunks' time ranges (from the summary) must not overlap, and the times within
a chunk must not decrease. Where either fails, the messages are sorted stably
by log time, which is exactly ``mcap``'s log-time order (ties in file order),
and :attr:`OrderReport.moved` counts the messages that moved.
"""

from __future__ import annotations

import dataclasses
import struct
from typing import Any, Callable, Iterable, Iterator, NamedTuple
import zlib

import numpy as np

from bcid_ros.bag.summary import CrcMismatch
from bcid_ros.identifier.cdr import decode_head, Float64MultiArray

#: MCAP opcodes.
MESSAGE, CHUNK, MESSAGE_INDEX = 0x05, 0x06, 0x07
#: Opcode (u8) and record length (u64) before every record.
RECORD = struct.Struct('<BQ')
#: A Message record: channel u16, sequence u32, log time u64, publish time u64, then data.
CHANNEL_AT, LOG_TIME_AT, DATA_AT = 9, 15, 31
MESSAGE_FIELDS = DATA_AT - RECORD.size
#: A Chunk record after opcode and length: start, end, uncompressed size, uncompressed CRC.
CHUNK_FIELDS = struct.Struct('<QQQI')
#: A Message Index record after opcode and length: channel u16, byte length of the entries.
INDEX_FIELDS = struct.Struct('<HI')
#: Rows compared at first when looking for the end of a run of equal heads (then 4x more).
FIRST_WINDOW = 64


@dataclasses.dataclass(frozen=True)
class MessageBlock:
    """
    Consecutive messages of one topic with the same layout and number of values.

    Attributes
    ----------
    times_ns : numpy.ndarray, shape ``(m,)``
        Log times, int64 nanoseconds.
    layout : Layout or alike
        The messages' common ``layout`` (``dim``, ``data_offset``).
    data : numpy.ndarray, shape ``(m, length)``
        Each message's ``data``, native float64, one row per message.

    """

    times_ns: np.ndarray
    layout: Any
    data: np.ndarray

    def __len__(self) -> int:
        """Return the number of messages."""
        return int(self.times_ns.shape[0])

    def message(self, index: int) -> Float64MultiArray:
        """Return message ``index`` with the fields of a Float64MultiArray."""
        return Float64MultiArray(self.layout, self.data[index])


@dataclasses.dataclass
class OrderReport:
    """How far the file order was from log-time order (see the module docstring)."""

    #: Messages read.
    messages: int = 0
    #: Messages that a stable sort by log time moved.
    moved: int = 0
    #: Whether the chunks' time ranges overlapped, so that all were read before sorting.
    overlapping_chunks: bool = False

    @property
    def in_file_order(self) -> bool:
        """Whether file order was log-time order."""
        return self.moved == 0


class Segment(NamedTuple):
    """Messages of one topic: log times and where each one's CDR bytes are in ``buffer``."""

    times: np.ndarray
    buffer: np.ndarray
    starts: np.ndarray
    lengths: np.ndarray


def topic_blocks(stream: Any, summary: Any, channel_ids: set[int],
                 fallback: Callable[[bytes], Any],
                 order: OrderReport) -> Iterator[MessageBlock]:
    """
    Yield the blocks of the messages on ``channel_ids`` in log-time order.

    Parameters
    ----------
    stream : binary file
        The MCAP file, seekable.
    summary : bcid_ros.bag.summary.Summary
        Its summary (chunk indexes with message index offsets).
    channel_ids : set of int
        The topic's channels.
    fallback : callable
        ``fallback(raw)`` decodes a message that
        :func:`~bcid_ros.identifier.cdr.decode_head` refuses (``mcap_ros2``).
    order : OrderReport
        Updated with the messages read and moved.

    Raises
    ------
    ValueError, struct.error, zstandard.ZstdError
        If a chunk or an index is corrupt (the caller says so in one line).

    """
    chunks = sorted((c for c in summary.chunk_indexes
                     if not c.message_index_offsets
                     or channel_ids.intersection(c.message_index_offsets)),
                    key=lambda c: c.chunk_start_offset)
    ranges_overlap = any(a.message_end_time > b.message_start_time
                         for a, b in zip(chunks, chunks[1:]))
    segments = (chunk_segment(stream, chunk, channel_ids) for chunk in chunks)
    if ranges_overlap:
        # Any chunk may hold a message that goes before one of another: sort them all.
        order.overlapping_chunks = True
        segments = iter([concatenate([s for s in segments if s is not None])])
    for segment in segments:
        if segment is not None and segment.times.shape[0]:
            yield from segment_blocks(in_time_order(segment, order), fallback)


def chunk_segment(stream: Any, chunk: Any, channel_ids: set[int]) -> Segment | None:
    """Return the messages of ``channel_ids`` in one chunk, in file order (None if none)."""
    indexes = [read_message_index(stream, chunk.message_index_offsets[channel], channel)
               for channel in sorted(channel_ids.intersection(chunk.message_index_offsets))]
    if chunk.message_index_offsets and not any(index.shape[0] for index in indexes):
        return None
    records = chunk_records(stream, chunk)
    buffer = np.frombuffer(records, dtype=np.uint8)
    if chunk.message_index_offsets:
        offsets = np.concatenate([index[:, 1] for index in indexes]).astype(np.int64)
        if len(indexes) > 1 or np.any(offsets[1:] < offsets[:-1]):
            offsets.sort()
    else:
        offsets = scan_messages(records, channel_ids)
    if offsets.shape[0] == 0:
        return None
    if offsets[0] < 0 or offsets[-1] + DATA_AT > buffer.shape[0]:
        raise ValueError('a message index points outside its chunk')
    if not np.all(buffer[offsets] == MESSAGE):
        raise ValueError('a message index points at a record that is not a message')
    channels = gather(buffer, offsets + CHANNEL_AT, 2).view('<u2')[:, 0]
    if not np.all(np.isin(channels, list(channel_ids))):
        raise ValueError('a message index points at a message of another channel')
    lengths = gather(buffer, offsets + 1, 8).view('<u8')[:, 0].astype(np.int64) - MESSAGE_FIELDS
    starts = offsets + DATA_AT
    if np.any(lengths < 0) or np.any(starts + lengths > buffer.shape[0]):
        raise ValueError('a message record runs past its chunk')
    times = gather(buffer, offsets + LOG_TIME_AT, 8).view('<u8')[:, 0].astype(np.int64)
    return Segment(times, buffer, starts, lengths)


def read_message_index(stream: Any, offset: int, channel: int) -> np.ndarray:
    """Return the ``(log time, offset)`` entries of a Message Index record, shape ``(m, 2)``."""
    stream.seek(offset)
    head = stream.read(RECORD.size + INDEX_FIELDS.size)
    opcode, _ = RECORD.unpack_from(head)
    indexed, size = INDEX_FIELDS.unpack_from(head, RECORD.size)
    if opcode != MESSAGE_INDEX or indexed != channel or size % 16:
        raise ValueError(f'no message index of channel {channel} at offset {offset}')
    entries = stream.read(size)
    if len(entries) != size:
        raise ValueError(f'the message index at offset {offset} is truncated')
    return np.frombuffer(entries, dtype='<u8').reshape(-1, 2)


def chunk_records(stream: Any, chunk: Any) -> bytes:
    """
    Return the decompressed records of the chunk that ``chunk`` (a ChunkIndex) points to.

    The chunk's CRC, when it has one, is checked (:class:`~bcid_ros.bag.summary.CrcMismatch`).
    """
    stream.seek(chunk.chunk_start_offset)
    raw = memoryview(stream.read(chunk.chunk_length))
    opcode, length = RECORD.unpack_from(raw)
    if opcode != CHUNK or RECORD.size + length > len(raw):
        raise ValueError(f'no whole chunk at offset {chunk.chunk_start_offset}')
    _, _, size, crc = CHUNK_FIELDS.unpack_from(raw, RECORD.size)
    pos = RECORD.size + CHUNK_FIELDS.size
    (name_length,) = struct.unpack_from('<I', raw, pos)
    compression = bytes(raw[pos + 4:pos + 4 + name_length]).decode('utf-8')
    pos += 4 + name_length
    (records_length,) = struct.unpack_from('<Q', raw, pos)
    data = raw[pos + 8:pos + 8 + records_length]
    if len(data) != records_length:
        raise ValueError(f'the chunk at offset {chunk.chunk_start_offset} is truncated')
    try:
        records = decompress(data, compression, size)
    except ValueError:
        raise
    except Exception as error:  # zstd's and lz4's own errors: the compressed bytes are corrupt
        raise ValueError(f'chunk at offset {chunk.chunk_start_offset} is corrupt: it cannot '
                         f'be decompressed ({type(error).__name__}: {error})') from None
    if len(records) != size:
        raise ValueError(f'the chunk at offset {chunk.chunk_start_offset} decompressed to '
                         f'{len(records)} bytes, not {size}')
    if crc and zlib.crc32(records) != crc:  # 0: the writer computed none (MCAP spec)
        raise CrcMismatch(f'chunk at offset {chunk.chunk_start_offset} (messages '
                          f'{chunk.message_start_time * 1e-9:.9f} s to '
                          f'{chunk.message_end_time * 1e-9:.9f} s): CRC mismatch, the chunk '
                          'is corrupt')
    return records


def decompress(data: Any, compression: str, size: int) -> bytes:
    """Return the records of a chunk compressed with ``compression`` (zstd, lz4 or none)."""
    if compression == 'zstd':
        import zstandard

        return zstandard.decompress(data, size)
    if compression == 'lz4':
        import lz4.frame

        return lz4.frame.decompress(data)
    if compression == '':
        return bytes(data)
    raise ValueError(f'chunk compression {compression!r} is not supported')


def scan_messages(records: bytes, channel_ids: set[int]) -> np.ndarray:
    """Return the offsets of the messages of ``channel_ids`` in a chunk without an index."""
    offsets = []
    pos, end = 0, len(records)
    while pos < end:
        opcode, length = RECORD.unpack_from(records, pos)
        if opcode == MESSAGE and struct.unpack_from('<H', records, pos + CHANNEL_AT)[0] \
                in channel_ids:
            offsets.append(pos)
        pos += RECORD.size + length
    return np.array(offsets, dtype=np.int64)


def gather(buffer: np.ndarray, positions: np.ndarray, width: int) -> np.ndarray:
    """Return the ``width`` bytes at each of ``positions``, shape ``(m, width)``."""
    return buffer[positions[:, None] + np.arange(width)]


def concatenate(segments: list[Segment]) -> Segment:
    """Return one segment holding the messages of ``segments`` in the same order."""
    if not segments:
        empty = np.zeros(0, dtype=np.int64)
        return Segment(empty, np.zeros(0, dtype=np.uint8), empty, empty)
    bases = np.cumsum([0] + [s.buffer.shape[0] for s in segments[:-1]])
    return Segment(np.concatenate([s.times for s in segments]),
                   np.concatenate([s.buffer for s in segments]),
                   np.concatenate([s.starts + base for s, base in zip(segments, bases)]),
                   np.concatenate([s.lengths for s in segments]))


def in_time_order(segment: Segment, order: OrderReport) -> Segment:
    """Return ``segment`` sorted stably by log time (itself if it is in order already)."""
    times = segment.times
    order.messages += times.shape[0]
    if not np.any(times[1:] < times[:-1]):
        return segment
    permutation = np.argsort(times, kind='stable')
    order.moved += int(np.count_nonzero(permutation != np.arange(times.shape[0])))
    return Segment(times[permutation], segment.buffer, segment.starts[permutation],
                   segment.lengths[permutation])


def segment_blocks(segment: Segment, fallback: Callable[[bytes], Any]
                   ) -> Iterator[MessageBlock]:
    """Cut a segment into blocks: runs of equal CDR length, then of equal head."""
    times, buffer, starts, lengths = segment
    cuts = np.flatnonzero(lengths[1:] != lengths[:-1]) + 1
    bounds = [0, *cuts.tolist(), times.shape[0]]
    for first, end in zip(bounds[:-1], bounds[1:]):
        matrix = byte_matrix(buffer, starts[first:end], int(lengths[first]))
        yield from equal_head_blocks(times[first:end], matrix, fallback)


def byte_matrix(buffer: np.ndarray, starts: np.ndarray, length: int) -> np.ndarray:
    """Return the ``length`` bytes from each start as rows; a view when evenly spaced."""
    count = starts.shape[0]
    steps = np.diff(starts)
    if count > 1 and steps[0] >= length and np.all(steps == steps[0]):
        return np.lib.stride_tricks.as_strided(buffer[starts[0]:], (count, length),
                                               (int(steps[0]), 1), writeable=False)
    if count == 1:
        return buffer[starts[0]:starts[0] + length][None, :]
    return gather(buffer, starts, length)


def equal_head_blocks(times: np.ndarray, matrix: np.ndarray,
                      fallback: Callable[[bytes], Any]) -> Iterator[MessageBlock]:
    """Yield the runs of rows of ``matrix`` (CDR messages of one length) with equal heads."""
    count = matrix.shape[0]
    first = 0
    while first < count:
        raw = matrix[first].tobytes()
        try:
            layout, start, length, dtype = decode_head(raw)
        except ValueError:
            message = fallback(raw)
            values = np.asarray(message.data, dtype=float).reshape(1, -1)
            yield MessageBlock(times[first:first + 1], message.layout, values)
            first += 1
            continue
        end = run_end(matrix, first, start)
        values = np.ascontiguousarray(matrix[first:end, start:start + 8 * length])
        data = values.view(dtype).astype(float, copy=False).reshape(end - first, length)
        yield MessageBlock(times[first:end], layout, data)
        first = end


def run_end(matrix: np.ndarray, first: int, head: int) -> int:
    """Return the end of the run of rows from ``first`` whose first ``head`` bytes are equal."""
    reference = matrix[first, :head]
    count = matrix.shape[0]
    end, window = first + 1, FIRST_WINDOW
    while end < count:
        stop = min(count, end + window)
        same = np.all(matrix[end:stop, :head] == reference, axis=1)
        if not same.all():
            return end + int(np.argmin(same))
        end, window = stop, window * 4
    return end


def ordered_blocks(blocks: Iterable[MessageBlock]) -> Iterator[tuple[int, Any]]:
    """Yield ``(log time ns, message)`` one message at a time from blocks."""
    for block in blocks:
        for index, stamp in enumerate(block.times_ns.tolist()):
            yield stamp, block.message(index)


__all__ = ['MessageBlock', 'OrderReport', 'ordered_blocks', 'topic_blocks']
