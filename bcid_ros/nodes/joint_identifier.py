"""
The identifier node's ``input_mode: joint_state`` on rclpy (docs/nodes.md, "Many joints").

A thin adapter: :class:`bcid_ros.identifier.joint_feeder.JointFeeder` does the work (the
demultiplexing by name, the batched update, the per-joint publication rule)
and this class turns its results into ROS messages: it subscribes to
``joint_states``, publishes each joint's estimates and validity on its own
latched topics ``~/<joint>/...``, serves ``~/reset`` and publishes one
``/diagnostics`` status for the node and one per joint.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from rclpy.event_handler import PublisherEventCallbacks
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import Bool, Float64MultiArray
from std_srvs.srv import Trigger

from bcid_ros.identifier import interface
from bcid_ros.identifier.joint_feeder import (joint_feeder_from_parameters, JOINT_STATES,
                                              joint_topic, JointFeedResult)
from bcid_ros.identifier.pairing import SequenceTracker
from bcid_ros.nodes.common import LATCHED_QOS, Throttle
from bcid_ros.nodes.diagnostics import CounterTask, SampleRateTask
from bcid_ros.nodes.joint_diagnostics import JointDiagnosticsUpdater, JointStatuses, JointsTask
from bcid_ros.nodes.messages import as_doubles, estimate_message, valid_message
from bcid_ros.nodes.sample_topics import IncompatibleQoS, StalenessWatch, subscribe_samples

#: No QoS event handlers on the per-joint publishers: rclpy's default ones (a warning
#: for an incompatible subscriber) put two waitables per publisher into every wait of
#: the executor, which at a thousand joints costs more than the estimation.
QUIET_PUBLISHER = PublisherEventCallbacks(use_default_callbacks=False)


class JointStateIdentifier:
    """
    One estimator per joint of ``joints``, fed from the ``joint_states`` topic.

    Parameters
    ----------
    node : rclpy.node.Node
        The identifier node that owns the topics, the service and the timer.
    settings : dict
        The identifier's checked parameters (``input_mode: joint_state``).
    qos_events : IncompatibleQoS
        Reports publishers of ``joint_states`` refused for their QoS.

    Attributes
    ----------
    feeder : JointFeeder
        The joints' feeder; ``feeder.estimator`` is the batched estimator.
    counters : dict
        The node's counters (keys of ``interface.COUNTERS``), summed over the joints.

    """

    def __init__(self, node: Node, settings: dict[str, Any],
                 qos_events: IncompatibleQoS) -> None:
        self._node = node
        self.feeder = feeder = joint_feeder_from_parameters(settings)
        estimator = feeder.estimator
        self.counters = dict.fromkeys(interface.COUNTERS, 0)
        self.messages = 0
        self.estimates_published = 0
        self._throttle = Throttle(node.get_logger())
        self._sequences = SequenceTracker()

        def publishers(kind: type, topic: str) -> list[Any]:
            return [node.create_publisher(kind, joint_topic(joint, topic), LATCHED_QOS,
                                          event_callbacks=QUIET_PUBLISHER)
                    for joint in feeder.joints]

        self._parameters = publishers(Float64MultiArray, interface.PARAMETERS)
        self._noise = publishers(Float64MultiArray, interface.NOISE_VARIANCE)
        self._std = publishers(Float64MultiArray, interface.PARAMETER_STD)
        self._valid = publishers(Bool, interface.VALID)
        # one reusable message per topic kind: a publication copies it out
        self._parameters_message = estimate_message(estimator.parameter_names)
        self._noise_message = estimate_message(estimator.noise_names)
        for publisher in self._valid:
            publisher.publish(valid_message(False))
        # no joint_states for stale_after seconds: every joint's ~/valid turns false
        self.staleness = StalenessWatch(node, settings['stale_after'],
                                        lambda: self._publish_valid(np.arange(len(feeder.joints))))
        self.subscription = self.subscribe(qos_events)
        self.reset_service = node.create_service(Trigger, interface.RESET, self.on_reset)
        name = node.get_fully_qualified_name()
        self.diagnostics = JointDiagnosticsUpdater(
            node, interface.status_name(name), [
                JointsTask(settings['estimator'], feeder, lambda: feeder.publish_period),
                CounterTask(self.counters, lambda: feeder.excitation_lost),
                SampleRateTask(feeder, lambda: node.get_clock().now().nanoseconds * 1e-9, self),
                self.staleness, qos_events],
            JointStatuses(name, feeder), hardware_id=name)
        self.staleness.start()

    def resume(self) -> None:
        """
        Take the samples again after a pause (a deactivated managed node).

        What was published meanwhile was not taken, not lost in transport:
        every regressor restarts, without a count.
        """
        self._sequences.reset()
        self.feeder.gap()
        self.staleness.start()

    def subscribe(self, qos_events: IncompatibleQoS) -> Any:
        """Subscribe to ``joint_states`` (again, after a deactivation); return the subscription."""
        self.subscription = subscribe_samples(self._node, JointState, JOINT_STATES,
                                              self.on_joint_state, qos_events)
        return self.subscription

    # --------------------------------------------------------------- input
    def on_joint_state(self, message: JointState, info: Any) -> None:
        """Take one JointState: update every joint it carries, publish what is due."""
        self.messages += 1
        self.staleness.arrived(self.staleness.now())
        sequence = info.get('publication_sequence_number') if isinstance(info, dict) else None
        lost = self._sequences.lost(JOINT_STATES, sequence)
        if lost:
            self.feeder.gap()
            self._count('lost', f'{lost} {JOINT_STATES} message(s) lost in transport: every '
                        'regressor restarts', lost)
        self._take(self.feeder.take(message))

    def _take(self, result: JointFeedResult) -> None:
        if result.dropped:
            self._count(result.dropped, f'estimator update failed: {result.reason}')
        if result.length_mismatch:
            demux = self.feeder.demux
            self._count('bad_layout', f'{JOINT_STATES} message whose {demux.input_field} or '
                        f'{demux.output_field} array has not one value per name: its joints '
                        'counted missing')
        if result.missing:
            self._throttle.warn('missing', f'{result.missing} joint(s) missing from a '
                                f'{JOINT_STATES} message (counted per joint in /diagnostics)')
        if result.nonfinite:
            self._count('nonfinite', 'joint sample with NaN or Inf skipped; that joint\'s '
                        'regressor refills', result.nonfinite)
        if result.unexcited:
            self._count('unexcited', 'a joint\'s input has been constant for '
                        f'{self.feeder.excitation_window} samples or more: no excitation',
                        result.unexcited)
        if result.withheld.size:
            self._count('nonfinite_estimates', 'a joint\'s estimate is not finite; not '
                        'published', int(result.withheld.size))
        self._publish_valid(result.valid_changed)
        if result.due.size:
            self.publish_estimates(result.due, result.theta, result.noise, result.std)

    def _count(self, kind: str, text: str, count: int = 1) -> None:
        self.counters[kind] += count
        self._throttle.warn(kind, text)

    # -------------------------------------------------------------- output
    def publish_estimates(self, joints: np.ndarray, theta: np.ndarray, noise: np.ndarray,
                          std: np.ndarray) -> None:
        """Publish the estimates of ``joints`` (indices): rows of ``theta``, ``noise``, ``std``."""
        parameters, noise_message = self._parameters_message, self._noise_message
        finite = np.isfinite(noise).all(axis=1) if noise.size else np.zeros(len(joints), bool)
        # a joint without a standard deviation yet (NaN row) publishes none
        known = np.isfinite(std).all(axis=1)
        for row, joint in enumerate(joints.tolist()):
            parameters.data = as_doubles(theta[row])
            self._parameters[joint].publish(parameters)
            if finite[row]:
                noise_message.data = as_doubles(noise[row])
                self._noise[joint].publish(noise_message)
            if known[row]:
                parameters.data = as_doubles(std[row])  # the same names as the parameters
                self._std[joint].publish(parameters)
        self.estimates_published += len(joints)

    def _publish_valid(self, joints: np.ndarray) -> None:
        valid = self.feeder.valid & (not self.staleness.reason)
        for joint in joints.tolist():
            self._valid[joint].publish(valid_message(valid[joint]))

    def on_reset(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        """Restart every joint's estimator from its initial state (~/reset)."""
        used = int(self.feeder.estimator.samples.sum())
        self._publish_valid(self.feeder.reset().valid_changed)
        self._sequences.reset()
        response.success = True
        response.message = (f'estimators of {len(self.feeder.joints)} joints reset after '
                            f'{used} joint samples')
        self._node.get_logger().info(response.message)
        return response


__all__ = ['JointStateIdentifier']
