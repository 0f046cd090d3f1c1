"""
Read and repair an MCAP file whose footer is missing (a recording that was killed).

``bcid record`` closes a chunk at least every second (:meth:`BagWriter.flush
<bcid_ros.bag.writer.BagWriter.flush>`), and rosbags writes the schemas and channels
into the chunks. So a file cut off anywhere holds whole chunks up to about a
second before the cut, then perhaps part of one. :func:`scan_summary` walks the
records from the start and rebuilds the summary that the footer would have
pointed to: the schemas and channels, one chunk index per whole chunk (without
message indexes: :mod:`bcid_ros.bag.blocks` then scans the chunk) and the
statistics. A chunk cut off by the end of the file ends the scan and is
reported; a whole chunk whose CRC does not match is an error, as anywhere else.

:func:`reindex_bag` (``bcid reindex``) writes the messages so found to a new
file with :class:`~bcid_ros.bag.writer.BagWriter` (summary, CRCs and
``metadata.yaml``, as a finished recording) and puts it in place of the old one.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
import shutil
import struct
from typing import BinaryIO, Iterator

from bcid_ros.bag.blocks import CHANNEL_AT, chunk_records, CHUNK_FIELDS, LOG_TIME_AT, MESSAGE
from bcid_ros.bag.summary import (CHANNEL, ChunkIndex, DATA_END, FOOTER, MAGIC, parse_summary,
                                  read_errors, read_header, RECORD, SCHEMA, Statistics,
                                  Summary)
from bcid_ros.errors import BcidError

#: MCAP opcode of a Chunk record.
CHUNK = 0x06


@dataclasses.dataclass
class Recovered:
    """A summary rebuilt by scanning, and what the scan could not read."""

    summary: Summary
    #: Offset where the readable records end.
    end: int
    #: Bytes after it (a chunk or record cut off by the end of the file).
    dropped_bytes: int
    #: Whether the data section was complete (a Data End record was found).
    complete: bool

    def describe(self) -> str:
        """Return what was found, for a warning."""
        stats = self.summary.statistics
        text = (f'{stats.message_count} messages in {stats.chunk_count} whole chunks '
                'found by scanning')
        if self.dropped_bytes:
            text += f'; the last {self.dropped_bytes} bytes (a chunk cut off) are lost'
        return text


def scan_summary(stream: BinaryIO) -> Recovered:
    """
    Rebuild the summary of an MCAP file by reading its records from the start.

    Raises
    ------
    ValueError, struct.error, zstandard.ZstdError
        If the file does not start as an MCAP, a whole chunk is corrupt (its
        CRC), or messages are stored outside chunks.

    """
    read_header(stream)
    stream.seek(0, os.SEEK_END)
    size = stream.tell()
    pos = len(MAGIC)
    summary = Summary({}, {}, [], None)
    counts: dict[int, int] = {}
    first, last = None, None
    complete = False
    while pos + RECORD.size <= size:
        stream.seek(pos)
        opcode, length = RECORD.unpack(stream.read(RECORD.size))
        end = pos + RECORD.size + length
        if end > size:
            break
        if opcode == CHUNK:
            index, records = _read_chunk(stream, pos, length)
            summary.chunk_indexes.append(index)
            _add_records(summary, records)
            for channel, stamp, _, _ in _message_records(records):
                counts[channel] = counts.get(channel, 0) + 1
                first = stamp if first is None else min(first, stamp)
                last = stamp if last is None else max(last, stamp)
        elif opcode in (SCHEMA, CHANNEL):
            stream.seek(pos)
            _add_records(summary, stream.read(RECORD.size + length))
        elif opcode == MESSAGE:
            raise ValueError('messages outside chunks cannot be read without the footer')
        elif opcode in (DATA_END, FOOTER):
            complete = True
            pos = end
            break
        pos = end
    statistics = Statistics(sum(counts.values()), len(summary.schemas), len(summary.channels),
                            0, 0, len(summary.chunk_indexes), first or 0, last or 0, counts)
    return Recovered(summary._replace(statistics=statistics), pos,
                     0 if complete else size - pos, complete)


def _read_chunk(stream: BinaryIO, pos: int, length: int) -> tuple[ChunkIndex, bytes]:
    """Return the chunk index of the Chunk record at ``pos`` and its checked records."""
    stream.seek(pos + RECORD.size)
    start, end, uncompressed, _ = CHUNK_FIELDS.unpack(stream.read(CHUNK_FIELDS.size))
    (name_length,) = struct.unpack('<I', stream.read(4))
    compression = stream.read(name_length).decode('utf-8')
    (compressed,) = struct.unpack('<Q', stream.read(8))
    index = ChunkIndex(start, end, pos, RECORD.size + length, {}, 0, compression, compressed,
                       uncompressed)
    return index, chunk_records(stream, index)


def _add_records(summary: Summary, records: bytes) -> None:
    """Add the schemas and channels among ``records`` to ``summary``."""
    found = parse_summary(records)
    summary.schemas.update(found.schemas)
    summary.channels.update(found.channels)


def _message_records(records: bytes) -> Iterator[tuple[int, int, int, int]]:
    """Yield ``(channel id, log time, record start, record end)`` of each Message of a chunk."""
    pos, end = 0, len(records)
    while pos < end:
        opcode, length = RECORD.unpack_from(records, pos)
        if opcode == MESSAGE:
            (channel,) = struct.unpack_from('<H', records, pos + CHANNEL_AT)
            (stamp,) = struct.unpack_from('<Q', records, pos + LOG_TIME_AT)
            yield channel, stamp, pos, pos + RECORD.size + length
        pos += RECORD.size + length


def chunk_messages(stream: BinaryIO, summary: Summary) -> Iterator[tuple[int, int, bytes]]:
    """Yield ``(channel id, log time, CDR bytes)`` of every message, in file order."""
    data_at = LOG_TIME_AT + 16
    for index in sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset):
        records = chunk_records(stream, index)
        for channel, stamp, start, end in _message_records(records):
            yield channel, stamp, records[start + data_at:end]


def reindex_bag(path: str | Path) -> str:
    """
    Repair a bag whose MCAP lost its footer: rewrite summary, CRCs and ``metadata.yaml``.

    The messages of every whole chunk are written, in file order with their
    log times, channels' types and offered QoS, to a new file that replaces
    the old one when it is complete (a crash meanwhile leaves the old one).

    Parameters
    ----------
    path : str or pathlib.Path
        A bag directory holding one MCAP file, or an ``.mcap`` file.

    Returns
    -------
    str
        One line saying what was written.

    Raises
    ------
    BcidError
        If there is no MCAP, more than one, or it cannot be read.

    """
    from bcid_ros.bag.qos import parse_offered
    from bcid_ros.bag.writer import BagWriter

    path = Path(path)
    if path.is_dir():
        files = sorted(path.glob('*.mcap'))
        if len(files) != 1:
            raise BcidError(f'{path}: reindex takes a bag of one MCAP file; found '
                            f'{len(files)}')
        source, directory = files[0], path
    elif path.is_file():
        source, directory = path, None
    else:
        raise BcidError(f'{path}: no such bag')
    work = source.parent / f'.{source.name}.reindex'
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir()
    name = directory.name if directory is not None else source.stem
    try:
        with source.open('rb') as stream:
            recovered = scan_summary(stream)
            summary = recovered.summary
            with BagWriter(work / name) as writer:
                topics = {}
                for channel in sorted(summary.channels.values(), key=lambda c: c.id):
                    schema = summary.schemas[channel.schema_id]
                    qos = parse_offered(channel.metadata.get('offered_qos_profiles', ''))
                    if channel.topic not in writer.counts:
                        writer.add_topic(channel.topic, schema.name, qos)
                    topics[channel.id] = channel.topic
                for channel, stamp, data in chunk_messages(stream, summary):
                    writer.write(topics[channel], stamp, data)
    except read_errors() as error:
        shutil.rmtree(work, ignore_errors=True)
        raise BcidError(f'{source}: cannot be reindexed ({type(error).__name__}: '
                        f'{error})') from None
    except BaseException:
        shutil.rmtree(work, ignore_errors=True)
        raise
    written = work / name / f'{name}_0.mcap'
    target = source if directory is None else directory / written.name
    os.replace(written, target)
    if directory is not None:
        os.replace(work / name / 'metadata.yaml', directory / 'metadata.yaml')
        if source != target:
            source.unlink()
    shutil.rmtree(work, ignore_errors=True)
    stats = summary.statistics
    lost = (f'; {recovered.dropped_bytes} bytes of a cut-off chunk dropped'
            if recovered.dropped_bytes else '')
    return (f'reindexed {target}: {stats.message_count} messages on {len(set(topics.values()))} '
            f'topics in {stats.chunk_count} chunks{lost}')


__all__ = ['Recovered', 'chunk_messages', 'reindex_bag', 'scan_summary']
