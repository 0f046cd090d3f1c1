"""
The identification node: samples in, bias-compensated estimates out (docs/nodes.md).

The node holds one estimator and does no numerics of its own. It is an
adapter between rclpy and four ROS-free parts: the message table of
:mod:`bcid_ros.nodes.interface` reads the separate topics,
:class:`bcid_ros.nodes.pairing.Pairing` pairs them,
:class:`bcid_ros.samples.SampleFeeder` feeds the samples with the same rule
as the offline replay (so the node gives the same estimates as
``bcid replay`` on the same samples), and the tasks of
:mod:`bcid_ros.nodes.diagnostics` report on ``/diagnostics``. With
``state_file`` set, :mod:`bcid_ros.persistence` keeps the state across
restarts.

Run it as ``identifier_node --ros-args --params-file config/ding_miso.yaml``.
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from rclpy.parameter import Parameter
from std_msgs.msg import Bool, Float64MultiArray
from std_srvs.srv import Trigger

from bcid_ros.control.design import controller_from_message
from bcid_ros import persistence
from bcid_ros.estimators.base import standard_deviations
from bcid_ros.nodes import interface
from bcid_ros.nodes.common import (declare_table, LATCHED_QOS, make_parameter_check, run_node,
                                   SAMPLES_QOS, Throttle, usage)
from bcid_ros.nodes.diagnostics import (CounterTask, DiagnosticsUpdater, EstimatorTask,
                                        SampleRateTask)
from bcid_ros.nodes.joint_identifier import JointStateIdentifier
from bcid_ros.nodes.messages import (as_doubles, covariance_message, estimate_message,
                                     topic_class, valid_message)
from bcid_ros.nodes.pairing import GAP, Paired, Pairing, SequenceTracker
from bcid_ros.parameters import (check_identifier_parameters, estimator_from_parameters,
                                 IDENTIFIER_PARAMETERS, spec_by_name, unused_options)
from bcid_ros.samples import FeedResult, names_label, SampleFeeder


class IdentifierNode(Node):
    """
    Online identification of an ARX model from a stream of samples.

    Parameters
    ----------
    node_name : str
        Default ``bcid_identifier``.
    **kwargs
        Passed to :class:`rclpy.node.Node` (``context``, ``parameter_overrides``, ...).

    Raises
    ------
    ValueError
        If a parameter is not allowed; the message names it and its allowed
        values.

    """

    def __init__(self, node_name: str = interface.IDENTIFIER_NODE, **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        specs = spec_by_name(IDENTIFIER_PARAMETERS)
        self.settings = settings = check_identifier_parameters(
            declare_table(self, IDENTIFIER_PARAMETERS))
        for name in unused_options(settings):
            self.get_logger().warning(f'parameter {name!r} does not apply to estimator '
                                      f'{settings["estimator"]!r}; ignored')
        if settings['input_mode'] == 'joint_state':
            self._start_joint_state(settings, specs)
            return
        self.estimator = estimator_from_parameters(settings)  # as bcid replay builds it
        self.feeder = SampleFeeder(self.estimator, settings['excitation_window'],
                                   settings['publish_period'], settings['freeze_unexcited'])
        if settings['detrend'] == 'none':
            self.estimator.monitor_centring()  # /diagnostics warns about offsets
        restored = self._restore_state(settings)
        self.counters = dict.fromkeys(interface.COUNTERS, 0)
        self.messages = 0
        self.estimates_published = 0
        self._throttle = Throttle(self.get_logger())
        self._sequences = SequenceTracker()
        self.pairing = Pairing.from_settings(settings)

        names = self.estimator.parameter_names
        self._estimates = {  # publisher and reusable message of each estimate topic
            topic: (self.create_publisher(Float64MultiArray, topic, LATCHED_QOS),
                    estimate_message(labels))
            for topic, labels in ((interface.PARAMETERS, names),
                                  (interface.PARAMETERS_UNCOMPENSATED, names),
                                  (interface.NOISE_VARIANCE, tuple(self.estimator.noise_names)),
                                  (interface.PARAMETER_STD, names))}
        self._estimates[interface.PARAMETER_COVARIANCE] = (
            self.create_publisher(Float64MultiArray, interface.PARAMETER_COVARIANCE,
                                  LATCHED_QOS), covariance_message(names))
        if settings['detrend'] == 'mean':
            self._estimates[interface.OPERATING_POINT] = (
                self.create_publisher(Float64MultiArray, interface.OPERATING_POINT,
                                      LATCHED_QOS),
                estimate_message(self.estimator.operating_point_names))
        self.valid_publisher = self.create_publisher(Bool, interface.VALID, LATCHED_QOS)
        self._valid = bool(self.estimator.valid)
        self.valid_publisher.publish(valid_message(self._valid))
        self._subscribe(settings)

        self.reset_service = self.create_service(Trigger, interface.RESET, self.on_reset)
        self.diagnostics = DiagnosticsUpdater(
            self, interface.status_name(self.get_name()), [
                EstimatorTask(settings['estimator'], self.estimator, lambda: self.publish_period),
                CounterTask(self.counters, lambda: self.feeder.excitation_lost),
                SampleRateTask(self.feeder, lambda: self.get_clock().now().nanoseconds * 1e-9,
                               self)],
            hardware_id=self.get_name())
        self._subscribe_controller(settings)
        self._table_check = make_parameter_check(specs)
        self.add_on_set_parameters_callback(self.check_parameters)
        self.add_post_set_parameters_callback(self.on_parameters_set)
        self._keep_state(settings, restored)
        self.get_logger().info(
            f'{settings["estimator"]} with n={settings["order"]}, r={settings["num_inputs"]}, '
            f'feedthrough={settings["feedthrough"]}; input_mode {settings["input_mode"]}'
            + (f' (sync {settings["sync"]})' if settings['input_mode'] == 'separate' else '')
            + f'; parameters {names_label(names)}')

    def _start_joint_state(self, settings: dict[str, Any], specs: dict[str, Any]) -> None:
        """Set up ``input_mode: joint_state``: one estimator per joint, all batched."""
        self.joint_state = JointStateIdentifier(self, settings)
        self.feeder = self.joint_state.feeder
        self.estimator = self.feeder.estimator
        self.counters = self.joint_state.counters
        self._table_check = make_parameter_check(specs)
        self.add_on_set_parameters_callback(self.check_parameters)
        self.add_post_set_parameters_callback(self.on_parameters_set)
        joints = self.feeder.joints
        shown = ', '.join(joints[:5]) + (f' and {len(joints) - 5} more' if len(joints) > 5 else '')
        self.get_logger().info(
            f'{settings["estimator"]} with n={settings["order"]}, '
            f'feedthrough={settings["feedthrough"]} for each of {len(joints)} joints ({shown}); '
            f'input_mode joint_state, u = {settings["input_field"]}, '
            f'y = {settings["output_field"]}; parameters '
            f'{names_label(self.estimator.parameter_names)}')

    def _subscribe(self, settings: dict[str, Any]) -> None:
        if settings['input_mode'] == 'combined':
            self.create_subscription(Float64MultiArray, interface.SAMPLES, self.on_samples,
                                     SAMPLES_QOS)
            return
        for side, topic in (('input', interface.INPUT), ('output', interface.OUTPUT)):
            read = interface.reader(side, settings)
            self.create_subscription(
                topic_class(settings[f'{side}_type']), topic,
                lambda message, info, side=side, read=read: self.on_separate(
                    side, read, message, info),
                SAMPLES_QOS)

    # ----------------------------------------------- the controller in the loop
    def _subscribe_controller(self, settings: dict[str, Any]) -> None:
        """With controller_topic: take cl_bcls's controller from the adaptive controller."""
        topic = settings['controller_topic']
        self.controller_counts = {'changes': 0, 'unchanged': 0, 'refused': 0}
        self._controller_data: tuple[list[float], list[float]] | None = None
        if not topic:
            return
        if not hasattr(self.estimator, 'set_controller'):
            raise ValueError(f"parameter 'controller_topic' applies to estimator cl_bcls only "
                             f"(the closed-loop estimator that needs the controller), got "
                             f"estimator {settings['estimator']!r} with controller_topic "
                             f"{topic!r}")
        controller = self.estimator.controller
        self._controller_data = (controller.numerator.tolist(),
                                 controller.denominator.tolist())
        try:
            self.controller_subscription = self.create_subscription(
                Float64MultiArray, topic, self.on_controller, LATCHED_QOS)
        except Exception as error:  # rclpy's InvalidTopicNameException
            raise ValueError(f"parameter 'controller_topic' must be a valid topic name, got "
                             f"{topic!r}: {error}") from None
        self.diagnostics.tasks.append(self._diagnose_controller)
        self.get_logger().info(f'controller in the loop from {topic}')

    def on_controller(self, message: Float64MultiArray) -> None:
        """Restart the compensation at a new controller; ignore an identical republish."""
        dims = message.layout.dim
        try:
            controller = controller_from_message([d.label for d in dims],
                                                 [d.size for d in dims], message.data)
            # the estimator's own form (b_c padded to a_c), to compare with the one in use
            numerator, denominator = controller.message_data()
            if self._same_controller(numerator, denominator):
                self.controller_counts['unchanged'] += 1
                return
            used = self.estimator.samples
            self.estimator.set_controller(numerator, denominator, 'negative')
        except ValueError as error:
            self.controller_counts['refused'] += 1
            self._throttle.warn('controller_refused', f'controller message refused, the '
                                f'controller in use kept: {error}')
            return
        self._controller_data = (numerator, denominator)
        self.controller_counts['changes'] += 1
        if self._valid != self.estimator.valid:
            self._publish_valid()
        self.get_logger().info(f'new controller in the loop {numerator} / {denominator}: '
                               f'compensation restarted (after {used} samples)')

    def _same_controller(self, numerator: list[float], denominator: list[float]) -> bool:
        old_numerator, old_denominator = self._controller_data
        width = max(len(numerator), len(old_numerator))
        pad = [0.0] * width
        return (denominator == old_denominator
                and (pad + numerator)[-width:] == (pad + old_numerator)[-width:])

    def _diagnose_controller(self, status: Any) -> None:
        numerator, denominator = self._controller_data
        status.add('controller in the loop', f'{numerator} / {denominator}')
        status.add('controller changes (compensation restarted)',
                   self.controller_counts['changes'])
        status.add('controller republished unchanged', self.controller_counts['unchanged'])
        status.add('controller messages refused (malformed)', self.controller_counts['refused'])

    @property
    def publish_period(self) -> int:
        """Return the samples between published estimates (live parameter)."""
        return self.feeder.publish_period

    # ------------------------------------------------------------ parameters
    def check_parameters(self, parameters: list[Parameter]) -> SetParametersResult:
        """Refuse values outside the table's ranges or that the estimator does not take."""
        result = self._table_check(parameters)
        if not result.successful:
            return result
        for parameter in parameters:
            if parameter.name == 'forgetting_factor':
                old = self.estimator.forgetting_factor
                try:
                    # the estimator's own rule (cl_bcls takes only 1); applied after the check
                    self.estimator.forgetting_factor = parameter.value
                except ValueError as error:
                    return SetParametersResult(successful=False, reason=str(error))
                finally:
                    self.estimator.forgetting_factor = old
        return result

    def on_parameters_set(self, parameters: list[Parameter]) -> None:
        """Apply the parameters that may change while running."""
        for parameter in parameters:
            if parameter.name == 'forgetting_factor':
                self.estimator.forgetting_factor = parameter.value
            elif parameter.name == 'publish_period':
                self.feeder.publish_period = parameter.value
            elif parameter.name in ('adapt', 'outlier_threshold'):
                setattr(self.estimator, parameter.name, parameter.value)
            else:
                continue
            self.settings[parameter.name] = parameter.value
            self.get_logger().info(f'{parameter.name} set to {parameter.value}')

    # --------------------------------------------------------------- input
    def on_samples(self, message: Float64MultiArray, info: dict) -> None:
        """Decode a samples message (one sample or a frame) and feed it."""
        self.messages += 1
        if self._lost(interface.SAMPLES, info):
            self.feeder.gap()
        self._take(self.feeder.take_message(message))

    def on_separate(self, side: str, read: Callable[[Any], Any], message: Any,
                    info: dict) -> None:
        """Take one message of the ``input`` or ``output`` topic and feed what pairs."""
        self.messages += 1
        lost = self._lost(side, info)
        try:
            value = read(message)
        except ValueError as error:
            self._count('bad_layout', f'{side} message dropped: {error}')
            self._take_paired(self.pairing.refuse(side, lost))
            return
        stamp = interface.stamp_ns(message) if self.pairing.stamped else None
        self._take_paired(self.pairing.add(side, value, stamp, lost))

    def _lost(self, topic: str, info: Any) -> int:
        sequence = info.get('publication_sequence_number') if isinstance(info, dict) else None
        lost = self._sequences.lost(topic, sequence)
        if lost:
            self.counters['lost'] += lost
            self._throttle.warn('lost', f'{lost} {topic} message(s) lost in transport (is the '
                                'node too slow for the rate? use frames)')
        return lost

    def _take_paired(self, paired: Paired) -> None:
        for kind, text in paired.problems:
            self._count(kind, text)
        for note in paired.notes:
            self.get_logger().info(note)
        for sample in paired.samples:
            if sample is GAP:
                self.feeder.gap()
            else:
                self._take(self.feeder.take_rows(np.array([sample], dtype=float)))

    def _take(self, result: FeedResult) -> None:
        """Count and warn about what the feeder did; publish the estimates it returned."""
        if result.dropped:
            what = ('estimator update failed' if result.dropped == 'estimator_errors'
                    else 'samples message dropped')
            self._count(result.dropped, f'{what}: {result.reason}')
        if result.nonfinite:
            self._count('nonfinite', 'sample with NaN or Inf dropped; the regressor refills '
                        'before the next update', result.nonfinite)
        if result.unexcited:
            self._count('unexcited', 'the input has been constant for '
                        f'{self.feeder.excitation_window} samples or more: no excitation, '
                        'the estimate cannot improve', result.unexcited)
        if result.withheld:
            self._count('nonfinite_estimates', 'the estimator returned a non-finite estimate; '
                        'not published')
        if self._valid != self.estimator.valid:
            self._publish_valid()
        if result.estimates is not None:
            self.publish_estimates(*result.estimates)

    def _count(self, kind: str, text: str, count: int = 1) -> None:
        self.counters[kind] += count
        self._throttle.warn(kind, text)

    # -------------------------------------------------------------- output
    def publish_estimates(self, theta: np.ndarray, uncompensated: np.ndarray,
                          noise: np.ndarray) -> None:
        """Publish the estimates (the feeder has checked that they are due and finite)."""
        self._publish(interface.PARAMETERS, theta)
        self._publish(interface.PARAMETERS_UNCOMPENSATED, uncompensated)
        if noise.size and np.isfinite(noise).all():
            self._publish(interface.NOISE_VARIANCE, noise)
        self._publish_uncertainty()
        operating_point = self.estimator.operating_point
        if operating_point is not None:
            self._publish(interface.OPERATING_POINT, operating_point)
        self.estimates_published += 1

    def _publish_uncertainty(self) -> None:
        """Publish the parameter std and covariance, if the estimator has them now."""
        covariance = self.estimator.parameter_covariance
        if covariance is not None:
            self._publish(interface.PARAMETER_STD, standard_deviations(covariance))
            self._publish(interface.PARAMETER_COVARIANCE, covariance)

    def _publish(self, topic: str, values: np.ndarray) -> None:
        publisher, message = self._estimates[topic]
        message.data = as_doubles(values)
        publisher.publish(message)

    def _publish_valid(self) -> None:
        self._valid = bool(self.estimator.valid)
        self.valid_publisher.publish(valid_message(self._valid))

    def on_reset(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        """Restart the estimator from its initial state (~/reset)."""
        used = self.estimator.samples
        self.feeder.reset()
        self._sequences.reset()
        self.pairing.reset()
        if self._valid != self.estimator.valid:
            self._publish_valid()
        response.success = True
        response.message = f'estimator reset after {used} samples'
        self.get_logger().info(response.message)
        return response

    # ---------------------------------------------------------- state file
    def _restore_state(self, settings: dict[str, Any]) -> bool:
        """Restore the estimator and feeder from ``state_file`` if it fits; log one line."""
        self._state_path = settings['state_file']
        if not self._state_path:
            return False
        self._state_fingerprint = persistence.configuration_fingerprint(settings)
        self._state_failing = False
        self._state_saved = None
        try:
            sections = persistence.load_state(self._state_path, self._state_fingerprint)
            if sections is None:
                self.get_logger().info(f'state file {self._state_path} does not exist yet; '
                                       'starting fresh')
                return False
            self._load_state_sections(sections)
        except persistence.StateRefused as error:
            self.get_logger().warning(f'{error}; starting fresh')
            return False
        self.get_logger().info(
            f'state restored from {self._state_path}: {self.feeder.used} samples used, '
            f'{self.estimator.samples} since reset, valid {self.estimator.valid}')
        return True

    def _load_state_sections(self, sections: dict[str, persistence.Section]) -> None:
        """Restore every section, or nothing (StateRefused): a half-restored node is worse."""
        fresh = self.feeder.get_state()
        try:
            persistence.restore_estimator(self.estimator, sections['estimator'])
            self.feeder.set_state(sections['feeder'][1])
            # a live parameter: the value the node starts with applies, as without a state
            self.estimator.forgetting_factor = self.settings['forgetting_factor']
        except Exception as error:  # a missing key, a shape, a value the estimator refuses
            self.estimator.reset()
            self.feeder.set_state(fresh)
            raise persistence.StateRefused(
                f'state file {self._state_path} does not fit this estimator '
                f'({type(error).__name__}: {error})') from None

    def _state_sections(self) -> dict[str, persistence.Section]:
        """Return everything the next estimates depend on, by section."""
        return {'estimator': persistence.estimator_section(self.estimator),
                'feeder': ({}, self.feeder.get_state())}

    def _state_signature(self) -> tuple[int, int]:
        """Return what changes whenever the state does (messages taken, or a reset)."""
        return self.messages, self.estimator.samples

    def _keep_state(self, settings: dict[str, Any], restored: bool) -> None:
        """Publish a restored estimate at once (latched) and save every period."""
        if not self._state_path:
            return
        if restored:
            self._state_saved = self._state_signature()  # the file holds it already
        if restored and self.estimator.ready:
            theta, uncompensated = self.estimator.theta, self.estimator.theta_uncompensated
            if np.isfinite(theta).all() and np.isfinite(uncompensated).all():
                self.publish_estimates(theta, uncompensated, self.estimator.noise)
        self.state_timer = self.create_timer(settings['state_save_period'],
                                             self._on_state_timer)

    def _on_state_timer(self) -> None:
        if self._state_signature() != self._state_saved:
            self.save_state()

    def save_state(self) -> bool:
        """
        Write ``state_file`` now (atomically); return whether it was written.

        A failure is logged once (and the recovery once); the node keeps
        running and tries again at the next period.
        """
        error = self._write_state()
        if error is None and self._state_failing:
            self.get_logger().info(f'state file {self._state_path} written again')
        elif error is not None and not self._state_failing:
            self.get_logger().error(error)
        self._state_failing = error is not None
        return error is None

    def _write_state(self) -> str | None:
        """Write ``state_file``; return None, or the line that says why it failed."""
        signature = self._state_signature()
        try:
            persistence.save_state(self._state_path, self._state_fingerprint,
                                   self._state_sections())
        except (OSError, TypeError, ValueError) as error:
            return (f'cannot write state file {self._state_path}: {error}; the node keeps '
                    f'running and tries again every {self.settings["state_save_period"]:g} s')
        self._state_saved = signature
        return None

    def destroy_node(self) -> None:
        """Save the state (with ``state_file`` set) before the node goes: nothing is lost."""
        if not getattr(self, '_state_path', ''):
            super().destroy_node()
            return
        error = self._write_state()
        # logged after the node is gone, when its /rosout publisher (whose context a
        # signal has already shut down) no longer takes the line
        super().destroy_node()
        if error is None:
            self.get_logger().info(f'state saved to {self._state_path} at shutdown '
                                   f'({self.feeder.used} samples used)')
        elif not self._state_failing:
            self.get_logger().error(error)


def main(argv: list[str] | None = None) -> int:
    """Run ``identifier_node`` until SIGINT or SIGTERM."""
    return run_node(IdentifierNode, argv, 'identifier_node',
                    help_text=usage('identifier_node', __doc__.strip().splitlines()[0],
                                    IDENTIFIER_PARAMETERS))


if __name__ == '__main__':
    raise SystemExit(main())
