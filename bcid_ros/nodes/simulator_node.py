"""
The simulator node: a scenario's samples at a fixed rate (docs/nodes.md).

The samples come from :mod:`bcid_ros.simulation`, the code the paper
reproductions use. The node draws them in blocks from one stream whose
samples do not depend on the block size, so the same seed gives the same
data at every rate and frame size. Pacing follows the wall clock: each
timer tick publishes the samples that are due, so the average rate is
exact even when ticks are late.

Run it as ``simulator_node --ros-args --params-file config/ding_miso.yaml``.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
from rclpy.duration import Duration
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from bcid_ros.joint_feeder import JOINT_STATES, joint_topic
from bcid_ros.nodes import interface
from bcid_ros.nodes.common import declare_table, LATCHED_QOS, run_node, SAMPLES_QOS, usage
from bcid_ros.nodes.joint_identifier import QUIET_PUBLISHER
from bcid_ros.nodes.messages import as_doubles, estimate_message, SamplesLayouts, topic_class
from bcid_ros.parameters import (check_simulator_parameters, CUSTOM_SETTINGS,
                                 SIMULATOR_PARAMETERS)
from bcid_ros.samples import samples_data
from bcid_ros.simulation import make_scenario

#: Longest timer period (s); ticks publish whatever is due.
MAX_TICK = 0.01
#: Shortest timer period (s).
MIN_TICK = 0.001
#: Most seconds of samples published in one tick when catching up after a stall.
MAX_BURST = 0.05
#: Seconds to wait for the subscribers to acknowledge the last messages.
FLUSH_TIMEOUT = 5.0


class SimulatorNode(Node):
    """
    Publish a scenario's (y, u) samples and its true parameters.

    Parameters
    ----------
    node_name : str
        Default ``bcid_simulator``.
    **kwargs
        Passed to :class:`rclpy.node.Node`.

    Raises
    ------
    ValueError
        If a parameter is not allowed; the message names it.

    """

    def __init__(self, node_name: str = interface.SIMULATOR_NODE, **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        settings = check_simulator_parameters(declare_table(self, SIMULATOR_PARAMETERS))
        self.settings = settings
        if settings['scenario'] == 'custom':
            self.scenario = make_scenario('custom',
                                          **{k: settings[k] for k in CUSTOM_SETTINGS})
        elif settings['scenario'] == 'joints':
            self.scenario = make_scenario('joints', num_joints=settings['num_joints'],
                                          seed=settings['seed'])
        else:
            self.scenario = make_scenario(settings['scenario'])
        self.num_inputs = self.scenario.num_inputs
        mode = settings['output_mode']
        self.joint_state_publisher = None
        if settings['scenario'] == 'joints':
            mode = 'joint_state'
        elif mode != 'combined':
            interface.check_input_width(settings['input_type'], self.num_inputs)
        self.rate = settings['rate_hz']
        self.frame_size = settings['frame_size']
        self.num_samples = settings['num_samples']
        self.stream = self.scenario.stream(np.random.default_rng(settings['seed']))
        self.sent = 0
        self.done = False
        self._created = time.monotonic()
        self._start: float | None = None
        self._stamp0_ns = 0

        truth = self.scenario.truth()
        self.truth = truth
        self.true_parameters_publisher = self.create_publisher(
            Float64MultiArray, interface.TRUE_PARAMETERS, LATCHED_QOS)
        self.true_noise_publisher = self.create_publisher(
            Float64MultiArray, interface.TRUE_NOISE_VARIANCE, LATCHED_QOS)
        self.true_parameters_publisher.publish(
            estimate_message(truth.parameter_names, truth.parameters))
        self.true_noise_publisher.publish(estimate_message(truth.noise_names, truth.noise))

        self.samples_publisher = None
        self.input_publisher = None
        self.output_publisher = None
        if mode == 'joint_state':
            self._start_joints(settings)
        if mode in ('combined', 'both'):
            self.samples_publisher = self.create_publisher(
                Float64MultiArray, interface.SAMPLES, SAMPLES_QOS)
        if mode in ('separate', 'both'):
            self._input = (interface.MESSAGE_TYPES[settings['input_type']].build,
                           topic_class(settings['input_type']))
            self._output = (interface.MESSAGE_TYPES[settings['output_type']].build,
                            topic_class(settings['output_type']))
            self.input_publisher = self.create_publisher(self._input[1], interface.INPUT,
                                                         SAMPLES_QOS)
            self.output_publisher = self.create_publisher(self._output[1], interface.OUTPUT,
                                                          SAMPLES_QOS)
        self._layouts = SamplesLayouts(self.num_inputs)
        self._input_names = [f'u{i}' for i in range(1, self.num_inputs + 1)]

        frame_period = self.frame_size / self.rate
        self.timer = self.create_timer(min(max(frame_period, MIN_TICK), MAX_TICK), self.tick)
        total = 'forever' if not self.num_samples else f'{self.num_samples} samples'
        true = ', '.join(f'{n}={v:.6g}' for n, v in zip(truth.parameter_names, truth.parameters))
        if mode == 'joint_state':
            true = f'of {len(self.joint_names)} joints on ~/<joint>/true_parameters'
        self.get_logger().info(
            f'scenario {settings["scenario"]}, seed {settings["seed"]}: {total} at '
            f'{self.rate:g} Hz, {self.frame_size} per message, output_mode {mode}; true {true}')

    def _start_joints(self, settings: dict[str, Any]) -> None:
        """Scenario joints: one JointState per sample; each joint's truth on its own topics."""
        self.joint_names = list(settings['joints'] or self.scenario.joint_names)
        self._joint_truth_publishers = []
        for joint, truth in zip(self.joint_names, self.scenario.joint_truths().values()):
            for topic, names, values in (
                    (interface.TRUE_PARAMETERS, truth.parameter_names, truth.parameters),
                    (interface.TRUE_NOISE_VARIANCE, truth.noise_names, truth.noise)):
                publisher = self.create_publisher(Float64MultiArray, joint_topic(joint, topic),
                                                  LATCHED_QOS, event_callbacks=QUIET_PUBLISHER)
                publisher.publish(estimate_message(names, values))
                self._joint_truth_publishers.append(publisher)
        self.joint_state_publisher = self.create_publisher(JointState, JOINT_STATES,
                                                           SAMPLES_QOS)
        self._joint_state = JointState(name=self.joint_names)

    def _publish_joint_states(self, y: np.ndarray, u: np.ndarray, first_index: int) -> None:
        """Publish one JointState per sample: y as velocity, u as effort, position empty."""
        message = self._joint_state
        period_ns = 1e9 / self.rate
        for row in range(y.shape[0]):
            stamp = self._stamp0_ns + int(round((first_index + row) * period_ns))
            message.header.stamp.sec, message.header.stamp.nanosec = divmod(stamp, 10 ** 9)
            message.velocity = as_doubles(y[row])
            message.effort = as_doubles(u[row])
            self.joint_state_publisher.publish(message)

    # ------------------------------------------------------------- pacing
    def _ready(self) -> bool:
        if time.monotonic() - self._created < self.settings['start_delay']:
            return False
        wanted = self.settings['wait_for_subscribers']
        if wanted:
            publisher = (self.samples_publisher or self.output_publisher
                         or self.joint_state_publisher)
            if publisher.get_subscription_count() < wanted:
                return False
        return True

    def tick(self) -> None:
        """Publish the samples that are due by the wall clock."""
        if self.done:
            return
        if self._start is None:
            if not self._ready():
                return
            self._start = time.monotonic()
            self._stamp0_ns = self.get_clock().now().nanoseconds
        due = int((time.monotonic() - self._start) * self.rate) + self.frame_size
        due = min(due, self.sent + max(self.frame_size, int(MAX_BURST * self.rate)))
        if self.num_samples:
            due = min(due, self.num_samples)
        count = due - self.sent
        if not (self.num_samples and due == self.num_samples):
            count -= count % self.frame_size  # whole frames, but for the last one
        if count > 0:
            y, u = self.stream.take(count)
            for start in range(0, count, self.frame_size):
                stop = min(start + self.frame_size, count)
                self._publish(y[start:stop], u[start:stop], self.sent + start)
            self.sent += count
        if self.num_samples and self.sent >= self.num_samples:
            self.finish()

    def finish(self) -> None:
        """Wait until the subscribers have the last messages, then mark the node done."""
        for publisher in (self.samples_publisher, self.input_publisher, self.output_publisher,
                          self.joint_state_publisher):
            if publisher is not None:
                publisher.wait_for_all_acked(Duration(seconds=FLUSH_TIMEOUT))
        self.get_logger().info(f'published all {self.sent} samples')
        self.done = True

    # ---------------------------------------------------------- messages
    def _publish(self, y: np.ndarray, u: np.ndarray, first_index: int) -> None:
        if self.joint_state_publisher is not None:
            self._publish_joint_states(y, u, first_index)
        if self.samples_publisher is not None:
            self.samples_publisher.publish(
                self._layouts.message(samples_data(y, u), y.shape[0]))
        if self.input_publisher is None:
            return
        (build_input, input_class), (build_output, output_class) = self._input, self._output
        period_ns = 1e9 / self.rate
        for row in range(y.shape[0]):
            stamp = self._stamp0_ns + int(round((first_index + row) * period_ns))
            self.input_publisher.publish(build_input(input_class, u[row], self._input_names,
                                                     'effort', stamp))
            self.output_publisher.publish(build_output(output_class, [y[row]], ['y'],
                                                       'position', stamp))


def main(argv: list[str] | None = None) -> int:
    """Run ``simulator_node`` until it has published num_samples, or SIGINT/SIGTERM."""
    return run_node(SimulatorNode, argv, 'simulator_node', until=lambda node: node.done,
                    help_text=usage('simulator_node', __doc__.strip().splitlines()[0],
                                    SIMULATOR_PARAMETERS))


if __name__ == '__main__':
    raise SystemExit(main())
