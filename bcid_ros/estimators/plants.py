"""
What the batched estimators keep per plant besides the estimates: histories, reasons, size.

And the sample policy per plant, which the single-plant feeder, the many-joint feeder and
the batched estimators share: :func:`usable_samples`.

The K plants of one structure share one array per quantity (a leading plant
axis); these classes hold the bookkeeping around the estimates, so that the
batched estimators (:mod:`~bcid_ros.estimators.batched`) hold only their
recursions.
"""

from __future__ import annotations

from typing import Any, Iterable

import numpy as np


def usable_samples(y: np.ndarray, u: np.ndarray, present: np.ndarray | None = None) -> np.ndarray:
    """
    Return which samples are used: those present, with a finite output and finite inputs.

    The sample policy per plant (docs/nodes.md): the others are counted and
    restart their plant's regressor, and no other plant is touched. ``y``
    shape ``(K,)``, ``u`` ``(K,)`` or ``(K, r)``, ``present`` ``(K,)`` (None:
    all); K plants at one time, or one plant's K samples in a row.
    """
    usable = np.isfinite(y) & np.isfinite(u).reshape(y.shape[0], -1).all(axis=1)
    return usable if present is None else usable & present


class StackedRegressors:
    """
    The regressor histories of K plants of one structure (no dead time), shifted together.

    ``history[k, j]`` is ``[-y, u_1, ..., u_r]`` of plant k's sample t - j
    (j = 0 newest), so phi(t) of every plant is one gather with one fixed
    index. A plant whose history was cleared is ready again after n + 1
    pushes; the pushes are counted for all plants at once.

    Parameters
    ----------
    num_plants, order, num_inputs, feedthrough
        K, n, r and whether phi(t) holds u_i(t).

    """

    def __init__(self, num_plants: int, order: int, num_inputs: int,
                 feedthrough: bool) -> None:
        self.order = order
        rows, width = order + 1, 1 + num_inputs
        self.history = np.zeros((num_plants, rows, width))
        self._flat = self.history.reshape(num_plants, rows * width)
        first_lag = 0 if feedthrough else 1
        index = [lag * width for lag in range(1, order + 1)]
        for i in range(num_inputs):
            index.extend(lag * width + 1 + i for lag in range(first_lag, order + 1))
        self._index = np.array(index, dtype=np.intp)
        #: Pushes so far, and the push count at each plant's last clear.
        self.pushes = 0
        self.cleared_at = np.zeros(num_plants, dtype=np.int64)
        self._last_clear = 0

    def push(self, y: np.ndarray, u: np.ndarray) -> None:
        """Shift every plant's history by one sample and put ``y`` ``(K,)``, ``u`` ``(K, r)``."""
        history = self.history
        history[:, 1:] = history[:, :-1]
        history[:, 0, 0] = -y
        history[:, 0, 1:] = u
        self.pushes += 1

    def clear(self, rows: Any) -> None:
        """Empty the histories of ``rows``; they refill from the next push on."""
        self.history[rows] = 0.0
        self.cleared_at[rows] = self.pushes
        self._last_clear = self.pushes

    def ready_rows(self) -> slice | np.ndarray | None:
        """Return the plants whose phi(t) is filled: a slice if all, else indices or None."""
        if self.pushes - self._last_clear > self.order:
            return slice(None)
        ready = np.flatnonzero(self.pushes - self.cleared_at > self.order)
        if ready.size == self.cleared_at.size:
            return slice(None)
        return ready if ready.size else None

    def phi(self, rows: Any) -> np.ndarray:
        """Return the regressors of the plants ``rows`` at t, shape ``(k, p)``."""
        # take, not [:, index]: fancy indexing lays the result out by columns, and
        # BLAS ddot sums a strided row in another order than the single plant's phi
        return self._flat[rows].take(self._index, axis=1)

    def peaks(self, plants: np.ndarray) -> np.ndarray:
        """Return the largest magnitude per channel of each of ``plants``, ``(k, 1 + r)``."""
        return np.abs(self.history[plants]).max(axis=1)

    def plant_ring(self, plant: int) -> tuple[np.ndarray, int, int]:
        """
        Return plant k's history as a single plant's ring: (history, filled, position).

        The ring is that of :class:`~bcid_ros.estimators.regressor.ArxRegressor`.
        """
        rows = self.order + 1
        pushes = self.pushes - int(self.cleared_at[plant])
        position = pushes % rows
        # the single-plant regressor is a ring: sample t - j sits in row position - 1 - j
        ring = np.zeros_like(self.history[plant])
        for lag in range(min(pushes, rows)):
            ring[(position - 1 - lag) % rows] = self.history[plant, lag]
        return ring, min(pushes, rows), position

    def load_plant_ring(self, plant: int, ring: np.ndarray, filled: int, position: int) -> None:
        """Take over plant k's history from a single plant's ring (as :meth:`plant_ring`)."""
        rows = self.order + 1
        pushes = filled if filled < rows else rows + position
        self.cleared_at[plant] = self.pushes - pushes
        self._last_clear = max(self._last_clear, self.pushes - pushes)
        history = np.zeros_like(self.history[plant])
        for lag in range(min(filled, rows)):
            history[lag] = ring[(position - 1 - lag) % rows]
        self.history[plant] = history


class PlantReasons:
    """The validity reasons of K plants: a flag per plant, and the reasons where there are any."""

    def __init__(self, num_plants: int) -> None:
        #: Whether plant k has reasons not to be trusted, shape ``(K,)``.
        self.any = np.zeros(num_plants, dtype=bool)
        self._reasons: dict[int, tuple[str, ...]] = {}

    def of(self, plant: int) -> tuple[str, ...]:
        """Return plant k's reasons (empty when it has none)."""
        return self._reasons.get(plant, ())

    def set(self, plant: int, reasons: Iterable[str]) -> None:
        """Make ``reasons`` plant k's (none: it has none)."""
        reasons = tuple(reasons)
        self.any[plant] = bool(reasons)
        if reasons:
            self._reasons[plant] = reasons
        else:
            self._reasons.pop(plant, None)

    def clear(self, plants: np.ndarray) -> None:
        """Forget the reasons of ``plants`` (an index array)."""
        for plant in plants.tolist():
            self.set(plant, ())


def held_nbytes(holder: Any) -> int:
    """
    Return the bytes of every numpy array that ``holder`` holds, its helpers' included.

    Helpers are the objects of this package that ``holder`` (or a helper)
    keeps as attributes; an array shared by views is counted once.
    """
    arrays: dict[int, np.ndarray] = {}
    holders, seen = [holder], set()
    while holders:
        current = holders.pop()
        seen.add(id(current))
        for value in vars(current).values():
            if isinstance(value, np.ndarray):
                owner = value if value.base is None else value.base
                if isinstance(owner, np.ndarray):
                    arrays[id(owner)] = owner
            elif isinstance(value, dict):
                arrays.update((id(item), item) for item in value.values()
                              if isinstance(item, np.ndarray))
            elif hasattr(value, '__dict__') and id(value) not in seen and \
                    type(value).__module__.startswith('bcid_ros.estimators'):
                holders.append(value)
    return sum(array.nbytes for array in arrays.values())


__all__ = ['PlantReasons', 'StackedRegressors', 'held_nbytes', 'usable_samples']
