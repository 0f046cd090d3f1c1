"""
The adaptive controller node in an executor, with a fake identifier and a plant loop in the test.

The fake identifier publishes latched estimates, like the identifier node;
the plant 0.5/(q - 0.8) runs here, one output at a time, holding the last
input it received (the input computed from y_t is applied at t + 1).
"""

import math
import os
from pathlib import Path
import subprocess
import sys

import numpy as np
import pytest

from conftest import fresh_domain_id, spin_until

rclpy = pytest.importorskip('rclpy')

from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from std_msgs.msg import (Bool, Float64, Float64MultiArray,  # noqa: E402
                          MultiArrayDimension)

from bcid_ros.control import AdaptiveController, closed_loop_poles, Controller  # noqa: E402
from bcid_ros.control.design import ModelStructure, Plant  # noqa: E402
from bcid_ros.control.parameters import CONTROLLER_PARAMETERS  # noqa: E402
from bcid_ros.identifier.parameters import load_yaml_parameters  # noqa: E402
from bcid_ros.nodes.adaptive_controller_node import AdaptiveControllerNode  # noqa: E402
from bcid_ros.nodes.common import LATCHED_QOS, SAMPLES_QOS  # noqa: E402

pytestmark = pytest.mark.ros

ROOT = Path(__file__).resolve().parents[2]
TRUE_THETA = [-0.8, 0.5]
NAMES = ['a1', 'b1_1']
SETTINGS = dict(identifier='/fake_identifier', order=1, closed_loop_poles=[0.5, 0.5],
                fallback_numerator=[0.2289], fallback_denominator=[1.0, -0.09004],
                input_limit=5.0, redesign_period=0.05, max_relative_std=0.1,
                reference_signal='square', reference_amplitude=0.5, reference_period=16)
DEEP_LATCHED = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.TRANSIENT_LOCAL)


def estimate(names, values):
    """Return an estimate message with the names in its label."""
    message = Float64MultiArray()
    message.layout.dim = [MultiArrayDimension(label=','.join(names), size=len(names),
                                              stride=len(names))]
    message.data = [float(v) for v in values]
    return message


class Harness:
    """The controller node, a fake identifier and the plant, on one executor."""

    def __init__(self, context, executor, **changes):
        values = dict(SETTINGS, **changes)
        self.controller = AdaptiveControllerNode(
            context=context,
            parameter_overrides=[Parameter(k, value=v) for k, v in values.items()])
        self.offline = AdaptiveController(values)  # the same loop, without ROS
        self.node = rclpy.create_node('fake_plant_and_identifier', context=context)
        self.executor = executor
        executor.add_node(self.controller)
        executor.add_node(self.node)
        node = self.node
        self.output = node.create_publisher(Float64, 'output', SAMPLES_QOS)
        self.reference = node.create_publisher(Float64, 'reference', SAMPLES_QOS)
        self.parameters = node.create_publisher(Float64MultiArray, '/fake_identifier/parameters',
                                                LATCHED_QOS)
        self.std = node.create_publisher(Float64MultiArray, '/fake_identifier/parameter_std',
                                         LATCHED_QOS)
        self.valid = node.create_publisher(Bool, '/fake_identifier/valid', LATCHED_QOS)
        self.inputs, self.controllers, self.diagnostics = [], [], []
        node.create_subscription(Float64, 'input', lambda m: self.inputs.append(m.data),
                                 SAMPLES_QOS)
        node.create_subscription(Float64MultiArray, '/bcid_controller/controller',
                                 self.controllers.append, DEEP_LATCHED)
        node.create_subscription(DiagnosticArray, '/diagnostics',
                                 lambda m: self.diagnostics.extend(m.status), 100)
        self.y_state = 0.0
        self.applied = 0.0
        self.ys = []
        assert spin_until(executor, lambda: self.output.get_subscription_count() == 1
                          and self.controllers)

    def run_plant(self, samples, bad_outputs=()):
        """Run the plant loop; an index in ``bad_outputs`` sends NaN instead of y."""
        for t in range(samples):
            # y_t = 0.8 y_(t-1) + 0.5 u_(t-1); u_t is the input computed from y_(t-1)
            y = self.y_state
            sent = math.nan if t in bad_outputs else y
            count = len(self.inputs)
            self.output.publish(Float64(data=sent))
            assert spin_until(self.executor, lambda: len(self.inputs) > count, timeout=5.0)
            assert len(self.inputs) == count + 1  # one input per output
            self.ys.append(sent)
            self.y_state = 0.8 * y + 0.5 * self.applied
            self.applied = self.inputs[-1]

    def publish_estimate(self, names, values, std, valid):
        """Publish a latched estimate (std, valid, then parameters)."""
        self.std.publish(estimate(names, std))
        self.valid.publish(Bool(data=valid))
        self.parameters.publish(estimate(names, values))

    def wait_for(self, predicate, timeout=10.0):
        """Spin until ``predicate()``; fail the test if it never holds."""
        assert spin_until(self.executor, predicate, timeout=timeout)

    def counter(self, key):
        """Return the latest diagnostic value of ``key`` (None if no diagnostics yet)."""
        for status in reversed(self.diagnostics):
            if status.name == 'bcid_controller: controller':
                return {v.key: v.value for v in status.values}.get(key)
        return None


