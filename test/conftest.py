"""Fixtures for the node tests: an rclpy Context on a domain of its own, and spin helpers."""

import itertools
import os
import time

import pytest

_domains = itertools.count()

#: Test modules that read data made on another machine (committed bags, saved
#: references). `.ci/run` runs them a second time with numpy's highest SIMD
#: targets disabled, so a test that depends on the CPU fails on any machine.
RECORDED_DATA_MODULES = {'test_bag.py', 'test_bag_ros.py', 'test_bciv_speed_equivalence.py'}


def pytest_collection_modifyitems(config, items):
    """Mark the tests of :data:`RECORDED_DATA_MODULES` as ``recorded_data``."""
    for item in items:
        if item.path.name in RECORDED_DATA_MODULES:
            item.add_marker(pytest.mark.recorded_data)


def fresh_domain_id():
    """Return a ROS domain id for one test, apart from scripts/test.sh's 1..100."""
    return 130 + (os.getpid() * 7 + next(_domains)) % 100


@pytest.fixture
def ros_context():
    """Yield an initialised rclpy Context on a fresh domain, shut down afterwards."""
    rclpy = pytest.importorskip('rclpy')
    from rclpy.context import Context

    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    context = Context()
    rclpy.init(context=context, domain_id=fresh_domain_id())
    try:
        yield context
    finally:
        rclpy.try_shutdown(context=context)


@pytest.fixture
def executor(ros_context):
    """Yield a single-threaded executor on the test's context; its nodes are destroyed after."""
    from rclpy.executors import SingleThreadedExecutor

    executor = SingleThreadedExecutor(context=ros_context)
    try:
        yield executor
    finally:
        for node in list(executor.get_nodes()):
            executor.remove_node(node)
            node.destroy_node()
        executor.shutdown()


def spin_until(executor, predicate, timeout=20.0):
    """Spin ``executor`` until ``predicate()`` is true; return whether it became true."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        executor.spin_once(timeout_sec=0.01)
    return predicate()
