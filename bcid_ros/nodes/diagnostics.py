"""
A small stand-in for diagnostic_updater, which is not in the PyPI wheels.

As in diagnostic_updater, a status is composed of tasks: each task is a
callable that adds its key-value pairs to a :class:`Status` and merges its
level and message into it (:meth:`Status.merge_summary`). A
:class:`DiagnosticsUpdater` runs its tasks on a timer of the node's clock
(so ``use_sim_time`` works) and publishes one
``diagnostic_msgs/DiagnosticStatus`` on ``/diagnostics``.

The identifier's three tasks follow: :class:`SampleRateTask`,
:class:`CounterTask` and :class:`EstimatorTask`. Their keys are the
constants of :mod:`bcid_ros.identifier.interface`.
"""

from __future__ import annotations

import math
from typing import Any, Callable, Sequence

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node
from rclpy.qos import QoSProfile

from bcid_ros.identifier.interface import (BAD, COUNTERS, DiagnosticKey as Key, DIAGNOSTICS,
                                           DROPPED, FAILING)

#: Levels, as integers (``DiagnosticStatus`` holds them as one byte).
OK, WARN, ERROR = 0, 1, 2

#: /diagnostics QoS: the ROS default (reliable, volatile, depth 10).
DIAGNOSTICS_QOS = QoSProfile(depth=10)


#: Flags that count a routine event, not a problem: /diagnostics shows their counts but does
#: not warn when they rise (rpem's return to its fit comes, by design, after up to 5 % of its
#: fits where the recursion keeps to the fit, more where it walks away: docs/estimators.md,
#: "Back to the fit").
ROUTINE_FLAGS = frozenset({'returned_to_fit'})


def format_value(value: object) -> str:
    """Return a diagnostic value as text: floats with 6 significant digits."""
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, float):
        return f'{value:.6g}'
    return str(value)


class Status:
    """The status being composed: level, message and values (diagnostic_updater's wrapper)."""

    def __init__(self) -> None:
        self.level = OK
        self.message = ''
        self.values: list[tuple[str, object]] = []

    def add(self, key: str, value: object) -> None:
        """Add one key-value pair."""
        self.values.append((key, value))

    def merge_summary(self, level: int, message: str) -> None:
        """
        Merge a task's level and message into the status.

        A higher level replaces the message; at the same level a problem's
        message is appended and an OK one kept only if there is none yet.
        """
        if not message:
            self.level = max(self.level, level)
        elif level > self.level:
            self.level, self.message = level, message
        elif level == self.level and (level > OK or not self.message):
            self.message = f'{self.message}; {message}' if self.message else message

    def as_dict(self) -> dict[str, object]:
        """Return the values as a dict."""
        return dict(self.values)


#: A task adds its values and its summary to a status.
Task = Callable[[Status], None]


class DiagnosticsUpdater:
    """
    Publish the status composed by ``tasks`` on /diagnostics every ``period`` seconds.

    Parameters
    ----------
    node : rclpy.node.Node
        The owning node; its clock stamps the messages and drives the timer.
    name : str
        ``DiagnosticStatus.name``, e.g. ``'bcid_identifier: identifier'``.
    tasks : sequence of callable
        Run in order on a fresh :class:`Status` for every message.
    period : float
        Seconds between messages.
    hardware_id : str
        ``DiagnosticStatus.hardware_id``.

    """

    def __init__(self, node: Node, name: str, tasks: Sequence[Task], *,
                 period: float = 1.0, hardware_id: str = '') -> None:
        self._node = node
        self.name = name
        self.tasks = list(tasks)
        self._hardware_id = hardware_id
        self.publisher = node.create_publisher(DiagnosticArray, DIAGNOSTICS, DIAGNOSTICS_QOS)
        self.timer = node.create_timer(period, self.publish)

    def status(self) -> Status:
        """Run the tasks and return the status they composed."""
        status = Status()
        for task in self.tasks:
            task(status)
        if not status.message and status.level == OK:
            status.message = 'ok'
        return status

    def publish(self) -> None:
        """Compose the status now and publish it."""
        status = self.status()
        message = DiagnosticStatus(level=bytes([status.level]), name=self.name,
                                   message=status.message, hardware_id=self._hardware_id,
                                   values=[KeyValue(key=key, value=format_value(value))
                                           for key, value in status.values])
        array = DiagnosticArray(status=[message])
        array.header.stamp = self._node.get_clock().now().to_msg()
        self.publisher.publish(array)


