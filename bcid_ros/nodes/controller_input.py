"""
The identifier's ``controller_topic`` on rclpy (docs/nodes.md, "the controller in the loop").

:class:`ControllerInput` subscribes to the controller that an adaptive
controller publishes and hands every change to ``cl_bcls``'s
``set_controller`` (the compensation restarts from it); it ignores an
identical republish, refuses a malformed message with a throttled warning
and adds its counts to the identifier's /diagnostics status.
"""

from __future__ import annotations

from typing import Any, Callable

from rclpy.node import Node
from std_msgs.msg import Float64MultiArray

from bcid_ros.control.design import controller_from_message
from bcid_ros.estimators import RecursiveEstimator
from bcid_ros.nodes.common import LATCHED_QOS, Throttle
from bcid_ros.nodes.diagnostics import DiagnosticsUpdater


class ControllerInput:
    """
    Take ``cl_bcls``'s controller in the loop from ``controller_topic``.

    Parameters
    ----------
    node : rclpy.node.Node
        The identifier node that owns the subscription.
    settings : dict
        The identifier's checked parameters, ``controller_topic`` set.
    estimator : RecursiveEstimator
        The node's estimator; it must have ``set_controller`` (``cl_bcls``).
    diagnostics : DiagnosticsUpdater
        The identifier's status, to which the controller's lines are added.
    on_change : callable
        Called after the controller changed (the estimate's validity may have).

    Attributes
    ----------
    counts : dict
        Controller messages by outcome: ``changes``, ``unchanged``, ``refused``.

    Raises
    ------
    ValueError
        If the estimator takes no controller, or ``controller_topic`` is not a
        valid topic name.

    """

    def __init__(self, node: Node, settings: dict[str, Any], estimator: RecursiveEstimator,
                 diagnostics: DiagnosticsUpdater, on_change: Callable[[], None]) -> None:
        topic = settings['controller_topic']
        if not hasattr(estimator, 'set_controller'):
            raise ValueError(f"parameter 'controller_topic' applies to estimator cl_bcls only "
                             f"(the closed-loop estimator that needs the controller), got "
                             f"estimator {settings['estimator']!r} with controller_topic "
                             f"{topic!r}")
        self._node = node
        self._estimator = estimator
        self._on_change = on_change
        self._throttle = Throttle(node.get_logger())
        self.counts = {'changes': 0, 'unchanged': 0, 'refused': 0}
        controller = estimator.controller
        self._in_use = (controller.numerator.tolist(), controller.denominator.tolist())
        try:
            self.subscription = node.create_subscription(
                Float64MultiArray, topic, self.on_controller, LATCHED_QOS)
        except Exception as error:  # rclpy's InvalidTopicNameException
            raise ValueError(f"parameter 'controller_topic' must be a valid topic name, got "
                             f"{topic!r}: {error}") from None
        diagnostics.tasks.append(self.diagnose)
        node.get_logger().info(f'controller in the loop from {topic}')

    def on_controller(self, message: Float64MultiArray) -> None:
        """Restart the compensation at a new controller; ignore an identical republish."""
        dims = message.layout.dim
        try:
            controller = controller_from_message([d.label for d in dims],
                                                 [d.size for d in dims], message.data)
            # the estimator's own form (b_c padded to a_c), to compare with the one in use
            numerator, denominator = controller.message_data()
            if self._same(numerator, denominator):
                self.counts['unchanged'] += 1
                return
            used = self._estimator.samples
            self._estimator.set_controller(numerator, denominator, 'negative')
        except ValueError as error:
            self.counts['refused'] += 1
            self._throttle.warn('controller_refused', f'controller message refused, the '
                                f'controller in use kept: {error}')
            return
        self._in_use = (numerator, denominator)
        self.counts['changes'] += 1
        self._on_change()
        self._node.get_logger().info(f'new controller in the loop {numerator} / {denominator}: '
                                     f'compensation restarted (after {used} samples)')

    def _same(self, numerator: list[float], denominator: list[float]) -> bool:
        """Return whether the controller is the one in use (numerators equal up to lead 0s)."""
        old_numerator, old_denominator = self._in_use
        width = max(len(numerator), len(old_numerator))
        pad = [0.0] * width
        return (denominator == old_denominator
                and (pad + numerator)[-width:] == (pad + old_numerator)[-width:])

    def diagnose(self, status: Any) -> None:
        """Add the controller in use and the message counts to the identifier's status."""
        numerator, denominator = self._in_use
        status.add('controller in the loop', f'{numerator} / {denominator}')
        status.add('controller changes (compensation restarted)', self.counts['changes'])
        status.add('controller republished unchanged', self.counts['unchanged'])
        status.add('controller messages refused (malformed)', self.counts['refused'])


__all__ = ['ControllerInput']
