"""
The identification node: samples in, bias-compensated estimates out (SPEC sections 3-5).

The node holds one estimator and does no numerics of its own: it decodes
messages (:meth:`bcid_ros.samples.SampleFeeder.take_message`), pairs separate input and
output topics, and feeds the samples through the same
:class:`bcid_ros.samples.SampleFeeder` that the offline replay uses, so it
gives the same estimates as ``bcid replay`` on the same samples.

Run it as ``identifier_node --ros-args --params-file config/ding_miso.yaml``.
"""

from __future__ import annotations

import array
import collections
import math
import statistics
from typing import Any

import numpy as np
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64, Float64MultiArray, MultiArrayDimension
from std_srvs.srv import Trigger

from bcid_ros.estimators import estimator_class
from bcid_ros.nodes.common import (declare_table, LATCHED_QOS, make_parameter_check, run_node,
                                   SAMPLES_QOS, Throttle, usage)
from bcid_ros.nodes.diagnostics import DiagnosticsTimer, ERROR, OK, WARN
from bcid_ros.parameters import (check_identifier_parameters, estimator_settings,
                                 IDENTIFIER_PARAMETERS, spec_by_name, unused_options)
from bcid_ros.samples import names_label, SampleFeeder

#: Intervals used to learn the sample period in stamp mode when sample_period is 0.
PERIOD_LEARNING_INTERVALS = 20
#: An interval longer than this many sample periods is a gap (stamp mode).
GAP_FACTOR = 1.5
#: Placeholder of a message lost in transport in an arrival-mode queue.
HOLE = (None, None)

#: The diagnostic counters of bad or lost samples, with their diagnostic keys.
COUNTERS = {
    'nonfinite': 'bad samples: NaN or Inf',
    'bad_layout': 'bad messages: wrong length or layout',
    'empty': 'bad messages: empty',
    'duplicate': 'dropped: duplicated stamp',
    'out_of_order': 'dropped: stamp out of order',
    'unpaired': 'dropped: unpaired',
    'lost': 'lost in transport (messages, by sequence number)',
    'gaps': 'gaps in the stamps (regressor restarted)',
    'unexcited': 'samples without excitation (input constant)',
    'estimator_errors': 'estimator errors',
    'nonfinite_estimates': 'non-finite estimates withheld',
}


def estimate_message(names: tuple[str, ...]) -> Float64MultiArray:
    """Return an empty estimate message whose layout carries the names (SPEC section 4)."""
    message = Float64MultiArray()
    message.layout.dim = [MultiArrayDimension(label=names_label(names), size=len(names),
                                              stride=len(names))]
    return message


def as_doubles(values: np.ndarray) -> array.array:
    """Return a float64 array as array('d'), which the message setter takes without a check."""
    result = array.array('d')
    result.frombytes(np.ascontiguousarray(values, dtype=np.float64).tobytes())
    return result