class SampleRateTask:
    """
    Samples used per second over the last period, with the update times: WARN if none.

    Parameters
    ----------
    feeder : SampleFeeder
        Whose totals and update times to read.
    now : callable
        Returns the time in seconds (the node's clock).
    stats : object
        Has ``messages`` and ``estimates_published`` totals (the node).

    """

    def __init__(self, feeder: Any, now: Callable[[], float], stats: Any) -> None:
        self._feeder = feeder
        self._now = now
        self._stats = stats
        self._last_time = now()
        self._last_used = feeder.used

    def __call__(self, status: Status) -> None:
        """Add the rate and update times; summarise the rate."""
        now = self._now()
        elapsed = now - self._last_time
        used = self._feeder.used
        new = used - self._last_used
        self._last_time, self._last_used = now, used
        rate = new / elapsed if elapsed > 0 else 0.0
        updates, mean_us, max_us = self._feeder.take_update_times()
        status.add(Key.SAMPLES_USED, used)
        status.add(Key.MESSAGES, self._stats.messages)
        status.add(Key.ESTIMATES_PUBLISHED, self._stats.estimates_published)
        status.add(Key.SAMPLE_RATE, rate)
        status.add(Key.UPDATES, updates)
        status.add(Key.UPDATE_MEAN_US, mean_us)
        status.add(Key.UPDATE_MAX_US, max_us)
        if new:
            status.merge_summary(OK, f'estimating at {rate:.0f} samples/s')
        else:
            status.merge_summary(WARN, 'no samples in the last period')


class CounterTask:
    """
    The counters of bad, lost and dropped samples: WARN on new ones, ERROR on failures.

    Parameters
    ----------
    counters : dict
        ``{counter: total}``, keys of :data:`~bcid_ros.identifier.interface.COUNTERS`.
    excitation_lost : callable
        Whether the input is constant right now.

    """

    def __init__(self, counters: dict[str, int], excitation_lost: Callable[[], bool]) -> None:
        self._counters = counters
        self._excitation_lost = excitation_lost
        self._last = dict(counters)

    def __call__(self, status: Status) -> None:
        """Add the sums and every counter; summarise what is new since the last period."""
        counters = self._counters
        new = {kind: total - self._last.get(kind, 0) for kind, total in counters.items()}
        self._last = dict(counters)
        status.add(Key.SAMPLES_DROPPED, sum(counters[kind] for kind in DROPPED))
        status.add(Key.BAD_SAMPLES, sum(counters[kind] for kind in BAD))
        for kind, total in counters.items():
            status.add(COUNTERS[kind], total)
        failing = [COUNTERS[kind] for kind in FAILING if new[kind]]
        if failing:
            status.merge_summary(ERROR, 'estimator failing: ' + ', '.join(failing))
        problems = [COUNTERS[kind] for kind, count in new.items()
                    if count and kind not in FAILING]
        if self._excitation_lost() and not new['unexcited']:
            problems.append('no excitation (input constant)')
        if problems:
            status.merge_summary(WARN, 'in the last period: ' + ', '.join(problems))


class EstimatorTask:
    """
    The estimator's health: validity, flags raised in the last period, covariance, noise.

    WARN when a flag was raised in the last period; OK and "filling the
    regressor" while the estimate is not valid.

    Parameters
    ----------
    name : str
        The estimator's registry name.
    estimator : RecursiveEstimator
        The estimator.
    publish_period : callable
        Returns the current ``publish_period``.

    """

    def __init__(self, name: str, estimator: Any, publish_period: Callable[[], int]) -> None:
        self._name = name
        self._estimator = estimator
        self._publish_period = publish_period
        self._last_flags: dict[str, int] = dict(estimator.flags)

    def __call__(self, status: Status) -> None:
        """Add the estimator's values; summarise its new flags and its validity."""
        estimator = self._estimator
        flags = dict(estimator.flags)
        raised = [name for name, count in flags.items()
                  if count != self._last_flags.get(name, 0) and name not in ROUTINE_FLAGS]
        self._last_flags = flags
        trace = estimator.covariance_trace
        status.add(Key.ESTIMATOR, self._name)
        status.add(Key.VALID, bool(estimator.valid))
        reasons = tuple(getattr(estimator, 'validity_reasons', ()))
        if reasons:
            status.add(Key.NOT_VALID_BECAUSE, '; '.join(reasons))
        status.add(Key.SAMPLES_SINCE_RESET, estimator.samples)
        status.add(Key.COVARIANCE_TRACE, trace if math.isfinite(trace) else 'n/a')
        status.add(Key.FORGETTING_FACTOR, estimator.forgetting_factor)
        status.add(Key.PUBLISH_PERIOD, self._publish_period())
        status.add(Key.ADAPT, bool(getattr(estimator, 'adapt', True))
                   and not getattr(estimator, 'excitation_hold', False))
        status.add(Key.SAMPLES_HELD, getattr(estimator, 'held_samples', 0))
        for name, count in sorted(flags.items()):
            status.add(Key.FLAG + name, count)
        if estimator.valid:
            for name, value in zip(estimator.noise_names, estimator.noise):
                status.add(Key.NOISE + name, float(value))
        if reasons:
            # ~/valid is false although the estimator is ready: say why, so a person sees it
            status.merge_summary(WARN, 'estimate not valid: ' + '; '.join(reasons))
        centring = getattr(estimator, 'centring_problem', '')
        if centring:
            status.merge_summary(WARN, centring)
        if raised:
            status.merge_summary(WARN, 'estimator flags in the last period: '
                                 + ', '.join(raised))
        elif not estimator.ready:
            status.merge_summary(OK, f'filling the regressor ({estimator.samples} samples)')


__all__ = ['CounterTask', 'DiagnosticsUpdater', 'ERROR', 'EstimatorTask', 'OK',
           'ROUTINE_FLAGS', 'SampleRateTask', 'Status', 'Task', 'WARN', 'format_value']
