"""
The adaptive controller node: an indirect self-tuning regulator on the identifier's estimates.

The node holds one :class:`bcid_ros.control.AdaptiveController` and does no
numerics of its own: it hands it each measured output (publishing the input
it returns, once per output), each reference and each estimate message, asks
it to look at the estimates every ``redesign_period`` seconds, publishes the
controller in the loop on ``~/controller`` (latched) at start-up and at every
redesign, and reports its counters on /diagnostics. See docs/adaptive_loop.md.

Run it as ``adaptive_controller_node --ros-args --params-file config/adaptive_loop.yaml``.
"""

from __future__ import annotations

import math
from typing import Any

from rclpy.node import Node
from std_msgs.msg import Bool, Float64, Float64MultiArray, MultiArrayDimension

from bcid_ros.control.design import format_poles
from bcid_ros.control.loop import AdaptiveController, EVENTS, Outcome, REFUSALS
from bcid_ros.control.parameters import CONTROLLER_PARAMETERS
from bcid_ros.identifier import interface
from bcid_ros.identifier.layouts import parse_names_label
from bcid_ros.nodes.common import (declare_table, LATCHED_QOS, make_parameter_check, run_node,
                                   SAMPLES_QOS, Throttle, usage)
from bcid_ros.nodes.diagnostics import DiagnosticsUpdater, OK, Status, WARN
from bcid_ros.parameter_spec import spec_by_name


def controller_message(numerator: list[float], denominator: list[float]) -> Float64MultiArray:
    """Return the ``~/controller`` message: numerator then denominator, descending powers."""
    message = Float64MultiArray()
    message.layout.dim = [
        MultiArrayDimension(label='numerator', size=len(numerator), stride=len(numerator)),
        MultiArrayDimension(label='denominator', size=len(denominator),
                            stride=len(denominator))]
    message.data = [float(v) for v in numerator + denominator]
    return message


def message_names(message: Float64MultiArray) -> tuple[str, ...]:
    """Return the parameter names in the label of an estimate message (empty if none)."""
    return parse_names_label(message.layout.dim[0].label) if message.layout.dim else ()


