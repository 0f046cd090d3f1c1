"""
The block path of ``bcid replay``: file order, its check, block decoding, block feeding.

Every replay here is compared with a reference computed in the same test: the
node's per-message rule (:meth:`SampleFeeder.take_message`) on the messages as
``mcap``/``mcap_ros2`` read and order them. So the blocks, the order check and
:meth:`SampleFeeder.take_messages` must change nothing, to the last bit. That is
one arithmetic path: the block path gathers each phi(t) from the same values
(``ArxRegressor.push_rows``) as a contiguous row of the same length p and takes
the same step on it, so every BLAS call sees the same n and strides as sample by
sample; only the addresses differ.
"""

from pathlib import Path

from mcap.reader import make_reader
from mcap.writer import CompressionType, IndexType, Writer
from mcap_ros2.decoder import DecoderFactory
import numpy as np
import pytest
from recording_estimator import BlockRecorder

from bcid_ros.bag.reader import BagReader
from bcid_ros.bag.replay import replay
from bcid_ros.bag.simulate import simulate_bag
from bcid_ros.bag.writer import BagWriter, float64_multi_array
from bcid_ros.cli import main as bcid
from bcid_ros.identifier.feeder import SampleFeeder, VECTOR_CHECK_MIN
from bcid_ros.identifier.layouts import samples_layout
from bcid_ros.identifier.parameters import estimator_from_parameters, load_yaml_parameters
from bcid_ros.simulation import make_scenario

REPO = Path(__file__).resolve().parents[2]
CONFIG = REPO / 'config' / 'ding_miso.yaml'
F64MA = 'std_msgs/msg/Float64MultiArray'


def params(**changes):
    """Return the Ding MISO identifier parameters with ``changes``."""
    return {**load_yaml_parameters(CONFIG), **changes}


def mcap_of(bag):
    """Return the single MCAP file of a bag directory."""
    return next(Path(bag).glob('*.mcap'))


def raw_messages(bag):
    """Return (summary, [(channel id, log time, publish time, CDR bytes)]) in file order."""
    with mcap_of(bag).open('rb') as stream:
        reader = make_reader(stream)
        summary = reader.get_summary()
        messages = [(m.channel_id, m.log_time, m.publish_time, m.data)
                    for _, _, m in reader.iter_messages(log_time_order=False)]
    return summary, messages


def rewrite(bag, target, order=None, **options):
    """Write the messages of ``bag`` to the MCAP file ``target`` in ``order`` (file positions)."""
    summary, messages = raw_messages(bag)
    if order is not None:
        messages = [messages[k] for k in order]
    with open(target, 'wb') as stream:
        writer = Writer(stream, **options)
        writer.start(profile='ros2')
        for schema in summary.schemas.values():
            writer.register_schema(schema.name, schema.encoding, schema.data)
        for channel in sorted(summary.channels.values(), key=lambda c: c.id):
            writer.register_channel(channel.topic, channel.message_encoding, channel.schema_id,
                                    channel.metadata)
        for channel, log_time, publish_time, data in messages:
            writer.add_message(channel, log_time, data, publish_time)
        writer.finish()
    return target


def reference(path, values):
    """Return the per-message replay: mcap's log-time order, mcap_ros2, take_message."""
    feeder = SampleFeeder(estimator_from_parameters(values), values.get('excitation_window', 0),
                          values.get('publish_period', 1))
    stamps, thetas, counts = [], [], []
    dropped = 0
    files = [path] if Path(path).is_file() else sorted(Path(path).glob('*.mcap'))
    for file in files:
        with open(file, 'rb') as stream:
            reader = make_reader(stream, decoder_factories=[DecoderFactory()])
            for item in reader.iter_decoded_messages(topics=['/samples']):
                result = feeder.take_message(item.decoded_message)
                dropped += bool(result.dropped)
                if result.estimates is not None:
                    stamps.append(item.message.log_time)
                    thetas.append(result.estimates[0])
                    counts.append(feeder.used)
    return feeder, np.array(stamps), np.array(thetas), np.array(counts), dropped


