"""
``bcid replay --json``: every sample not used, counted by cause; why a result is not ready.

SPEC §18: the counts name the cause (malformed, empty, nonfinite, undone, ...), and a
result that never became ready says the real reason.
"""

import json
from pathlib import Path

import numpy as np

from bcid_ros.bag.writer import BagWriter, float64_multi_array
from bcid_ros.cli import main as bcid
from bcid_ros.simulation import make_scenario

REPO = Path(__file__).resolve().parents[2]


def write_bag(path, rows, label='y,u1,u2'):
    with BagWriter(path) as writer:
        writer.add_topic('/samples', 'std_msgs/msg/Float64MultiArray')
        for k, row in enumerate(rows):
            writer.write_message('/samples', 10**9 + k * 10**6,
                                 float64_multi_array([(label, len(row), len(row))], row))
    return path


def replay_json(capsys, bag):
    code = bcid(['replay', str(bag), '--params', str(REPO / 'config/ding_miso.yaml'), '--json'])
    out, err = capsys.readouterr()
    assert code == 0, err
    return json.loads(out)


def test_messages_of_the_wrong_length_are_counted_as_malformed_with_the_reason(
        tmp_path, capsys):
    bag = write_bag(tmp_path / 'short', [[0.1 * k, 1.0] for k in range(3000)], label='y,u1')
    result = replay_json(capsys, bag)
    assert result['samples'] == 0 and not result['valid']
    assert result['unused']['malformed'] == 3000
    assert 'no sample was used of 3000 messages (3000 malformed)' in result['not_ready']
    assert 'a sample has 2 values; expected 1 + num_inputs = 3' in result['not_ready']


def test_undone_updates_are_counted_and_named_as_the_reason(tmp_path, capsys):
    y, u = make_scenario('ding_miso').simulate(3000, 5)
    bag = write_bag(tmp_path / 'huge', 1e200 * np.column_stack([y, u]))
    result = replay_json(capsys, bag)
    assert result['samples'] == 3000 and not result['valid']
    undone = result['unused']['undone']
    assert undone > 0 and undone == result['flags']['update_undone']
    assert f'{undone} undone' in result['not_ready']
    assert 'too few samples' not in result['not_ready']


def test_nan_and_empty_messages_are_counted_by_cause(tmp_path, capsys):
    y, u = make_scenario('ding_miso').simulate(2000, 6)
    rows = [list(r) for r in np.column_stack([y, u])]
    rows[100] = [float('nan'), 1.0, 2.0]
    rows[200:203] = [[], [], []]
    result = replay_json(capsys, write_bag(tmp_path / 'mixed', rows))
    assert result['unused']['nonfinite'] == 1 and result['unused']['empty'] == 3
    assert result['samples'] == 2000 - 1 - 3 and 'not_ready' not in result


def test_a_good_bag_has_nothing_unused(capsys):
    result = replay_json(capsys, REPO / 'bags' / 'ding_miso')
    assert set(result['unused'].values()) == {0} and 'not_ready' not in result
