"""
Read rosbag2 MCAP bags (no rclpy).

:class:`BagReader` opens a bag directory (``metadata.yaml`` + ``*.mcap``) or
a single ``.mcap`` file, checks that it is a ROS 2 MCAP (profile ``ros2``,
``cdr`` messages), and turns every way a bag can be broken (missing,
truncated, corrupt, not MCAP, a topic missing or of the wrong type) into a
:class:`~bcid_ros.errors.BcidError` that says what is wrong in one line.

The samples are read by :meth:`BagReader.blocks` (:mod:`bcid_ros.bag.blocks`):
chunks in file order, checked to be in log-time order, and runs of messages
decoded at once; the header and summary are read by :mod:`bcid_ros.bag.summary`.
Only what that needs is imported up front; ``mcap`` (for :meth:`BagReader.messages`
and bags without chunk indexes), ``mcap_ros2`` (for messages of another form),
``rosbags`` (for the QoS) and ``yaml`` (for ``metadata.yaml``) are imported when
used, which keeps ``bcid replay``'s start-up short.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
import sys
from typing import Any, Iterator, Sequence

import numpy as np

from bcid_ros.bag.blocks import (chunk_records, MessageBlock, ordered_blocks, OrderReport,
                                 topic_blocks)
from bcid_ros.bag.summary import (check_data_crc, CrcMismatch, MissingFooter, parse_summary,
                                  read_errors, read_footer, read_header)
from bcid_ros.errors import BcidError
from bcid_ros.identifier.interface import (basename, FLOAT64_MULTI_ARRAY, TRUE_NOISE_VARIANCE,
                                           TRUE_PARAMETERS)
from bcid_ros.identifier.layouts import parse_names_label
from bcid_ros.simulation.base import Truth


def make_reader(stream: Any, **options: Any) -> Any:
    """Return ``mcap``'s reader of ``stream`` (imported here: summaries and blocks need none)."""
    from mcap.reader import make_reader as make

    return make(stream, validate_crcs=True, **options)


@dataclasses.dataclass(frozen=True)
class TopicInfo:
    """One topic of a bag: type, message count and the QoS its publishers offered."""

    name: str
    type: str
    count: int
    #: The ``offered_qos_profiles`` YAML of the topic's first channel that has one.
    qos_text: str
    encoding: str

    @property
    def qos(self) -> tuple[Any, ...]:
        """
        Return the offered QoS profiles (rosbags ``Qos``), parsed now.

        Raises
        ------
        BcidError
            If the ``offered_qos_profiles`` YAML cannot be parsed.

        """
        from bcid_ros.bag.qos import parse_offered

        try:
            return tuple(parse_offered(self.qos_text))
        except ValueError as error:
            raise BcidError(f'topic {self.name}: {error}') from None


@dataclasses.dataclass(frozen=True)
class BagTruth(Truth):
    """The simulator's truth as recorded in a bag (empty names when absent)."""

    def as_dict(self) -> dict[str, dict[str, float]]:
        """Return ``{'parameters': {name: value}, 'noise': {name: value}}``."""
        return {'parameters': dict(zip(self.parameter_names, map(float, self.parameters))),
                'noise': dict(zip(self.noise_names, map(float, self.noise)))}


def bag_files(path: Path) -> list[Path]:
    """
    Return the MCAP files of a bag directory (in metadata order) or of a file path.

    Raises
    ------
    BcidError
        If the path does not exist, or holds no MCAP file.

    """
    if not path.exists():
        raise BcidError(f'{path}: no such bag (expected a rosbag2 directory or an .mcap file)')
    if path.is_file():
        return [path]
    metadata = path / 'metadata.yaml'
    if metadata.is_file():
        import yaml

        loader = getattr(yaml, 'CSafeLoader', yaml.SafeLoader)  # libyaml's, where built
        try:
            info = yaml.load(metadata.read_text(), Loader=loader)['rosbag2_bagfile_information']
            names = list(info['relative_file_paths'])
            storage = info.get('storage_identifier', 'mcap')
        except (yaml.YAMLError, TypeError, KeyError) as error:
            raise BcidError(f'{metadata}: not a rosbag2 metadata file ({error!r})') from None
        if storage != 'mcap':
            raise BcidError(f'{path}: storage {storage!r} is not supported; only MCAP bags')
        files = [path / name for name in names]
        missing = [f.name for f in files if not f.is_file()]
        if missing:
            raise BcidError(f'{path}: metadata.yaml lists {", ".join(missing)}, which is '
                            'missing')
        return files
    files = sorted(path.glob('*.mcap'))
    if not files:
        raise BcidError(f'{path}: no metadata.yaml and no .mcap file; not a rosbag2 MCAP bag')
    return files


