"""
Read the header and the summary section of an MCAP file with ``struct`` alone.

``mcap``'s reader builds a dataclass per record through a stream wrapper, and importing it
costs more than the rest of a small replay's bag reading. A replay needs only the header's
profile and the summary: schemas, channels, statistics and chunk indexes. This module reads
those records (MCAP format, https://mcap.dev/spec) into named tuples with the fields and
names of ``mcap.records``, so that code written against one takes the other.

Anything malformed raises ValueError or struct.error; the caller turns that into one line.
So does a CRC that does not match (:class:`CrcMismatch`, a ValueError): the summary's CRC
(in the footer) is checked whenever the summary is read, the data section's (in Data End)
by :func:`check_data_crc`; a CRC of 0 means "not computed" (MCAP spec) and is not checked.
"""

from __future__ import annotations

import struct
import sys
from typing import BinaryIO, NamedTuple
import zlib

#: The magic bytes at both ends of an MCAP file.
MAGIC = b'\x89MCAP0\r\n'
#: Opcodes of the records read here.
HEADER, FOOTER, SCHEMA, CHANNEL, CHUNK_INDEX, STATISTICS = 0x01, 0x02, 0x03, 0x04, 0x08, 0x0B
DATA_END = 0x0F
#: Opcode (u8) and record length (u64) before every record.
RECORD = struct.Struct('<BQ')
#: Footer content: summary start, summary offset start, summary CRC.
FOOTER_FIELDS = struct.Struct('<QQI')
FOOTER_SIZE = RECORD.size + FOOTER_FIELDS.size
U16, U32, U64 = struct.Struct('<H'), struct.Struct('<I'), struct.Struct('<Q')
#: Statistics before its channel counts: messages, schemas, channels, attachments, metadata,
#: chunks, first and last message time.
STATISTICS_FIELDS = struct.Struct('<QHIIIIQQ')
#: Chunk Index before its message index offsets: first and last message time, chunk start
#: and length.
CHUNK_INDEX_FIELDS = struct.Struct('<QQQQ')


#: Failures of the MCAP and CDR layers that mean "this file is broken" (and ``mcap``'s
#: McapError and zstd's ZstdError where those are used: :func:`read_errors`).
READ_ERRORS = (struct.error, EOFError, ValueError, KeyError, IndexError, UnicodeDecodeError,
               TypeError)


def read_errors() -> tuple[type[Exception], ...]:
    """Return :data:`READ_ERRORS` and the errors of ``mcap`` and ``zstandard`` once imported."""
    mcap, zstd = sys.modules.get('mcap.exceptions'), sys.modules.get('zstandard')
    return (READ_ERRORS + ((mcap.McapError,) if mcap is not None else ())
            + ((zstd.ZstdError,) if zstd is not None else ()))


class CrcMismatch(ValueError):
    """A CRC stored in the file does not match the bytes it covers: the file is corrupt."""


class Footer(NamedTuple):
    """The Footer record, and where it is."""

    summary_start: int
    summary_offset_start: int
    summary_crc: int
    #: Offset of the footer record in the file.
    offset: int


class Header(NamedTuple):
    """The Header record."""

    profile: str
    library: str


class Schema(NamedTuple):
    """A Schema record."""

    id: int
    name: str
    encoding: str
    data: bytes


class Channel(NamedTuple):
    """A Channel record."""

    id: int
    schema_id: int
    topic: str
    message_encoding: str
    metadata: dict[str, str]


class ChunkIndex(NamedTuple):
    """A Chunk Index record."""

    message_start_time: int
    message_end_time: int
    chunk_start_offset: int
    chunk_length: int
    message_index_offsets: dict[int, int]
    message_index_length: int
    compression: str
    compressed_size: int
    uncompressed_size: int


class Statistics(NamedTuple):
    """The Statistics record."""

    message_count: int
    schema_count: int
    channel_count: int
    attachment_count: int
    metadata_count: int
    chunk_count: int
    message_start_time: int
    message_end_time: int
    channel_message_counts: dict[int, int]


