"""
A small stand-in for diagnostic_updater, which is not in the PyPI wheels.

One :class:`DiagnosticsTimer` per node publishes one
``diagnostic_msgs/DiagnosticStatus`` on ``/diagnostics`` from a timer on
the node's clock (so ``use_sim_time`` works), filled by a callback.
"""

from __future__ import annotations

from typing import Callable

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node
from rclpy.qos import QoSProfile

OK = DiagnosticStatus.OK
WARN = DiagnosticStatus.WARN
ERROR = DiagnosticStatus.ERROR

#: /diagnostics QoS: the ROS default (reliable, volatile, depth 10).
DIAGNOSTICS_QOS = QoSProfile(depth=10)

#: A status callback returns (level, message, [(key, value), ...]).
StatusCallback = Callable[[], tuple[int, str, list[tuple[str, object]]]]


def format_value(value: object) -> str:
    """Return a diagnostic value as text: floats with 6 significant digits."""
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, float):
        return f'{value:.6g}'
    return str(value)


class DiagnosticsTimer:
    """
    Publish the status made by ``callback`` on /diagnostics every ``period`` seconds.

    Parameters
    ----------
    node : rclpy.node.Node
        The owning node; its clock stamps the messages and drives the timer.
    name : str
        ``DiagnosticStatus.name``, e.g. ``'bcid_identifier: estimator'``.
    callback : callable
        Returns ``(level, message, [(key, value), ...])``.
    period : float
        Seconds between messages.
    hardware_id : str
        ``DiagnosticStatus.hardware_id``.

    """

    def __init__(self, node: Node, name: str, callback: StatusCallback, *,
                 period: float = 1.0, hardware_id: str = '') -> None:
        self._node = node
        self._name = name
        self._callback = callback
        self._hardware_id = hardware_id
        self.publisher = node.create_publisher(DiagnosticArray, '/diagnostics', DIAGNOSTICS_QOS)
        self.timer = node.create_timer(period, self.publish)

    def publish(self) -> None:
        """Build the status now and publish it."""
        level, message, values = self._callback()
        status = DiagnosticStatus(level=level, name=self._name, message=message,
                                  hardware_id=self._hardware_id,
                                  values=[KeyValue(key=key, value=format_value(value))
                                          for key, value in values])
        array = DiagnosticArray(status=[status])
        array.header.stamp = self._node.get_clock().now().to_msg()
        self.publisher.publish(array)

    def destroy(self) -> None:
        """Destroy the timer and the publisher."""
        self._node.destroy_timer(self.timer)
        self._node.destroy_publisher(self.publisher)
