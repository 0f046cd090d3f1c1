"""
The identification node: samples in, bias-compensated estimates out (docs/nodes.md).

The node holds one estimator and does no numerics of its own. It is an
adapter between rclpy and four ROS-free parts: the message table of
:mod:`bcid_ros.identifier.interface` reads the separate topics,
:class:`bcid_ros.identifier.pairing.Pairing` pairs them,
:class:`bcid_ros.identifier.feeder.SampleFeeder` feeds the samples with the same rule
as the offline replay (so the node gives the same estimates as
``bcid replay`` on the same samples), and the tasks of
:mod:`bcid_ros.nodes.diagnostics` report on ``/diagnostics``. Three helpers
that the node composes do the rest on rclpy:
:class:`~bcid_ros.nodes.estimate_publisher.EstimatePublisher` publishes the
estimates, :class:`~bcid_ros.nodes.state_keeping.StateKeeper` keeps the
state across restarts (``state_file``) and
:class:`~bcid_ros.nodes.controller_input.ControllerInput` takes the
controller in the loop (``controller_topic``); ``input_mode: joint_state`` is
:class:`~bcid_ros.nodes.joint_identifier.JointStateIdentifier`.

Run it as ``identifier_node --ros-args --params-file config/ding_miso.yaml``.
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from rclpy.parameter import Parameter
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import Trigger

from bcid_ros.identifier import interface
from bcid_ros.identifier.feeder import FeedResult, SampleFeeder
from bcid_ros.identifier.layouts import names_label
from bcid_ros.identifier.pairing import GAP, Paired, Pairing, SequenceTracker
from bcid_ros.identifier.parameters import (check_identifier_parameters, estimator_from_parameters,
                                            IDENTIFIER_PARAMETERS, spec_by_name, unused_options)
from bcid_ros.nodes.common import (create_draining_subscription, declare_table,
                                   make_parameter_check, run_node, SAMPLES_QOS, Throttle,
                                   usage)
from bcid_ros.nodes.controller_input import ControllerInput
from bcid_ros.nodes.diagnostics import (CounterTask, DiagnosticsUpdater, EstimatorTask,
                                        SampleRateTask)
from bcid_ros.nodes.estimate_publisher import EstimatePublisher
from bcid_ros.nodes.joint_identifier import JointStateIdentifier
from bcid_ros.nodes.messages import topic_class
from bcid_ros.nodes.state_keeping import StateKeeper


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
        self.state_keeper = (StateKeeper(self, settings, self.estimator, self.feeder,
                                         lambda: (self.messages, self.estimator.samples))
                             if settings['state_file'] else None)
        self.counters = dict.fromkeys(interface.COUNTERS, 0)
        self.messages = 0
        self._throttle = Throttle(self.get_logger())
        self._sequences = SequenceTracker()
        self.pairing = Pairing.from_settings(settings)
        self.estimates = EstimatePublisher(self, self.estimator, settings['detrend'])
        self._subscribe(settings)

        self.reset_service = self.create_service(Trigger, interface.RESET, self.on_reset)
        self.diagnostics = DiagnosticsUpdater(
            self, interface.status_name(self.get_name()), [
                EstimatorTask(settings['estimator'], self.estimator, lambda: self.publish_period),
                CounterTask(self.counters, lambda: self.feeder.excitation_lost),
                SampleRateTask(self.feeder, lambda: self.get_clock().now().nanoseconds * 1e-9,
                               self)],
            hardware_id=self.get_name())
        self.controller = (ControllerInput(self, settings, self.estimator, self.diagnostics,
                                           self.estimates.update_valid)
                           if settings['controller_topic'] else None)
        self._table_check = make_parameter_check(specs)
        self.add_on_set_parameters_callback(self.check_parameters)
        self.add_post_set_parameters_callback(self.on_parameters_set)
        if self.state_keeper:
            self.state_keeper.start(self.estimates.publish)
        names = self.estimator.parameter_names
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
            create_draining_subscription(self, Float64MultiArray, interface.SAMPLES,
                                         self.on_samples, SAMPLES_QOS)
            return
        for side, topic in (('input', interface.INPUT), ('output', interface.OUTPUT)):
            read = interface.reader(side, settings)
            self.create_subscription(
                topic_class(settings[f'{side}_type']), topic,
                lambda message, info, side=side, read=read: self.on_separate(
                    side, read, message, info),
                SAMPLES_QOS)

    @property
    def publish_period(self) -> int:
        """Return the samples between published estimates (live parameter)."""
        return self.feeder.publish_period

    @property
    def estimates_published(self) -> int:
        """Return the estimates published so far."""
        return self.estimates.published

    @property
    def controller_counts(self) -> dict[str, int]:
        """Return the controller messages by outcome (zeros without ``controller_topic``)."""
        if self.controller is None:
            return {'changes': 0, 'unchanged': 0, 'refused': 0}
        return self.controller.counts

    # ------------------------------------------------------------ parameters
    def check_parameters(self, parameters: list[Parameter]) -> SetParametersResult:
        """Refuse values outside the table's ranges or that the estimator does not take."""
        result = self._table_check(parameters)
        if not result.successful:
            return result
        for parameter in parameters:
            if parameter.name in ('forgetting_factor', 'parameter_drift'):
                old = getattr(self.estimator, parameter.name)
                try:
                    # the estimator's own rule (cl_bcls takes only lambda = 1, parameter_drift
                    # needs adaptation: kalman); applied after the check
                    setattr(self.estimator, parameter.name, parameter.value)
                except ValueError as error:
                    return SetParametersResult(successful=False, reason=str(error))
                finally:
                    setattr(self.estimator, parameter.name, old)
        return result

    def on_parameters_set(self, parameters: list[Parameter]) -> None:
        """Apply the parameters that may change while running."""
        for parameter in parameters:
            if parameter.name == 'forgetting_factor':
                self.estimator.forgetting_factor = parameter.value
            elif parameter.name == 'publish_period':
                self.feeder.publish_period = parameter.value
            elif parameter.name in ('adapt', 'outlier_threshold', 'change_detection',
                                    'parameter_drift'):
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
        self.estimates.update_valid()
        if result.estimates is not None:
            self.estimates.publish(*result.estimates)

    def _count(self, kind: str, text: str, count: int = 1) -> None:
        self.counters[kind] += count
        self._throttle.warn(kind, text)

    # ---------------------------------------------------- reset and shutdown
    def on_reset(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        """Restart the estimator from its initial state (~/reset)."""
        used = self.estimator.samples
        self.feeder.reset()
        self._sequences.reset()
        self.pairing.reset()
        self.estimates.update_valid()
        response.success = True
        response.message = f'estimator reset after {used} samples'
        self.get_logger().info(response.message)
        return response

    def destroy_node(self) -> None:
        """Save the state (with ``state_file`` set) before the node goes: nothing is lost."""
        if getattr(self, 'state_keeper', None):
            self.state_keeper.save_and_destroy(super().destroy_node)
        else:
            super().destroy_node()


def main(argv: list[str] | None = None) -> int:
    """Run ``identifier_node`` until SIGINT or SIGTERM."""
    return run_node(IdentifierNode, argv, 'identifier_node',
                    help_text=usage('identifier_node', __doc__.strip().splitlines()[0],
                                    IDENTIFIER_PARAMETERS))


if __name__ == '__main__':
    raise SystemExit(main())