class Summary(NamedTuple):
    """The records of a summary section that a reader of messages needs."""

    schemas: dict[int, Schema]
    channels: dict[int, Channel]
    chunk_indexes: list[ChunkIndex]
    statistics: Statistics | None


class _Fields:
    """Read the little-endian fields of one record in order."""

    def __init__(self, data: bytes) -> None:
        self.data = data
        self.pos = 0

    def unpack(self, layout: struct.Struct) -> tuple[int, ...]:
        values = layout.unpack_from(self.data, self.pos)
        self.pos += layout.size
        return values

    def number(self, layout: struct.Struct) -> int:
        return self.unpack(layout)[0]

    def raw(self) -> bytes:
        length = self.number(U32)
        end = self.pos + length
        if end > len(self.data):
            raise ValueError('a string or byte field runs past its record')
        value = self.data[self.pos:end]
        self.pos = end
        return value

    def text(self) -> str:
        return self.raw().decode('utf-8')

    def pairs(self, key: struct.Struct, value: struct.Struct) -> dict[int, int]:
        length = self.number(U32)
        end = self.pos + length
        out = {}
        while self.pos < end:
            name = self.number(key)
            out[name] = self.number(value)
        return out

    def texts(self) -> dict[str, str]:
        length = self.number(U32)
        end = self.pos + length
        out = {}
        while self.pos < end:
            name = self.text()
            out[name] = self.text()
        return out


def read_header(stream: BinaryIO) -> Header:
    """
    Return the Header record at the start of an MCAP file.

    Raises
    ------
    ValueError
        If the file does not start with the magic and a Header record.

    """
    stream.seek(0)
    start = stream.read(len(MAGIC) + RECORD.size)
    if len(start) < len(MAGIC) + RECORD.size or not start.startswith(MAGIC):
        raise ValueError('not an MCAP file (no magic at its start)')
    opcode, length = RECORD.unpack_from(start, len(MAGIC))
    if opcode != HEADER:
        raise ValueError(f'expected a header record at the start, found opcode {opcode:#x}')
    fields = _Fields(_read_exactly(stream, length))
    return Header(fields.text(), fields.text())


def read_summary(stream: BinaryIO) -> Summary | None:
    """
    Return the summary section of an MCAP file, or None if it has none.

    Raises
    ------
    ValueError, struct.error
        If the footer or a summary record is malformed or truncated.

    """
    footer = read_footer(stream)
    if footer.summary_start == 0:
        return None
    stream.seek(footer.summary_start)
    return parse_summary(_read_exactly(stream, footer.offset - footer.summary_start))


class MissingFooter(ValueError):
    """The file does not end with a footer and the magic (an unfinished recording)."""


def read_footer(stream: BinaryIO) -> Footer:
    """
    Return the footer of an MCAP file, after checking the summary CRC if there is one.

    Raises
    ------
    MissingFooter
        If the file does not end with a footer record and the magic.
    CrcMismatch
        If the summary CRC does not match the summary and footer bytes.
    ValueError
        If the footer points outside the file.

    """
    stream.seek(0, 2)
    size = stream.tell()
    if size < len(MAGIC) * 2 + FOOTER_SIZE:
        raise MissingFooter('too short for an MCAP file with a footer')
    footer_at = size - FOOTER_SIZE - len(MAGIC)
    stream.seek(footer_at)
    tail = _read_exactly(stream, FOOTER_SIZE + len(MAGIC))
    if not tail.endswith(MAGIC):
        raise MissingFooter('no magic at the end (a truncated or unfinished file?)')
    opcode, length = RECORD.unpack_from(tail)
    if opcode != FOOTER or length != FOOTER_FIELDS.size:
        raise MissingFooter('no footer record before the closing magic')
    footer = Footer(*FOOTER_FIELDS.unpack_from(tail, RECORD.size), footer_at)
    if footer.summary_start > footer_at or footer.summary_offset_start > footer_at:
        raise ValueError('the footer points past itself')
    if footer.summary_crc:
        start = footer.summary_start or footer_at
        stream.seek(start)
        covered = _read_exactly(stream, footer_at - start) + tail[:FOOTER_SIZE - 4]
        if zlib.crc32(covered) != footer.summary_crc:
            raise CrcMismatch(f'summary CRC mismatch (summary section at offset {start}): '
                              'the summary or footer is corrupt')
    return footer


