"""
The identifier's ``input_mode: joint_state`` without ROS: JointState in, estimates per joint out.

:class:`JointFeeder` is to many joints what :class:`bcid_ros.identifier.feeder.SampleFeeder`
is to one plant. It takes one ``sensor_msgs/JointState`` message at a time
(duck-typed: anything with ``name``, ``position``, ``velocity`` and
``effort``), splits it into one ``(y, u)`` sample per configured joint with
:class:`~bcid_ros.identifier.joint_demux.JointStateDemux` (matched by name, in any order),
feeds all joints in one update of a batched estimator
(:mod:`bcid_ros.estimators.batched`), and says in a :class:`JointFeedResult`
which joints' estimates are due for publication and whose validity changed.
The policy is the single-plant one, per joint: a joint whose sample is
missing or not finite is counted and restarts its own regressor, and the
other joints are not touched; each joint publishes every ``publish_period``
of its own used samples once its estimator is ready, never a non-finite one.
The identifier node only turns the result into ROS messages.
"""

from __future__ import annotations

import dataclasses
import re
import time
from typing import Any, Sequence

import numpy as np

from bcid_ros.estimators.blocks import UpdateTimes
from bcid_ros.estimators.plants import usable_samples
from bcid_ros.identifier.interface import JOINT_STATES
from bcid_ros.identifier.joint_demux import JointStateDemux

#: A joint name becomes one token of its topic names (``~/<joint>/parameters``):
#: letters, digits and underscores, not starting with a digit, as ROS requires.
JOINT_NAME = re.compile(r'[A-Za-z_][A-Za-z0-9_]*')


def check_joint_names(joints: Sequence[Any], parameter: str = 'joints') -> tuple[str, ...]:
    """
    Return the joint names if every one can be a ROS topic token, unique; else raise.

    Raises
    ------
    ValueError
        Naming the parameter, the rule and the offending names.

    """
    joints = tuple(joints)
    if not joints:
        raise ValueError(f'parameter {parameter!r} must list at least one joint name with '
                         f'input_mode: joint_state, got []')
    bad = [name for name in joints
           if not isinstance(name, str) or not JOINT_NAME.fullmatch(name)]
    if bad:
        raise ValueError(f'parameter {parameter!r} must hold names made of letters, digits and '
                         f'underscores, not starting with a digit (each becomes a topic name '
                         f'token, ~/<joint>/parameters), got {bad!r}')
    repeated = sorted({name for name in joints if joints.count(name) > 1})
    if repeated:
        raise ValueError(f'parameter {parameter!r} must hold unique names, got '
                         f'{", ".join(repeated)} more than once')
    return joints


def joint_topic(joint: str, topic: str) -> str:
    """Return a private topic's per-joint name: ``('elbow', '~/valid')`` -> ``'~/elbow/valid'``."""
    if not topic.startswith('~/'):
        raise ValueError(f'topic must be a private name (~/...), got {topic!r}')
    return f'~/{joint}/{topic[2:]}'


@dataclasses.dataclass(slots=True)
class JointFeedResult:
    """
    What :class:`JointFeeder` did with one JointState message.

    Attributes
    ----------
    used : int
        Joint samples that went into the estimator.
    missing : int
        Configured joints without a sample in the message (not listed, or a
        field array without one value per name).
    length_mismatch : bool
        Whether the input or output array did not have one value per name.
    nonfinite : int
        Joint samples skipped for a NaN or Inf.
    unexcited : int
        Joint samples used although that joint's input had not changed for
        ``excitation_window`` samples.
    dropped : str
        ``'estimator_errors'`` if the estimator raised (every regressor
        restarts), else empty.
    reason : str
        The estimator's exception, for the log.
    valid_changed : numpy.ndarray of int
        Joints whose validity changed with this message.
    due : numpy.ndarray of int
        Joints whose estimates are due for publication (ready and finite).
    theta, noise : numpy.ndarray
        Their estimates, shapes ``(len(due), p)`` and ``(len(due), m)``.
    std : numpy.ndarray
        Their parameter standard deviations, ``(len(due), p)``; a row of NaN
        where a joint has none yet (not published).
    withheld : numpy.ndarray of int
        Joints whose due estimate was not finite, so not returned.

    """

    used: int = 0
    missing: int = 0
    length_mismatch: bool = False
    nonfinite: int = 0
    unexcited: int = 0
    dropped: str = ''
    reason: str = ''
    valid_changed: np.ndarray = dataclasses.field(default_factory=lambda: _NONE)
    due: np.ndarray = dataclasses.field(default_factory=lambda: _NONE)
    theta: np.ndarray | None = None
    noise: np.ndarray | None = None
    std: np.ndarray | None = None
    withheld: np.ndarray = dataclasses.field(default_factory=lambda: _NONE)


