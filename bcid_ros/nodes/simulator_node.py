"""
The simulator node: a scenario's samples at a fixed rate (docs/nodes.md).

The samples come from :mod:`bcid_ros.simulation`, the code the paper
reproductions use. The node draws them in blocks from one stream whose
samples do not depend on the block size, so the same seed gives the same
data at every rate and frame size. Pacing follows the wall clock: each
timer tick publishes the samples that are due, so the average rate is
exact even when ticks are late.

With ``mode: plant`` the node is a plant in a loop instead: it holds the
latest command received on ``input`` (zero-order hold) and publishes one
sample per tick; :mod:`bcid_ros.simulation.plant` does the stepping
(docs/adaptive_loop.md).

Run it as ``simulator_node --ros-args --params-file config/ding_miso.yaml``.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
from rclpy.duration import Duration
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64, Float64MultiArray

from bcid_ros.identifier import interface
from bcid_ros.identifier.joint_feeder import JOINT_STATES, joint_topic
from bcid_ros.identifier.layouts import samples_data
from bcid_ros.identifier.parameters import (check_simulator_parameters, CUSTOM_SETTINGS,
                                            OPERATING_POINT_SETTINGS, SIMULATOR_PARAMETERS)
from bcid_ros.nodes.common import (declare_table, LATCHED_QOS, run_node, SAMPLES_QOS,
                                   Throttle, usage)
from bcid_ros.nodes.joint_identifier import QUIET_PUBLISHER
from bcid_ros.nodes.messages import as_doubles, estimate_message, SamplesLayouts, topic_class
from bcid_ros.simulation import make_scenario
from bcid_ros.simulation.plant import ChangingStream, HeldInputPlant, plant_pair

#: Longest timer period (s); ticks publish whatever is due.
MAX_TICK = 0.01
#: Shortest timer period (s).
MIN_TICK = 0.001
#: Most seconds of samples published in one tick when catching up after a stall.
MAX_BURST = 0.05
#: Seconds to wait for the subscribers to acknowledge the last messages.
FLUSH_TIMEOUT = 5.0
#: Plant mode with lockstep: longest wait (s) for the command of the last output.
LOCKSTEP_TIMEOUT = 1.0
#: Plant mode: seconds between two checks of the input topic's publishers' types.
GRAPH_CHECK_PERIOD = 1.0


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
        self.plant: HeldInputPlant | None = None
        self.changing: ChangingStream | None = None
        self.joint_state_publisher = None  # scenario joints only (finish() looks at it)
        if settings['mode'] == 'plant':
            self._start_plant_mode(settings)
            return
        if settings['change_after_samples'] and settings['scenario'] != 'custom':
            raise ValueError("parameter 'change_after_samples' needs scenario: custom (the "
                             "plant after the change is given by the custom parameters), got "
                             f"{settings['change_after_samples']} with scenario "
                             f"{settings['scenario']!r}")
        changing = None
        if settings['scenario'] == 'custom':
            self.scenario, after = plant_pair(settings,
                                              CUSTOM_SETTINGS + OPERATING_POINT_SETTINGS)
            if after is not None:
                changing = ChangingStream(self.scenario, np.random.default_rng(settings['seed']),
                                          after=after,
                                          change_after=settings['change_after_samples'])
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
        self.stream = changing or self.scenario.stream(np.random.default_rng(settings['seed']))
        #: The open-loop plant that changes (change_after_samples), or None.
        self.changing = changing
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
        change = (f'; the plant changes after {changing.plant.change_after} samples'
                  if changing is not None else '')
        self.get_logger().info(
            f'scenario {settings["scenario"]}, seed {settings["seed"]}: {total} at '
            f'{self.rate:g} Hz, {self.frame_size} per message, output_mode {mode}; true '
            f'{true}{change}')

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
            changed = self.changing is not None and self.changing.plant.changed
            y, u = self.stream.take(count)
            for start in range(0, count, self.frame_size):
                stop = min(start + self.frame_size, count)
                self._publish(y[start:stop], u[start:stop], self.sent + start)
            self.sent += count
            if self.changing is not None and self.changing.plant.changed and not changed:
                self._open_loop_changed()
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

    # ------------------------------------------------------------ plant mode
    def _start_plant_mode(self, settings: dict[str, Any]) -> None:
        """Set up ``mode: plant``: the custom plant, a held input, one sample per tick."""
        if settings['scenario'] != 'custom':
            raise ValueError("parameter 'mode' plant needs scenario: custom (the plant is "
                             f"given by the custom parameters), got {settings['scenario']!r}")
        if settings['frame_size'] != 1:
            raise ValueError("parameter 'frame_size' must be 1 in mode: plant (one sample "
                             f"per tick, each answered by a command), got "
                             f"{settings['frame_size']}")
        before, after = plant_pair(settings, CUSTOM_SETTINGS + OPERATING_POINT_SETTINGS)
        self.scenario = before
        self.num_inputs = before.num_inputs
        self.plant = HeldInputPlant(before, np.random.default_rng(settings['seed']),
                                    after=after, change_after=settings['change_after_samples'])
        self.rate = settings['rate_hz']
        self.frame_size = 1
        self.num_samples = settings['num_samples']
        self.sent = 0
        self.done = False
        self._created = time.monotonic()
        self._start = None
        self._throttle = Throttle(self.get_logger())
        #: Plant-mode counters (logged; the summary line at the end).
        self.plant_counters = {'commands': 0, 'refused commands': 0, 'late commands': 0,
                               'lockstep timeouts': 0, 'wrong-type input publishers': 0}
        self._fresh_command = False
        self._waiting_since: float | None = None
        self._wrong_publishers: set[bytes] = set()

        self.true_parameters_publisher = self.create_publisher(
            Float64MultiArray, interface.TRUE_PARAMETERS, LATCHED_QOS)
        self.true_noise_publisher = self.create_publisher(
            Float64MultiArray, interface.TRUE_NOISE_VARIANCE, LATCHED_QOS)
        self._publish_truth()
        self.samples_publisher = self.create_publisher(Float64MultiArray, interface.SAMPLES,
                                                       SAMPLES_QOS)
        self.output_publisher = self.create_publisher(Float64, interface.OUTPUT, SAMPLES_QOS)
        self.input_publisher = None
        self._layouts = SamplesLayouts(self.num_inputs)
        # Float64 for one input, Float64MultiArray for several (docs/adaptive_loop.md)
        self.input_class = Float64 if self.num_inputs == 1 else Float64MultiArray
        self.input_subscription = self.create_subscription(
            self.input_class, interface.INPUT, self.on_input, SAMPLES_QOS)
        self.input_topic = self.input_subscription.topic_name
        self.graph_timer = self.create_timer(GRAPH_CHECK_PERIOD, self.check_input_publishers)
        self.timer = self.create_timer(max(1.0 / self.rate, MIN_TICK), self.plant_tick)
        total = 'forever' if not self.num_samples else f'{self.num_samples} samples'
        change = (f'; the plant changes after {settings["change_after_samples"]} samples'
                  if self.plant.change_after else '')
        self.get_logger().info(
            f'mode plant (custom), seed {settings["seed"]}: {total} at {self.rate:g} Hz, '
            f'input held from {self.input_topic} ({self.input_class.__name__}); true '
            f'{self._truth_text()}{change}')

    def _stepped_plant(self) -> HeldInputPlant:
        """Return the plant stepped sample by sample: plant mode's, or the changing stream's."""
        return self.plant if self.plant is not None else self.changing.plant

    def _open_loop_changed(self) -> None:
        """Publish and log the truth of the open-loop plant after its change."""
        self._publish_truth()
        self.get_logger().info(f'plant changed after {self.changing.plant.change_after} '
                               f'samples: true {self._truth_text()}')

    def _truth_text(self) -> str:
        truth = self._stepped_plant().truth()
        pairs = zip(truth.parameter_names, truth.parameters)
        return ', '.join(f'{n}={v:.6g}' for n, v in pairs)

    def _publish_truth(self) -> None:
        truth = self._stepped_plant().truth()
        self.truth = truth
        self.true_parameters_publisher.publish(
            estimate_message(truth.parameter_names, truth.parameters))
        self.true_noise_publisher.publish(estimate_message(truth.noise_names, truth.noise))

    def on_input(self, message: Any) -> None:
        """Hold a command (u_1..u_r) from the next sample on; refuse a malformed one."""
        values = [message.data] if self.num_inputs == 1 else list(message.data)
        try:
            self.plant.hold(values)
        except ValueError as error:
            self.plant_counters['refused commands'] += 1
            self._throttle.warn('refused_command', f'input command refused ({error}); '
                                f'holding {self.plant.held.tolist()}')
            return
        self.plant_counters['commands'] += 1
        self._fresh_command = True
        if self.settings['lockstep'] and self._waiting_since is not None:
            # the sample was due and waited for this command: no need to wait for the timer
            self.plant_tick()

    def check_input_publishers(self) -> None:
        """Report publishers of the input topic with another type (they never connect)."""
        expected = f'std_msgs/msg/{self.input_class.__name__}'
        for info in self.get_publishers_info_by_topic(self.input_topic):
            gid = bytes(info.endpoint_gid)
            if info.topic_type == expected or gid in self._wrong_publishers:
                continue
            self._wrong_publishers.add(gid)
            self.plant_counters['wrong-type input publishers'] += 1
            self.get_logger().error(
                f'{info.node_namespace.rstrip("/")}/{info.node_name} publishes '
                f'{info.topic_type} on {self.input_topic}; this plant has r = '
                f'{self.num_inputs} input(s) and takes {expected} only: its commands are '
                f'not received')

    def _plant_ready(self) -> bool:
        if not self._ready():
            return False
        wanted = self.settings['wait_for_subscribers']
        return not wanted or self.output_publisher.get_subscription_count() >= 1

    def plant_tick(self) -> None:
        """Publish the next sample with the held input (one sample per tick)."""
        if self.done:
            return
        if self._start is None:
            if not self._plant_ready():
                return
            self._start = time.monotonic()
        # at most rate_hz: a sample waits for its time (the timer may tick early after a
        # sample that a command triggered)
        if self.sent and time.monotonic() < self._start + self.sent / self.rate - 0.5 / self.rate:
            return
        if self.sent and not self._fresh_command:
            # the command computed from the last output has not arrived yet
            if self.settings['lockstep']:
                now = time.monotonic()
                if self._waiting_since is None:
                    self._waiting_since = now
                if now - self._waiting_since < LOCKSTEP_TIMEOUT:
                    return
                self.plant_counters['lockstep timeouts'] += 1
                self._throttle.warn('lockstep_timeout', f'lockstep: no command '
                                    f'{LOCKSTEP_TIMEOUT:g} s after the last output (is a '
                                    f'controller running?); the held input is applied')
            if self.plant.commands:
                self.plant_counters['late commands'] += 1
                self._throttle.warn('late_command', 'no command since the last output: the '
                                    'held input is applied again (a slow controller; see '
                                    'lockstep)')
        self._waiting_since = None
        self._fresh_command = False
        changed = self.plant.changed
        y, u = self.plant.step()
        if self.plant.changed and not changed:
            self._publish_truth()
            self.get_logger().info(f'plant changed after {self.sent} samples: true '
                                   f'{self._truth_text()}')
        self.samples_publisher.publish(
            self._layouts.message(samples_data(np.array([y]), u[None, :]), 1))
        self.output_publisher.publish(Float64(data=float(y)))
        self.sent += 1
        if self.num_samples and self.sent >= self.num_samples:
            counts = ', '.join(f'{k} {v}' for k, v in self.plant_counters.items())
            self.get_logger().info(f'plant mode: {counts}')
            self.finish()


def main(argv: list[str] | None = None) -> int:
    """Run ``simulator_node`` until it has published num_samples, or SIGINT/SIGTERM."""
    return run_node(SimulatorNode, argv, 'simulator_node', until=lambda node: node.done,
                    help_text=usage('simulator_node', __doc__.strip().splitlines()[0],
                                    SIMULATOR_PARAMETERS))


if __name__ == '__main__':
    raise SystemExit(main())
