"""
Diagnostics of ``input_mode: joint_state``: one status for the node and one per joint.

The node's status is composed of tasks, as in single-plant mode: the
:class:`~bcid_ros.nodes.diagnostics.CounterTask` and
:class:`~bcid_ros.nodes.diagnostics.SampleRateTask` of the single-plant
identifier (their counts summed over the joints) and :class:`JointsTask`,
the summary of the joints. :class:`JointStatuses` makes the per-joint
statuses; :class:`JointDiagnosticsUpdater` publishes all of them in one
``DiagnosticArray``.

At a thousand joints the 1 Hz statuses are thousands of key-value pairs, so
:class:`JointStatuses` computes every figure for all joints at once with
numpy, gives a joint without trouble four values, and the statuses are
serialised straight to CDR (:mod:`bcid_ros.identifier.cdr`) instead
of going through rclpy's message objects.
"""

from __future__ import annotations

from typing import Any, Callable, Sequence

import numpy as np
from rclpy.node import Node

from bcid_ros.identifier.cdr import DiagnosticArrayEncoder, StatusTuple
from bcid_ros.identifier.interface import COUNTERS, DiagnosticKey as Key
from bcid_ros.nodes.diagnostics import (DiagnosticsUpdater, ERROR, format_value, OK, Status,
                                        Task, WARN)

#: Joints named in a summary message before "and N more".
NAMED_JOINTS = 5


def joint_status_name(node: str, joint: str) -> str:
    """Return the ``DiagnosticStatus.name`` of one joint: ``'bcid_arm: joint elbow'``."""
    return f'{node}: joint {joint}'


class JointKey:
    """The keys of the joints' statuses (besides ``valid``, ``flag <name>``, ``noise <name>``)."""

    SAMPLES_USED = Key.SAMPLES_USED
    SAMPLES_SINCE_RESET = Key.SAMPLES_SINCE_RESET
    MISSING = 'missing from the message'
    LENGTH_MISMATCH = 'field without one value per name'
    NONFINITE = COUNTERS['nonfinite']
    DUPLICATE = 'listed twice in a message'
    UNEXCITED = COUNTERS['unexcited']
    WITHHELD = COUNTERS['nonfinite_estimates']
    #: Node status: joints configured, joints valid, joint samples missing (all joints).
    JOINTS = 'joints'
    JOINTS_VALID = 'joints valid'
    MISSING_TOTAL = 'joint samples missing'


#: Per-joint counters of the feeder -> key, and what a new count says (None: nothing).
_JOINT_COUNTERS = (
    ('missing', JointKey.MISSING, 'missing from the message'),
    ('length_mismatch', JointKey.LENGTH_MISMATCH, 'field without one value per name'),
    ('nonfinite', JointKey.NONFINITE, 'NaN or Inf'),
    ('duplicate', JointKey.DUPLICATE, None),
    ('unexcited', JointKey.UNEXCITED, 'no excitation (input constant)'),
    ('withheld', JointKey.WITHHELD, None),
)


def _named(joints: Sequence[str], rows: np.ndarray) -> str:
    names = ', '.join(joints[k] for k in rows[:NAMED_JOINTS])
    more = rows.size - NAMED_JOINTS
    return names + (f' and {more} more' if more > 0 else '')


class JointsTask:
    """
    The node's summary of the joints: estimator, validity, missing samples, new flags.

    WARN when joints missed samples or raised estimator flags in the last
    period (naming the first joints); OK "filling the regressors" while not
    every joint is valid.

    Parameters
    ----------
    name : str
        The estimator's registry name.
    feeder : JointFeeder
        Whose estimator and counters to read.
    publish_period : callable
        Returns the current ``publish_period``.

    """

    def __init__(self, name: str, feeder: Any, publish_period: Callable[[], int]) -> None:
        self._name = name
        self._feeder = feeder
        self._publish_period = publish_period
        self._last_missing = self._missing()
        self._last_flags = {key: counts.copy() for key, counts in feeder.estimator.flags.items()}

    def _missing(self) -> np.ndarray:
        demux = self._feeder.demux
        return demux.missing + demux.length_mismatch

    def __call__(self, status: Status) -> None:
        """Add the joints' summary values; summarise missing samples, flags and validity."""
        feeder = self._feeder
        estimator = feeder.estimator
        joints = feeder.joints
        valid = feeder.valid
        missing = self._missing()
        new_missing = np.flatnonzero(missing != self._last_missing)
        self._last_missing = missing
        raised = {}
        for key, counts in estimator.flags.items():
            rows = np.flatnonzero(counts != self._last_flags.get(key, 0))
            if rows.size:
                raised[key] = rows
        self._last_flags = {key: counts.copy() for key, counts in estimator.flags.items()}
        status.add(Key.ESTIMATOR, self._name)
        status.add(JointKey.JOINTS, len(joints))
        status.add(JointKey.JOINTS_VALID, int(valid.sum()))
        status.add(JointKey.MISSING_TOTAL, int(missing.sum()))
        status.add(Key.FORGETTING_FACTOR, estimator.forgetting_factor)
        status.add(Key.PUBLISH_PERIOD, self._publish_period())
        for key, counts in sorted(estimator.flags.items()):
            status.add(Key.FLAG + key, int(counts.sum()))
        if new_missing.size:
            status.merge_summary(WARN, f'samples missing in the last period: '
                                 f'{_named(joints, new_missing)}')
        for key, rows in raised.items():
            status.merge_summary(WARN, f'estimator flag {key} in the last period: '
                                 f'{_named(joints, rows)}')
        if not valid.all():
            status.merge_summary(OK, f'filling the regressors ({int(valid.sum())} of '
                                 f'{len(joints)} joints valid)')


