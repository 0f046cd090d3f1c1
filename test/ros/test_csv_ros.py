"""A CSV log imported with ``bcid import`` and played into identifier_node: the CSV replay."""

import os
from pathlib import Path
import subprocess
import sys
import time

from conftest import fresh_domain_id
import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')

from rclpy.context import Context  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from std_msgs.msg import Float64MultiArray  # noqa: E402

from bcid_ros.bag.csv_samples import read_csv_samples, write_samples_bag  # noqa: E402
from bcid_ros.bag.replay import replay  # noqa: E402
from bcid_ros.simulation import make_scenario  # noqa: E402


@pytest.mark.ros
@pytest.mark.slow
def test_the_imported_bag_played_into_identifier_node_gives_the_csv_replay(tmp_path):
    y, u = make_scenario('ding_miso').simulate(1000, seed=8)
    lines = [','.join(repr(float(v)) for v in row) for row in np.column_stack([y, u])]
    lines[400] = lines[400].rsplit(',', 2)[0] + ',,' + lines[400].rsplit(',', 1)[1]
    # an empty u1 in row 400: a gap, the node skips the NaN sample as the replay does
    path = tmp_path / 'log.csv'
    path.write_text('\n'.join(['y,u1,u2'] + lines) + '\n')
    offline = replay(read_csv_samples(path), {'estimator': 'rls', 'order': 2, 'num_inputs': 2})
    bag = write_samples_bag(read_csv_samples(path, rate_hz=1000.0), tmp_path / 'bag')
    domain = fresh_domain_id()
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain),
               ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    context = Context()
    rclpy.init(context=context, domain_id=domain)
    node = rclpy.create_node('csv_test', context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    received = []
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    node.create_subscription(Float64MultiArray, '/bcid_identifier/parameters',
                             lambda message: received.append(np.array(message.data)), latched)
    bin_dir = Path(sys.executable).parent
    identifier = subprocess.Popen(
        [str(bin_dir / 'identifier_node'), '--ros-args', '-p', 'estimator:=rls',
         '-p', 'order:=2', '-p', 'num_inputs:=2'], env=env, stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE, text=True)
    try:
        play = subprocess.run([str(bin_dir / 'bcid'), 'play', str(bag),
                               '--wait-for-subscribers', '30'], env=env, capture_output=True,
                              text=True, timeout=120)
        assert play.returncode == 0, play.stderr
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and not (
                received and np.array_equal(received[-1], offline.theta)):
            executor.spin_once(timeout_sec=0.02)
    finally:
        identifier.terminate()
        identifier.wait(timeout=10)
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=context)
    assert received, identifier.stderr.read()[-2000:]
    assert offline.nonfinite == 1
    # the node's per-message rule on the same messages: the same bits
    np.testing.assert_array_equal(received[-1], offline.theta)