def published(message):
    """Return (numerator, denominator) of a ``~/controller`` message."""
    sizes = [d.size for d in message.layout.dim]
    assert [d.label for d in message.layout.dim] == ['numerator', 'denominator']
    data = list(message.data)
    return data[:sizes[0]], data[sizes[0]:sizes[0] + sizes[1]]


def test_fallback_then_trusted_redesign_latched_and_safe_on_bad_input(ros_context, executor):
    h = Harness(ros_context, executor)
    loop = h.controller.loop
    # --- fallback until a trusted estimate; the controller is latched from the start
    assert published(h.controllers[0]) == ([0.2289], [1.0, -0.09004])
    h.run_plant(30)
    # the node does no numerics of its own: the offline loop on the same outputs agrees
    np.testing.assert_array_equal(h.inputs, [h.offline.step(y) for y in h.ys])
    # an estimate the identifier calls not valid is refused and counted
    h.publish_estimate(NAMES, TRUE_THETA, [0.001, 0.001], False)
    h.wait_for(lambda: loop.counters['not_valid'] >= 1)
    h.run_plant(10)
    assert not loop.trusted and len(h.controllers) == 1

    # --- the true parameters, valid: redesign, published (latched), poles on target
    h.publish_estimate(NAMES, TRUE_THETA, [0.001, 0.001], True)
    h.wait_for(lambda: len(h.controllers) == 2)
    numerator, denominator = published(h.controllers[1])
    controller = Controller.from_coefficients(numerator, denominator)
    poles = closed_loop_poles(Plant.from_estimate(TRUE_THETA, ModelStructure(1)), controller)
    np.testing.assert_allclose(np.sort(poles.real), [0.5, 0.5], atol=1e-6)
    assert np.all(np.abs(poles.imag) < 1e-6)
    assert loop.trusted and loop.counters['redesigns'] == 1
    late = rclpy.create_node('late_joiner', context=ros_context)
    executor.add_node(late)
    received = []
    late.create_subscription(Float64MultiArray, '/bcid_controller/controller',
                             received.append, LATCHED_QOS)
    h.wait_for(lambda: received)
    assert published(received[0]) == (numerator, denominator)
    h.run_plant(40)

    # --- bad input: a NaN reference, NaN outputs, wrong names, wrong order
    h.reference.publish(Float64(data=math.nan))
    h.wait_for(lambda: loop.counters['nonfinite_reference'] == 1)
    h.run_plant(10, bad_outputs={3, 4})
    assert loop.counters['nonfinite_output'] == 2
    h.publish_estimate(['x1', 'b1_1'], TRUE_THETA, [0.001, 0.001], True)
    h.wait_for(lambda: loop.counters['bad_names'] >= 1)
    h.run_plant(5)
    h.publish_estimate(['a1', 'a2', 'b1_1', 'b1_2'], [-0.8, 0.0, 0.5, 0.0], [0.001] * 4, True)
    h.wait_for(lambda: loop.counters['wrong_order'] >= 1)
    h.run_plant(5)
    assert len(h.controllers) == 2  # still the designed controller
    assert all(math.isfinite(u) and abs(u) <= 5.0 for u in h.inputs)

    # --- the counters reach /diagnostics
    def diagnosed():
        return all(h.counter(key) not in (None, '0') for key in (
            'refused: estimate not valid', 'refused: names not a1..an,b1_<lag>',
            'refused: order/lags differ from the configuration',
            'refused references: NaN or Inf (last kept)',
            'refused outputs: NaN or Inf (input held)', 'redesigns (controller switched)'))
    h.wait_for(diagnosed, timeout=5.0)
    assert h.counter('controller') == 'designed'
    assert h.counter('poles with the latest estimate')  # text, present
    assert float(h.counter('rate (outputs/s)')) >= 0.0