def assert_same_as_reference(path, values):
    """Replay ``path`` and assert bit equality with :func:`reference`; return the result."""
    result = replay(path, values)
    feeder, stamps, thetas, counts, dropped = reference(path, values)
    np.testing.assert_array_equal(result.theta, feeder.estimator.theta)
    np.testing.assert_array_equal(result.theta_uncompensated,
                                  feeder.estimator.theta_uncompensated)
    np.testing.assert_array_equal(result.noise, feeder.estimator.noise)
    assert (result.samples, result.nonfinite) == (feeder.used, feeder.nonfinite)
    assert result.malformed + result.empty + result.failures == dropped
    np.testing.assert_array_equal(result.times_ns, stamps)
    np.testing.assert_array_equal(result.sample_counts, counts)
    np.testing.assert_array_equal(result.theta_trajectory, thetas.reshape(-1, 6))
    return result


@pytest.fixture(scope='module')
def bag(tmp_path_factory):
    """Return a 3,000-sample ding_miso bag written by ``bcid simulate`` (in order)."""
    return simulate_bag('ding_miso', 3000, 6, 1000.0, tmp_path_factory.mktemp('b') / 'bag')


# ------------------------------------------------------------------ order
def test_an_ordered_bag_is_read_in_file_order(bag):
    reader = BagReader(bag)
    blocks = list(reader.blocks('/samples'))
    assert reader.order['/samples'].in_file_order
    assert reader.order['/samples'].messages == 3000
    assert not reader.order['/samples'].overlapping_chunks
    # One sample per message, same layout: one block per chunk (this bag has one chunk).
    assert [len(b) for b in blocks] == [3000]
    assert_same_as_reference(bag, params(estimator='bcrls'))


def swapped_pairs(count, every):
    """Return file positions 0..count-1 with each ``every``-th pair swapped."""
    order = list(range(count))
    for k in range(2, count - 1, every):
        order[k], order[k + 1] = order[k + 1], order[k]
    return order


def test_messages_out_of_order_in_a_chunk_are_sorted(bag, tmp_path):
    # Positions 0 and 1 are the truth topics; swap pairs of samples in file order.
    _, messages = raw_messages(bag)
    path = rewrite(bag, tmp_path / 'swapped.mcap', swapped_pairs(len(messages), 97))
    reader = BagReader(path)
    times = np.concatenate([b.times_ns for b in reader.blocks('/samples')])
    order = reader.order['/samples']
    assert not order.in_file_order and order.moved == 2 * len(range(2, len(messages) - 1, 97))
    assert np.all(np.diff(times) > 0)
    result = assert_same_as_reference(path, params(estimator='bcrls'))
    assert not result.in_file_order
    # The same samples in order give the same estimates.
    np.testing.assert_array_equal(result.theta, replay(bag, params(estimator='bcrls')).theta)


def test_overlapping_chunks_are_sorted_across_chunks(bag, tmp_path):
    # The second half first, in small chunks: chunk time ranges overlap.
    _, messages = raw_messages(bag)
    half = len(messages) // 2
    order = [0, 1] + list(range(half, len(messages))) + list(range(2, half))
    path = rewrite(bag, tmp_path / 'halves.mcap', order, chunk_size=4096)
    reader = BagReader(path)
    list(reader.blocks('/samples'))
    report = reader.order['/samples']
    assert report.overlapping_chunks and not report.in_file_order
    result = assert_same_as_reference(path, params(estimator='rls'))
    np.testing.assert_array_equal(result.theta, replay(bag, params(estimator='rls')).theta)


def test_cli_notes_a_bag_out_of_order(bag, tmp_path, capsys):
    _, messages = raw_messages(bag)
    path = rewrite(bag, tmp_path / 'swapped.mcap', swapped_pairs(len(messages), 500))
    assert bcid(['replay', str(path), '--params', str(CONFIG), '--json']) == 0
    assert 'not stored in log-time order' in capsys.readouterr().err
    assert bcid(['replay', str(bag), '--params', str(CONFIG), '--json']) == 0
    assert capsys.readouterr().err == ''


