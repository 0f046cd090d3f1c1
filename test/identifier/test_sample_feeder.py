"""
Unit tests of SampleFeeder's per-message rule and the FeedResult it returns, without ROS.

A recording estimator shows where the regressor restarts; a real one shows
that feeding a block at once equals feeding it message by message.
"""

from types import SimpleNamespace

import numpy as np
from recording_estimator import BlockRecorder

from bcid_ros.identifier.feeder import FeedResult, SampleFeeder
from bcid_ros.identifier.layouts import samples_layout
from bcid_ros.identifier.parameters import estimator_from_parameters
from bcid_ros.simulation import make_scenario


class RecordingEstimator(BlockRecorder):
    """Records updates and restarts; valid after ``valid_after`` updates."""

    num_inputs = 1

    def __init__(self, valid_after=2, fail_on=None):
        self.log = []
        self.valid_after = valid_after
        self.fail_on = set() if fail_on is None else {fail_on}
        self.theta = np.array([1.0, 2.0])
        self.theta_uncompensated = np.array([1.5, 2.5])
        self.noise = np.array([0.1])

    @property
    def ready(self):
        """Whether enough updates were made."""
        return sum(1 for entry in self.log if entry != 'restart') >= self.valid_after

    valid = ready

    def restart_regressor(self):
        """Record a restart."""
        self.log.append('restart')

    def reset(self):
        """Forget everything."""
        self.log.clear()


def message(rows, layout=None):
    """Return a duck-typed samples message."""
    rows = np.asarray(rows, dtype=float)
    if layout is None:
        layout = samples_layout(rows.shape[0], rows.shape[1] - 1)
    dims = [SimpleNamespace(label=label, size=size, stride=stride)
            for label, size, stride in layout]
    return SimpleNamespace(data=rows.reshape(-1).tolist(),
                           layout=SimpleNamespace(dim=dims, data_offset=0))


def test_nonfinite_samples_are_counted_and_restart_the_regressor():
    estimator = RecordingEstimator()
    feeder = SampleFeeder(estimator)
    result = feeder.take_rows(np.array([[1.0, 0.0], [np.nan, 0.0], [3.0, np.inf], [4.0, 1.0]]))
    assert (result.used, result.nonfinite, result.dropped) == (2, 2, '')
    assert estimator.log == [1.0, 'restart', 4.0]
    assert (feeder.used, feeder.nonfinite) == (2, 2)


def test_malformed_message_is_dropped_and_restarts_but_an_empty_one_does_not():
    estimator = RecordingEstimator()
    feeder = SampleFeeder(estimator)
    feeder.take_message(message([[1.0, 0.0]]))
    result = feeder.take_message(SimpleNamespace(data=[], layout=None))
    assert result == FeedResult(dropped='empty', reason='empty message (no values)')
    feeder.take_message(message([[2.0, 0.0]]))
    result = feeder.take_message(message([[3.0, 0.0, 0.0]]))    # one value too many
    assert result.dropped == 'bad_layout' and 'expected 1 + num_inputs = 2' in result.reason
    assert result.used == 0 and result.estimates is None
    feeder.take_message(message([[4.0, 0.0]]))
    assert estimator.log == [1.0, 2.0, 'restart', 4.0]


def test_estimator_error_drops_the_rest_and_restarts():
    estimator = RecordingEstimator(fail_on=2.0)
    feeder = SampleFeeder(estimator)
    result = feeder.take_rows(np.array([[1.0, 0.0], [2.0, 0.0], [3.0, 0.0]]))
    assert result.dropped == 'estimator_errors' and 'boom' in result.reason
    assert result.estimates is None
    feeder.take_rows(np.array([[4.0, 0.0]]))
    assert estimator.log == [1.0, 'restart', 4.0]


def test_estimates_are_due_every_publish_period_once_valid():
    estimator = RecordingEstimator(valid_after=2)
    feeder = SampleFeeder(estimator, publish_period=3)
    due = [feeder.take_rows(np.array([[float(k), 0.0]])).estimates is not None
           for k in range(9)]
    # Valid from the 2nd sample; the count runs from the start, so the 3rd is due.
    assert due == [False, False, True, False, False, True, False, False, True]
    # One frame crossing the period gives at most one publication, after its last sample.
    result = feeder.take_rows(np.zeros((7, 2)))
    theta, uncompensated, noise = result.estimates
    np.testing.assert_array_equal(theta, estimator.theta)
    np.testing.assert_array_equal(noise, estimator.noise)


def test_nonfinite_estimate_is_withheld_and_stays_due():
    estimator = RecordingEstimator(valid_after=1)
    feeder = SampleFeeder(estimator)
    estimator.theta = np.array([np.nan, 1.0])
    result = feeder.take_rows(np.array([[1.0, 0.0]]))
    assert result.withheld and result.estimates is None
    estimator.theta = np.array([0.0, 1.0])
    result = feeder.take_rows(np.array([[2.0, 0.0]]))
    assert not result.withheld and result.estimates is not None


def test_unexcited_samples_are_counted_but_used():
    feeder = SampleFeeder(RecordingEstimator(), excitation_window=3)
    rows = np.column_stack([np.arange(8.0), [1.0, 2.0] + [5.0] * 6])
    result = feeder.take_rows(rows)
    # The constant run starts at the 3rd sample; repeats 3, 4 and 5 count.
    assert (result.used, result.unexcited) == (8, 3)
    assert feeder.excitation_lost


def test_counts_of_a_block_add_up():
    feeder = SampleFeeder(RecordingEstimator())
    result = FeedResult()
    feeder.feed(np.array([[1.0, 0.0], [np.nan, 0.0]]), result)
    feeder.feed(np.array([[2.0, 0.0], [3.0, 1.0]]), result)
    assert (result.used, result.nonfinite) == (3, 1)


def test_a_block_fed_at_once_equals_message_by_message():
    values = {'estimator': 'bcrls', 'order': 2, 'num_inputs': 2}
    y, u = make_scenario('ding_miso').simulate(300, 5)
    rows = np.column_stack([y, u])
    rows[100, 0] = np.nan
    one = SampleFeeder(estimator_from_parameters(values))
    for k in range(rows.shape[0]):
        one.take_message(message(rows[k:k + 1]))
    block = SampleFeeder(estimator_from_parameters(values))
    result = block.take_rows(rows)
    assert (result.used, result.nonfinite) == (one.used, one.nonfinite) == (299, 1)
    # one arithmetic path: the block's regressors are the same values as contiguous rows of
    # the same length, and the same step runs on them (test_bag_blocks.py): the same bits
    np.testing.assert_array_equal(block.estimator.theta, one.estimator.theta)
