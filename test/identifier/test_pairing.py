"""
Unit tests of the separate-topic pairing (bcid_ros.identifier.pairing), without ROS.

The node test test_nodes_robustness.py runs the same rules through a live
node; here each rule is checked on its own, message by message.
"""

import pytest

from bcid_ros.identifier.pairing import (GAP, GAP_FACTOR, Pairing, PERIOD_LEARNING_INTERVALS,
                                         SequenceTracker)

MS = 1_000_000  # ns


def arrival(queue_size=100):
    """Return an arrival-mode pairing."""
    return Pairing(stamped=False, tolerance_ns=0, queue_size=queue_size)


def stamped(period_ms=10, tolerance_ms=1, queue_size=100):
    """Return a stamp-mode pairing with a given (or, with 0, learnt) period."""
    return Pairing(stamped=True, tolerance_ns=tolerance_ms * MS, queue_size=queue_size,
                   period_ns=period_ms * MS)


def kinds(paired):
    """Return the counters of a Paired's problems."""
    return [kind for kind, _ in paired.problems]


def test_arrival_pairs_first_in_first_out():
    pairing = arrival()
    assert pairing.add('input', [1.0, 2.0]).samples == []
    assert pairing.add('input', [3.0, 4.0]).samples == []
    assert pairing.add('output', 10.0).samples == [[10.0, 1.0, 2.0]]
    assert pairing.add('output', 11.0).samples == [[11.0, 3.0, 4.0]]
    # Output first works the same way.
    assert pairing.add('output', 12.0).samples == []
    paired = pairing.add('input', [5.0, 6.0])
    assert paired.samples == [[12.0, 5.0, 6.0]] and paired.problems == []


def test_arrival_lost_message_leaves_a_hole_that_drops_its_partner():
    pairing = arrival()
    # The input before this one was lost in transport: its output must not pair with [2].
    assert pairing.add('input', [2.0], lost=1).samples == []
    assert pairing.add('output', 1.0).samples == [GAP]
    assert pairing.add('output', 2.0).samples == [[2.0, 2.0]]


def test_arrival_refused_message_restarts_at_once_and_drops_its_partner():
    pairing = arrival()
    paired = pairing.refuse('output')
    assert paired.samples == [GAP] and paired.problems == []
    assert pairing.add('input', [1.0]).samples == [GAP]   # the refused output's partner
    assert pairing.add('input', [2.0]).samples == []
    assert pairing.add('output', 2.0).samples == [[2.0, 2.0]]


def test_queue_over_its_size_drops_the_oldest_and_restarts():
    pairing = arrival(queue_size=2)
    pairing.add('input', [1.0])
    pairing.add('input', [2.0])
    paired = pairing.add('input', [3.0])
    assert kinds(paired) == ['unpaired'] and paired.samples == [GAP]
    assert pairing.add('output', 2.0).samples == [[2.0, 2.0]]