# ------------------------------------------------------------------ MCAP forms
@pytest.mark.parametrize('options', [
    {'compression': CompressionType.NONE, 'chunk_size': 2000},
    {'compression': CompressionType.LZ4},
    {'index_types': IndexType.CHUNK},  # no message indexes: the chunks are scanned
    {'index_types': IndexType.NONE},  # no chunk index: mcap's own iterator
], ids=['uncompressed', 'lz4', 'no_message_index', 'no_chunk_index'])
def test_other_mcap_forms_give_the_same_replay(bag, tmp_path, options):
    path = rewrite(bag, tmp_path / 'other.mcap', **options)
    assert_same_as_reference(path, params(estimator='bcrls'))


def test_blocks_equal_mcap_ros2_message_for_message(tmp_path):
    path = mixed_bag(tmp_path / 'mixed')
    reader = BagReader(path)
    fast = list(reader.float64_multi_arrays('/samples'))
    with open(mcap_of(path), 'rb') as stream:
        slow = [(m.log_time, d) for _, _, m, d in make_reader(
            stream, decoder_factories=[DecoderFactory()]).iter_decoded_messages(
                topics=['/samples'])]
    assert [t for t, _ in fast] == [t for t, _ in slow]
    for (_, a), (_, b) in zip(fast, slow):
        assert list(a.layout.dim) == [(d.label, d.size, d.stride) for d in b.layout.dim]
        assert a.layout.data_offset == b.layout.data_offset
        np.testing.assert_array_equal(a.data, np.asarray(b.data))


def mixed_bag(path):
    """
    Return a bag whose samples change form: samples, frames, bad and empty messages, NaN.

    So it splits into many blocks, and some of them go message by message.
    """
    y, u = make_scenario('ding_miso').simulate(1200, 9)
    rows = np.column_stack([y, u])
    rows[700, 1] = np.nan
    messages = []
    k = 0
    while k < rows.shape[0]:
        if k == 450:  # one value short: malformed
            messages.append(float64_multi_array([('y,u1', 2, 2)], [1.0, 2.0]))
        if k == 900:  # no values: empty
            messages.append(float64_multi_array([], []))
        size = 5 if 300 <= k < 500 else 1
        frame = rows[k:k + size]
        messages.append(float64_multi_array(samples_layout(size, 2), frame.reshape(-1)))
        k += size
    with BagWriter(path) as writer:
        writer.add_topic('/samples', F64MA)
        for index, message in enumerate(messages):
            writer.write_message('/samples', (index + 1) * 1_000_000, message)
    return path


@pytest.mark.parametrize('estimator, period', [('bcrls', 1), ('rls', 7)])
def test_a_bag_of_mixed_messages_replays_as_the_node_would(tmp_path, estimator, period):
    path = mixed_bag(tmp_path / 'mixed')
    result = assert_same_as_reference(path, params(estimator=estimator, publish_period=period))
    assert (result.malformed, result.empty, result.nonfinite) == (1, 1, 1)
    # The final estimate without the trajectory is the same.
    quiet = replay(path, params(estimator=estimator, publish_period=period), trajectory=False)
    np.testing.assert_array_equal(quiet.theta, result.theta)
    assert quiet.times_ns.shape == (0,) and quiet.theta_trajectory.shape == (0, 6)


@pytest.mark.parametrize('name', ['ding_miso', 'ikenoue_colored'])
def test_the_summary_reader_reads_what_mcap_reads(name):
    from bcid_ros.bag.summary import read_header, read_summary

    with mcap_of(REPO / 'bags' / name).open('rb') as stream:
        reader = make_reader(stream)
        header, summary = reader.get_header(), reader.get_summary()
        ours_header, ours = read_header(stream), read_summary(stream)
    assert (ours_header.profile, ours_header.library) == (header.profile, header.library)
    for ours_table, table in ((ours.schemas, summary.schemas),
                              (ours.channels, summary.channels)):
        assert sorted(ours_table) == sorted(table)
        for key, record in ours_table.items():
            for field in record._fields:
                assert getattr(record, field) == getattr(table[key], field), field
    assert len(ours.chunk_indexes) == len(summary.chunk_indexes) > 0
    for record, theirs in zip(ours.chunk_indexes, summary.chunk_indexes):
        for field in record._fields:
            assert getattr(record, field) == getattr(theirs, field), field
    for field in ours.statistics._fields:
        assert getattr(ours.statistics, field) == getattr(summary.statistics, field), field