def file_crc(stream: BinaryIO, start: int, end: int, piece: int = 1 << 22) -> int:
    """Return the CRC-32 of bytes ``start`` to ``end - 1`` of ``stream``, read in pieces."""
    stream.seek(start)
    crc, left = 0, end - start
    while left > 0:
        data = stream.read(min(piece, left))
        if not data:
            raise ValueError(f'the file ends {left} bytes early')
        crc = zlib.crc32(data, crc)
        left -= len(data)
    return crc


def check_data_crc(stream: BinaryIO, footer: Footer) -> bool:
    """
    Check the data section's CRC (Data End record); return whether there was one to check.

    Raises
    ------
    CrcMismatch
        If the CRC-32 of every byte before Data End differs from the stored one.

    """
    data_end_at = (footer.summary_start or footer.offset) - RECORD.size - 4
    if data_end_at < len(MAGIC):
        return False
    stream.seek(data_end_at)
    record = stream.read(RECORD.size + 4)
    opcode, length = RECORD.unpack_from(record)
    if opcode != DATA_END or length != 4:
        return False  # not where a writer that follows the spec puts it: nothing to check
    (stored,) = U32.unpack_from(record, RECORD.size)
    if not stored:
        return False
    if file_crc(stream, 0, data_end_at) != stored:
        raise CrcMismatch(f'data section CRC mismatch (bytes 0 to {data_end_at}): a chunk, '
                          'message index or other record before the summary is corrupt')
    return True


def parse_summary(section: bytes) -> Summary:
    """Return the schemas, channels, chunk indexes and statistics of a summary section."""
    summary = Summary({}, {}, [], None)
    statistics = None
    pos, end = 0, len(section)
    while pos < end:
        opcode, length = RECORD.unpack_from(section, pos)
        pos += RECORD.size
        if pos + length > end:
            raise ValueError(f'a summary record (opcode {opcode:#x}) runs past the section')
        body = section[pos:pos + length]
        pos += length
        if opcode == SCHEMA:
            fields = _Fields(body)
            schema = Schema(fields.number(U16), fields.text(), fields.text(), fields.raw())
            summary.schemas[schema.id] = schema
        elif opcode == CHANNEL:
            fields = _Fields(body)
            channel_id, schema_id = fields.number(U16), fields.number(U16)
            channel = Channel(channel_id, schema_id, fields.text(), fields.text(),
                              fields.texts())
            summary.channels[channel.id] = channel
        elif opcode == CHUNK_INDEX:
            fields = _Fields(body)
            head = fields.unpack(CHUNK_INDEX_FIELDS)
            offsets = fields.pairs(U16, U64)
            index_length = fields.number(U64)
            compression = fields.text()
            summary.chunk_indexes.append(ChunkIndex(*head, offsets, index_length, compression,
                                                    fields.number(U64), fields.number(U64)))
        elif opcode == STATISTICS:
            fields = _Fields(body)
            statistics = Statistics(*fields.unpack(STATISTICS_FIELDS), fields.pairs(U16, U64))
    return summary._replace(statistics=statistics)


def _read_exactly(stream: BinaryIO, size: int) -> bytes:
    data = stream.read(size)
    if len(data) != size:
        raise ValueError(f'the file ends {size - len(data)} bytes early')
    return data


__all__ = ['Channel', 'ChunkIndex', 'CrcMismatch', 'Footer', 'Header', 'MissingFooter',
           'READ_ERRORS', 'Schema', 'Statistics', 'Summary', 'check_data_crc', 'file_crc',
           'parse_summary', 'read_errors', 'read_footer', 'read_header', 'read_summary']
