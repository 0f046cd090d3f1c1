r"""
Exponentially weighted lagged products of a stream of rows, added a block at a time.

The HAC covariance (:mod:`bcid_ros.estimators.hac`) keeps

.. math::

    S(k) = \sum_t w_t\, z_t z_{t-k}^T, \quad k = 0 \ldots L, \qquad
    w_t = \mu^{T - t},

of its scores :math:`z_t` (the newest row has weight 1). A row costs one
list append; every ``BLOCK`` rows the block is added in one matrix product:
the rows of the block times the windows :math:`[z_t, z_{t-1}, \ldots,
z_{t-L}]` (a strided view of the block and the L rows before it). At
p = 6, L = 17 that took 18 us per block of 64 rows where one product per lag
(as ``bcrls.add_lagged_moments`` does) took 32 us, on the same machine.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

#: Rows kept in lists before they are added to the sums in one product.
BLOCK = 64


def add_lagged_products(sums: np.ndarray, context: np.ndarray, rows: np.ndarray,
                        decay: float) -> np.ndarray:
    r"""
    Return the lagged product sums with a block of new rows added.

    Parameters
    ----------
    sums : numpy.ndarray, shape ``(..., d, d, L + 1)``
        :math:`S(k)_{ab} = \sum_t w_t z_{t,a} z_{t-k,b}` at ``[..., a, b, k]``.
    context : numpy.ndarray, shape ``(..., L, d)``
        The L rows before the block, oldest first (zeros before the start).
    rows : numpy.ndarray, shape ``(..., m, d)``
        The new rows, oldest first. Leading dimensions are plants.
    decay : float
        :math:`\mu`: the old sums are multiplied by :math:`\mu^m`, the rows by
        :math:`\mu^{\mathrm{age}}` (the newest by 1).

    Returns
    -------
    numpy.ndarray, shape ``(..., d, d, L + 1)``
        The new sums (a new array).

    """
    count, width = rows.shape[-2], rows.shape[-1]
    lags = sums.shape[-1] - 1
    ring = np.concatenate((context, rows), axis=-2)
    # windows[..., t, b, k] = z_{t-k, b}: the window of each new row, newest first
    windows = sliding_window_view(ring, lags + 1, axis=-2)[..., ::-1]
    right = windows.reshape(windows.shape[:-3] + (count, width * (lags + 1)))
    if decay == 1.0:
        left = rows
    else:
        # w = mu^(age): the newest row has weight 1
        left = rows * (decay ** np.arange(count - 1, -1, -1, dtype=float))[:, None]
    block = np.swapaxes(left, -1, -2) @ right
    return sums * decay ** count + block.reshape(sums.shape)


def decayed_weights(weight: float, squared: float, count: int,
                    decay: float) -> tuple[float, float]:
    r"""
    Return :math:`\sum w` and :math:`\sum w^2` after ``count`` more rows with forgetting ``decay``.

    Each new row has weight 1 and multiplies the old weights by :math:`\mu`
    (their squares by :math:`\mu^2`).
    """
    if decay == 1.0:
        return weight + count, squared + count
    factor, factor2 = decay ** count, decay ** (2 * count)
    return (weight * factor + (1.0 - factor) / (1.0 - decay),
            squared * factor2 + (1.0 - factor2) / (1.0 - decay * decay))


class LaggedProducts:
    r"""
    The lagged product sums of :func:`add_lagged_products` fed one row at a time.

    Parameters
    ----------
    width : int
        d, the length of a row.
    lags : int
        L, the largest lag kept.
    decay : float
        :math:`\mu` in (0, 1].
    plants : int, optional
        K: rows are ``(K, d)``. None: rows are ``(d,)`` (one plant).

    """

    def __init__(self, *, width: int, lags: int, decay: float, plants: int | None = None) -> None:
        self.width = width
        self.lags = lags
        self.decay = decay
        self.plants = plants
        self._lead = () if plants is None else (plants,)
        self.reset()

    def reset(self) -> None:
        """Forget every row."""
        self.sums = np.zeros(self._lead + (self.width, self.width, self.lags + 1))
        self.context = np.zeros(self._lead + (self.lags, self.width))
        self.pending: list[Any] = []
        #: sum of the weights and of their squares over the rows in the sums
        self.weight = 0.0
        self.squared_weight = 0.0
        #: rows in the sums
        self.count = 0

    def append(self, row: Any) -> bool:
        """Keep ``row`` (by reference: do not change it); return whether a block was added."""
        pending = self.pending
        pending.append(row)
        if len(pending) < BLOCK:
            return False
        self.flush()
        return True

    def flush(self) -> None:
        """Add the pending rows to the sums."""
        if not self.pending:
            return
        rows = np.array(self.pending, dtype=float)  # (m, d) or (m, K, d)
        self.pending = []
        self.add(rows)

    def add(self, rows: np.ndarray) -> None:
        """
        Add a block of rows, ``(m, d)`` or ``(m, K, d)``, oldest first, to the sums.

        Non-finite rows count as zero rows (their weight still counts).
        """
        if self.plants is not None:
            rows = np.swapaxes(rows, 0, 1)
        finite = np.isfinite(rows).all(axis=-1)
        if not finite.all():
            rows = np.where(finite[..., None], rows, 0.0)
        self.sums = add_lagged_products(self.sums, self.context, rows, self.decay)
        ring = np.concatenate((self.context, rows), axis=-2)
        self.context = ring[..., ring.shape[-2] - self.lags:, :].copy()
        self.weight, self.squared_weight = decayed_weights(
            self.weight, self.squared_weight, rows.shape[-2], self.decay)
        self.count += rows.shape[-2]

    def lag(self, k: int) -> np.ndarray:
        """Return S(k), shape ``(..., d, d)``, of the rows added so far."""
        return self.sums[..., k]

    def state(self) -> dict[str, Any]:
        """Return copies of everything that defines the sums and the pending rows."""
        pending = np.array(self.pending, dtype=float).reshape(
            (len(self.pending),) + self._lead + (self.width,))
        return {'sums': self.sums.copy(), 'context': self.context.copy(), 'pending': pending,
                'weight': self.weight, 'squared_weight': self.squared_weight,
                'count': self.count}

    def load(self, state: dict[str, Any]) -> None:
        """Continue from a :meth:`state`."""
        self.sums = np.array(state['sums'], dtype=float)
        self.context = np.array(state['context'], dtype=float)
        self.pending = list(np.array(state['pending'], dtype=float))
        self.weight = float(state['weight'])
        self.squared_weight = float(state['squared_weight'])
        self.count = int(state['count'])
