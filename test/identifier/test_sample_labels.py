"""
Sample rows are read by their labels, or refused (SPEC §18): never misread.

A row labelled ``u1,u2,y`` is reordered to ``y,u1,u2``, in one sample and in
frames, by the node's rule (``decode_samples``) and by ``bcid replay``'s block
path alike; a row labelled with other column names is refused with a reason.
"""

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from bcid_ros.bag.replay import replay
from bcid_ros.bag.writer import BagWriter, float64_multi_array
from bcid_ros.identifier.layouts import decode_samples
from bcid_ros.identifier.parameters import load_yaml_parameters
from bcid_ros.simulation import make_scenario

CONFIG = Path(__file__).resolve().parents[2] / 'config' / 'ding_miso.yaml'


def message(label, data, frame=0):
    dims = [SimpleNamespace(label=label, size=3, stride=3)]
    if frame:
        dims.insert(0, SimpleNamespace(label='samples', size=frame, stride=3 * frame))
    return SimpleNamespace(layout=SimpleNamespace(dim=dims, data_offset=0), data=data)


@pytest.mark.parametrize('label', ['u1,u2,y', 'u2, y, u1', 'y,u2,u1'])
def test_a_row_in_another_order_is_read_by_its_labels(label):
    names = [name.strip() for name in label.split(',')]
    values = {'y': 1.0, 'u1': 2.0, 'u2': 3.0}
    row = [values[name] for name in names]
    assert decode_samples(message(label, row), 2).tolist() == [[1.0, 2.0, 3.0]]
    frame = decode_samples(message(label, row * 4, frame=4), 2)
    assert frame.tolist() == [[1.0, 2.0, 3.0]] * 4


@pytest.mark.parametrize('label', ['temp,heater,fan', 'y,u1,u1', 'y,u1,u3', 'y,u1'])
def test_a_row_labelled_with_other_columns_is_refused(label):
    with pytest.raises(ValueError, match='names other columns than y,u1,u2'):
        decode_samples(message(label, [1.0, 2.0, 3.0]), 2)
    with pytest.raises(ValueError, match='names other columns'):
        decode_samples(message(label, [1.0, 2.0, 3.0] * 2, frame=2), 2)


@pytest.mark.parametrize('label', ['', 'y,u1,u2', 'row'])
def test_an_empty_or_wordless_label_keeps_the_order(label):
    assert decode_samples(message(label, [1.0, 2.0, 3.0]), 2).tolist() == [[1.0, 2.0, 3.0]]


def write_bag(path, label, rows):
    with BagWriter(path) as writer:
        writer.add_topic('/samples', 'std_msgs/msg/Float64MultiArray')
        for k, row in enumerate(rows):
            writer.write_message('/samples', 10**9 + k * 10**6,
                                 float64_multi_array([(label, 3, 3)], row))


def test_replay_reads_a_relabelled_bag_as_the_ordered_one_and_refuses_other_columns(tmp_path):
    y, u = make_scenario('ding_miso').simulate(600, 4)
    ordered = np.column_stack([y, u])
    parameters = load_yaml_parameters(CONFIG)
    write_bag(tmp_path / 'ordered', 'y,u1,u2', ordered)
    write_bag(tmp_path / 'relabelled', 'u2,y,u1', ordered[:, [2, 0, 1]])
    write_bag(tmp_path / 'other', 'temp,heater,fan', ordered)
    reference = replay(tmp_path / 'ordered', parameters)
    relabelled = replay(tmp_path / 'relabelled', parameters)
    assert relabelled.samples == reference.samples == 600
    np.testing.assert_array_equal(relabelled.theta, reference.theta)  # same code path
    other = replay(tmp_path / 'other', parameters)
    assert other.samples == 0 and other.malformed == 600
