"""
The identifier's diagnostics, composed of tasks: each task on its own, then all of them.

The tasks read plain objects, so fakes stand in for the feeder, the
estimator and the clock; no ROS graph is needed.
"""

from types import SimpleNamespace

import pytest

pytest.importorskip('diagnostic_msgs')

from bcid_ros.identifier.interface import COUNTERS, DiagnosticKey  # noqa: E402
from bcid_ros.nodes.diagnostics import (CounterTask, ERROR, EstimatorTask, OK,  # noqa: E402
                                        SampleRateTask, Status, WARN)


class FakeFeeder:
    """The feeder's totals and update times."""

    def __init__(self):
        self.used = 0
        self.excitation_lost = False

    def take_update_times(self):
        """Return (updates, mean us, max us)."""
        return 3, 10.0, 20.0


class FakeEstimator:
    """What EstimatorTask reads."""

    def __init__(self):
        self.flags = {}
        self.valid = False
        self.ready = False
        self.validity_reasons = ()
        self.samples = 2
        self.covariance_trace = float('inf')
        self.forgetting_factor = 1.0
        self.noise_names = ('sigma2',)
        self.noise = [0.01]


def run(*tasks):
    """Return the status the tasks compose."""
    status = Status()
    for task in tasks:
        task(status)
    return status


def test_merge_summary_keeps_the_worst_and_joins_problems():
    status = Status()
    status.merge_summary(OK, 'first ok')
    status.merge_summary(OK, 'second ok')
    assert (status.level, status.message) == (OK, 'first ok')
    status.merge_summary(WARN, 'a')
    status.merge_summary(WARN, 'b')
    status.merge_summary(OK, 'later ok')
    assert (status.level, status.message) == (WARN, 'a; b')
    status.merge_summary(ERROR, 'c')
    assert (status.level, status.message) == (ERROR, 'c')


def test_counter_task_warns_on_new_counts_only_and_errors_on_failures():
    counters = dict.fromkeys(COUNTERS, 0)
    excitation = SimpleNamespace(lost=False)
    task = CounterTask(counters, lambda: excitation.lost)
    assert run(task).level == OK
    counters['nonfinite'] += 2
    counters['lost'] += 1
    status = run(task)
    assert status.level == WARN
    assert status.message == ('in the last period: ' + COUNTERS['nonfinite'] + ', '
                              + COUNTERS['lost'])
    values = status.as_dict()
    assert values[DiagnosticKey.BAD_SAMPLES] == 2 and values[DiagnosticKey.SAMPLES_DROPPED] == 1
    assert values[COUNTERS['nonfinite']] == 2
    assert run(task).level == OK                      # nothing new since
    excitation.lost = True
    assert run(task).message == 'in the last period: no excitation (input constant)'
    counters['estimator_errors'] += 1
    status = run(task)
    assert (status.level, status.message) == (ERROR, 'estimator failing: estimator errors')


def test_estimator_task_warns_on_raised_flags_and_says_when_filling():
    estimator = FakeEstimator()
    task = EstimatorTask('bcrls', estimator, lambda: 5)
    status = run(task)
    assert (status.level, status.message) == (OK, 'filling the regressor (2 samples)')
    assert status.as_dict()[DiagnosticKey.COVARIANCE_TRACE] == 'n/a'
    assert DiagnosticKey.NOISE + 'sigma2' not in status.as_dict()
    estimator.valid = estimator.ready = True
    estimator.flags = {'windup_limited': 1}
    status = run(task)
    assert (status.level, status.message) == (WARN, 'estimator flags in the last period: '
                                                    'windup_limited')
    values = status.as_dict()
    assert values[DiagnosticKey.FLAG + 'windup_limited'] == 1
    assert values[DiagnosticKey.NOISE + 'sigma2'] == 0.01
    assert values[DiagnosticKey.PUBLISH_PERIOD] == 5
    status = run(task)
    assert (status.level, status.message) == (OK, '')
    # a routine event is counted, not warned about
    estimator.flags = {'windup_limited': 1, 'returned_to_fit': 3}
    status = run(task)
    assert (status.level, status.message) == (OK, '')
    assert status.as_dict()[DiagnosticKey.FLAG + 'returned_to_fit'] == 3


