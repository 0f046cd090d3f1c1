"""
The simulation check's windows of K plants, recorded together (the batched estimators).

:class:`SimulationWindows` holds every plant's samples in one ring, so a batched update
records them in a few numpy operations; each plant's window is a
:class:`~bcid_ros.estimators.simulation_check.SimulationWindow` on its rows there, so the
check, the snapshot and a restart of one plant are the one-plant window's own code.
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from bcid_ros.estimators.simulation_check import (numerator_lags, SAMPLES_PER_PARAMETER,
                                                  SimulationWindow, state_count,
                                                  window_length)


class SimulationWindows:
    """
    The :class:`SimulationWindow` of each of K plants of one structure, recorded together.

    The batched estimators record every stepped plant's sample at once (:meth:`record`,
    a few numpy operations on a ``(K, 2L, 1 + r)`` ring, where K windows would take K
    Python calls a sample); ``windows[k]`` is plant k's window, a
    :class:`SimulationWindow` whose samples and counters are plant k's rows here, for what
    is done per plant (its check, its snapshot, its restart). The windows share lambda, so
    :meth:`follow_forgetting_factor` sets L for all of them.

    Parameters
    ----------
    plants : int
        K.
    order, num_inputs, feedthrough, input_delay, forgetting_factor
        As for :class:`SimulationWindow`, shared by all plants.

    """

    def __init__(self, plants: int, order: int, num_inputs: int, feedthrough: bool,
                 input_delay: Sequence[int], forgetting_factor: float = 1.0) -> None:
        self.order = order
        self.lags = numerator_lags(order, num_inputs, feedthrough, input_delay)
        self.minimum = SAMPLES_PER_PARAMETER * (state_count(order, self.lags) + 1 + order
                                                + self.lags.size)
        self.window = window_length(forgetting_factor)
        self._rows = np.zeros((plants, 2 * self.window, 1 + num_inputs))
        # each plant's counters of SimulationWindow (_end, _filled, _since, _judged,
        # _recorded)
        self._recorded = np.zeros(plants, dtype=np.int64)
        self._end = np.zeros(plants, dtype=np.int64)
        self._filled = np.zeros(plants, dtype=np.int64)
        self._since = np.zeros(plants, dtype=np.int64)
        self._judged = np.zeros(plants, dtype=bool)
        self._windows = [_PlantWindow(self, plant) for plant in range(plants)]

    def __getitem__(self, plant: int) -> SimulationWindow:
        return self._windows[plant]

    def __len__(self) -> int:
        return len(self._windows)

    def __iter__(self) -> Any:
        return iter(self._windows)

    def record(self, plants: np.ndarray, y: np.ndarray, u: np.ndarray) -> None:
        """Keep one sample of each of ``plants`` (distinct), as :meth:`SimulationWindow.record`."""
        end = self._end[plants]
        full = end == self._rows.shape[1]
        if full.any():
            moved = plants[full]
            self._rows[moved, :self.window] = self._rows[moved, self.window:]
            end[full] = self.window
        self._rows[plants, end, 0] = y
        self._rows[plants, end, 1:] = u
        self._end[plants] = end + 1
        filled = np.minimum(self._filled[plants] + 1, self.window)
        self._filled[plants] = filled
        self._since[plants] += 1
        self._recorded[plants] += 1
        self._judged[plants[filled < self.minimum]] = False

    def gap(self, plants: np.ndarray) -> None:
        """Forget the samples of ``plants``, keep their verdicts (:meth:`SimulationWindow.gap`)."""
        self._end[plants] = 0
        self._filled[plants] = 0
        self._since[plants] = 0
        self._judged[plants] = False

    def clear(self, plants: np.ndarray) -> None:
        """Forget the samples and verdicts of ``plants`` (:meth:`SimulationWindow.clear`)."""
        for plant in plants.tolist():
            self._windows[plant].clear()

    def follow_forgetting_factor(self, forgetting_factor: float) -> None:
        """Take the window length of a new lambda for every plant, keeping the last samples."""
        window = window_length(forgetting_factor)
        if window == self.window:
            return
        kept = np.minimum(self._filled, window)
        rows = np.zeros((len(self), 2 * window, self._rows.shape[2]))
        for plant, (count, end) in enumerate(zip(kept.tolist(), self._end.tolist())):
            rows[plant, :count] = self._rows[plant, end - count:end]
        self.window, self._rows = window, rows
        self._end[:] = kept
        self._filled[:] = kept
        self._judged[:] = False


def _plant_entry(name: str, kind: type) -> property:
    """Return a property that reads and writes plant k's entry of the windows' array ``name``."""
    def read(window: _PlantWindow) -> Any:
        return kind(getattr(window._windows, name)[window._plant])

    def write(window: _PlantWindow, value: Any) -> None:
        getattr(window._windows, name)[window._plant] = value

    return property(read, write)


class _PlantWindow(SimulationWindow):
    """Plant k's :class:`SimulationWindow` in a :class:`SimulationWindows`: its rows there."""

    def __init__(self, windows: SimulationWindows, plant: int) -> None:  # noqa: D107
        self._windows = windows
        self._plant = plant
        self.order = windows.order
        self.lags = windows.lags
        self.minimum = windows.minimum
        self.looks_at_tail = False  # the batched estimators take no change from the check
        self.clear()  # the verdict and the run as a new window's (its counters are zeros)

    def follow_forgetting_factor(self, forgetting_factor: float) -> None:
        """Take the window length of a new lambda (shared: every plant's window takes it)."""
        self._windows.follow_forgetting_factor(forgetting_factor)

    @property
    def window(self) -> int:  # noqa: D102
        return self._windows.window

    @property
    def _rows(self) -> np.ndarray:
        return self._windows._rows[self._plant]

    # SimulationWindow's counters, as plant k's entries of the windows' arrays
    _end = _plant_entry('_end', int)
    _filled = _plant_entry('_filled', int)
    _since = _plant_entry('_since', int)
    _judged = _plant_entry('_judged', bool)
    _recorded = _plant_entry('_recorded', int)


__all__ = ['SimulationWindows']