def test_stamp_pairs_within_the_tolerance_in_any_order():
    pairing = stamped()
    assert pairing.add('input', [1.0], stamp_ns=0).samples == []
    assert pairing.add('output', 1.5, stamp_ns=MS // 2).samples == [[1.5, 1.0]]
    assert pairing.add('output', 2.5, stamp_ns=10 * MS).samples == []
    paired = pairing.add('input', [2.0], stamp_ns=10 * MS + MS)   # exactly the tolerance
    assert paired.samples == [[2.5, 2.0]] and paired.problems == []


def test_stamp_drops_the_head_the_other_topic_has_passed():
    pairing = stamped()
    pairing.add('input', [1.0], stamp_ns=0)
    paired = pairing.add('output', 2.0, stamp_ns=10 * MS)   # its input 10 ms is missing
    assert kinds(paired) == ['unpaired'] and paired.samples == [GAP]
    assert 'input' in paired.problems[0][1]
    assert pairing.add('input', [2.0], stamp_ns=10 * MS).samples == [[2.0, 2.0]]


def test_stamp_drops_duplicates_and_out_of_order_without_a_gap():
    pairing = stamped()
    pairing.add('input', [1.0], stamp_ns=10 * MS)
    paired = pairing.add('input', [9.0], stamp_ns=10 * MS)
    assert kinds(paired) == ['duplicate'] and paired.samples == []
    paired = pairing.add('input', [9.0], stamp_ns=5 * MS)
    assert kinds(paired) == ['out_of_order'] and paired.samples == []
    assert pairing.add('output', 1.0, stamp_ns=10 * MS).samples == [[1.0, 1.0]]


def test_stamp_gap_restarts_before_the_pair_after_it():
    pairing = stamped(period_ms=10)
    for k in (0, 1, 2):
        pairing.add('input', [float(k)], stamp_ns=k * 10 * MS)
        assert pairing.add('output', float(k), stamp_ns=k * 10 * MS).problems == []
    # An interval just under GAP_FACTOR periods is no gap; just over it is.
    t = 20 * MS + int((GAP_FACTOR - 0.01) * 10 * MS)
    pairing.add('input', [3.0], stamp_ns=t)
    assert pairing.add('output', 3.0, stamp_ns=t).samples == [[3.0, 3.0]]
    t += int((GAP_FACTOR + 0.01) * 10 * MS)
    pairing.add('input', [4.0], stamp_ns=t)
    paired = pairing.add('output', 4.0, stamp_ns=t)
    assert kinds(paired) == ['gaps'] and paired.samples == [GAP, [4.0, 4.0]]


def test_stamp_learns_the_period_from_the_median_interval():
    pairing = stamped(period_ms=0)
    intervals = [10 * MS] * PERIOD_LEARNING_INTERVALS
    intervals[3] = 35 * MS     # an outlier the median ignores; no gap while learning
    t, notes = 0, []
    pairing.add('input', [0.0], stamp_ns=t)
    pairing.add('output', 0.0, stamp_ns=t)
    for interval in intervals:
        t += interval
        pairing.add('input', [1.0], stamp_ns=t)
        paired = pairing.add('output', 1.0, stamp_ns=t)
        assert paired.problems == []
        notes += paired.notes
    assert pairing.period_ns == 10 * MS and len(notes) == 1 and '0.01 s' in notes[0]
    t += 20 * MS
    pairing.add('input', [1.0], stamp_ns=t)
    assert kinds(pairing.add('output', 1.0, stamp_ns=t)) == ['gaps']


def test_stamp_lost_message_is_a_gap_not_a_hole():
    pairing = stamped()
    assert pairing.add('input', [1.0], stamp_ns=0, lost=2).samples == [GAP]
    assert pairing.add('output', 1.0, stamp_ns=0).samples == [[1.0, 1.0]]
    assert pairing.refuse('output').samples == [GAP]


def test_reset_forgets_the_queues_and_the_last_pair():
    pairing = stamped()
    pairing.add('input', [1.0], stamp_ns=0)
    pairing.add('output', 1.0, stamp_ns=0)
    pairing.add('input', [2.0], stamp_ns=10 * MS)
    pairing.reset()
    # The queued input is gone, and a long interval after a reset is no gap.
    paired = pairing.add('output', 5.0, stamp_ns=100 * MS)
    assert paired.samples == [] and paired.problems == []
    assert pairing.add('input', [5.0], stamp_ns=100 * MS).samples == [[5.0, 5.0]]


def test_from_settings():
    pairing = Pairing.from_settings({'sync': 'stamp', 'sync_tolerance': 0.002,
                                     'queue_size': 7, 'sample_period': 0.01})
    assert pairing.stamped and pairing.tolerance_ns == 2 * MS and pairing.queue_size == 7
    assert pairing.period_ns == pytest.approx(10 * MS)


def test_sequence_tracker_counts_jumps_per_topic():
    tracker = SequenceTracker()
    assert tracker.lost('a', 1) == 0
    assert tracker.lost('a', 2) == 0
    assert tracker.lost('a', 5) == 2
    assert tracker.lost('b', 9) == 0         # first message of another topic
    assert tracker.lost('a', 1) == 0         # a smaller number: a new publisher
    assert tracker.lost('a', None) == 0 and tracker.lost('a', 0) == 0
    tracker.reset()
    assert tracker.lost('a', 10) == 0


# ------------------------------------------------------------------ time jumps (SPEC §18)
def feed_pairs(pairing, stamps_ms, value=1.0):
    """Add input then output at each stamp; return the rows paired and the problems."""
    rows, problems = [], []
    for stamp in stamps_ms:
        for side, item in (('input', [value]), ('output', value)):
            paired = pairing.add(side, item, stamp_ns=int(stamp * MS))
            rows += [r for r in paired.samples if r is not GAP]
            problems += kinds(paired)
    return rows, problems


def test_stamp_jump_back_starts_the_pairing_over_with_a_diagnostic():
    # A looped bag: 2,100 samples at 10 ms, then the stamps go back 100 s and go on.
    pairing = stamped()
    before, _ = feed_pairs(pairing, [100_000 + 10 * k for k in range(2100)])
    assert len(before) == 2100
    after, problems = feed_pairs(pairing, [10 * k for k in range(500)])
    # One time jump (the input's; the output's next stamp is then no jump), and every
    # sample after it is paired again.
    assert problems == ['time_jumps']
    assert len(after) == 500


def test_stamp_jump_back_on_one_side_first_recovers_once_both_have_jumped():
    pairing = stamped()
    feed_pairs(pairing, [100_000 + 10 * k for k in range(100)])
    # The input's clock restarts three samples before the output's.
    problems = []
    for k in range(3):
        problems += kinds(pairing.add('input', [1.0], stamp_ns=10 * k * MS))
        problems += kinds(pairing.add('output', 1.0, stamp_ns=(101_000 + 10 * k) * MS))
    assert problems.count('time_jumps') == 1
    rows, problems = feed_pairs(pairing, [30 + 10 * k for k in range(100)])
    assert problems.count('time_jumps') == 1 and len(rows) >= 99


def test_small_step_back_is_still_out_of_order_not_a_jump():
    pairing = stamped()
    feed_pairs(pairing, [1000 + 10 * k for k in range(10)])
    paired = pairing.add('input', [1.0], stamp_ns=1050 * MS)
    assert kinds(paired) == ['out_of_order']


def test_reset_forgets_the_last_stamps():
    pairing = stamped()
    feed_pairs(pairing, [100_000 + 10 * k for k in range(10)])
    pairing.reset()
    # After ~/reset, an earlier stamp (less than a jump back) is taken, not dropped.
    rows, problems = feed_pairs(pairing, [99_800 + 10 * k for k in range(5)])
    assert problems == [] and len(rows) == 5
