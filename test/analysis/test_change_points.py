"""benchmarks/change_points.py: each detection's change point and the test that found it."""

from benchmarks.change_points import detections, summary
from benchmarks.tracking import TrackingCase
from bcid_ros.estimators.change_detection import BLOCK_LENGTH

CASE = (0, 8)  # an abrupt slow pole move (0.994 -> 0.988) that the block-mean test finds


def test_a_block_test_detection_is_named_and_placed_at_most_a_block_early():
    case = TrackingCase(CASE, 'family')
    found = detections(case, 'rpem')
    first = case.change_at + 1  # the new plant's first sample, counted from 1
    assert [f['test'] for f in found] == ['block test']
    # the block test places the change late rather than early, at most a block early
    # (change_detection.BlockMeanDetector._detected), and before the detection itself
    assert first - BLOCK_LENGTH <= found[0]['point'] <= found[0]['sample']
    assert found[0]['sample'] > first


def test_the_summary_counts_late_and_early_points():
    assert summary([-4, 0, 2, 10]) == ['4', '3', '0.50', '0.25', '-4 .. +10']
    assert summary([]) == ['0', '-', '-', '-', '-']