class JointStatuses:
    """
    One ``DiagnosticStatus`` per joint, its figures computed for all joints at once.

    A joint's status is ERROR if its estimate was withheld (not finite) in
    the last period; WARN if it missed samples, had NaN or Inf, had no
    excitation or raised an estimator flag in the last period (each named in
    the message); OK "filling the regressor (k samples)" while not valid,
    else OK "ok". Values: ``valid``, ``samples used``, ``samples since
    reset`` and ``noise <name>`` (``n/a`` while not valid) always; the
    per-joint counters of :class:`JointKey` and ``flag <name>`` only once
    they are not zero, so that a joint without trouble costs four pairs.

    Parameters
    ----------
    node : str
        The node name (status names and hardware id).
    feeder : JointFeeder
        Whose estimator and counters to read.

    """

    def __init__(self, node: str, feeder: Any) -> None:
        self._feeder = feeder
        self._last = feeder.counters()
        self._last_flags = {key: counts.copy() for key, counts in feeder.estimator.flags.items()}
        self._keys = ([Key.VALID, JointKey.SAMPLES_USED, JointKey.SAMPLES_SINCE_RESET]
                      + [Key.NOISE + name for name in feeder.estimator.noise_names])
        self._node = node
        self._names = [joint_status_name(node, joint) for joint in feeder.joints]

    def compose(self) -> list[tuple[int, str, list[tuple[str, str]]]]:
        """Return ``(level, message, [(key, text), ...])`` of every joint, for this period."""
        feeder = self._feeder
        estimator = feeder.estimator
        counters = feeder.counters()
        new = {name: counters[name] != self._last[name] for name, _, _ in _JOINT_COUNTERS}
        self._last = counters
        flags = estimator.flags
        new_flags = {key: counts != self._last_flags.get(key, 0) for key, counts in flags.items()}
        self._last_flags = {key: counts.copy() for key, counts in flags.items()}
        valid = feeder.valid
        columns = [np.where(valid, 'true', 'false').tolist(), estimator.used.astype(str).tolist(),
                   estimator.samples.astype(str).tolist()]
        noise = estimator.noise
        for i in range(noise.shape[1]):
            shown = valid & np.isfinite(noise[:, i])
            columns.append(np.where(shown, np.char.mod('%.6g', noise[:, i]), 'n/a').tolist())
        rows = [list(zip(self._keys, row)) for row in zip(*columns)]
        # the rare extras: counters and flags that are not zero
        for k in np.flatnonzero(np.any([counts > 0 for counts in counters.values()]
                                       + [counts > 0 for counts in flags.values()], axis=0)):
            rows[k] += [(key, str(int(counters[name][k]))) for name, key, _ in _JOINT_COUNTERS
                        if counters[name][k]]
            rows[k] += [(Key.FLAG + key, str(int(counts[k])))
                        for key, counts in sorted(flags.items()) if counts[k]]
        troubled = np.zeros(len(valid), dtype=bool)
        for changed in list(new.values()) + list(new_flags.values()):
            troubled |= changed
        samples = estimator.samples
        result = []
        for k, pairs in enumerate(rows):
            level, message = OK, 'ok'
            if troubled[k]:
                level, message = self._problem(k, new, new_flags)
            elif not valid[k]:
                message = f'filling the regressor ({int(samples[k])} samples)'
            result.append((level, message, pairs))
        return result

    @staticmethod
    def _problem(k: int, new: dict[str, np.ndarray],
                 new_flags: dict[str, np.ndarray]) -> tuple[int, str]:
        if new['withheld'][k]:
            return ERROR, 'estimator failing: ' + COUNTERS['nonfinite_estimates']
        problems = [text for name, _, text in _JOINT_COUNTERS if text and new[name][k]]
        problems += [f'flag {key}' for key, changed in sorted(new_flags.items()) if changed[k]]
        if not problems:
            return OK, 'ok'
        return WARN, 'in the last period: ' + ', '.join(problems)

    def statuses(self) -> list[StatusTuple]:
        """Return every joint's ``(level, name, message, hardware_id, values)`` for this period."""
        return [(level, name, message, self._node, pairs)
                for name, (level, message, pairs) in zip(self._names, self.compose())]


class JointDiagnosticsUpdater(DiagnosticsUpdater):
    """
    A :class:`~bcid_ros.nodes.diagnostics.DiagnosticsUpdater` that adds one status per joint.

    The node's status (composed of ``tasks``) comes first, then the joints'
    statuses, all in one ``DiagnosticArray`` serialised by
    :class:`~bcid_ros.identifier.cdr.DiagnosticArrayEncoder`.
    """

    def __init__(self, node: Node, name: str, tasks: Sequence[Task],
                 joints: JointStatuses, *, period: float = 1.0,
                 hardware_id: str = '') -> None:
        self.joints = joints
        self._encoder = DiagnosticArrayEncoder()
        super().__init__(node, name, tasks, period=period, hardware_id=hardware_id)

    def publish(self) -> None:
        """Compose the node's and the joints' statuses now and publish them, serialised."""
        status = self.status()
        own = (status.level, self.name, status.message, self._hardware_id,
               [(key, format_value(value)) for key, value in status.values])
        stamp = self._node.get_clock().now().seconds_nanoseconds()
        self.publisher.publish(self._encoder.encode(stamp, [own, *self.joints.statuses()]))


__all__ = ['JointDiagnosticsUpdater', 'JointKey', 'JointStatuses', 'JointsTask',
           'joint_status_name']
