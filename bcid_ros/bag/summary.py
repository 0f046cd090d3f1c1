"""
Read the header and the summary section of an MCAP file with ``struct`` alone.

``mcap``'s reader builds a dataclass per record through a stream wrapper, and importing it
costs more than the rest of a small replay's bag reading. A replay needs only the header's
profile and the summary: schemas, channels, statistics and chunk indexes. This module reads
those records (MCAP format, https://mcap.dev/spec) into named tuples with the fields and
names of ``mcap.records``, so that code written against one takes the other.

Anything malformed raises ValueError or struct.error; the caller turns that into one line.
"""

from __future__ import annotations

import struct
from typing import BinaryIO, NamedTuple

#: The magic bytes at both ends of an MCAP file.
MAGIC = b'\x89MCAP0\r\n'
#: Opcodes of the records read here.
HEADER, FOOTER, SCHEMA, CHANNEL, CHUNK_INDEX, STATISTICS = 0x01, 0x02, 0x03, 0x04, 0x08, 0x0B
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
    stream.seek(0, 2)
    size = stream.tell()
    if size < len(MAGIC) * 2 + FOOTER_SIZE:
        raise ValueError('too short for an MCAP file with a footer')
    stream.seek(size - FOOTER_SIZE - len(MAGIC))
    tail = _read_exactly(stream, FOOTER_SIZE + len(MAGIC))
    if not tail.endswith(MAGIC):
        raise ValueError('no magic at the end (a truncated or unfinished file?)')
    opcode, length = RECORD.unpack_from(tail)
    if opcode != FOOTER or length != FOOTER_FIELDS.size:
        raise ValueError('no footer record before the closing magic')
    summary_start, _, _ = FOOTER_FIELDS.unpack_from(tail, RECORD.size)
    if summary_start == 0:
        return None
    footer_at = size - FOOTER_SIZE - len(MAGIC)
    if summary_start > footer_at:
        raise ValueError('the footer points past itself')
    stream.seek(summary_start)
    return parse_summary(_read_exactly(stream, footer_at - summary_start))


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


__all__ = ['Channel', 'ChunkIndex', 'Header', 'Schema', 'Statistics', 'Summary',
           'parse_summary', 'read_header', 'read_summary']