class BagReader:
    """
    A read-only view of a rosbag2 MCAP bag.

    Every CRC the file carries is checked (docs/guarantees.md): the summary's
    and the data section's on opening, each chunk's when it is read (also by
    ``mcap``'s reader, which is asked to validate them). A file without a
    footer (a recording that was killed) is read by scanning its whole
    chunks (:mod:`bcid_ros.bag.recovery`), with a warning in :attr:`warnings`,
    also printed to stderr.

    Parameters
    ----------
    path : str or pathlib.Path
        The bag directory or one ``.mcap`` file.

    Raises
    ------
    BcidError
        If the bag is missing, truncated, corrupt (a CRC that does not match)
        or not a ROS 2 MCAP.

    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.files = bag_files(self.path)
        self.topics: dict[str, TopicInfo] = {}
        self.start_ns: int | None = None
        self.end_ns: int | None = None
        #: How far file order was from log-time order, per topic read by :meth:`blocks`.
        self.order: dict[str, OrderReport] = {}
        #: What was read in a way that needs a word (a missing footer), one line each.
        self.warnings: list[str] = []
        self._summaries: dict[Path, Any] = {}
        for file in self.files:
            self._read_summary(file)

    def _read_summary(self, file: Path) -> None:
        try:
            with file.open('rb') as stream:
                header = read_header(stream)
                summary = self._summary(file, stream)
        except CrcMismatch as error:
            raise BcidError(f'{file}: corrupt: {error}') from None
        except read_errors() as error:
            raise BcidError(f'{file}: not a readable MCAP file, truncated or corrupt '
                            f'({type(error).__name__}: {error})') from None
        if header.profile != 'ros2':
            raise BcidError(f'{file}: MCAP profile is {header.profile!r}, not \'ros2\'')
        self._summaries[file] = summary
        counts = summary.statistics.channel_message_counts
        for channel in summary.channels.values():
            schema = summary.schemas.get(channel.schema_id)
            if schema is None:
                raise BcidError(f'{file}: topic {channel.topic} has no schema')
            if channel.message_encoding != 'cdr' or schema.encoding not in ('ros2msg',
                                                                            'ros2idl'):
                raise BcidError(f'{file}: topic {channel.topic} is encoded as '
                                f'{channel.message_encoding}/{schema.encoding}, not '
                                'cdr/ros2msg')
            qos = channel.metadata.get('offered_qos_profiles', '')
            previous = self.topics.get(channel.topic)
            if previous is not None and previous.type != schema.name:
                raise BcidError(f'{file}: topic {channel.topic} has two types, '
                                f'{previous.type} and {schema.name}')
            count = counts.get(channel.id, 0) + (previous.count if previous else 0)
            self.topics[channel.topic] = TopicInfo(
                channel.topic, schema.name, count, (previous.qos_text if previous else '') or qos,
                channel.message_encoding)
        stats = summary.statistics
        if stats.message_count:
            self.start_ns = (stats.message_start_time if self.start_ns is None
                             else min(self.start_ns, stats.message_start_time))
            self.end_ns = (stats.message_end_time if self.end_ns is None
                           else max(self.end_ns, stats.message_end_time))

    def _summary(self, file: Path, stream: Any) -> Any:
        """Return the file's summary after checking its CRCs, or rebuild it (no footer)."""
        try:
            footer = read_footer(stream)
        except MissingFooter as error:
            return self._recover(file, stream, str(error))
        if footer.summary_start == 0:
            check_data_crc(stream, footer)
            return self._recover(file, stream, 'no summary section')
        stream.seek(footer.summary_start)
        summary = parse_summary(stream.read(footer.offset - footer.summary_start))
        try:
            check_data_crc(stream, footer)
        except CrcMismatch:
            for chunk in summary.chunk_indexes:  # name the corrupt chunk, if it is one
                chunk_records(stream, chunk)
            raise
        if summary.statistics is None:
            return self._recover(file, stream, 'no statistics in the summary')
        return summary

    def _recover(self, file: Path, stream: Any, reason: str) -> Any:
        from bcid_ros.bag.recovery import scan_summary

        recovered = scan_summary(stream)
        self.warn(f'{file}: {reason}: an unfinished recording? {recovered.describe()}; '
                  f'`bcid reindex {self.path}` repairs it')
        return recovered.summary

    def warn(self, text: str) -> None:
        """Keep a warning in :attr:`warnings` and print it to stderr."""
        self.warnings.append(text)
        print(f'bcid: warning: {text}', file=sys.stderr)

    @property
    def duration_s(self) -> float:
        """Return the time from the first to the last message, in seconds."""
        if self.start_ns is None or self.end_ns is None:
            return 0.0
        return (self.end_ns - self.start_ns) / 1e9

    @property
    def message_count(self) -> int:
        """Return the number of messages on all topics."""
        return sum(t.count for t in self.topics.values())

    def require(self, topic: str, msgtype: str) -> TopicInfo:
        """
        Return the info of ``topic`` after checking that it exists with type ``msgtype``.

        Raises
        ------
        BcidError
            If the bag has no such topic, or it has another type.

        """
        info = self.topics.get(topic)
        if info is None:
            have = ', '.join(sorted(self.topics)) or 'none'
            raise BcidError(f'{self.path}: no topic {topic} in the bag (topics: {have})')
        if info.type != msgtype:
            raise BcidError(f'{self.path}: topic {topic} has type {info.type}, expected '
                            f'{msgtype}')
        return info

    def blocks(self, topic: str) -> Iterator[MessageBlock]:
        """
        Yield the messages of a Float64MultiArray topic in log-time order, in blocks.

        A block is a run of messages with the same layout and number of
        values, decoded at once (:mod:`bcid_ros.bag.blocks`); a message that
        the fast CDR decoder does not recognise comes alone, decoded by
        ``mcap_ros2``, with the same fields. Each file is read in file order
        where that is log-time order, else sorted; :attr:`order` says which.

        Raises
        ------
        BcidError
            If a chunk, record or CDR message is corrupt.

        """
        order = self.order[topic] = OrderReport()
        for file in self.files:
            summary = self._summaries[file]
            channels = {c.id for c in summary.channels.values() if c.topic == topic}
            if not channels:
                continue
            schema = summary.schemas[summary.channels[min(channels)].schema_id]
            fallback = _Fallback(schema)
            try:
                with file.open('rb') as stream:
                    if summary.chunk_indexes:
                        yield from topic_blocks(stream, summary, channels, fallback, order)
                    else:
                        yield from self._unindexed_blocks(stream, topic, fallback, order)
            except read_errors() as error:
                raise BcidError(f'{file}: corrupt MCAP data or CDR message '
                                f'({type(error).__name__}: {error})') from None

    @staticmethod
    def _unindexed_blocks(stream: Any, topic: str, fallback: _Fallback,
                          order: OrderReport) -> Iterator[MessageBlock]:
        """Yield one-message blocks from an MCAP without chunk indexes (``mcap``'s order)."""
        from bcid_ros.bag.blocks import equal_head_blocks

        reader = make_reader(stream)
        for _, _, message in reader.iter_messages(topics=[topic]):
            raw = np.frombuffer(message.data, dtype=np.uint8)[None, :]
            order.messages += 1
            yield from equal_head_blocks(np.array([message.log_time], dtype=np.int64), raw,
                                         fallback)

    def float64_multi_arrays(self, topic: str) -> Iterator[tuple[int, Any]]:
        """
        Yield ``(log time ns, message)`` of a Float64MultiArray topic, in log-time order.

        The messages come from :meth:`blocks` and have the fields of the ROS
        type (``layout.dim[i].label/size/stride``, ``layout.data_offset``,
        ``data``).

        Raises
        ------
        BcidError
            If a chunk, record or CDR message is corrupt.

        """
        return ordered_blocks(self.blocks(topic))

    def messages(self, topics: Sequence[str] | None = None
                 ) -> Iterator[tuple[str, int, bytes]]:
        """
        Yield ``(topic, log time ns, CDR bytes)`` in log-time order.

        Raises
        ------
        BcidError
            If a chunk or record is corrupt.

        """
        for file in self.files:
            try:
                with file.open('rb') as stream:
                    reader = make_reader(stream)
                    for _, channel, message in reader.iter_messages(topics=topics):
                        yield channel.topic, message.log_time, message.data
            except read_errors() as error:
                raise BcidError(f'{file}: corrupt MCAP data ({type(error).__name__}: '
                                f'{error})') from None

    def decoded(self, topics: Sequence[str] | None = None) -> Iterator[tuple[str, int, Any]]:
        """
        Yield ``(topic, log time ns, decoded message)`` in log-time order.

        The messages are ``mcap_ros2`` objects with the fields of the ROS type.

        Raises
        ------
        BcidError
            If a chunk, record or CDR message is corrupt.

        """
        for file in self.files:
            try:
                with file.open('rb') as stream:
                    from mcap_ros2.decoder import DecoderFactory

                    reader = make_reader(stream, decoder_factories=[DecoderFactory()])
                    for item in reader.iter_decoded_messages(topics=topics):
                        yield item.channel.topic, item.message.log_time, item.decoded_message
            except read_errors() as error:
                raise BcidError(f'{file}: corrupt MCAP data or CDR message '
                                f'({type(error).__name__}: {error})') from None

    def last_decoded(self, topic: str) -> Any:
        """Return the last message of ``topic``, decoded by ``mcap_ros2``, or None."""
        last = None
        for _, _, message in self.decoded([topic]):
            last = message
        return last

    def last_float64_multi_array(self, topic: str) -> Any:
        """Return the last message of a Float64MultiArray topic, or None if it has none."""
        last = None
        for block in self.blocks(topic):
            last = block
        return None if last is None else last.message(len(last) - 1)

    def find_topic(self, suffix: str, msgtype: str = FLOAT64_MULTI_ARRAY) -> str | None:
        """Return the topic whose name ends with ``/suffix`` and has ``msgtype``, if one."""
        matches = sorted(name for name, info in self.topics.items()
                         if name.rsplit('/', 1)[-1] == suffix and info.type == msgtype
                         and info.count)
        return matches[0] if matches else None

    def truth(self) -> BagTruth | None:
        """
        Return the simulator truth recorded on ``*/true_parameters`` and ``*/true_noise_variance``.

        Returns None when the bag has no ``true_parameters`` topic.
        """
        topic = self.find_topic(basename(TRUE_PARAMETERS))
        if topic is None:
            return None
        names, values = _named_values(self.last_float64_multi_array(topic), topic)
        noise_names: tuple[str, ...] = ()
        noise = np.zeros(0)
        noise_topic = self.find_topic(basename(TRUE_NOISE_VARIANCE))
        if noise_topic is not None:
            noise_names, noise = _named_values(self.last_float64_multi_array(noise_topic),
                                               noise_topic)
        return BagTruth(names, values, noise_names, noise)


class _Fallback:
    """Decode a CDR message with ``mcap_ros2`` from its schema (imported on first use)."""

    def __init__(self, schema: Any) -> None:
        self.schema = schema
        self.decoder: Any = None

    def __call__(self, raw: bytes) -> Any:
        if self.decoder is None:
            from mcap_ros2.decoder import DecoderFactory

            self.decoder = DecoderFactory().decoder_for('cdr', self.schema)
        return self.decoder(raw)


def _named_values(message: Any, topic: str) -> tuple[tuple[str, ...], np.ndarray]:
    """Return ``(names, values)`` of an estimate-format Float64MultiArray."""
    dims = list(message.layout.dim)
    values = np.asarray(message.data, dtype=float)
    names = parse_names_label(dims[0].label) if dims else ()
    if len(names) != values.shape[0]:
        raise BcidError(f'topic {topic}: the label names {len(names)} values but the '
                        f'message has {values.shape[0]}')
    return names, values


__all__ = ['BagReader', 'BagTruth', 'TopicInfo', 'bag_files']