def test_the_identifier_going_away_is_counted_and_the_controller_kept(ros_context, executor):
    h = Harness(ros_context, executor)
    loop = h.controller.loop
    h.publish_estimate(NAMES, TRUE_THETA, [0.001, 0.001], True)
    h.wait_for(lambda: len(h.controllers) == 2)
    for publisher in (h.parameters, h.std, h.valid):
        h.node.destroy_publisher(publisher)
    h.wait_for(lambda: loop.counters['identifier_lost'] == 1)
    h.run_plant(5)
    assert loop.trusted and len(h.controllers) == 2


def test_the_config_file_starts_the_node(ros_context, executor):
    values = load_yaml_parameters(ROOT / 'config' / 'adaptive_loop.yaml', 'bcid_controller',
                                  {spec.name for spec in CONTROLLER_PARAMETERS})
    node = AdaptiveControllerNode(
        context=ros_context, parameter_overrides=[Parameter(k, value=v)
                                                  for k, v in values.items()])
    executor.add_node(node)
    assert node.loop.settings['closed_loop_poles'] == [0.4, 0.6]
    # the design the file asks for: C = 0.16/(q - 0.2) on the true plant
    node.loop.offer_parameters(NAMES, TRUE_THETA, 0.0)
    node.loop.offer_std(NAMES, [0.001, 0.001])
    node.loop.offer_valid(True)
    assert node.loop.redesign(0.0).kind == 'switched'
    # the closed form from a solve of 2 unknowns: its condition number times 2 x 2 eps
    bound = 4 * 2 * node.loop.controller.condition * np.finfo(float).eps
    np.testing.assert_allclose(node.loop.controller.numerator, [0.16], rtol=bound, atol=0)
    np.testing.assert_allclose(node.loop.controller.denominator, [1.0, -0.2], rtol=bound,
                               atol=0)


def test_bad_parameters_stop_the_node_with_a_clear_message():
    environment = dict(os.environ, ROS_DOMAIN_ID=str(fresh_domain_id()),
                       ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    command = [sys.executable, '-m', 'bcid_ros.nodes.adaptive_controller_node', '--ros-args',
               '-p', 'order:=1', '-p', 'closed_loop_poles:=[0.5]']
    result = subprocess.run(command, capture_output=True, text=True, timeout=60,
                            env=environment)
    assert result.returncode == 2
    assert "parameter 'closed_loop_poles' must be at least 2" in result.stderr
    result = subprocess.run(command[:3] + ['--help'], capture_output=True, text=True,
                            timeout=60, env=environment)
    assert result.returncode == 0 and 'closed_loop_poles' in result.stdout


def test_the_entry_point_is_declared():
    assert "'adaptive_controller_node = bcid_ros.entry_points:adaptive_controller_node'" in \
        (ROOT / 'setup.py').read_text()
