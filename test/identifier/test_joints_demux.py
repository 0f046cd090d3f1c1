"""The JointState demultiplexer: per-joint samples matched by name, counted per joint."""

import array
import types

import numpy as np
import pytest

from bcid_ros.identifier.joint_demux import JointStateDemux


def joint_state(names, position=(), velocity=(), effort=()):
    """Return a duck-typed JointState, with the arrays as rclpy delivers them."""
    return types.SimpleNamespace(name=list(names), position=array.array('d', position),
                                 velocity=array.array('d', velocity),
                                 effort=array.array('d', effort))


def test_fields_are_matched_by_name_in_any_order():
    demux = JointStateDemux(['hip', 'knee', 'ankle'])
    first = demux.take(joint_state(['hip', 'knee', 'ankle'], [1, 2, 3], [10, 20, 30],
                                   [100, 200, 300]))
    np.testing.assert_array_equal(first.y, [10, 20, 30])
    np.testing.assert_array_equal(first.u, [100, 200, 300])
    np.testing.assert_array_equal(first.present, [True, True, True])
    shuffled = demux.take(joint_state(['ankle', 'hip', 'wrist', 'knee'], [3, 1, 9, 2],
                                      [30, 10, 90, 20], [300, 100, 900, 200]))
    np.testing.assert_array_equal(shuffled.y, [10, 20, 30])
    np.testing.assert_array_equal(shuffled.u, [100, 200, 300])
    # the order changes back: matched again, not taken from the last message's order
    again = demux.take(joint_state(['knee', 'ankle', 'hip'], [], [2.5, 3.5, 1.5],
                                   [25, 35, 15]))
    np.testing.assert_array_equal(again.y, [1.5, 2.5, 3.5])
    assert demux.messages == 3
    assert not any(counts.any() for counts in demux.counters().values())


def test_other_fields_by_parameter():
    demux = JointStateDemux(['a', 'b'], input_field='velocity', output_field='position')
    samples = demux.take(joint_state(['b', 'a'], [1, 2], [3, 4], []))
    np.testing.assert_array_equal(samples.y, [2, 1])
    np.testing.assert_array_equal(samples.u, [4, 3])
    assert samples.present.all()


def test_missing_joints_are_counted_per_joint():
    demux = JointStateDemux(['a', 'b', 'c'])
    samples = demux.take(joint_state(['c', 'a'], [], [3, 1], [30, 10]))
    np.testing.assert_array_equal(samples.present, [True, False, True])
    np.testing.assert_array_equal(samples.y[[0, 2]], [1, 3])
    assert np.isnan(samples.y[1]) and np.isnan(samples.u[1])
    demux.take(joint_state(['a'], [], [1], [10]))
    nobody = demux.take(joint_state([], [], [], []))
    assert not nobody.present.any()
    np.testing.assert_array_equal(demux.missing, [1, 3, 2])
    np.testing.assert_array_equal(demux.length_mismatch, [0, 0, 0])


def test_nan_is_passed_on_and_counted_for_that_joint_only():
    demux = JointStateDemux(['a', 'b', 'c'])
    samples = demux.take(joint_state(['a', 'b', 'c'], [], [1, float('nan'), 3],
                                     [10, 20, float('inf')]))
    np.testing.assert_array_equal(samples.present, [True, True, True])
    assert np.isnan(samples.y[1]) and np.isinf(samples.u[2])
    np.testing.assert_array_equal(demux.nonfinite, [0, 1, 1])
    np.testing.assert_array_equal(demux.missing, [0, 0, 0])


def test_length_mismatch_keeps_the_listed_joints_out_and_counts_them():
    demux = JointStateDemux(['a', 'b', 'c'])
    # effort (the input) is empty: no joint has a u
    samples = demux.take(joint_state(['a', 'b'], [1, 2], [1, 2], []))
    assert not samples.present.any()
    # velocity (the output) has one value too many
    demux.take(joint_state(['b', 'c'], [], [1, 2, 3], [1, 2]))
    np.testing.assert_array_equal(demux.length_mismatch, [1, 2, 1])
    np.testing.assert_array_equal(demux.missing, [1, 0, 1])
    # the same names with the right lengths work again
    samples = demux.take(joint_state(['b', 'c'], [], [5, 6], [7, 8]))
    np.testing.assert_array_equal(samples.present, [False, True, True])
    np.testing.assert_array_equal(samples.y[1:], [5, 6])


def test_a_joint_listed_twice_takes_the_first_entry_and_is_counted():
    demux = JointStateDemux(['a', 'b'])
    samples = demux.take(joint_state(['a', 'b', 'a'], [], [1, 2, 3], [4, 5, 6]))
    np.testing.assert_array_equal(samples.y, [1, 2])
    np.testing.assert_array_equal(demux.duplicate, [1, 0])


def test_returned_arrays_are_the_callers():
    demux = JointStateDemux(['a', 'b'])
    message = joint_state(['a', 'b'], [], [1, 2], [3, 4])
    first = demux.take(message)
    first.y[:] = 0.0
    first.present[:] = False
    second = demux.take(message)
    np.testing.assert_array_equal(second.y, [1, 2])
    assert second.present.all()


def test_plain_sequences_work_too():
    message = types.SimpleNamespace(name=('x',), position=[], velocity=[0.5], effort=(2.0,))
    samples = JointStateDemux(['x']).take(message)
    assert (samples.y[0], samples.u[0]) == (0.5, 2.0)


@pytest.mark.parametrize('joints, fields, message', [
    ([], {}, 'joints must be a non-empty list of non-empty names, got \\[\\]'),
    (['a', ''], {}, "non-empty names, got \\['a', ''\\]"),
    (['a', 'b', 'a'], {}, 'joints must be unique names, got a more than once'),
    (['a'], {'input_field': 'torque'},
     "input_field must be one of position, velocity, effort, got 'torque'"),
    (['a'], {'output_field': 'effort'},
     "input_field and output_field must differ, both are 'effort'"),
])
def test_bad_settings_are_refused(joints, fields, message):
    with pytest.raises(ValueError, match=message):
        JointStateDemux(joints, **fields)
