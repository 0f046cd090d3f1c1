"""
rpem in the identifier node and in ``bcid replay``: the same estimates, bit for bit.

The node does no numerics of its own: what it publishes for rpem (estimate,
std, validity, operating point, the ARMAX c's in the label) is compared with
the estimator run offline over the same samples. ``bcid replay`` shares the
node's feeder; it is compared with the estimator run on the bag's samples.
"""

from pathlib import Path

import numpy as np
import pytest

from conftest import spin_until

from bcid_ros.bag.reader import BagReader
from bcid_ros.bag.replay import replay
from bcid_ros.identifier.parameters import estimator_from_parameters
from bcid_ros.parameter_spec import load_yaml_parameters
from bcid_ros.identifier.layouts import decode_samples
from bcid_ros.simulation.custom import CustomScenario

REPO = Path(__file__).resolve().parents[2]
PLANT = CustomScenario(plant_denominator=[1.0, -1.5, 0.7], plant_numerator=[0, 1.0, 0.5],
                       noise_variance=0.5, input_delay=1, input_offset=2.0, output_offset=5.0)


def bag_rows(path):
    """Return the samples of a bag as rows ``[y, u1, ..., ur]``."""
    return np.vstack([decode_samples(m) for _, _, m in BagReader(path).decoded(['/samples'])])


@pytest.mark.parametrize('model', ['oe', 'armax'])
def test_replay_equals_the_estimator_run_on_the_bag(model):
    path = REPO / 'bags' / 'ding_miso'
    values = dict(load_yaml_parameters(REPO / 'config' / 'ding_miso.yaml'), model=model)
    result = replay(path, values, estimator='rpem')
    rows = bag_rows(path)
    estimator = estimator_from_parameters({**values, 'estimator': 'rpem'})
    direct = estimator.run(rows[:, 0], rows[:, 1:])
    np.testing.assert_array_equal(result.theta, direct.final)
    np.testing.assert_array_equal(result.theta_uncompensated, direct.theta_uncompensated[-1])
    assert result.theta_trajectory.shape[0] == int(direct.ready.sum())
    np.testing.assert_array_equal(result.theta_trajectory, direct.theta[direct.ready])


@pytest.mark.ros
@pytest.mark.parametrize('model', ['oe', 'armax'])
def test_node_publishes_what_the_estimator_computes(ros_context, executor, model):
    rclpy = pytest.importorskip('rclpy')
    from rclpy.parameter import Parameter
    from std_msgs.msg import Bool, Float64MultiArray

    from bcid_ros.nodes.common import LATCHED_QOS
    from bcid_ros.nodes.identifier_node import IdentifierNode
    from bcid_ros.nodes.messages import samples_message

    values = {'estimator': 'rpem', 'model': model, 'order': 2, 'input_delay': 1,
              'detrend': 'mean', 'outlier_threshold': 5.0}
    node = IdentifierNode(context=ros_context, parameter_overrides=[
        Parameter(name, value=value) for name, value in values.items()])
    received = {}
    listener = rclpy.create_node('listener', context=ros_context)
    for topic, kind in (('parameters', Float64MultiArray), ('parameter_std', Float64MultiArray),
                        ('operating_point', Float64MultiArray), ('valid', Bool)):
        listener.create_subscription(
            kind, f'/bcid_identifier/{topic}',
            lambda message, topic=topic: received.__setitem__(topic, message), LATCHED_QOS)
    executor.add_node(node)
    executor.add_node(listener)
    y, u = PLANT.simulate(2500, 13)
    rows = np.column_stack([y, u])
    for start in range(0, 2500, 250):  # frames of 250 samples
        node.on_samples(samples_message(rows[start:start + 250]), {})
    reference = estimator_from_parameters(values)
    reference.run(y, u)
    assert spin_until(executor, lambda: len(received) == 4, timeout=10)
    names = 'a1,a2,b1_2,b1_3' + (',c1,c2' if model == 'armax' else '')
    assert received['parameters'].layout.dim[0].label == names
    np.testing.assert_array_equal(received['parameters'].data, reference.theta)
    np.testing.assert_array_equal(received['parameter_std'].data, reference.parameter_std)
    np.testing.assert_array_equal(received['operating_point'].data, reference.operating_point)
    assert received['valid'].data == reference.valid
    np.testing.assert_allclose(reference.operating_point, [5.0, 2.0], atol=0.5)
