"""Fixtures for the node tests: an rclpy Context on a domain of its own, and spin helpers."""

import itertools
import os
from pathlib import Path
import subprocess
import sys
import time

import pytest

#: The test domains: 101..232, above 0..100 where callers run their own graphs
#: (scripts/test.sh and .ci/run pick ROS_DOMAIN_ID in 1..100) and up to the highest
#: domain id DDS can map to ports. They are cut into SLICES slices of DOMAINS_PER_SUITE.
FIRST_TEST_DOMAIN, LAST_DOMAIN = 101, 232
DOMAINS_PER_SUITE = 4
SLICES = (LAST_DOMAIN + 1 - FIRST_TEST_DOMAIN) // DOMAINS_PER_SUITE


def _caller_domain():
    """Return the ROS_DOMAIN_ID the suite was started with (from the pid if it is unset)."""
    text = os.environ.get('ROS_DOMAIN_ID', '').strip()
    if not text:
        return os.getpid() % SLICES
    if not text.isdigit() or int(text) > LAST_DOMAIN:
        raise ValueError(f'ROS_DOMAIN_ID must be an integer in [0, {LAST_DOMAIN}], got {text!r}')
    return int(text)


def _worker():
    """Return this pytest-xdist worker's number and the workers' count ((0, 1): no xdist)."""
    name = os.environ.get('PYTEST_XDIST_WORKER', '')
    if not name.startswith('gw'):
        return 0, 1
    return int(name[2:]), int(os.environ.get('PYTEST_XDIST_WORKER_COUNT', '1'))


def suite_domains(caller, worker=0, workers=1):
    """
    Return the test domains of a suite started on domain ``caller`` (a range).

    Worker w of a run spread over ``workers`` (pytest-xdist) takes the w-th
    slice after the caller's, so that the graphs of tests running at once in
    two workers never meet.
    """
    for shift in (0, workers):  # a caller inside the band never gets its own domain
        first = FIRST_TEST_DOMAIN + (caller + worker + shift) % SLICES * DOMAINS_PER_SUITE
        domains = range(first, first + DOMAINS_PER_SUITE)
        if caller not in domains:
            return domains


# read once, at collection: a test that sets ROS_DOMAIN_ID for its children moves nothing
_SUITE_DOMAINS = suite_domains(_caller_domain(), *_worker())
_sequence = itertools.count()

#: The test folder: every test module lives in a folder below it that says its kind.
TEST_DIR = Path(__file__).resolve().parent

#: The folders and the marker each gives its tests (the folder's name). ``-m`` selects
#: by kind: ``scripts/test.sh --fast`` leaves out ros, statistical, papers and slow.
KINDS = ('estimators', 'simulation', 'identifier', 'bag', 'control', 'analysis', 'nodes',
         'cli', 'equivalence', 'statistical', 'papers', 'ros', 'lint')

#: Test modules that read data made on another machine (committed bags, saved
#: references), as paths below test/. `.ci/run` runs them a second time with numpy's
#: highest SIMD targets disabled, so a test that depends on the CPU fails on any machine.
RECORDED_DATA_MODULES = {'bag/test_bag.py', 'ros/test_bag_ros.py',
                         'equivalence/test_bciv_speed_equivalence.py'}


def pytest_configure(config):
    """Refuse a RECORDED_DATA_MODULES entry that names no file (a moved test)."""
    missing = sorted(name for name in RECORDED_DATA_MODULES if not (TEST_DIR / name).is_file())
    if missing:
        raise pytest.UsageError(f'RECORDED_DATA_MODULES in test/conftest.py names no file: '
                                f'{missing}')


def kind_of(path):
    """
    Return the kind of a test module: the folder below test/ that holds it.

    Raises
    ------
    pytest.UsageError
        For a module directly in test/ or in a folder that is not one of :data:`KINDS`.

    """
    parts = Path(path).resolve().relative_to(TEST_DIR).parts
    if len(parts) < 2 or parts[0] not in KINDS:
        raise pytest.UsageError(f'{path}: a test module lives in one of the folders '
                                f'test/{{{",".join(KINDS)}}}/')
    return parts[0]


def pytest_collection_modifyitems(config, items):
    """
    Mark each test with its folder's kind, and ``recorded_data`` where it reads such data.

    A test marked ``ros`` (it starts a ROS graph) outside test/ros/ is refused, so
    that ``-m "not ros"`` and the folder agree.
    """
    for item in items:
        kind = kind_of(item.path)
        item.add_marker(getattr(pytest.mark, kind))
        if kind != 'ros' and item.get_closest_marker('ros') is not None:
            raise pytest.UsageError(f'{item.nodeid} starts a ROS graph (marker ros): move '
                                    'its module to test/ros/')
        if item.path.resolve().relative_to(TEST_DIR).as_posix() in RECORDED_DATA_MODULES:
            item.add_marker(pytest.mark.recorded_data)
    if os.environ.get('PYTEST_XDIST_WORKER'):
        # spread over workers (scripts/test.sh), the long tests go first: started last, one
        # of 30-90 s keeps the run waiting on one worker while the others are idle
        items.sort(key=lambda item: not (item.get_closest_marker('slow')
                                         or item.get_closest_marker('statistical')))


def run_demo(arguments, out_dir, timeout):
    """Run ``bcid demo`` with ``arguments`` on a fresh domain, its files in ``out_dir``."""
    env = dict(os.environ, ROS_DOMAIN_ID=str(fresh_domain_id()),
               ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    return subprocess.run([sys.executable, '-m', 'bcid_ros.cli', 'demo', *arguments,
                           '--out-dir', str(out_dir)],
                          capture_output=True, text=True, env=env, timeout=timeout)


def fresh_domain_id():
    """
    Return a ROS domain id for one test: the next of its suite's slice, in turn.

    The slice (:func:`suite_domains`) follows from the ROS_DOMAIN_ID the
    suite was started with, read once at collection, and from its xdist
    worker. Suites run at once on one machine with ROS_DOMAIN_IDs in 0..100
    whose slices differ modulo :data:`SLICES` (33) never share a domain: a
    suite over W workers takes W slices from its ROS_DOMAIN_ID on, so give
    concurrent runs ROS_DOMAIN_IDs at least W apart modulo 33 (one process:
    21 and 61..64 are). The test domains lie in 101..232 and never on the caller's own
    domain, so a graph the caller runs on its ROS_DOMAIN_ID is not crossed
    either. Without ROS_DOMAIN_ID the slice follows from the pid. Consecutive
    calls cycle through the slice's :data:`DOMAINS_PER_SUITE` domains: a test
    may use up to four at once, and a domain comes back only after three
    other tests.
    """
    return _SUITE_DOMAINS[next(_sequence) % DOMAINS_PER_SUITE]


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
