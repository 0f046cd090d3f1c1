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
:class:`~bcid_ros.nodes.joint_identifier.JointStateIdentifier`. The sample
subscriptions, their QoS overrides and the staleness of the estimate are
:mod:`bcid_ros.nodes.sample_topics`'s.

The behaviour is :class:`Identifier`, in steps that the plain node runs at
once and the managed form (:mod:`bcid_ros.nodes.identifier_lifecycle_node`)
runs at its transitions: :meth:`Identifier.declare_identifier` (parameters),
:meth:`Identifier.configure_identifier` (check them, build the estimator,
restore the state file), :meth:`Identifier.activate_identifier` (publish,
subscribe) and :meth:`Identifier.deactivate_identifier` (stop taking samples).

Run it as ``identifier_node --ros-args --params-file config/ding_miso.yaml``.
"""

from __future__ import annotations

from typing import Any, Callable

from builtin_interfaces.msg import Time
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
from bcid_ros.identifier.slicing import SlicedFeeder
from bcid_ros.identifier.parameters import (check_identifier_parameters, estimator_from_parameters,
                                            IDENTIFIER_PARAMETERS, spec_by_name, unused_options)
from bcid_ros.nodes.common import (declare_table, make_parameter_check, qos_override_names,
                                   read_table, run_node, Throttle, usage, warn_undeclared)
from bcid_ros.nodes.controller_input import ControllerInput
from bcid_ros.nodes.diagnostics import (CounterTask, DiagnosticsUpdater, EstimatorTask,
                                        SampleRateTask)
from bcid_ros.nodes.estimate_publisher import EstimatePublisher
from bcid_ros.nodes.joint_identifier import JointStateIdentifier
from bcid_ros.nodes.messages import topic_class
from bcid_ros.nodes.sample_topics import IncompatibleQoS, StalenessWatch, subscribe_samples
from bcid_ros.nodes.state_keeping import StateKeeper

#: The sample topics of each input mode (the QoS override parameters they take).
SAMPLE_TOPICS = {'combined': (interface.SAMPLES,),
                 'separate': (interface.INPUT, interface.OUTPUT),
                 'joint_state': (interface.JOINT_STATES,)}


class Identifier:
    """
    The identifier's behaviour on an rclpy node, in the steps of a managed node.

    A mixin: :class:`IdentifierNode` (a plain ``Node``) runs the steps in its
    constructor, :class:`~bcid_ros.nodes.identifier_lifecycle_node.IdentifierLifecycleNode`
    at its transitions.
    """

    estimator: Any = None
    state_keeper: StateKeeper | None = None
    joint_state: JointStateIdentifier | None = None

    def declare_identifier(self) -> None:
        """Declare the parameters and the callbacks that check and apply live changes."""
        self._specs = spec_by_name(IDENTIFIER_PARAMETERS)
        declare_table(self, IDENTIFIER_PARAMETERS)
        self._table_check = make_parameter_check(self._specs)
        self.add_on_set_parameters_callback(self.check_parameters)
        self.add_post_set_parameters_callback(self.on_parameters_set)

    def configure_identifier(self) -> None:
        """
        Check the parameters, build the estimator and restore the state file.

        Raises
        ------
        ValueError
            If a parameter is not allowed; the message names it and its
            allowed values.

        """
        self.settings = settings = check_identifier_parameters(
            read_table(self, IDENTIFIER_PARAMETERS))
        warn_undeclared(self, [name for topic in SAMPLE_TOPICS[settings['input_mode']]
                               for name in qos_override_names(self.resolve_topic_name(topic))])
        for name in unused_options(settings):
            self.get_logger().warning(f'parameter {name!r} does not apply to estimator '
                                      f'{settings["estimator"]!r}; ignored')
        self.messages = 0
        self.qos_events = IncompatibleQoS(self, lambda: self.messages)
        self.subscriptions_of_samples: list[Any] = []
        if settings['input_mode'] == 'joint_state':
            return  # JointStateIdentifier builds all at activation
        self.estimator = estimator_from_parameters(settings)  # as bcid replay builds it
        self.feeder = SampleFeeder(self.estimator, settings['excitation_window'],
                                   settings['publish_period'], settings['freeze_unexcited'])
        if settings['detrend'] == 'none':
            self.estimator.monitor_centring()  # /diagnostics warns about offsets
        self.state_keeper = (StateKeeper(self, settings, self.estimator, self.feeder,
                                         lambda: (self.messages, self.estimator.samples))
                             if settings['state_file'] else None)
        self.counters = dict.fromkeys(interface.COUNTERS, 0)
        self._throttle = Throttle(self.get_logger())
        self._sequences = SequenceTracker()
        self.pairing = Pairing.from_settings(settings)
        # large frames go in slices from a timer, so that other callbacks wait <= 20 ms
        self.slices = SlicedFeeder(self.feeder)
        self._slice_timer = self.create_timer(0.0, self._feed_slices)
        self._slice_timer.cancel()
        self._sample_stamp: Time | None = None
        self._resumed: set[str] = set()
        self.estimates = None

    def activate_identifier(self) -> None:
        """
        Publish and subscribe: at the first activation after configuring, make the topics.

        Raises
        ------
        ValueError
            If a parameter that only the topics check (``controller_topic``)
            is not allowed.

        """
        settings = self.settings
        if settings['input_mode'] == 'joint_state':
            self._activate_joint_state(settings)
            return
        first = self.estimates is None
        if first:
            self.staleness = StalenessWatch(self, settings['stale_after'],
                                            lambda: self.estimates.update_valid())
            self.estimates = EstimatePublisher(self, self.estimator, settings['detrend'],
                                               lambda: self.staleness.reason)
            self.reset_service = self.create_service(Trigger, interface.RESET, self.on_reset)
            self.diagnostics = DiagnosticsUpdater(
                self, interface.status_name(self.get_fully_qualified_name()), [
                    EstimatorTask(settings['estimator'], self.estimator,
                                  lambda: self.publish_period),
                    CounterTask(self.counters, lambda: self.feeder.excitation_lost),
                    SampleRateTask(self.feeder,
                                   lambda: self.get_clock().now().nanoseconds * 1e-9, self),
                    self.staleness, self.qos_events],
                hardware_id=self.get_fully_qualified_name())
            self.controller = (ControllerInput(self, settings, self.estimator, self.diagnostics,
                                               self.estimates.update_valid)
                               if settings['controller_topic'] else None)
        else:
            self.diagnostics.timer.reset()
            # messages published while inactive were not lost: they were not taken
            self._resumed = set(SAMPLE_TOPICS[settings['input_mode']])
        self._subscribe(settings)
        self.staleness.start()
        if first and self.state_keeper:
            self.state_keeper.start(self.estimates.publish)
        names = self.estimator.parameter_names
        self.get_logger().info(
            f'{settings["estimator"]} with n={settings["order"]}, r={settings["num_inputs"]}, '
            f'feedthrough={settings["feedthrough"]}; input_mode {settings["input_mode"]}'
            + (f' (sync {settings["sync"]})' if settings['input_mode'] == 'separate' else '')
            + f'; parameters {names_label(names)}')

    def deactivate_identifier(self) -> None:
        """Stop taking samples (the subscriptions go); the state and the topics stay."""
        for subscription in self.subscriptions_of_samples:
            self.destroy_subscription(subscription)
        self.subscriptions_of_samples = []
        if self.joint_state is not None:
            self.joint_state.diagnostics.timer.cancel()
            self.joint_state.staleness.stop()
            return
        self.staleness.stop()
        self.diagnostics.timer.cancel()

    def _activate_joint_state(self, settings: dict[str, Any]) -> None:
        """Set up ``input_mode: joint_state``: one estimator per joint, all batched."""
        if self.joint_state is not None:  # activated again
            self.joint_state.diagnostics.timer.reset()
            self.joint_state.resume()
            self.subscriptions_of_samples = [self.joint_state.subscribe(self.qos_events)]
            return
        self.joint_state = JointStateIdentifier(self, settings, self.qos_events)
        self.subscriptions_of_samples = [self.joint_state.subscription]
        self.feeder = self.joint_state.feeder
        self.estimator = self.feeder.estimator
        self.counters = self.joint_state.counters
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
            self.subscriptions_of_samples = [subscribe_samples(
                self, Float64MultiArray, interface.SAMPLES, self.on_samples, self.qos_events)]
            return
        self.subscriptions_of_samples = [
            subscribe_samples(self, topic_class(settings[f'{side}_type']), topic,
                              lambda message, info, side=side, read=interface.reader(
                                  side, settings): self.on_separate(side, read, message, info),
                              self.qos_events, draining=False)
            for side, topic in (('input', interface.INPUT), ('output', interface.OUTPUT))]

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
        if not result.successful or self.estimator is None:  # not configured: read later
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
        if self.estimator is None:  # not configured yet: configuring reads them
            return
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
        self._arrived()
        lost = bool(self._lost(interface.SAMPLES, info))
        if self.slices.takes(message):
            self.slices.push(message, gap=lost)
            self._slice_timer.reset()
            return
        if lost:
            self.feeder.gap()
        self._take(self.feeder.take_message(message))

    def _feed_slices(self) -> None:
        """Feed the next slices of the large frames waiting (identifier/slicing.py)."""
        for result in self.slices.step():
            self._take(result)
        if not self.slices.busy:
            self._slice_timer.cancel()

    def on_separate(self, side: str, read: Callable[[Any], Any], message: Any,
                    info: dict) -> None:
        """Take one message of the ``input`` or ``output`` topic and feed what pairs."""
        self.messages += 1
        self._arrived(message.header.stamp if self.pairing.stamped else None)
        lost = self._lost(side, info)
        try:
            value = read(message)
        except ValueError as error:
            self._count('bad_layout', f'{side} message dropped: {error}')
            self._take_paired(self.pairing.refuse(side, lost))
            return
        stamp = interface.stamp_ns(message) if self.pairing.stamped else None
        self._take_paired(self.pairing.add(side, value, stamp, lost))

    def _arrived(self, stamp: Time | None = None) -> None:
        """
        Note a message's arrival: its stamp dates the next estimate, and it is not stale.

        ``stamp``: the header stamp of a stamped message (the one that
        completes a pair); None takes the node clock's receive time.
        """
        now = self.get_clock().now()
        self._sample_stamp = now.to_msg() if stamp is None else stamp
        self.staleness.arrived(now.nanoseconds * 1e-9)

    def _lost(self, topic: str, info: Any) -> int:
        sequence = info.get('publication_sequence_number') if isinstance(info, dict) else None
        lost = self._sequences.lost(topic, sequence)
        if topic in self._resumed:
            # the first message after an activation: a jump in the numbers is the samples
            # published while the node was inactive; the regressor restarts, nothing is lost
            self._resumed.discard(topic)
            if lost:
                self.get_logger().info(f'{lost} {topic} message(s) published while inactive '
                                       'were not taken; the regressor restarts')
            return lost
        if lost:
            self.counters['lost'] += lost
            # the total, since the throttle's repeat count counts warnings, not messages
            self._throttle.warn('lost', f'{lost} {topic} message(s) lost in transport, '
                                f'{self.counters["lost"]} in all (is the node too slow for the '
                                'rate? use frames)')
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
            self.estimates.publish(*result.estimates, self._sample_stamp)

    def _count(self, kind: str, text: str, count: int = 1) -> None:
        self.counters[kind] += count
        self._throttle.warn(kind, text)

    # ---------------------------------------------------- reset and shutdown
    def on_reset(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        """Restart the estimator from its initial state (~/reset)."""
        used = self.estimator.samples
        self.feeder.reset()
        self.slices.clear()
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


class IdentifierNode(Identifier, Node):
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
        self.declare_identifier()
        self.configure_identifier()
        self.activate_identifier()


def main(argv: list[str] | None = None) -> int:
    """Run ``identifier_node`` until SIGINT or SIGTERM."""
    return run_node(IdentifierNode, argv, 'identifier_node',
                    help_text=usage('identifier_node', __doc__.strip().splitlines()[0],
                                    IDENTIFIER_PARAMETERS))


if __name__ == '__main__':
    raise SystemExit(main())
