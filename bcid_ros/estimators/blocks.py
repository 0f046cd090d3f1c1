"""
A block of samples at an estimator's way in: its check, the error that ends it, its times.

:meth:`~bcid_ros.estimators.base.RecursiveEstimator.update_block` takes a block
of rows ``[y, u1, ..., ur]``; the identifier's feeders check their rows with the
same :func:`checked_rows`, catch :class:`BlockStopped` and report the
:class:`UpdateTimes` it recorded.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np


def checked_rows(rows: Any, num_inputs: int) -> np.ndarray:
    """
    Return ``rows`` as a float array of samples ``[y, u1, ..., ur]``, shape ``(k, 1 + r)``.

    Raises
    ------
    ValueError
        If the rows do not have 1 + ``num_inputs`` columns.

    """
    rows = np.asarray(rows, dtype=float)
    if rows.ndim != 2 or rows.shape[1] != 1 + num_inputs:
        raise ValueError(f'rows must have 1 + num_inputs = {1 + num_inputs} '
                         f'columns, got shape {rows.shape}')
    return rows


class BlockStopped(Exception):
    """
    A row's update raised in :meth:`RecursiveEstimator.update_block`; the block ended there.

    Attributes
    ----------
    taken : int
        The rows taken before the one that raised.
    error : Exception
        What its update raised (also the ``__cause__``).

    """

    def __init__(self, taken: int, error: Exception) -> None:
        super().__init__(f'the update of row {taken} raised {error!r}')
        self.taken = taken
        self.error = error


@dataclasses.dataclass(slots=True)
class UpdateTimes:
    """The count, total and largest time of updates since :meth:`take` (the diagnostics')."""

    count: int = 0
    total_ns: int = 0
    largest_ns: int = 0

    def add(self, count: int, total_ns: int = 0, largest_ns: int = 0) -> None:
        """Count ``count`` updates taking ``total_ns``, the longest ``largest_ns`` (0: untimed)."""
        self.count += count
        self.total_ns += total_ns
        self.largest_ns = max(self.largest_ns, largest_ns)

    def take(self) -> tuple[int, float, float]:
        """Return ``(updates, mean µs, max µs)`` since the last call, and start over."""
        count = self.count
        mean = self.total_ns / count / 1e3 if count else 0.0
        largest = self.largest_ns / 1e3
        self.count = self.total_ns = self.largest_ns = 0
        return count, mean, largest


__all__ = ['BlockStopped', 'UpdateTimes', 'checked_rows']
