"""CSV logs: ``bcid replay`` and ``analyze`` of a CSV, ``bcid import``, one line per bad CSV."""

import json
from pathlib import Path
import re
import subprocess
import sys

import numpy as np
import pytest

from bcid_ros.bag import csv_samples
from bcid_ros.bag.csv_samples import read_csv_samples, write_samples_bag
from bcid_ros.bag.reader import BagReader
from bcid_ros.bag.replay import replay
from bcid_ros.cli import main as bcid
from bcid_ros.errors import BcidError
from bcid_ros.identifier.layouts import decode_samples
from bcid_ros.simulation import make_scenario

REPO = Path(__file__).resolve().parents[2]
DING = REPO / 'config' / 'ding_miso.yaml'
F64MA = 'std_msgs/msg/Float64MultiArray'


def write_csv(path, header, rows):
    """Write ``header`` and ``rows`` (lists of cells; floats as repr, None as empty)."""
    def cell(value):
        return '' if value is None else value if isinstance(value, str) else repr(float(value))

    lines = [','.join(header)] + [','.join(cell(v) for v in row) for row in rows]
    path.write_text('\n'.join(lines) + '\n')
    return path


@pytest.fixture(scope='module')
def ding():
    """Return 1500 samples of Ding's MISO plant (seed 8), as rows [y, u1, u2]."""
    y, u = make_scenario('ding_miso').simulate(1500, seed=8)
    return np.column_stack([y, u])


@pytest.fixture
def ding_csv(tmp_path, ding):
    """Return a CSV of the Ding rows, a time column at 250 Hz, an empty cell and a 'nan'."""
    rows = [[k / 250, *row] for k, row in enumerate(ding.tolist())]
    rows[300][2] = None           # an empty u1: a gap
    rows[700][1] = 'nan'          # a NaN y
    return write_csv(tmp_path / 'ding.csv', ['time', 'y', 'u1', 'u2'], rows)