_NONE = np.zeros(0, dtype=np.intp)


class JointFeeder:
    """
    Feed JointState messages to one batched estimator, one plant per joint.

    Parameters
    ----------
    joints : sequence of str
        The joint names (see :func:`check_joint_names`); plant k is ``joints[k]``.
    estimator : BatchedRls
        The batched estimator over ``len(joints)`` single-input plants.
    input_field, output_field : str
        The JointState arrays that hold u and y.
    excitation_window : int
        Samples of unchanged input (per joint) before a sample counts as
        unexcited; 0 turns the check off.
    publish_period : int
        Used samples of a joint between its published estimates.

    Raises
    ------
    ValueError
        If a name, a field or the estimator's size or inputs do not fit.

    """

    def __init__(self, joints: Sequence[str], estimator: Any, input_field: str = 'effort',
                 output_field: str = 'velocity', excitation_window: int = 0,
                 publish_period: int = 1) -> None:
        self.joints = check_joint_names(joints)
        count = len(self.joints)
        if estimator.num_plants != count or estimator.num_inputs != 1:
            raise ValueError(f'estimator must be a batched single-input estimator over '
                             f'{count} plants, got {estimator!r}')
        self.demux = JointStateDemux(self.joints, input_field, output_field)
        self.estimator = estimator
        self.excitation_window = int(excitation_window)
        self.publish_period = int(publish_period)
        self.since_publish = np.zeros(count, dtype=np.int64)
        #: Per joint: samples used although unexcited, estimates withheld (not finite).
        self.unexcited = np.zeros(count, dtype=np.int64)
        self.withheld = np.zeros(count, dtype=np.int64)
        #: Totals over all joints since construction (a reset keeps them).
        self.used = 0
        self.estimator_errors = 0
        #: The batched update's times since the diagnostics last took them.
        self.times = UpdateTimes()
        self._valid = np.zeros(count, dtype=bool)
        self._last_u = np.full(count, np.nan)
        self._constant_run = np.zeros(count, dtype=np.int64)
        self._mismatch_total = 0

    # ----------------------------------------------------------------- input
    def take(self, message: Any) -> JointFeedResult:
        """
        Take one JointState message: update every joint it carries; return what happened.

        Parameters
        ----------
        message : sensor_msgs.msg.JointState or alike
            ``name`` with parallel ``position``, ``velocity``, ``effort``.

        Returns
        -------
        JointFeedResult

        """
        demux = self.demux
        samples = demux.take(message)
        present = samples.present
        usable = usable_samples(samples.y, samples.u, present)
        present_count, used = int(present.sum()), int(usable.sum())
        result = JointFeedResult(missing=len(self.joints) - present_count,
                                 nonfinite=present_count - used)
        if not present_count:
            # a field without one value per name leaves every joint of the message absent
            mismatch = int(demux.length_mismatch.sum())
            result.length_mismatch = mismatch != self._mismatch_total
            self._mismatch_total = mismatch
        if self.excitation_window:
            result.unexcited = self._check_excitation(samples.u, usable)
        start = time.perf_counter_ns()
        try:
            self.estimator.update(samples.y, samples.u, samples.present)
        except Exception as error:  # an estimator failure must not stop the stream
            self.estimator.restart_regressor()
            self.estimator_errors += 1
            result.dropped, result.reason = 'estimator_errors', repr(error)
            return result
        elapsed = time.perf_counter_ns() - start
        self.times.add(1, elapsed, elapsed)
        self.used += used
        result.used = used
        self.since_publish += usable
        self._note_validity(result)
        self._add_estimates(result)
        return result

    def _check_excitation(self, u: np.ndarray, usable: np.ndarray) -> int:
        """Count the usable samples whose joint's input has been constant for the window."""
        same = usable & (u == self._last_u)
        changed = usable & ~same
        self._constant_run[same] += 1
        self._constant_run[changed] = 0
        self._last_u[changed] = u[changed]
        unexcited = same & (self._constant_run >= self.excitation_window)
        self.unexcited += unexcited
        return int(unexcited.sum())

    def _note_validity(self, result: JointFeedResult) -> None:
        valid = self.estimator.valid
        changed = valid != self._valid
        if changed.any():
            result.valid_changed = np.flatnonzero(changed)
            self._valid = valid

    def _add_estimates(self, result: JointFeedResult) -> None:
        """Put the due estimates into ``result`` and restart those joints' counts."""
        # Published once ready, as the single-plant node does; ~/valid says whether to trust it.
        due = (self.since_publish >= self.publish_period) & self.estimator.ready
        if not due.any():
            return
        rows = np.flatnonzero(due)
        estimator = self.estimator
        theta = estimator.theta[rows]
        noise = estimator.noise[rows]
        std = estimator.parameter_std[rows]
        finite = np.isfinite(theta).all(axis=1)
        if not finite.all():
            result.withheld = rows[~finite]
            self.withheld[result.withheld] += 1
            rows, theta, noise, std = rows[finite], theta[finite], noise[finite], std[finite]
        self.since_publish[rows] = 0
        result.due, result.theta, result.noise, result.std = rows, theta, noise, std

    # -------------------------------------------------------------- control
    def gap(self) -> None:
        """Restart every joint's regressor: samples of all joints are missing (messages lost)."""
        self.estimator.restart_regressor()

    def reset(self) -> JointFeedResult:
        """Reset every joint's estimator and input history; return the validity changes."""
        self.estimator.reset()
        self.since_publish[:] = 0
        self._last_u[:] = np.nan
        self._constant_run[:] = 0
        result = JointFeedResult()
        self._note_validity(result)
        return result

    def take_update_times(self) -> tuple[int, float, float]:
        """Return ``(updates, mean µs, max µs)`` of the batched update since the last call."""
        return self.times.take()

    @property
    def valid(self) -> np.ndarray:
        """Whether each joint's estimate is valid, shape ``(K,)`` (a copy)."""
        return self._valid.copy()

    @property
    def excitation_lost(self) -> bool:
        """Whether the input of some joint is constant right now (for longer than the window)."""
        return bool(self.excitation_window) and bool(
            (self._constant_run >= self.excitation_window).any())

    def counters(self) -> dict[str, np.ndarray]:
        """Return the per-joint counters by name (copies), for the per-joint diagnostics."""
        counts = self.demux.counters()
        counts['unexcited'] = self.unexcited.copy()
        counts['withheld'] = self.withheld.copy()
        return counts


def joint_feeder_from_parameters(values: dict[str, Any]) -> JointFeeder:
    """
    Build the joint feeder that the identifier builds in ``input_mode: joint_state``.

    Parameters
    ----------
    values : dict
        Identifier parameters checked by
        :func:`bcid_ros.identifier.parameters.check_identifier_parameters`.

    Raises
    ------
    ValueError
        If the estimator has no batched form (named in the message).

    """
    from bcid_ros.estimators import make_batched_estimator

    joints = check_joint_names(values['joints'])
    estimator = make_batched_estimator(
        values['estimator'], len(joints), order=values['order'], num_inputs=1,
        feedthrough=values['feedthrough'], initial_covariance=values['initial_covariance'],
        forgetting_factor=values['forgetting_factor'],
        change_detection=values['change_detection'], adaptation=values['adaptation'],
        parameter_drift=values['parameter_drift'])
    return JointFeeder(joints, estimator, values['input_field'], values['output_field'],
                       values['excitation_window'], values['publish_period'])


__all__ = ['JOINT_NAME', 'JOINT_STATES', 'JointFeedResult', 'JointFeeder',
           'check_joint_names', 'joint_feeder_from_parameters', 'joint_topic']
