"""
Per-joint samples out of sensor_msgs/JointState messages, free of ROS.

A JointState message lists joints by ``name`` with parallel ``position``,
``velocity`` and ``effort`` arrays, in any order and possibly only some of
the joints. :class:`JointStateDemux` turns one message into one sample per
configured joint, ``y`` from the output field and ``u`` from the input
field, matched by name, and counts per joint what kept a sample out. It
reads the message's attributes only (any object with ``name`` and the three
arrays will do), so it is tested and used without rclpy.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Sequence

import numpy as np

#: The JointState arrays that can carry a joint's input or output.
FIELDS = ('position', 'velocity', 'effort')


@dataclasses.dataclass(frozen=True)
class JointSamples:
    """
    One message's samples, one entry per configured joint.

    Attributes
    ----------
    y : numpy.ndarray, shape ``(K,)``
        Output field of each joint (NaN where not present).
    u : numpy.ndarray, shape ``(K,)``
        Input field of each joint (NaN where not present).
    present : numpy.ndarray of bool, shape ``(K,)``
        Whether the message carried both fields of the joint. A present
        sample may still hold NaN or Inf (counted in ``nonfinite``).

    """

    y: np.ndarray
    u: np.ndarray
    present: np.ndarray


class JointStateDemux:
    """
    Demultiplex JointState messages into per-joint ``(y, u)`` samples, matched by name.

    A joint's sample is absent from a message, and counted per joint, when:

    * ``missing``: the joint is not in the message's ``name`` list;
    * ``length_mismatch``: the message lists the joint, but the input or
      output array does not have one value per name (an empty array
      included), so no value can be told to belong to it.

    ``nonfinite`` counts present samples whose y or u is NaN or Inf; those
    are passed on as they are (the estimator refuses them and restarts that
    joint's regressor). ``duplicate`` counts messages that list a joint more
    than once; the first entry is used.

    Parameters
    ----------
    joints : sequence of str
        The joint names, in the order of the returned arrays; unique, non-empty.
    input_field : str
        The array that holds u: ``'position'``, ``'velocity'`` or ``'effort'``.
    output_field : str
        The array that holds y; another one than ``input_field``.

    Raises
    ------
    ValueError
        If a joint name is empty or repeated, or a field is not one of the above.

    """

    def __init__(self, joints: Sequence[str], input_field: str = 'effort',
                 output_field: str = 'velocity') -> None:
        joints = tuple(joints)
        if not joints or not all(isinstance(name, str) and name for name in joints):
            raise ValueError(f'joints must be a non-empty list of non-empty names, got '
                             f'{list(joints)!r}')
        repeated = sorted({name for name in joints if joints.count(name) > 1})
        if repeated:
            raise ValueError(f'joints must be unique names, got {", ".join(repeated)} '
                             f'more than once')
        for parameter, field in (('input_field', input_field), ('output_field', output_field)):
            if field not in FIELDS:
                raise ValueError(f'{parameter} must be one of {", ".join(FIELDS)}, got '
                                 f'{field!r}')
        if input_field == output_field:
            raise ValueError(f'input_field and output_field must differ, both are '
                             f'{input_field!r}')
        self.joints = joints
        self.input_field = input_field
        self.output_field = output_field
        count = len(joints)
        self.messages = 0
        #: Per-joint counts of samples kept out (see the class docstring).
        self.missing = np.zeros(count, dtype=np.int64)
        self.length_mismatch = np.zeros(count, dtype=np.int64)
        self.nonfinite = np.zeros(count, dtype=np.int64)
        self.duplicate = np.zeros(count, dtype=np.int64)
        self._names: list[str] | None = None
        self._index = np.zeros(count, dtype=np.intp)
        self._listed = np.zeros(count, dtype=bool)
        self._repeated = np.zeros(count, dtype=bool)

    def take(self, message: Any) -> JointSamples:
        """
        Return the samples of one JointState message and count what is missing.

        Parameters
        ----------
        message : sensor_msgs.msg.JointState or alike
            Anything with the sequences ``name``, ``position``, ``velocity``
            and ``effort``.

        Returns
        -------
        JointSamples
            One sample per configured joint.

        """
        names = list(message.name)
        if names != self._names:
            self._match(names)
        listed = self._listed
        self.messages += 1
        self.missing += ~listed
        self.duplicate += self._repeated
        if not listed.any():
            return self._absent()
        y = self._field(message, self.output_field, len(names))
        u = self._field(message, self.input_field, len(names))
        if y is None or u is None:
            self.length_mismatch += listed
            return self._absent()
        index = self._index
        y, u = y[index], u[index]
        y[~listed] = np.nan
        u[~listed] = np.nan
        self.nonfinite += listed & ~(np.isfinite(y) & np.isfinite(u))
        return JointSamples(y, u, listed.copy())

    def counters(self) -> dict[str, np.ndarray]:
        """Return the per-joint counters by name (copies), for diagnostics."""
        return {'missing': self.missing.copy(), 'length_mismatch': self.length_mismatch.copy(),
                'nonfinite': self.nonfinite.copy(), 'duplicate': self.duplicate.copy()}

    def __repr__(self) -> str:
        return (f'JointStateDemux(joints={len(self.joints)}, input_field={self.input_field!r}, '
                f'output_field={self.output_field!r})')

    def _absent(self) -> JointSamples:
        """Return samples with no joint present."""
        count = len(self.joints)
        return JointSamples(np.full(count, np.nan), np.full(count, np.nan),
                            np.zeros(count, dtype=bool))

    def _match(self, names: list[str]) -> None:
        """Find the configured joints in a new ``name`` list (kept for the next messages)."""
        position: dict[str, int] = {}
        repeated = set()
        for k, name in enumerate(names):
            if name in position:
                repeated.add(name)
            else:
                position[name] = k
        found = [position.get(joint, -1) for joint in self.joints]
        self._index = np.maximum(np.array(found, dtype=np.intp), 0)
        self._listed = np.array(found, dtype=np.intp) >= 0
        self._repeated = np.array([joint in repeated for joint in self.joints], dtype=bool)
        self._names = names

    @staticmethod
    def _field(message: Any, field: str, length: int) -> np.ndarray | None:
        """Return the array ``field`` as floats, or None if it has not one value per name."""
        values = np.asarray(getattr(message, field), dtype=float)
        if values.ndim != 1 or values.shape[0] != length:
            return None
        return values


__all__ = ['FIELDS', 'JointSamples', 'JointStateDemux']