def run_cli(capsys, *argv):
    """Run ``bcid argv`` in-process; return (exit code, stdout, stderr)."""
    code = bcid([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


# ------------------------------------------------------------------ reading
def test_default_columns_time_column_and_gaps(ding_csv, ding):
    samples = read_csv_samples(ding_csv, time_column='time')
    assert samples.columns == ('y', 'u1', 'u2') and samples.num_inputs == 2
    expected = ding.copy()
    expected[300, 1] = expected[700, 0] = np.nan
    # the file holds repr() of each double, which reads back exactly
    np.testing.assert_array_equal(samples.rows, expected)
    np.testing.assert_array_equal(samples.times_ns, np.rint(np.arange(1500) / 250 * 1e9))
    assert samples.nonfinite_rows == 2
    blocks = list(samples.blocks())
    assert {block.layout.dim[0].label for block in blocks} == {'y,u1,u2'}
    assert sum(len(block) for block in blocks) == 1500
    np.testing.assert_array_equal(decode_samples(blocks[0].message(5), 2), ding[5:6])


def test_without_a_time_column_rows_are_stamped_at_the_rate(ding_csv):
    assert read_csv_samples(ding_csv).times_ns[:3].tolist() == [0, 10_000_000, 20_000_000]
    stamps = read_csv_samples(ding_csv, rate_hz=1000.0).times_ns
    assert stamps[-1] == 1_499_000_000 and np.all(np.diff(stamps) == 1_000_000)


def test_columns_pick_and_order(tmp_path):
    rng = np.random.default_rng(1)
    data = rng.standard_normal((50, 4))
    path = write_csv(tmp_path / 'plant.csv', ['heater', 'temp', 'note', 'fan'],
                     [[a, b, 'x', d] for a, b, _, d in data.tolist()])
    samples = read_csv_samples(path, columns='temp, heater,fan')
    assert samples.columns == ('temp', 'heater', 'fan')
    np.testing.assert_array_equal(samples.rows, data[:, [1, 0, 3]])
    picked = read_csv_samples(path, columns=('fan', 'temp'))
    np.testing.assert_array_equal(picked.rows, data[:, [3, 1]])


def test_the_default_takes_consecutive_u_columns_only(tmp_path):
    path = write_csv(tmp_path / 'gap.csv', ['u1', 'y', 'u3', 'u2', 'u5'], [[1, 2, 3, 4, 5]])
    samples = read_csv_samples(path)
    assert samples.columns == ('y', 'u1', 'u2', 'u3')  # no u4: u5 is not an input
    assert samples.rows.tolist() == [[2.0, 1.0, 4.0, 3.0]]


def test_blank_lines_bom_crlf_quotes_and_spaces_read_as_the_plain_file(tmp_path, ding):
    plain = write_csv(tmp_path / 'plain.csv', ['y', 'u1', 'u2'], ding[:40].tolist())
    lines = plain.read_text().splitlines()
    odd = ['', ' y , "u1",u2 '] + lines[1:20] + ['', '   '] \
        + [f'"{line.split(",")[0]}", {line.split(",", 1)[1]}' for line in lines[20:]]
    messy = tmp_path / 'messy.csv'
    messy.write_bytes(b'\xef\xbb\xbf' + '\r\n'.join(odd).encode() + b'\r\n')
    # one parser (Python's float, which numpy calls for strings) on the same digits: equal
    np.testing.assert_array_equal(read_csv_samples(messy).rows, read_csv_samples(plain).rows)


def test_chunks_give_the_same_rows_and_row_numbers(tmp_path, ding, monkeypatch):
    path = write_csv(tmp_path / 'ding.csv', ['y', 'u1', 'u2'], ding.tolist())
    whole = read_csv_samples(path)
    monkeypatch.setattr(csv_samples, 'CHUNK_BYTES', 1000)  # about 16 lines a chunk
    np.testing.assert_array_equal(read_csv_samples(path).rows, whole.rows)
    lines = path.read_text().splitlines()
    lines[1234] = lines[1234].replace(',', ',oops', 1)
    path.write_text('\n'.join(lines) + '\n')
    with pytest.raises(BcidError, match=r"row 1235, column 'u1': 'oops"):
        read_csv_samples(path)


def test_a_gap_does_not_change_the_other_cells(tmp_path, ding):
    # The column with a gap is converted cell by cell (float), the others by numpy: both
    # parse the same digits correctly rounded, so the values are the same doubles.
    rows = ding[:30].tolist()
    clean = read_csv_samples(write_csv(tmp_path / 'a.csv', ['y', 'u1', 'u2'], rows)).rows
    rows[7][1] = None
    gappy = read_csv_samples(write_csv(tmp_path / 'b.csv', ['y', 'u1', 'u2'], rows)).rows
    assert np.isnan(gappy[7, 1])
    gappy[7, 1] = clean[7, 1]
    np.testing.assert_array_equal(gappy, clean)


# ------------------------------------------------------------------ one line per bad CSV
BAD = {
    'missing column': ('time,y,u2\n0,1,2\n', [], r"row 1 \(the header\) has no column 'u1' "
                       r'\(it has: time,y,u2\); name the output and input columns'),
    'missing --columns column': ('y,u1,u2\n1,2,3\n', ['--columns', 'y,u1,u9'],
                                 r"row 1 \(the header\) has no column 'u9'"),
    'missing time column': ('y,u1,u2\n1,2,3\n', ['--time-column', 't'],
                            r"row 1 \(the header\) has no column 't'"),
    'column named twice': ('y,u1,u2,u1\n1,2,3,4\n', [],
                           r"names column 'u1' twice \(columns 2 and 4\)"),
    'text in a number': ('y,u1,u2\n1,2,3\n1,2,3\n1,x1.5,3\n', [],
                         r"row 4, column 'u1': 'x1.5' is not a number"),
    'decimal comma': ('y;u1;u2\n1;2;3\n', [], r"row 1 \(the header\) has no column 'y'"),
    'short row': ('y,u1,u2\n1,2,3\n1,2\n', [],
                  r"row 3 has 2 fields but the header \(row 1\) has 3: column 3 \('u2'\) is "
                  'missing'),
    'long row': ('y,u1,u2\n1,2,3\n\n1,2,3,4\n', [],
                 r"row 4 has 4 fields but the header \(row 1\) has 3: column 4 is one past"),
    'empty file': ('', [], r'empty file; expected a header row'),
    'only blank lines': ('\n  \n', [], r'empty file; expected a header row'),
    'no data rows': ('y,u1,u2\n\n', [], r'no data rows after the header \(row 1\)'),
    'empty time': ('t,y,u1,u2\n0,1,2,3\n,1,2,3\n', ['--time-column', 't'],
                   r"row 3, column 't': empty: every row needs a time"),
    'NaN time': ('t,y,u1,u2\n0,1,2,3\nnan,1,2,3\n', ['--time-column', 't'],
                 r"row 3, column 't': nan is not a finite time"),
    'infinite time': ('t,y,u1,u2\ninf,1,2,3\n', ['--time-column', 't'],
                      r"row 2, column 't': inf is not a finite time"),
    'negative time': ('t,y,u1,u2\n-0.5,1,2,3\n', ['--time-column', 't'],
                      r"row 2, column 't': time -0.5 s is negative"),
    'time too large': ('t,y,u1,u2\n1e10,1,2,3\n', ['--time-column', 't'],
                       r"row 2, column 't': time 10000000000.0 s is too large"),
    'time backwards': ('t,y,u1,u2\n0,1,2,3\n0.02,1,2,3\n0.01,1,2,3\n', ['--time-column', 't'],
                       r"row 4, column 't': time 0.01 s is before the row above \(0.02 s\)"),
    'open quote': ('y,u1,u2\n1,2,3\n"1,2,3\n', [], r'row 3: a quoted field is not closed'),
    # SPEC §18: the open quote's own row, not the last one the csv module read on to
    'open quote, rows after': ('y,u1,u2\n1,2,3\n"1,2,3\n1,2,3\n1,2,3\n4,5,6\n', [],
                               r'row 3: a quoted field is not closed'),
    'quoted line break': ('y,u1,u2\n1,2,3\n"1\n",2,3\n', [], r'row 3: a quoted field'),
    'digit separator': ('y,u1,u2\n1,2,3\n1_000,2,3\n', [],
                        r"row 3, column 'y': '1_000' is not a number"),
    'separator in a fraction': ('y,u1,u2\n1,2,3\n1,2,1_0.5\n', [],
                                r"row 3, column 'u2': '1_0.5' is not a number"),
    'full-width digits': ('y,u1,u2\n1,2,3\n1,\uff11\uff12\uff13,3\n', [],
                          "row 3, column 'u1': '\uff11\uff12\uff13' is not a number"),
    'arabic-indic digits': ('y,u1,u2\n\u0661,2,3\n', [],
                            "row 2, column 'y': '\u0661' is not a number"),
    'inputs unlike the parameters': ('y,u1\n1,2\n', [], r'has 1 input.* but the parameter file '
                                     'sets num_inputs = 2'),
    'one --columns name': ('y,u1,u2\n1,2,3\n', ['--columns', 'y'],
                           r'--columns .y.: give the output column, then at least one input'),
    'a --columns name twice': ('y,u1,u2\n1,2,3\n', ['--columns', 'y,u1,y'],
                               r"--columns 'y,u1,y': y named twice"),
    'rate zero': ('y,u1,u2\n1,2,3\n', ['--rate', '0'], r'--rate must be a positive number'),
    'time column as a sample': ('y,u1,u2\n1,2,3\n', ['--time-column', 'u2'],
                                r"--time-column 'u2' is also a sample column"),
    'time column and rate': ('t,y,u1,u2\n0,1,2,3\n', ['--time-column', 't', '--rate', '5'],
                             r'give --time-column or --rate, not both'),
}


@pytest.mark.parametrize('case', list(BAD))
@pytest.mark.parametrize('command', ['replay', 'import', 'analyze'])
def test_a_bad_csv_is_one_line_naming_row_and_column(case, command, tmp_path, capsys):
    text, options, pattern = BAD[case]
    if command == 'analyze' and '--rate' in options:
        pytest.skip('analyze takes no --rate')
    if command == 'import' and 'parameter' in pattern:
        pytest.skip('import reads no parameter file')
    path = tmp_path / 'bad.csv'
    path.write_text(text)
    extra = {'replay': ['--params', DING], 'analyze': ['--params', DING],
             'import': ['--out', tmp_path / 'bag']}[command]
    code, out, err = run_cli(capsys, command, path, *extra, *options)
    assert code == 1 and 'Traceback' not in err
    # analyze reports its progress on stderr too: one line is the error
    lines = [line for line in err.splitlines() if 'error' in line]
    assert len(lines) == 1, err
    assert lines[0].startswith(f'bcid {command}: error: '), lines[0]
    assert re.search(pattern, lines[0]), lines[0]
    assert not (tmp_path / 'bag').exists()


def test_csv_options_on_a_bag_are_refused(tmp_path, ding_csv, capsys):
    bag = write_samples_bag(read_csv_samples(ding_csv), tmp_path / 'bag')
    code, _, err = run_cli(capsys, 'replay', bag, '--params', DING, '--columns', 'y,u1,u2')
    assert code == 1 and err.strip() == (f'bcid replay: error: --columns: for a CSV log only '
                                         f'(suffix .csv), and {bag} is read as a bag')


def test_a_missing_file_and_a_non_utf8_file(tmp_path, capsys):
    code, _, err = run_cli(capsys, 'replay', tmp_path / 'none.csv', '--params', DING)
    assert code == 1 and err.strip().endswith('none.csv: no such file')
    (tmp_path / 'latin.csv').write_bytes(b'y,u1,u2\n1,2,3 \xb0C\n')
    code, _, err = run_cli(capsys, 'replay', tmp_path / 'latin.csv', '--params', DING)
    assert code == 1 and 'not a UTF-8 text file' in err and err.count('\n') == 1


# ------------------------------------------------------------------ import, replay, analyze
@pytest.mark.parametrize('estimator', ['rls', 'bcrls'])
def test_replay_of_a_csv_equals_replay_of_its_imported_bag(estimator, ding_csv, tmp_path,
                                                           capsys, monkeypatch):
    # the CSV in blocks of 250 rows (two of them with a gap), the bag in one chunk
    monkeypatch.setattr(csv_samples, 'BLOCK_ROWS', 250)
    bag = tmp_path / 'imported'
    code, out, err = run_cli(capsys, 'import', ding_csv, '--out', bag, '--time-column', 'time')
    assert code == 0, err
    assert out.startswith(f'wrote {bag}: 1500 samples on /samples (y,u1,u2 from columns '
                          "y,u1,u2), times from column 'time'")
    assert '2 row(s) with an empty, NaN or infinite value' in out
    outputs = []
    for source, options in ((ding_csv, ['--time-column', 'time']), (bag, [])):
        trajectory = tmp_path / f'{source.name}.trajectory.csv'
        code, out, err = run_cli(capsys, 'replay', source, '--params', DING, '--estimator',
                                 estimator, '--json', '--output', trajectory, *options)
        assert code == 0, err
        outputs.append((out, trajectory.read_text()))
    # the same rows through the same per-message rule: the same bits, the same stamps
    assert outputs[0] == outputs[1]
    summary = json.loads(outputs[0][0])
    assert summary['samples'] == 1498 and 'truth' not in summary
    result = replay(read_csv_samples(ding_csv), {'order': 2, 'num_inputs': 2,
                                                 'estimator': estimator})
    assert result.nonfinite == 2 and result.messages == 1500


def test_the_imported_bag_is_a_rosbag2_mcap_of_samples(ding_csv, tmp_path):
    from rosbags.rosbag2 import Reader

    samples = read_csv_samples(ding_csv, time_column='time')
    bag = write_samples_bag(samples, tmp_path / 'imported')
    assert (bag / 'metadata.yaml').is_file() and (bag / 'imported_0.mcap').is_file()
    reader = BagReader(bag)
    assert {t: (i.type, i.count) for t, i in reader.topics.items()} == {'/samples': (F64MA, 1500)}
    qos = reader.topics['/samples'].qos[0]
    assert (qos.reliability.name, qos.durability.name, qos.depth) == ('RELIABLE', 'VOLATILE',
                                                                      1000)
    # every message as mcap_ros2 decodes it from its schema (not the fast decoder of replay)
    decoded = list(reader.decoded(['/samples']))
    assert [t for _, t, _ in decoded] == samples.times_ns.tolist()
    assert {m.layout.dim[0].label for _, _, m in decoded} == {'y,u1,u2'}
    np.testing.assert_array_equal(np.vstack([decode_samples(m, 2) for _, _, m in decoded]),
                                  samples.rows)
    with Reader(bag) as other:  # rosbags reads metadata.yaml and the QoS metadata
        assert [c.topic for c in other.connections] == ['/samples']
        assert other.message_count == 1500 and other.duration == 1499 * 4_000_000 + 1


def test_import_of_a_two_input_csv_and_info(tmp_path, capsys, ding):
    path = write_csv(tmp_path / 'two.csv', ['u2', 'u1', 'y'], ding[:, ::-1][:200].tolist())
    bag = tmp_path / 'two'
    code, out, err = run_cli(capsys, 'import', path, '--out', bag, '--rate', '50')
    assert code == 0, err
    assert 'stamped at 50 Hz, 3.98 s' in out
    reader = BagReader(bag)
    rows = np.vstack([b.data for b in reader.blocks('/samples')])
    np.testing.assert_array_equal(rows, ding[:200])
    code, out, err = run_cli(capsys, 'info', bag)
    assert code == 0, err
    assert '/samples  std_msgs/msg/Float64MultiArray  200 msgs' in out
    assert 'duration:  3.980 s' in out
    code, _, err = run_cli(capsys, 'import', path, '--out', bag)
    assert code == 1 and 'exists already' in err


def test_replay_with_columns_equals_replay_of_the_reordered_file(tmp_path, ding, capsys):
    named = write_csv(tmp_path / 'named.csv', ['fan', 'junk', 'temp', 'heater'],
                      [[c, 'n/a', a, b] for a, b, c in ding.tolist()])
    plain = write_csv(tmp_path / 'plain.csv', ['y', 'u1', 'u2'], ding.tolist())
    outs = []
    for path, options in ((named, ['--columns', 'temp,heater,fan']), (plain, [])):
        code, out, err = run_cli(capsys, 'replay', path, '--params', DING, '--json', *options)
        assert code == 0, err
        outs.append(out)
    assert outs[0] == outs[1]


def test_analyze_takes_a_csv_as_it_takes_the_imported_bag(tmp_path, capsys):
    from bcid_ros.simulation.custom import CustomScenario

    plant = CustomScenario(plant_denominator=[1.0, -0.7], plant_numerator=[0.0, 0.5],
                           noise_variance=0.01)
    y, u = plant.simulate(600, seed=3)
    path = write_csv(tmp_path / 'first.csv', ['t', 'u1', 'y'],
                     [[k * 0.02, a, b] for k, (a, b) in enumerate(zip(u[:, 0], y))])
    params = tmp_path / 'p.yaml'
    params.write_text('bcid_identifier:\n  ros__parameters:\n    estimator: bcrls\n'
                      '    order: 1\n    num_inputs: 1\n')
    bag = tmp_path / 'first'
    assert run_cli(capsys, 'import', path, '--out', bag, '--time-column', 't')[0] == 0
    outs = []
    for source, options in ((path, ['--time-column', 't']), (bag, [])):
        code, out, err = run_cli(capsys, 'analyze', source, '--params', params, '--orders',
                                 '1-2', '--json', *options)
        assert code == 0, err
        assert '600 samples, 1 input(s)' in err
        outs.append(out)
    assert outs[0] == outs[1]
    assert json.loads(outs[0])['recommended_order'] == 1


def test_csv_commands_import_no_rclpy_and_replay_no_bag_library(tmp_path, ding_csv):
    code = (
        'import sys\n'
        'from bcid_ros.cli import main\n'
        f'assert main(["replay", r"{ding_csv}", "--params", r"{DING}", "--json"]) == 0\n'
        'loaded = {name.split(".")[0] for name in sys.modules}\n'
        'print(sorted(loaded & {"rclpy", "mcap", "mcap_ros2", "rosbags"}))\n'
        f'assert main(["import", r"{ding_csv}", "--out", r"{tmp_path / "b"}"]) == 0\n'
        'assert "rclpy" not in sys.modules, "rclpy was imported"\n')
    done = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines()[1] == '[]'
