"""The per-joint statuses and their direct CDR serialisation, against rclpy's own."""

import pytest

from bcid_ros.identifier.cdr import DiagnosticArrayEncoder

pytest.importorskip('rclpy')

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue  # noqa: E402
from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402

STATUSES = [
    (0, 'bcid_arm: identifier', 'estimating at 1000 samples/s', 'bcid_arm',
     [('update time mean (µs)', '12.5'), ('samples used', '1234'), ('valid', 'true')]),
    (1, 'bcid_arm: joint j', 'in the last period: NaN or Inf', 'bcid_arm', []),
    (2, '', '', '', [('', '')]),
    (255, 'bcid_arm: joint elbow_2', 'ok', 'h', [('a', 'b'), ('ab', 'abc'), ('abcd', 'é')]),
]


def rclpy_array(stamp, statuses, frame_id=''):
    """Return the same array as an rclpy message."""
    array = DiagnosticArray(status=[
        DiagnosticStatus(level=bytes([level]), name=name, message=message,
                         hardware_id=hardware_id,
                         values=[KeyValue(key=key, value=value) for key, value in values])
        for level, name, message, hardware_id, values in statuses])
    array.header.stamp.sec, array.header.stamp.nanosec = stamp
    array.header.frame_id = frame_id
    return array


@pytest.mark.parametrize('count', [0, 1, 2, 3, 4])
@pytest.mark.parametrize('frame_id', ['', 'abc', 'abcd'])
def test_the_bytes_are_rclpy_s(count, frame_id):
    encoder = DiagnosticArrayEncoder()
    for first in range(len(STATUSES)):
        # every status at every alignment, from the cache and without
        statuses = (STATUSES[first:] + STATUSES[:first])[:count]
        expected = rclpy_array((1_700_000_000, 123), statuses, frame_id)
        reference = serialize_message(expected)
        for _ in range(2):
            raw = encoder.encode((1_700_000_000, 123), statuses, frame_id)
            # the same layout byte for byte but the padding, which rclpy leaves undefined
            assert len(raw) == len(reference)
            assert deserialize_message(raw, DiagnosticArray) == expected


def test_rclpy_reads_the_bytes_back():
    raw = DiagnosticArrayEncoder().encode((-5, 7), STATUSES)
    array = deserialize_message(raw, DiagnosticArray)
    assert (array.header.stamp.sec, array.header.stamp.nanosec) == (-5, 7)
    assert [status.name for status in array.status] == [status[1] for status in STATUSES]
    assert array.status[3].level == b'\xff' and array.status[3].values[2].value == 'é'
