"""
The state of an :class:`~bcid_ros.estimators.adequacy.AdequacyMonitor`: its copy and the moves.

:class:`MonitorState` is the copy (:meth:`MonitorStates.get_state`), of all plants
or, as one plant's, of a single plant's monitor (:meth:`MonitorStates.plant_state`,
:meth:`MonitorStates.load_plant`): the snapshot of an estimator, its restart and
the batched forms' per-plant moves go through it (residual_state.py).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

#: Every plant, as rows (a slice: views, not copies).
_ALL = slice(None)


@dataclasses.dataclass(frozen=True)
class MonitorState:
    """A copy of an :class:`AdequacyMonitor`'s state (:meth:`AdequacyMonitor.get_state`)."""

    residual_sums: np.ndarray
    input_sums: np.ndarray
    weights: tuple[Any, Any]
    ring: np.ndarray
    pending_residuals: np.ndarray
    pending_inputs: np.ndarray
    alarms: np.ndarray
    statistics: np.ndarray
    worst: np.ndarray
    values: np.ndarray
    checks: Any
    #: K plants: each plant's pending samples, which sit in ``ring`` after the history
    #: rows (``pending_residuals`` and ``pending_inputs`` are then empty). None: one
    #: plant, whose pending samples are ``pending_residuals`` and ``pending_inputs``.
    pending: np.ndarray | None = None
    #: The blocks added (an int, or ``(K,)``): the tests run every ``check_period``.
    blocks: Any = 0
    #: With ``num_parameters`` p > 0: the sums of psi(t - m) u_i(t - a) ``(K, (q + 1) p, r U)``,
    #: the last gradients ``(K, q + BLOCK, p)`` (as ``ring``) and a plant's pending ones
    #: ``(m, 1, p)`` (K plants: ``(0, K, p)``, they sit in ``gradient_ring``). None (a
    #: state from before the parameter term): loaded as zeros, so the term starts from the
    #: gradients recorded after the load.
    gradient_sums: np.ndarray | None = None
    gradient_ring: np.ndarray | None = None
    pending_gradients: np.ndarray | None = None
    #: With a whiteness test and p > 0 (:attr:`AdequacyMonitor.settling`): the sums of
    #: psi~(t) psi~(t - k)' ``(K, M + 1, p, p)``, k = 0..M. None: loaded as zeros.
    settling_sums: np.ndarray | None = None