def stamp_ns(message: Any) -> int:
    """Return a message's header stamp in integer nanoseconds."""
    stamp = message.header.stamp
    return stamp.sec * 1_000_000_000 + stamp.nanosec


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

    def __init__(self, node_name: str = 'bcid_identifier', **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self._specs = spec_by_name(IDENTIFIER_PARAMETERS)
        self.settings = check_identifier_parameters(declare_table(self, IDENTIFIER_PARAMETERS))
        settings = self.settings
        for name in unused_options(settings):
            self.get_logger().warning(f'parameter {name!r} does not apply to estimator '
                                      f'{settings["estimator"]!r}; ignored')
        self.estimator = estimator_class(settings['estimator'])(**estimator_settings(settings))
        self.feeder = SampleFeeder(self.estimator, settings['excitation_window'],
                                   settings['publish_period'])
        self._seen = {'nonfinite': 0, 'unexcited': 0}
        self.num_inputs = settings['num_inputs']
        self.counters = dict.fromkeys(COUNTERS, 0)
        self.messages = 0
        self.estimates_published = 0
        self._throttle = Throttle(self.get_logger())
        self._last_used = 0
        self._last_counts: dict[str, int] = {}
        self._last_flags: dict[str, int] = {}
        self._last_time = self.get_clock().now()

        self._parameters_msg = estimate_message(self.estimator.parameter_names)
        self._uncompensated_msg = estimate_message(self.estimator.parameter_names)
        self._noise_msg = estimate_message(tuple(self.estimator.noise_names))
        self.parameters_publisher = self.create_publisher(
            Float64MultiArray, '~/parameters', LATCHED_QOS)
        self.uncompensated_publisher = self.create_publisher(
            Float64MultiArray, '~/parameters_uncompensated', LATCHED_QOS)
        self.noise_publisher = self.create_publisher(
            Float64MultiArray, '~/noise_variance', LATCHED_QOS)

        self._init_pairing()
        if settings['input_mode'] == 'combined':
            self.samples_subscription = self.create_subscription(
                Float64MultiArray, 'samples', self.on_samples, SAMPLES_QOS)
        else:
            input_type = {'float64': Float64, 'float64_multi_array': Float64MultiArray,
                          'joint_state': JointState}[settings['input_type']]
            output_type = {'float64': Float64, 'joint_state': JointState}[
                settings['output_type']]
            self.input_subscription = self.create_subscription(
                input_type, 'input', self.on_input, SAMPLES_QOS)
            self.output_subscription = self.create_subscription(
                output_type, 'output', self.on_output, SAMPLES_QOS)

        self.reset_service = self.create_service(Trigger, '~/reset', self.on_reset)
        self.diagnostics = DiagnosticsTimer(self, f'{self.get_name()}: identifier',
                                            self.status, hardware_id=self.get_name())
        self._table_check = make_parameter_check(self._specs)
        self.add_on_set_parameters_callback(self.check_parameters)
        self.add_post_set_parameters_callback(self.on_parameters_set)
        self.get_logger().info(
            f'{settings["estimator"]} with n={settings["order"]}, r={self.num_inputs}, '
            f'feedthrough={settings["feedthrough"]}; input_mode {settings["input_mode"]}'
            + (f' (sync {settings["sync"]})' if settings['input_mode'] == 'separate' else '')
            + f'; parameters {names_label(self.estimator.parameter_names)}')

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
                self.settings['forgetting_factor'] = parameter.value
            elif parameter.name == 'publish_period':
                self.feeder.publish_period = parameter.value
                self.settings['publish_period'] = parameter.value
            else:
                continue
            self.get_logger().info(f'{parameter.name} set to {parameter.value}')

    # ------------------------------------------------------ combined samples
    def on_samples(self, message: Float64MultiArray, info: dict) -> None:
        """Decode a samples message (one sample or a frame) and feed it."""
        self.messages += 1
        if self._lost('samples', info):
            self.feeder.gap(count=False)
        self._after_feed(self.feeder.take_message(message))

    def _feed(self, rows: np.ndarray) -> None:
        self._after_feed(self.feeder.take_rows(rows))

    def _after_feed(self, problem: str | None) -> None:
        """Count and warn about what the feeder refused or noticed; publish when due."""
        feeder = self.feeder
        if problem == 'estimator_errors':
            self._bad(problem, f'estimator update failed: {feeder.problem}')
            return
        if problem:
            self._bad(problem, f'samples message dropped: {feeder.problem}')
            return
        for kind, text in (
                ('nonfinite', 'sample with NaN or Inf dropped; the regressor refills before '
                 'the next update'),
                ('unexcited', f'the input has been constant for {feeder.excitation_window} '
                 'samples or more: no excitation, the estimate cannot improve')):
            new = getattr(feeder, kind) - self._seen[kind]
            if new:
                self._seen[kind] += new
                self.counters[kind] += new
                self._throttle.warn(kind, text)
        self.publish_estimates()

    def publish_estimates(self) -> bool:
        """Publish the estimates if they are due, valid and finite; return whether."""
        withheld = self.feeder.nonfinite_estimates
        estimates = self.feeder.due_estimates()
        if self.feeder.nonfinite_estimates != withheld:
            self._bad('nonfinite_estimates', 'the estimator returned a non-finite estimate; '
                      'not published')
        if estimates is None:
            return False
        theta, uncompensated, noise = estimates
        self._parameters_msg.data = as_doubles(theta)
        self.parameters_publisher.publish(self._parameters_msg)
        self._uncompensated_msg.data = as_doubles(uncompensated)
        self.uncompensated_publisher.publish(self._uncompensated_msg)
        if noise.size and np.isfinite(noise).all():
            self._noise_msg.data = as_doubles(noise)
            self.noise_publisher.publish(self._noise_msg)
        self.estimates_published += 1
        return True

    def _bad(self, kind: str, text: str) -> None:
        self.counters[kind] += 1
        self._throttle.warn(kind, text)

    # ------------------------------------------------------ separate topics
    def _init_pairing(self) -> None:
        settings = self.settings
        self._stamped = settings['input_mode'] == 'separate' and settings['sync'] == 'stamp'
        self._tolerance_ns = int(round(settings['sync_tolerance'] * 1e9))
        self._queue_size = settings['queue_size']
        self._inputs: collections.deque = collections.deque()
        self._outputs: collections.deque = collections.deque()
        self._last_stamp = {'input': None, 'output': None}
        self._last_pair_ns: int | None = None
        self._period_ns = settings['sample_period'] * 1e9
        self._intervals: list[int] = []
        self._sequence: dict[str, int] = {}

    def _lost(self, topic: str, info: Any) -> int:
        # Messages lost in transport show as a jump of the publication sequence
        # number (one publisher per topic assumed; a smaller number is a new one).
        sequence = info.get('publication_sequence_number') if isinstance(info, dict) else None
        if not sequence:
            return 0
        last = self._sequence.get(topic)
        self._sequence[topic] = sequence
        if last is None or sequence <= last + 1:
            return 0
        lost = sequence - last - 1
        self.counters['lost'] += lost
        self._throttle.warn('lost', f'{lost} {topic} message(s) lost in transport (is the '
                            'node too slow for the rate? use frames)')
        return lost

    def on_input(self, message: Any, info: dict) -> None:
        """Take one input message (Float64, Float64MultiArray or JointState)."""
        self.messages += 1
        self._holes(self._inputs, self._lost('input', info))
        try:
            value = self._input_values(message)
        except ValueError as error:
            self._bad('bad_layout', f'input message dropped: {error}')
            self._holes(self._inputs, 1)
            self.feeder.gap(count=False)
            return
        self._enqueue('input', self._inputs, message, value)

    def on_output(self, message: Any, info: dict) -> None:
        """Take one output message (Float64 or JointState)."""
        self.messages += 1
        self._holes(self._outputs, self._lost('output', info))
        try:
            value = self._output_value(message)
        except ValueError as error:
            self._bad('bad_layout', f'output message dropped: {error}')
            self._holes(self._outputs, 1)
            self.feeder.gap(count=False)
            return
        self._enqueue('output', self._outputs, message, value)

    def _holes(self, queue: collections.deque, count: int) -> None:
        # In arrival mode a lost message leaves a hole at its place in the FIFO,
        # so that its partner is dropped instead of being paired with the next one.
        if count and not self._stamped:
            queue.extend([HOLE] * min(count, self._queue_size))
        elif count:
            self.feeder.gap(count=False)

    def _input_values(self, message: Any) -> list[float]:
        r = self.num_inputs
        if isinstance(message, Float64):
            return [message.data]
        if isinstance(message, Float64MultiArray):
            values = list(message.data)
            if not values:
                raise ValueError('empty input message')
            if len(values) != r:
                raise ValueError(f'input has {len(values)} values; expected num_inputs = {r}')
            return values
        field = list(getattr(message, self.settings['input_field']))
        joints = self.settings['input_joints']
        if joints:
            names = list(message.name)
            try:
                return [field[names.index(joint)] for joint in joints]
            except (ValueError, IndexError):
                raise ValueError(f'input JointState lacks {self.settings["input_field"]} of '
                                 f'joints {joints} (has {names})') from None
        if len(field) < r:
            raise ValueError(f'input JointState has {len(field)} '
                             f'{self.settings["input_field"]} values; expected {r}')
        return field[:r]

    def _output_value(self, message: Any) -> float:
        if isinstance(message, Float64):
            return message.data
        field = list(getattr(message, self.settings['output_field']))
        joint = self.settings['output_joint']
        if joint:
            names = list(message.name)
            if joint not in names or names.index(joint) >= len(field):
                raise ValueError(f'output JointState lacks {self.settings["output_field"]} of '
                                 f'joint {joint!r} (has {names})')
            return field[names.index(joint)]
        if not field:
            raise ValueError(f'output JointState has no {self.settings["output_field"]} value')
        return field[0]

    def _enqueue(self, side: str, queue: collections.deque, message: Any, value: Any) -> None:
        if self._stamped:
            stamp = stamp_ns(message)
            last = self._last_stamp[side]
            if last is not None and stamp <= last:
                kind = 'duplicate' if stamp == last else 'out_of_order'
                self._bad(kind, f'{side} message with a {kind.replace("_", " ")} stamp '
                          f'dropped ({stamp * 1e-9:.9f} s after {last * 1e-9:.9f} s)')
                return
            self._last_stamp[side] = stamp
        else:
            stamp = None
        queue.append((stamp, value))
        if len(queue) > self._queue_size:
            queue.popleft()
            self._bad('unpaired', f'{side} queue over queue_size={self._queue_size}: oldest '
                      f'{side} sample dropped (is the other topic published?)')
            self.feeder.gap(count=False)
        self._pair()

    def _pair(self) -> None:
        inputs, outputs = self._inputs, self._outputs
        while inputs and outputs:
            if self._stamped:
                t_in, t_out = inputs[0][0], outputs[0][0]
                if abs(t_in - t_out) > self._tolerance_ns:
                    # The older head can never be paired: the other topic has moved past it.
                    side, queue = (('input', inputs) if t_in < t_out else ('output', outputs))
                    queue.popleft()
                    self._bad('unpaired', f'{side} sample without a partner within '
                              f'sync_tolerance dropped')
                    self.feeder.gap(count=False)
                    continue
                self._check_interval(t_out)
            u = inputs.popleft()[1]
            y = outputs.popleft()[1]
            if u is None or y is None:
                self.feeder.gap(count=False)
                continue
            self._feed(np.array([[y, *u]], dtype=float))

    def _check_interval(self, stamp: int) -> None:
        last = self._last_pair_ns
        self._last_pair_ns = stamp
        if last is None:
            return
        interval = stamp - last
        if not self._period_ns:
            self._intervals.append(interval)
            if len(self._intervals) >= PERIOD_LEARNING_INTERVALS:
                self._period_ns = statistics.median(self._intervals)
                self.get_logger().info(f'sample period learnt from the stamps: '
                                       f'{self._period_ns * 1e-9:.6g} s')
            return
        if interval > GAP_FACTOR * self._period_ns:
            self.feeder.gap(count=False)
            self._bad('gaps', f'gap of {interval * 1e-9:.6g} s in the stamps (period '
                      f'{self._period_ns * 1e-9:.6g} s): regressor restarted')

    # --------------------------------------------------------------- reset
    def on_reset(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        """Restart the estimator from its initial state (~/reset)."""
        used = self.estimator.samples
        self.feeder.reset()
        self._sequence.clear()
        self._inputs.clear()
        self._outputs.clear()
        self._last_pair_ns = None
        response.success = True
        response.message = f'estimator reset after {used} samples'
        self.get_logger().info(response.message)
        return response

    # --------------------------------------------------------- diagnostics
    def status(self) -> tuple[int, str, list[tuple[str, object]]]:
        """Return the /diagnostics status: level, message and key-value pairs."""
        estimator = self.estimator
        now = self.get_clock().now()
        elapsed = (now - self._last_time).nanoseconds * 1e-9
        self._last_time = now
        used = self.feeder.used
        rate = (used - self._last_used) / elapsed if elapsed > 0 else 0.0
        new_samples = used - self._last_used
        self._last_used = used
        updates, mean_us, max_us = self.feeder.take_update_times()
        flags = dict(estimator.flags)
        new_counts = {k: v - self._last_counts.get(k, 0) for k, v in self.counters.items()}
        self._last_counts = dict(self.counters)
        new_flags = {k: v - self._last_flags.get(k, 0) for k, v in flags.items()
                     if v != self._last_flags.get(k, 0)}
        self._last_flags = flags
        trace = estimator.covariance_trace

        problems = [COUNTERS[k] for k, v in new_counts.items()
                    if v and k not in ('estimator_errors', 'nonfinite_estimates')]
        if new_counts['estimator_errors'] or new_counts['nonfinite_estimates']:
            level = ERROR
            message = 'estimator failing: ' + ', '.join(
                COUNTERS[k] for k in ('estimator_errors', 'nonfinite_estimates')
                if new_counts[k])
        elif problems or new_flags or self.feeder.excitation_lost:
            level = WARN
            reasons = problems + [f'estimator flag {k}' for k in new_flags]
            if self.feeder.excitation_lost and COUNTERS['unexcited'] not in reasons:
                reasons.append('no excitation (input constant)')
            message = 'in the last period: ' + ', '.join(reasons)
        elif not new_samples:
            level = WARN
            message = 'no samples in the last period'
        elif not estimator.valid:
            level = OK
            message = f'filling the regressor ({estimator.samples} samples)'
        else:
            level = OK
            message = f'estimating at {rate:.0f} samples/s'
        values: list[tuple[str, object]] = [
            ('estimator', self.settings['estimator']),
            ('valid', bool(estimator.valid)),
            ('samples used', used),
            ('samples since reset', estimator.samples),
            ('samples dropped', sum(self.counters[k] for k in
                                    ('unpaired', 'lost', 'duplicate', 'out_of_order'))),
            ('bad samples', sum(self.counters[k] for k in
                                ('nonfinite', 'bad_layout', 'empty'))),
        ]
        values += [(COUNTERS[k], v) for k, v in self.counters.items()]
        values += [
            ('messages received', self.messages),
            ('estimates published', self.estimates_published),
            ('sample rate (1/s)', rate),
            ('updates in the last period', updates),
            ('update time mean (µs)', mean_us),
            ('update time max (µs)', max_us),
            ('covariance trace', trace if math.isfinite(trace) else 'n/a'),
            ('forgetting factor', estimator.forgetting_factor),
            ('publish period (samples)', self.publish_period),
        ]
        values += [(f'flag {k}', v) for k, v in sorted(flags.items())]
        if estimator.valid:
            values += [(f'noise {k}', float(v))
                       for k, v in zip(estimator.noise_names, estimator.noise)]
        return level, message, values


def main(argv: list[str] | None = None) -> int:
    """Run ``identifier_node`` until SIGINT or SIGTERM."""
    return run_node(IdentifierNode, argv, 'identifier_node',
                    help_text=usage('identifier_node', __doc__.strip().splitlines()[0],
                                    IDENTIFIER_PARAMETERS))


if __name__ == '__main__':
    raise SystemExit(main())