class AdaptiveControllerNode(Node):
    """
    Pole placement on the latest trusted estimate, with a fallback until there is one.

    Parameters
    ----------
    node_name : str
        Default ``bcid_controller``.
    **kwargs
        Passed to :class:`rclpy.node.Node` (``context``, ``parameter_overrides``, ...).

    Raises
    ------
    ValueError
        If a parameter is not allowed; the message names it and its allowed
        values.

    """

    def __init__(self, node_name: str = interface.CONTROLLER_NODE, **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self.loop = AdaptiveController(declare_table(self, CONTROLLER_PARAMETERS))
        settings = self.loop.settings
        self.add_on_set_parameters_callback(make_parameter_check(
            spec_by_name(CONTROLLER_PARAMETERS)))
        self._throttle = Throttle(self.get_logger())
        self.outputs = 0
        self.inputs_published = 0
        self._last_outputs = 0
        self._last_refusals = 0
        self._last_time = self.get_clock().now()
        self._last_refusal = ''
        self._identifier_publishers = 0

        prefix = settings['identifier'].rstrip('/')
        self.parameters_topic = f'{prefix}/{interface.basename(interface.PARAMETERS)}'
        try:
            self.input_publisher = self.create_publisher(Float64, interface.INPUT, SAMPLES_QOS)
            self.controller_publisher = self.create_publisher(
                Float64MultiArray, interface.CONTROLLER, LATCHED_QOS)
            self.output_subscription = self.create_subscription(
                Float64, interface.OUTPUT, self.on_output, SAMPLES_QOS)
            self.reference_subscription = self.create_subscription(
                Float64, interface.REFERENCE, self.on_reference, SAMPLES_QOS)
            self.parameters_subscription = self.create_subscription(
                Float64MultiArray, self.parameters_topic, self.on_parameters, LATCHED_QOS)
            self.std_subscription = self.create_subscription(
                Float64MultiArray, f'{prefix}/{interface.basename(interface.PARAMETER_STD)}',
                self.on_std, LATCHED_QOS)
            self.valid_subscription = self.create_subscription(
                Bool, f'{prefix}/{interface.basename(interface.VALID)}', self.on_valid,
                LATCHED_QOS)
        except Exception as error:  # rclpy's InvalidTopicNameException
            raise ValueError(f'parameter \'identifier\' must be a valid topic prefix, got '
                             f'{settings["identifier"]!r}: {error}') from None
        self.redesign_timer = self.create_timer(settings['redesign_period'], self.on_redesign)
        self.diagnostics = DiagnosticsUpdater(self, f'{self.get_name()}: controller',
                                              [self.diagnose], hardware_id=self.get_name())
        self.publish_controller()
        self.get_logger().info(
            f'pole placement for {",".join(self.loop.structure.names)} (from {prefix}) with '
            f'poles {format_poles(self.loop.poles)}, integral action '
            f'{str(settings["integral_action"]).lower()}; fallback controller until a '
            f'trusted estimate')

    # --------------------------------------------------------------- the loop
    def on_output(self, message: Float64) -> None:
        """Take y_t and publish the input (once per output, never NaN)."""
        self.outputs += 1
        value = self.loop.step(message.data)
        if not math.isfinite(message.data):
            self._throttle.warn('nonfinite_output', f'output {message.data} refused; the '
                                f'input is held at {value:g}')
        self.input_publisher.publish(Float64(data=value))
        self.inputs_published += 1

    def on_reference(self, message: Float64) -> None:
        """Take a setpoint; a NaN or Inf one is refused and the last kept."""
        if not self.loop.set_reference(message.data):
            self._throttle.warn('nonfinite_reference', f'reference {message.data} refused; '
                                f'keeping the setpoint {self.loop.setpoint:g}')

    def publish_controller(self) -> None:
        """Publish the controller in the loop on ``~/controller`` (latched)."""
        numerator, denominator = self.loop.controller.message_data()
        self.controller_publisher.publish(controller_message(numerator, denominator))

    # ---------------------------------------------------------- the estimates
    def on_parameters(self, message: Float64MultiArray) -> None:
        """Store the latest estimate (looked at on the next redesign tick)."""
        self.loop.offer_parameters(message_names(message), message.data, self._now())

    def on_std(self, message: Float64MultiArray) -> None:
        """Store the latest parameter standard deviations."""
        self.loop.offer_std(message_names(message), message.data)

    def on_valid(self, message: Bool) -> None:
        """Store the latest validity flag."""
        self._report(self.loop.offer_valid(message.data))

    def on_redesign(self) -> None:
        """Every redesign_period: watch the identifier, look at the latest estimate."""
        publishers = self.count_publishers(self.parameters_topic)
        if self._identifier_publishers and not publishers:
            self._report(self.loop.identifier_lost())
        self._identifier_publishers = publishers
        outcome = self.loop.redesign(self._now())
        self._report(outcome)
        if outcome.kind == 'switched':
            self.publish_controller()

    def _report(self, outcome: Outcome) -> None:
        if outcome.kind == 'switched':
            self.get_logger().info(outcome.message)
        elif outcome.kind == 'kept':
            self.get_logger().debug(outcome.message)
        elif outcome.kind == 'refused':
            self._last_refusal = outcome.reason
            self._throttle.warn(outcome.reason, outcome.message)
        elif outcome.kind != 'none':
            self._throttle.warn(outcome.kind, outcome.message)

    def _now(self) -> float:
        return self.get_clock().now().nanoseconds * 1e-9

    # -------------------------------------------------------- the diagnostics
    def diagnose(self, status: Status) -> None:
        """Add the controller's level, message and counters to the /diagnostics status."""
        loop = self.loop
        now = self.get_clock().now()
        elapsed = (now - self._last_time).nanoseconds * 1e-9
        self._last_time = now
        rate = (self.outputs - self._last_outputs) / elapsed if elapsed > 0 else 0.0
        self._last_outputs = self.outputs
        new_refusals = loop.refusals - self._last_refusals
        self._last_refusals = loop.refusals
        numerator, denominator = loop.controller.message_data()
        if not loop.trusted:
            level, message = WARN, 'fallback controller: no trusted estimate yet'
        elif new_refusals:
            level, message = WARN, (f'{new_refusals} estimates refused '
                                    f'(last: {REFUSALS[self._last_refusal]}); keeping the '
                                    f'last designed controller')
        else:
            level, message = OK, 'designed controller in the loop'
        values: list[tuple[str, object]] = [
            ('outputs received', self.outputs),
            ('inputs published', self.inputs_published),
            ('rate (outputs/s)', rate),
            ('controller', 'designed' if loop.trusted else 'fallback'),
            ('controller numerator', ', '.join(f'{v:.6g}' for v in numerator)),
            ('controller denominator', ', '.join(f'{v:.6g}' for v in denominator)),
            ('target poles', format_poles(loop.poles)),
            ('poles with the latest estimate',
             format_poles(loop.predicted_poles(), missing='unknown (no estimate yet)')),
            ('input (last)', loop.runtime.last_input),
            ('reference (last)', loop.last_reference),
            ('refusals (all reasons)', loop.refusals),
        ]
        values += [(REFUSALS[key], loop.counters[key]) for key in REFUSALS]
        values += [(EVENTS[key], loop.counters[key]) for key in EVENTS]
        status.merge_summary(level, message)
        for key, value in values:
            status.add(key, value)


def main(argv: list[str] | None = None) -> int:
    """Run ``adaptive_controller_node`` until SIGINT or SIGTERM."""
    return run_node(AdaptiveControllerNode, argv, 'adaptive_controller_node',
                    help_text=usage('adaptive_controller_node', __doc__.strip().splitlines()[0],
                                    CONTROLLER_PARAMETERS))


if __name__ == '__main__':
    raise SystemExit(main())
