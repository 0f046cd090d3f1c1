"""
The update as a transaction: a step that would leave the state non-finite is undone.

:class:`Transaction` is a mixin of :class:`~bcid_ros.estimators.base.RecursiveEstimator`:
the generic form (a checkpoint of the whole state), the light exact form for
estimators that name what one step may change, and the undo that counts a
refused step (flag ``update_undone``) and restarts the regressor
(docs/estimators.md, "Estimates you can trust").
"""

from __future__ import annotations

import math
import operator

import numpy as np

#: The generic transaction copies a state of at most this many numbers before
#: every sample, and a larger one every CHECKPOINT_PERIOD samples.
EXACT_CHECKPOINT_SIZE = 4096
#: See EXACT_CHECKPOINT_SIZE.
CHECKPOINT_PERIOD = 64


def all_finite(*vectors: np.ndarray) -> bool:
    """
    Return whether every value of the 1-D float arrays ``vectors`` is finite.

    The sum of all the values is finite when they are, which one cheap sum of
    Python floats tells in the usual case; a non-finite sum is a NaN, an Inf
    or an overflow of finite values, which the exact test then tells apart.
    """
    total = 0.0
    for vector in vectors:
        total += sum(vector.tolist())
    return math.isfinite(total) or all(bool(np.isfinite(vector).all()) for vector in vectors)


class Transaction:
    """
    One step as a transaction (a mixin).

    The host provides ``_update`` (the step), ``_state_items``/``_load_state``,
    ``_theta``/``_theta_uncompensated``/``_noise``, ``_flag`` and
    ``_restart_regressor``; it keeps ``_checkpoint``, ``_since_checkpoint``,
    ``_checkpoint_period`` and ``_refused``.
    """

    def _guarded_update(self, y: float, u: np.ndarray) -> None:
        """
        Do one step as a transaction: step, check, and go back if the state is unsound.

        This generic form keeps a checkpoint of the state, renewed before
        every sample when the state holds at most ``EXACT_CHECKPOINT_SIZE``
        numbers and every ``CHECKPOINT_PERIOD`` samples otherwise (a copy of
        a long data window per sample would cost more than the step), and
        checks after every step that the estimates and noise statistics are
        finite. An unsound step takes the state back to the checkpoint
        (before the sample, or at most that many samples before it), is
        counted as ``update_undone`` and restarts the regressor, so the suspect
        sample does not enter the next regressors either. Estimators that can
        tell before committing whether a step is sound override this with an
        exact and cheaper form (:class:`~bcid_ros.estimators.rls.Rls`);
        those that name what a step changes take :meth:`_step_transaction`.
        """
        if self._checkpoint is None or self._since_checkpoint >= self._checkpoint_period:
            arrays, scalars = self._state_items()
            self._checkpoint = ({key: np.array(value, copy=True)
                                 for key, value in arrays.items()}, dict(scalars))
            self._since_checkpoint = 0
            size = sum(value.size for value in self._checkpoint[0].values())
            self._checkpoint_period = 1 if size <= EXACT_CHECKPOINT_SIZE else CHECKPOINT_PERIOD
        self._since_checkpoint += 1
        self._update(y, u)
        if not self._is_sound():
            arrays, scalars = self._checkpoint
            self._load_state({key: value.copy() for key, value in arrays.items()},
                             dict(scalars))
            self._undo('update_undone')

    def _name_step_state(self, attributes: tuple[str, ...], arrays: tuple[str, ...]) -> None:
        """
        Name what one step may change, for :meth:`_step_transaction`.

        ``attributes`` are those a step may rebind (kept by reference: the
        objects they refer to must not be changed in place), ``arrays`` the
        arrays or lists it may change in place (copied; dotted paths
        allowed). An array that a step may also rebind is named in both.
        """
        self._step_attributes = attributes
        self._step_split = len(attributes)
        # one C-level call reads them all (it returns a tuple from two names on)
        read = operator.attrgetter(*attributes, *arrays)
        self._read_step_state = read if len(attributes + arrays) > 1 else (
            lambda obj: (read(obj),))

    def _step_transaction(self, y: float, u: np.ndarray) -> None:
        """
        Do one step as an exact transaction that saves only what the step may change.

        The light form of :meth:`_guarded_update`, for estimators that name
        what one step may change (:meth:`_name_step_state`): before every
        sample it keeps references to those attributes and copies of those
        arrays (a few dozen numbers, where the generic checkpoint copies the
        whole state), steps, and checks with :meth:`_is_sound`. An unsound
        step puts them back, calls :meth:`_step_restored`, is counted as
        ``update_undone`` and restarts the regressor: the state is exactly the
        one before the sample with the regressor restarted (what the restart
        clears need not be saved; the flags and the gate's change score count
        on, as with the generic form).
        """
        saved = self._read_step_state(self)
        arrays = saved[self._step_split:]
        copies = [array.copy() for array in arrays]
        self._update(y, u)
        if self._is_sound():
            return
        for name, value in zip(self._step_attributes, saved):
            setattr(self, name, value)
        for array, copy in zip(arrays, copies):
            array[:] = copy
        self._step_restored()
        self._undo('update_undone')

    def _step_restored(self) -> None:
        """Recompute what derives from the state put back by :meth:`_step_transaction`."""

    def _is_sound(self) -> bool:
        """Whether the estimates and noise statistics are all finite."""
        return all_finite(self._theta(), self._theta_uncompensated(), self._noise())

    def _undo(self, flag: str) -> None:
        """Count a refused step and restart the regressor."""
        self._flag(flag)
        self._refused += 1
        self._restart_regressor()


__all__ = ['CHECKPOINT_PERIOD', 'EXACT_CHECKPOINT_SIZE', 'Transaction', 'all_finite']