def test_the_summary_reader_refuses_a_file_without_footer(tmp_path):
    from bcid_ros.bag.summary import read_summary

    path = tmp_path / 'cut.mcap'
    path.write_bytes(mcap_of(REPO / 'bags' / 'ikeda_closed_loop').read_bytes()[:-40])
    with path.open('rb') as stream, pytest.raises(ValueError, match='magic'):
        read_summary(stream)


def test_a_corrupt_message_index_is_a_clean_error(bag, tmp_path):
    from bcid_ros.errors import BcidError

    path = rewrite(bag, tmp_path / 'copy.mcap', compression=CompressionType.NONE)
    data = bytearray(path.read_bytes())
    with open(path, 'rb') as stream:
        chunk = make_reader(stream).get_summary().chunk_indexes[0]
    offset = chunk.message_index_offsets[1]
    data[offset + 15 + 8:offset + 15 + 16] = (10 ** 9).to_bytes(8, 'little')  # an offset
    path.write_bytes(bytes(data))
    with pytest.raises(BcidError, match='corrupt'):
        replay(path, params())


# ------------------------------------------------------------------ take_messages
class Recorder(BlockRecorder):
    """Records updates and restarts; raises on ``fail_on``; NaN estimates at ``nan_at``."""

    num_inputs = 1

    def __init__(self, fail_on=(), nan_at=()):
        self.flags = {}  # the estimator's flag counts, which a replay's rows report
        self.log = []
        self.fail_on = set(fail_on)
        self.nan_at = set(nan_at)

    @property
    def ready(self):
        """Whether three updates were made."""
        return sum(1 for entry in self.log if entry != 'restart') >= 3

    valid = ready

    @property
    def theta(self):
        """Return the number of log entries, or NaN after the chosen ones."""
        return np.array([np.nan if len(self.log) in self.nan_at else len(self.log), 1.0])

    theta_uncompensated = theta

    @property
    def noise(self):
        """Return a constant."""
        return np.array([0.5])

    def restart_regressor(self):
        """Record a restart."""
        self.log.append('restart')


