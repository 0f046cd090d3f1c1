"""
Plant logs from CSV files: the samples a bag's ``/samples`` topic gives, without a bag (no ROS).

A CSV log has a header row, then one row per sample. By default the columns
named ``y``, ``u1``, ``u2``, ... (as many consecutive ``u`` columns as the
header has) are the output and the inputs; ``columns`` picks and orders
others (output first). Other columns are ignored. An optional time column
holds the sample times in seconds; without one, row k (from 0) is stamped
k / rate, at :data:`DEFAULT_RATE_HZ` unless a rate is given.

:func:`read_csv_samples` returns :class:`CsvSamples`: the rows
``[y, u1, ..., ur]`` and their time stamps, and as :meth:`CsvSamples.blocks`
the one-sample messages a bag of the same samples holds, so ``bcid replay``
feeds a CSV through the same per-message rule as a bag
(:meth:`bcid_ros.identifier.feeder.SampleFeeder.take_messages`), and
:func:`write_samples_bag` (``bcid import``) writes exactly those messages to
a rosbag2 MCAP bag.

**Gaps.** An empty cell, ``nan`` or ``inf`` in a sample column is a
non-finite sample, as a NaN in a bag's message is: kept as NaN here, and the
identifier's feeder skips it and restarts the regressor (``bcid analyze``
drops it). In the time column every row needs a finite time of at least 0 s,
in non-decreasing order. Everything else that does not fit (no such column,
text where a number belongs, a row with more or fewer fields than the
header, an empty file, no data rows) is a :class:`~bcid_ros.errors.BcidError`
naming the file, the row (its line number, the header's counting as a row)
and the column.

**Speed.** Lines are read and converted in chunks of about
:data:`CHUNK_BYTES`: a chunk without a double quote is split with ``str``
methods and each column converted by numpy at once; a chunk with a quote
goes through the ``csv`` module. Only a column that numpy refuses (a gap or
a bad cell) is converted again cell by cell, with the same parser, Python's
``float`` (which numpy calls for strings), to find the gaps and the bad cell.
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import math
from operator import methodcaller
from pathlib import Path
import re
from typing import Any, Iterator, Sequence

import numpy as np

from bcid_ros.bag.blocks import MessageBlock
from bcid_ros.errors import BcidError
from bcid_ros.identifier.cdr import Dimension, Layout
from bcid_ros.identifier.layouts import sample_label

#: The file name suffix that makes ``bcid replay`` and ``bcid analyze`` read a CSV file.
CSV_SUFFIX = '.csv'

#: Sample rate (Hz) of the time stamps of a CSV without a time column, as ``bcid simulate``.
DEFAULT_RATE_HZ = 100.0

#: Bytes of lines read and converted at once (bounds the memory held by the cells' strings).
CHUNK_BYTES = 1 << 22

#: Times past this (s, the year 2255 as Unix time) would come near the int64 nanosecond
#: stamps' end (9.22e9 s).
LARGEST_TIME_S = 9e9

#: Rows per block of :meth:`CsvSamples.blocks`. A block is fed at once, but one with a NaN
#: message by message: a bag's chunk holds about 11,000 one-sample messages.
BLOCK_ROWS = 4096

_COUNT_COMMAS = methodcaller('count', ',')

#: A number as a CSV log writes it: ASCII digits, an optional sign, point and exponent, or
#: nan/inf; no digit separators ('1_000'), no other digits ('１２３'); blanks around it.
PLAIN_NUMBER = re.compile(r'\s*[+-]?(?:(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?'
                          r'|nan|inf|infinity)\s*', re.IGNORECASE | re.ASCII)


@dataclasses.dataclass
class CsvStats:
    """What one full pass over a CSV log found."""

    rows: int = 0
    nonfinite_rows: int = 0
    first_ns: int = 0
    last_ns: int = 0


class CsvSamples:
    """
    The samples of a CSV log, as a bag's ``/samples`` topic gives them, read as they are used.

    Made by :func:`read_csv_samples`, which has read and checked the header.
    :meth:`chunks` and :meth:`blocks` stream the file: each pass reads it
    again, in chunks of about :data:`CHUNK_BYTES`, so that a replay or an
    import holds a bounded part of it (docs/guarantees.md). :attr:`rows` and
    :attr:`times_ns` read it all into memory once, for the callers that need
    every sample at once (``bcid analyze``).

    Attributes
    ----------
    path : pathlib.Path
        The file.
    columns : tuple of str
        The file's columns read as ``y, u1, ..., ur``, in that order.
    time_column : str or None
        The column the time stamps come from (None: row k at k / ``rate_hz``).
    rate_hz : float
        The sample rate of the time stamps without a time column.
    stats : CsvStats or None
        Rows, non-finite rows and the time span, once a pass has read the whole file.

    """

    def __init__(self, path: Path, table: _Columns, header_line: int, header: list[str],
                 time_column: str | None, rate_hz: float) -> None:
        self.path = path
        self.columns = table.names
        self.time_column = time_column
        self.rate_hz = rate_hz
        self.stats: CsvStats | None = None
        self._table = table
        self._header_line = header_line
        self._header = header
        self._loaded: tuple[np.ndarray, np.ndarray] | None = None

    @property
    def num_inputs(self) -> int:
        """Return r, the number of input columns."""
        return len(self.columns) - 1

    def chunks(self) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        """
        Yield ``(times_ns, rows)`` chunk after chunk, reading and checking the file as it goes.

        Raises
        ------
        BcidError
            At the first row that does not fit (named by its row number), or if
            there is no data row.

        """
        if self._loaded is not None:
            yield self._loaded
            return
        table, header, path = self._table, self._header, self.path
        width = len(header)
        stats = CsvStats()
        previous_time = None
        with _open(path) as stream:
            for _ in range(self._header_line):
                stream.readline()
            for chunk in _chunks(stream, self._header_line):
                if not len(chunk):
                    continue
                cells = chunk.split(path, header, self._header_line)
                values = [_convert(cells[index::width], chunk, header[index], path,
                                   index == table.time_index) for index in table.indices]
                if table.time_index is not None:
                    seconds = values.pop()
                    previous_time = _check_times(seconds, chunk, self.time_column, path,
                                                 previous_time)
                    times = np.rint(seconds * 1e9).astype(np.int64)
                else:
                    steps = np.arange(stats.rows, stats.rows + len(chunk))
                    times = np.rint(steps * (1e9 / self.rate_hz)).astype(np.int64)
                rows = np.ascontiguousarray(np.column_stack(values), dtype=np.float64)
                if not stats.rows:
                    stats.first_ns = int(times[0])
                stats.rows += rows.shape[0]
                stats.nonfinite_rows += int(np.count_nonzero(~np.isfinite(rows).all(axis=1)))
                stats.last_ns = int(times[-1])
                yield times, rows
        if stats.rows == 0:
            raise BcidError(f'{path}: no data rows after the header (row {self._header_line})')
        self.stats = stats

    def blocks(self) -> Iterator[MessageBlock]:
        """
        Yield the rows as one-sample ``samples`` messages, as a bag of them is read.

        The layout is that of a one-sample message, ``dim[0] = {label:
        'y,u1,...,ur', size: 1 + r, stride: 1 + r}``
        (:func:`bcid_ros.identifier.layouts.samples_layout`): the messages that
        :meth:`bcid_ros.bag.reader.BagReader.blocks` yields for the bag that
        :func:`write_samples_bag` writes, in blocks of at most :data:`BLOCK_ROWS`
        (a block with a NaN goes message by message, as the bag's chunk would).
        """
        width = len(self.columns)
        layout = Layout((Dimension(sample_label(self.num_inputs), width, width),), 0)
        for times, rows in self.chunks():
            for start in range(0, rows.shape[0], BLOCK_ROWS):
                end = start + BLOCK_ROWS
                yield MessageBlock(times[start:end], layout, rows[start:end])

    def load(self) -> CsvSamples:
        """Read the whole file into memory (:attr:`rows`, :attr:`times_ns`); return self."""
        if self._loaded is None:
            parts = list(self.chunks())
            self._loaded = (np.concatenate([times for times, _ in parts]),
                            np.concatenate([rows for _, rows in parts]))
        return self

    @property
    def times_ns(self) -> np.ndarray:
        """Return the time stamps, int64 nanoseconds, non-decreasing (the file is loaded)."""
        return self.load()._loaded[0]

    @property
    def rows(self) -> np.ndarray:
        """Return the samples ``[y, u1, ..., ur]``, NaN where a cell was empty (loaded)."""
        return self.load()._loaded[1]

    @property
    def nonfinite_rows(self) -> int:
        """Return the number of rows with an empty, NaN or infinite sample value."""
        if self.stats is None:
            self.load()
        return self.stats.nonfinite_rows


def is_csv(path: str | Path) -> bool:
    """Return whether ``path`` names a CSV file (suffix ``.csv``, any case) rather than a bag."""
    path = Path(path)
    return path.suffix.lower() == CSV_SUFFIX and not path.is_dir()


def parse_columns(text: str | None) -> tuple[str, ...] | None:
    """
    Return the names of a ``--columns`` value (``'y,u1'`` -> ``('y', 'u1')``), or None.

    Raises
    ------
    BcidError
        If it names fewer than two columns, an empty name or a name twice.

    """
    if text is None:
        return None
    names = tuple(name.strip() for name in text.split(','))
    if len(names) < 2 or '' in names:
        raise BcidError(f'--columns {text!r}: give the output column, then at least one '
                        'input column, separated by commas (e.g. y,u1)')
    twice = sorted({name for name in names if names.count(name) > 1})
    if twice:
        raise BcidError(f'--columns {text!r}: {", ".join(twice)} named twice')
    return names


def samples_source(path: Path, columns: str | None = None, time_column: str | None = None,
                   rate_hz: float | None = None) -> Path | CsvSamples:
    """
    Return the CSV samples of ``path`` if it is a CSV file, else ``path`` (a bag).

    Raises
    ------
    BcidError
        If the CSV cannot be read (:func:`read_csv_samples`), or CSV options
        are given for a bag.

    """
    if is_csv(path):
        return read_csv_samples(path, columns, time_column, rate_hz, load=False)
    given = [option for option, value in (('--columns', columns),
                                          ('--time-column', time_column),
                                          ('--rate', rate_hz)) if value is not None]
    if given:
        raise BcidError(f'{", ".join(given)}: for a CSV log only (suffix {CSV_SUFFIX}), and '
                        f'{path} is read as a bag')
    return path


def read_csv_samples(path: str | Path, columns: str | Sequence[str] | None = None,
                     time_column: str | None = None,
                     rate_hz: float | None = None, load: bool = True) -> CsvSamples:
    """
    Read a CSV log into samples ``[y, u1, ..., ur]`` and time stamps.

    With ``load=False`` only the header is read now; the rows are read, and
    checked, as :meth:`CsvSamples.chunks` streams them (``bcid replay`` and
    ``bcid import``: memory that does not grow with the file).

    Parameters
    ----------
    path : str or pathlib.Path
        The CSV file (UTF-8, a byte-order mark allowed; comma-separated).
    columns : str or sequence of str, optional
        The output column, then the input columns: ``'y,u1'`` or
        ``('y', 'u1')``. Default: ``y``, ``u1``, ``u2``, ... as far as the
        header has them.
    time_column : str, optional
        The column of the sample times, in seconds (>= 0, non-decreasing).
    rate_hz : float, optional
        Without a time column, row k is stamped k / ``rate_hz``; default
        :data:`DEFAULT_RATE_HZ`.
    load : bool
        Read and check every row now (else as they are streamed).

    Returns
    -------
    CsvSamples

    Raises
    ------
    BcidError
        If the file cannot be read, or does not fit (the message names the
        row and the column); if both ``time_column`` and ``rate_hz`` are
        given, or ``rate_hz`` is not positive.

    """
    path = Path(path)
    if time_column is not None and rate_hz is not None:
        raise BcidError('give --time-column or --rate, not both: with a time column the '
                        'time stamps follow it')
    rate = DEFAULT_RATE_HZ if rate_hz is None else float(rate_hz)
    if not (math.isfinite(rate) and rate > 0):
        raise BcidError(f'--rate must be a positive number of samples per second, got {rate_hz}')
    wanted = parse_columns(columns) if isinstance(columns, str) or columns is None \
        else parse_columns(','.join(columns))
    with _open(path) as stream:
        header_line, header = _header(stream, path)
    table = _Columns(path, header_line, header, wanted, time_column)
    samples = CsvSamples(path, table, header_line, header, time_column, rate)
    return samples.load() if load else samples


@contextlib.contextmanager
def _open(path: Path) -> Iterator[Any]:
    """Open a CSV log as UTF-8 text; the errors of opening and decoding become BcidError."""
    try:
        stream = path.open(encoding='utf-8-sig')
    except FileNotFoundError:
        raise BcidError(f'{path}: no such file') from None
    except IsADirectoryError:
        raise BcidError(f'{path}: a directory, not a CSV file') from None
    try:
        yield stream
    except UnicodeDecodeError as error:
        raise BcidError(f'{path}: not a UTF-8 text file ({error.reason})') from None
    finally:
        stream.close()


def _header(stream: Any, path: Path) -> tuple[int, list[str]]:
    """Return the header's line number and its names (whitespace stripped); skip blank lines."""
    for number, text in enumerate(iter(stream.readline, ''), 1):
        if text.strip():
            names = next(csv.reader([text], skipinitialspace=True))
            return number, [name.strip() for name in names]
    raise BcidError(f'{path}: empty file; expected a header row (y,u1,...) and one row per '
                    'sample')


class _Columns:
    """The header positions of the sample columns (output first), then of the time column."""

    def __init__(self, path: Path, header_line: int, header: list[str],
                 wanted: tuple[str, ...] | None, time_column: str | None) -> None:
        self.names = wanted if wanted is not None else _default_columns(header)
        where = f'{path}: row {header_line} (the header)'
        if time_column is not None and time_column in self.names:
            raise BcidError(f'--time-column {time_column!r} is also a sample column '
                            f'({",".join(self.names)})')
        lookup = list(self.names) + ([time_column] if time_column is not None else [])
        self.indices = []
        for name in lookup:
            found = [k for k, have in enumerate(header) if have == name]
            if not found:
                hint = '' if wanted is not None or name == time_column else \
                    '; name the output and input columns with --columns'
                raise BcidError(f'{where} has no column {name!r} (it has: '
                                f'{",".join(header)}){hint}')
            if len(found) > 1:
                raise BcidError(f'{where} names column {name!r} twice (columns '
                                f'{found[0] + 1} and {found[1] + 1})')
            self.indices.append(found[0])
        self.time_index = self.indices[-1] if time_column is not None else None


def _default_columns(header: list[str]) -> tuple[str, ...]:
    """Return ``y, u1, ..., ur``: ``u`` columns as long as the header has the next one."""
    names = ['y', 'u1']
    while f'u{len(names)}' in header:
        names.append(f'u{len(names)}')
    return tuple(names)


class _Chunk:
    """Consecutive non-blank lines of the file, stripped, with their line numbers."""

    def __init__(self, lines: list[str], first_line: int) -> None:
        self.numbers: np.ndarray | None = None
        if '' in lines:
            kept = [k for k, text in enumerate(lines) if text]
            self.numbers = np.array(kept, dtype=np.int64) + first_line
            lines = [lines[k] for k in kept]
        self.lines = lines
        self.first_line = first_line
        #: Whether every cell is ASCII without '_' (set by :meth:`split`).
        self.plain = True

    def __len__(self) -> int:
        return len(self.lines)

    def line(self, row: int) -> int:
        """Return the line number of row ``row`` of the chunk."""
        return self.first_line + row if self.numbers is None else int(self.numbers[row])

    def split(self, path: Path, header: list[str], header_line: int) -> list[str]:
        """
        Return the cells, row after row (as many per row as the header has).

        Raises
        ------
        BcidError
            If a row has another number of fields than the header.

        """
        if not self.lines:
            return []
        width = len(header)
        joined = '\n'.join(self.lines)
        # Python's float (which numpy calls) takes 1_000 and non-ASCII digits: cells of a
        # chunk with either are checked one by one against the plain syntax (_convert).
        self.plain = joined.isascii() and '_' not in joined
        if '"' in joined:
            return self._split_quoted(path, width, header, header_line)
        counts = np.fromiter(map(_COUNT_COMMAS, self.lines), dtype=np.int64,
                             count=len(self.lines))
        ragged = np.flatnonzero(counts != width - 1)
        if ragged.size:
            row = int(ragged[0])
            raise _ragged(path, self.line(row), int(counts[row]) + 1, header, header_line)
        return joined.replace('\n', ',').split(',')

    def _split_quoted(self, path: Path, width: int, header: list[str],
                      header_line: int) -> list[str]:
        # A field quoted right has its quotes in pairs (one inside is doubled): a line with
        # an odd number opens a field that it does not close. Found here, by its own row;
        # the csv module would read on into the next lines and report a later one.
        for row, text in enumerate(self.lines):
            if text.count('"') % 2:
                raise BcidError(f'{path}: row {self.line(row)}: a quoted field is not closed '
                                'on its line (an open quote)')
        reader = csv.reader(self.lines, skipinitialspace=True, strict=True)
        cells: list[str] = []
        try:
            for row, fields in enumerate(reader):
                if reader.line_num != row + 1:
                    raise BcidError(f'{path}: row {self.line(row)}: a quoted field holds a '
                                    'line break; write one sample per line')
                if len(fields) != width:
                    raise _ragged(path, self.line(row), len(fields), header, header_line)
                cells.extend(fields)
        except csv.Error as error:
            raise BcidError(f'{path}: row {self.line(reader.line_num - 1)}: bad CSV quoting '
                            f'({error})') from None
        return cells


def _ragged(path: Path, line: int, fields: int, header: list[str],
            header_line: int) -> BcidError:
    """Return the error of a row with ``fields`` fields where the header has ``len(header)``."""
    width = len(header)
    if fields < width:
        column = f'column {fields + 1} ({header[fields]!r}) is missing'
    else:
        column = f'column {width + 1} is one past the header\'s last ({header[-1]!r})'
    return BcidError(f'{path}: row {line} has {fields} fields but the header (row '
                     f'{header_line}) has {width}: {column}')


def _chunks(stream: Any, header_line: int) -> Iterator[_Chunk]:
    """Yield the lines after the header in chunks of about :data:`CHUNK_BYTES`."""
    first = header_line + 1
    while True:
        lines = stream.readlines(CHUNK_BYTES)
        if not lines:
            return
        yield _Chunk(list(map(str.strip, lines)), first)
        first += len(lines)


def _convert(cells: list[str], chunk: _Chunk, name: str, path: Path, is_time: bool
             ) -> np.ndarray:
    """
    Return the values of one column of a chunk: numpy at once, cell by cell if it refuses.

    Raises
    ------
    BcidError
        If a cell is not a number, or a time cell is empty.

    """
    column = '' if chunk.plain else ''.join(cells)  # another column may hold the odd cells
    if chunk.plain or (column.isascii() and '_' not in column):
        try:
            return np.array(cells, dtype=np.float64)
        except ValueError:
            pass
    values = np.empty(len(cells))
    for row, text in enumerate(cells):
        try:
            if not PLAIN_NUMBER.fullmatch(text):
                raise ValueError(text)
            values[row] = float(text)
        except ValueError:
            if text.strip() or is_time:
                what = 'empty: every row needs a time' if not text.strip() else \
                    f'{text!r} is not a number'
                raise BcidError(f'{path}: row {chunk.line(row)}, column {name!r}: {what}'
                                ) from None
            values[row] = math.nan
    return values


def _check_times(seconds: np.ndarray, chunk: _Chunk, name: str | None, path: Path,
                 previous: float | None) -> float:
    """
    Check one chunk of the time column; return its last time.

    Raises
    ------
    BcidError
        At the first time that is not finite, negative, too large for a
        nanosecond stamp, or before the time of the row above.

    """
    bad = ~np.isfinite(seconds) | (seconds < 0) | (seconds >= LARGEST_TIME_S)
    before = np.concatenate([[-np.inf if previous is None else previous], seconds[:-1]])
    backwards = seconds < before
    problems = np.flatnonzero(bad | backwards)
    if problems.size:
        row = int(problems[0])
        raise BcidError(f'{path}: row {chunk.line(row)}, column {name!r}: '
                        + _time_problem(float(seconds[row]), float(before[row])))
    return float(seconds[-1])


def _time_problem(value: float, before: float) -> str:
    """Return what is wrong with a time of ``value`` s after one of ``before`` s."""
    if not math.isfinite(value):
        return f'{value!r} is not a finite time'
    if value < 0:
        return f'time {value!r} s is negative; bag time stamps start at 0'
    if value >= LARGEST_TIME_S:
        return (f'time {value!r} s is too large (at most {LARGEST_TIME_S:.4g} s, the year 2255 '
                'as Unix time)')
    return (f'time {value!r} s is before the row above ({before!r} s); the rows must be in '
            'time order')


def write_samples_bag(samples: CsvSamples, out: str | Path) -> Path:
    """
    Write the samples to a new rosbag2 MCAP bag: one ``/samples`` message per row.

    The bag is the simulator's format (docs/bags.md): a
    ``std_msgs/msg/Float64MultiArray`` per sample on ``/samples`` with
    ``layout.dim[0] = {label: 'y,u1,...,ur', size: 1 + r, stride: 1 + r}``,
    stamped :attr:`CsvSamples.times_ns`, with the simulator's QoS (reliable,
    volatile, depth 1000) in the channel metadata, written by
    :class:`~bcid_ros.bag.writer.BagWriter` (``metadata.yaml`` included).
    A non-finite sample is written as it is (NaN), for the identifier to skip.
    The log is streamed (:meth:`CsvSamples.chunks`); :attr:`CsvSamples.stats`
    holds the counts afterwards.

    Returns
    -------
    pathlib.Path
        The bag directory.

    Raises
    ------
    BcidError
        If ``out`` exists.

    """
    from bcid_ros.bag.simulate import SAMPLES_QOS, SAMPLES_TOPIC
    from bcid_ros.bag.writer import BagWriter
    from bcid_ros.identifier.interface import FLOAT64_MULTI_ARRAY

    out = Path(out)
    with BagWriter(out) as writer:
        writer.add_topic(SAMPLES_TOPIC, FLOAT64_MULTI_ARRAY, [SAMPLES_QOS])
        for times, rows in samples.chunks():
            for time_ns, message in zip(times.tolist(), _serialised(rows)):
                writer.write(SAMPLES_TOPIC, time_ns, message)
    return out


def _serialised(rows: np.ndarray) -> Iterator[bytes]:
    """
    Yield the CDR bytes of a one-sample ``samples`` message per row.

    rosbags serialises the first row; every message has the same layout, so
    the same bytes up to the values (the CDR *head*,
    :func:`~bcid_ros.identifier.cdr.decode_head`), and the others are that
    head and their values as little-endian doubles (the first message's
    encapsulation is CDR_LE). Where the first message
    does not end in its values so (another serialiser), each row is
    serialised by rosbags.
    """
    from bcid_ros.bag.writer import float64_multi_array, TYPESTORE
    from bcid_ros.identifier.interface import FLOAT64_MULTI_ARRAY
    from bcid_ros.identifier.layouts import samples_layout

    width = rows.shape[1]
    layout = samples_layout(1, width - 1)
    values = np.ascontiguousarray(rows, dtype='<f8')
    first = bytes(TYPESTORE.serialize_cdr(float64_multi_array(layout, rows[0]),
                                          FLOAT64_MULTI_ARRAY))
    head = first[:-8 * width]
    if first[:2] != b'\x00\x01' or first[-8 * width:] != values[0].tobytes():
        for row in rows:
            yield bytes(TYPESTORE.serialize_cdr(float64_multi_array(layout, row),
                                                FLOAT64_MULTI_ARRAY))
        return
    for row in values:
        yield head + row.tobytes()


__all__ = ['CSV_SUFFIX', 'CsvSamples', 'DEFAULT_RATE_HZ', 'is_csv', 'parse_columns',
           'read_csv_samples', 'samples_source', 'write_samples_bag']