def test_rate_task_measures_over_the_period_and_warns_without_samples():
    feeder = FakeFeeder()
    clock = SimpleNamespace(now=10.0)
    task = SampleRateTask(feeder, lambda: clock.now,
                          SimpleNamespace(messages=7, estimates_published=4))
    clock.now, feeder.used = 12.0, 500
    status = run(task)
    assert (status.level, status.message) == (OK, 'estimating at 250 samples/s')
    values = status.as_dict()
    assert values[DiagnosticKey.SAMPLE_RATE] == 250.0 and values[DiagnosticKey.UPDATES] == 3
    assert values[DiagnosticKey.MESSAGES] == 7
    clock.now = 13.0
    status = run(task)
    assert (status.level, status.message) == (WARN, 'no samples in the last period')


def test_the_tasks_together_give_every_documented_key():
    feeder, estimator = FakeFeeder(), FakeEstimator()
    estimator.valid = estimator.ready = True
    rate = SampleRateTask(feeder, iter([0.0, 1.0]).__next__,
                          SimpleNamespace(messages=1, estimates_published=0))
    feeder.used = 100
    from bcid_ros.nodes.sample_topics import StalenessWatch

    clock = SimpleNamespace(now=lambda: SimpleNamespace(nanoseconds=5 * 10 ** 9))
    staleness = StalenessWatch(SimpleNamespace(get_clock=lambda: clock), 0.0, lambda: None)
    status = run(EstimatorTask('rls', estimator, lambda: 1),
                 CounterTask(dict.fromkeys(COUNTERS, 0), lambda: False), rate, staleness)
    # prefixes, and a key only while there is a reason or a refused publisher
    keys = {value for name, value in vars(DiagnosticKey).items()
            if name.isupper() and name not in ('FLAG', 'NOISE', 'NOT_VALID_BECAUSE',
                                               'INCOMPATIBLE_QOS')}
    assert keys | set(COUNTERS.values()) <= set(status.as_dict())
    # A valid estimator at a steady rate: OK, and the rate task's message.
    assert (status.level, status.message) == (OK, 'estimating at 100 samples/s')


def test_a_ready_estimate_that_is_not_valid_says_why():
    estimator = FakeEstimator()
    estimator.ready = True
    estimator.validity_reasons = ('unstable model (pole radius 1.3) on bounded data',)
    status = run(EstimatorTask('bcrls', estimator, lambda: 1))
    assert status.level == WARN and 'unstable model' in status.message
    assert status.as_dict()[DiagnosticKey.NOT_VALID_BECAUSE] == estimator.validity_reasons[0]


def test_an_incompatible_publisher_is_named_until_messages_come():
    from rclpy.qos import QoSPolicyKind

    from bcid_ros.nodes.sample_topics import IncompatibleQoS

    warnings = []
    node = SimpleNamespace(get_logger=lambda: SimpleNamespace(warning=warnings.append))
    messages = [0]
    qos = IncompatibleQoS(node, lambda: messages[0])
    assert run(qos).level == OK
    qos.on_incompatible('/robot1/joint_states', SimpleNamespace(
        total_count=2, last_policy_kind=QoSPolicyKind.RELIABILITY))
    assert warnings and 'qos_overrides./robot1/joint_states.subscription.reliability' in \
        warnings[0]
    status = run(qos)
    assert status.level == WARN
    assert status.message == ('incompatible QoS on /robot1/joint_states (reliability): set '
                              'qos_overrides./robot1/joint_states.subscription.reliability')
    assert status.as_dict()['incompatible QoS /robot1/joint_states'] == \
        '2 publisher(s), reliability'
    messages[0] = 1  # samples come (a compatible publisher): the count stays, the warning goes
    status = run(qos)
    assert status.level == OK and 'incompatible QoS /robot1/joint_states' in status.as_dict()