def per_message(feeder, rows, count):
    """Feed message by message with take_rows; return (log, published, withheld, failed)."""
    published, withheld, failed = [], 0, []
    for index in range(rows.shape[0] // count):
        result = feeder.take_rows(rows[index * count:(index + 1) * count])
        if result.estimates is not None:
            published.append((index, feeder.used, result.estimates[0].tolist()))
        withheld += result.withheld
        if result.dropped:
            failed.append(index)
    return published, withheld, failed


@pytest.mark.parametrize('count, period, window, nan_row', [
    (1, 1, 0, None), (1, 3, 0, None), (4, 2, 0, None), (4, 5, 0, 13), (1, 2, 3, 40),
    (3, 1, 2, None)])
def test_take_messages_equals_take_rows_message_by_message(count, period, window, nan_row):
    rows = np.column_stack([np.arange(120.0), np.repeat(np.arange(30.0), 4)])
    if nan_row is not None:
        rows[nan_row, 0] = np.nan
    make = dict(fail_on={17.0, 18.0, 61.0}, nan_at={20, 21, 50})
    one = SampleFeeder(Recorder(**make), window, period)
    expected = per_message(one, rows, count)
    block = SampleFeeder(Recorder(**make), window, period)
    result = block.take_messages(rows, count)
    published = [(i, used, e[0].tolist()) for i, used, e in zip(
        result.published, result.used_totals, result.estimates)]
    assert block.estimator.log == one.estimator.log
    assert published == expected[0] and published
    assert result.withheld == expected[1]
    assert [index for index, _ in result.failures] == expected[2]
    assert all('boom' in reason for _, reason in result.failures)
    for name in ('used', 'nonfinite', 'unexcited', 'since_publish'):
        assert getattr(block, name) == getattr(one, name), name
    assert block.times.count == one.times.count
    assert result.used == one.used and result.nonfinite == one.nonfinite


@pytest.mark.parametrize('count, window, nan_row', [
    (1, 0, None), (4, 0, 13), (1, 3, 40), (3, 2, None), (5, 0, None)])
def test_take_messages_without_publishing_feeds_as_message_by_message(count, window, nan_row):
    # The one-loop path (publish=False, timed=False): same updates, restarts, failures, counts.
    rows = np.column_stack([np.arange(120.0), np.repeat(np.arange(30.0), 4)])
    if nan_row is not None:
        rows[nan_row, 0] = np.nan
    make = dict(fail_on={17.0, 18.0, 61.0})
    one = SampleFeeder(Recorder(**make), window, 2)
    expected = per_message(one, rows, count)
    block = SampleFeeder(Recorder(**make), window, 2)
    result = block.take_messages(rows, count, publish=False, timed=False)
    assert block.estimator.log == one.estimator.log
    assert result.published == [] and result.estimates == []
    assert [index for index, _ in result.failures] == expected[2] and result.failures
    for name in ('used', 'nonfinite', 'unexcited'):
        assert getattr(block, name) == getattr(one, name), name
    assert block.times.count == one.times.count
    assert result.used == one.used and result.unexcited == one.unexcited
    assert block.since_publish == block.used  # nothing was published
    if nan_row is None:  # a block with NaN goes message by message, timed
        assert block.times.total_ns == 0  # counted, not timed


def test_take_messages_checks_the_shape():
    feeder = SampleFeeder(Recorder())
    with pytest.raises(ValueError, match='whole messages of count = 2'):
        feeder.take_messages(np.zeros((3, 2)), 2)
    with pytest.raises(ValueError, match='1 \\+ num_inputs = 2'):
        feeder.take_messages(np.zeros((4, 3)), 2)
    assert feeder.estimator.log == []


@pytest.mark.parametrize('estimator', ['rls', 'bcrls'])
def test_take_messages_is_bit_equal_to_the_node_path(estimator):
    values = {'estimator': estimator, 'order': 2, 'num_inputs': 2}
    y, u = make_scenario('ding_miso').simulate(2000, 5)
    rows = np.column_stack([y, u])
    for count in (1, 50):
        one = SampleFeeder(estimator_from_parameters(values))
        thetas = [r.estimates[0] for r in (one.take_rows(rows[k:k + count])
                                           for k in range(0, 2000, count)) if r.estimates]
        block = SampleFeeder(estimator_from_parameters(values))
        result = block.take_messages(rows, count)
        np.testing.assert_array_equal(block.estimator.theta, one.estimator.theta)
        np.testing.assert_array_equal(np.array([e[0] for e in result.estimates]),
                                      np.array(thetas))


def excitation_by_the_rule(parts, window):
    """Return (run, last input, unexcited) after each part, by the rule sample by sample."""
    run, last, states = 0, None, []
    for part in parts:
        unexcited = 0
        for u in part[:, 1:].tolist():
            run, last = (run + 1, last) if u == last else (0, u)
            unexcited += run >= window
        states.append((run, last, unexcited))
    return states


@pytest.mark.parametrize('window', [1, 3, 8])
def test_the_excitation_check_of_a_block_follows_the_sample_rule(window):
    # Inputs that stay constant for runs of random length, fed in blocks of random size
    # (under VECTOR_CHECK_MIN rows sample by sample, from it vectorised).
    generator = np.random.default_rng(4)
    inputs = np.repeat(generator.normal(size=40), generator.integers(1, 12, size=40))
    rows = np.column_stack([np.arange(inputs.shape[0], dtype=float), inputs])
    cuts = np.sort(generator.choice(np.arange(1, rows.shape[0]), 15, replace=False))
    parts = np.split(rows, cuts)
    assert min(map(len, parts)) < VECTOR_CHECK_MIN <= max(map(len, parts))
    feeder = SampleFeeder(Recorder(), window)
    fed = [(feeder.feed(part).unexcited, feeder._constant_run, feeder._last_u)
           for part in parts]
    expected = excitation_by_the_rule(parts, window)
    assert fed == [(unexcited, run, last) for run, last, unexcited in expected]
    assert sum(unexcited for unexcited, _, _ in fed) > 0
    # a failing row's check comes before its update: the state after it is kept
    failing = SampleFeeder(Recorder(fail_on={30.0, 31.0, 100.0}), window)
    for part in parts:
        try:
            failing.feed(part)
        except FloatingPointError:
            pass
    assert (failing._constant_run, failing._last_u) == expected[-1][:2]