class MonitorStates:
    """The state moves of :class:`~bcid_ros.estimators.adequacy.AdequacyMonitor` (its base)."""

    def get_state(self) -> MonitorState:
        """Return a copy of the state (K plants: :meth:`plant_state` gives one plant's)."""
        if self.plants is not None:
            return MonitorState(
                residual_sums=self._residual_sums.copy(), input_sums=self._input_sums.copy(),
                weights=(self._weight.copy(), self._squared_weight.copy()),
                ring=self._ring.copy(), pending_residuals=np.zeros((0, self._plants)),
                pending_inputs=np.zeros((0, self._plants, self.num_inputs)),
                alarms=self._alarms.copy(), statistics=self._statistics.copy(),
                worst=self._worst.copy(), values=self._values.copy(),
                checks=self._checks.copy(), pending=self._cursors.counts().copy(),
                blocks=self._blocks.copy(), **self._gradient_state(0))
        lead = (len(self._residuals), self._plants)
        return MonitorState(
            residual_sums=self._residual_sums.copy(), input_sums=self._input_sums.copy(),
            weights=(self._weight, self._squared_weight),
            ring=self._ring.copy(),
            pending_residuals=np.array(self._residuals, dtype=float).reshape(lead),
            pending_inputs=self._inputs[:lead[0]].copy(),
            alarms=self._alarms.copy(), statistics=self._statistics.copy(),
            worst=self._worst.copy(), values=self._values.copy(), checks=int(self._checks[0]),
            blocks=int(self._blocks[0]), **self._gradient_state(lead[0]))

    def _gradient_state(self, pending: int) -> dict[str, Any]:
        """Return the gradient fields of a state: copies, with ``pending`` rows (one plant)."""
        if not self.num_parameters:
            return {}
        rows = (self._gradients[:pending] if self.plants is None
                else np.zeros((0, self._plants, self.num_parameters)))
        return {'gradient_sums': self._gradient_sums.copy(),
                'gradient_ring': self._gradient_ring.copy(), 'pending_gradients': rows.copy(),
                **self._settling_state(_ALL)}

    def _settling_state(self, plants: Any) -> dict[str, Any]:
        """Return the whiteness term's sums of ``plants`` as a state field (none: empty)."""
        if not self.settling:
            return {}
        return {'settling_sums': self._settling_sums[plants].copy()}

    def set_state(self, state: MonitorState) -> None:
        """Continue from a :meth:`get_state` of a monitor with the same settings."""
        self._residual_sums = state.residual_sums.copy()
        self._input_sums = state.input_sums.copy()
        self._ring = state.ring.copy()
        self._alarms = state.alarms.copy()
        self._statistics = state.statistics.copy()
        self._worst = state.worst.copy()
        self._values = state.values.copy()
        lead = (self._plants,)
        self._checks = np.broadcast_to(np.asarray(state.checks, dtype=np.int64), lead).copy()
        self._blocks = np.broadcast_to(np.asarray(state.blocks, dtype=np.int64), lead).copy()
        self._reset_gradients()
        if self.num_parameters and state.gradient_sums is not None:
            self._gradient_sums[:] = state.gradient_sums
            self._gradient_ring[:] = state.gradient_ring
        if self.settling and state.settling_sums is not None:
            self._settling_sums[:] = state.settling_sums
        if self.plants is None:
            self._weight, self._squared_weight = state.weights
            self._residuals = [float(r[0]) for r in state.pending_residuals]
            self._inputs[:len(self._residuals)] = state.pending_inputs
            if self.num_parameters and state.pending_gradients is not None:
                self._gradients[:len(self._residuals)] = state.pending_gradients
            return
        weight, squared = state.weights
        self._weight = np.broadcast_to(np.asarray(weight, dtype=float), lead).copy()
        self._squared_weight = np.broadcast_to(np.asarray(squared, dtype=float), lead).copy()
        if state.pending is not None:
            self._cursors.set(_ALL, state.pending)
        else:  # pending samples (m, K) that all plants shared before the cursors
            count = state.pending_residuals.shape[0]
            slots = slice(self._history, self._history + count)
            self._ring[:, slots, 0] = state.pending_residuals.T
            self._ring[:, slots, 1:] = np.swapaxes(state.pending_inputs, 0, 1)
            self._cursors.set(_ALL, count)

    def plant_state(self, plant: int) -> MonitorState:
        """Return plant k's state in the form of a single plant's :meth:`get_state` (K plants)."""
        count = int(self._cursors.counts()[plant])
        ring = self._ring[plant:plant + 1].copy()
        pending = ring[0, self._history:self._history + count]
        state = MonitorState(
            residual_sums=self._residual_sums[plant:plant + 1].copy(),
            input_sums=self._input_sums[plant:plant + 1].copy(),
            weights=(float(self._weight[plant]), float(self._squared_weight[plant])),
            ring=ring, pending_residuals=pending[:, :1].copy(),
            pending_inputs=pending[:, None, 1:].copy(),
            alarms=self._alarms[plant:plant + 1].copy(),
            statistics=self._statistics[plant:plant + 1].copy(),
            worst=self._worst[plant:plant + 1].copy(),
            values=self._values[plant:plant + 1].copy(), checks=int(self._checks[plant]),
            blocks=int(self._blocks[plant]), **self._plant_gradients(plant, count))
        ring[0, self._history:] = 0.0  # one plant keeps its pending samples in lists
        return state

    def _plant_gradients(self, plant: int, count: int) -> dict[str, Any]:
        """Return plant k's gradient fields in a single plant's form (``count`` pending)."""
        if not self.num_parameters:
            return {}
        q = self._gradient_history
        ring = self._gradient_ring[plant:plant + 1].copy()
        pending = ring[0, q:q + count, None].copy()
        ring[0, q:] = 0.0  # one plant keeps its pending gradients apart
        return {'gradient_sums': self._gradient_sums[plant:plant + 1].copy(),
                'gradient_ring': ring, 'pending_gradients': pending,
                **self._settling_state(slice(plant, plant + 1))}

    def load_plant(self, plant: int, state: MonitorState) -> None:
        """Take over plant k from a single plant's :meth:`get_state` (K plants)."""
        self._residual_sums[plant] = state.residual_sums[0]
        self._input_sums[plant] = state.input_sums[0]
        self._weight[plant], self._squared_weight[plant] = state.weights
        count = state.pending_residuals.shape[0]
        ring = self._ring[plant]
        ring[:] = state.ring[0]
        ring[self._history:self._history + count, 0] = state.pending_residuals[:, 0]
        ring[self._history:self._history + count, 1:] = state.pending_inputs[:, 0]
        self._cursors.set(plant, count)
        self._alarms[plant] = state.alarms[0]
        self._statistics[plant] = state.statistics[0]
        self._worst[plant] = state.worst[0]
        self._values[plant] = state.values[0]
        self._checks[plant] = int(state.checks)
        self._blocks[plant] = int(state.blocks)
        if not self.num_parameters:
            return
        q, ring = self._gradient_history, self._gradient_ring[plant]
        if self.settling:
            self._settling_sums[plant] = (0.0 if state.settling_sums is None
                                          else state.settling_sums[0])
        if state.gradient_sums is None:  # a state from before the parameter term
            self._gradient_sums[plant] = 0.0
            ring[:] = 0.0
            return
        self._gradient_sums[plant] = state.gradient_sums[0]
        ring[:] = state.gradient_ring[0]
        ring[q:q + count] = state.pending_gradients[:, 0]
