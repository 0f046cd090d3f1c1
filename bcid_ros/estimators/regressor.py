"""
The ARX information vector phi(t) of Ding et al. (2006), eqs. (53)-(55).

phi(t) = [-y(t-1) ... -y(t-n), u_1(t) ... u_1(t-n), ..., u_r(t) ... u_r(t-n)],
with the lag-0 input terms only when the model has direct feedthrough. With a
dead time d_i on input i its terms are u_i(t-d_i) ... u_i(t-d_i-n): the
regression of the undelayed model on the shifted input u_i(t-d_i), which is
why every estimate and its bias compensation carry over unchanged
(docs/estimators.md, "Dead time").
"""

from __future__ import annotations

from typing import Any

import numpy as np


def phi_channels(order: int, num_inputs: int, feedthrough: bool) -> np.ndarray:
    """Return the signal channel (0 = y, i = u_i) of each component of phi(t), shape ``(p,)``."""
    lags = order + (1 if feedthrough else 0)
    return np.array([0] * order + [i for i in range(1, num_inputs + 1) for _ in range(lags)],
                    dtype=np.intp)


class ArxRegressor:
    """
    Ring buffer of the last n+1+max(d_i) samples that yields phi(t) with one gather.

    Row ``k`` of ``history`` holds ``[-y, u_1, ..., u_r]`` of some sample;
    the newest sample goes to row ``position`` and overwrites the oldest.
    For each position a precomputed index picks phi(t) out of the buffer, so
    a push costs one row write and one gather whatever n and r are.

    Parameters
    ----------
    order : int
        n, the number of output lags.
    num_inputs : int
        r.
    feedthrough : bool
        Whether phi(t) includes u_i(t) (u_i(t-d_i) with a delay).
    input_delay : sequence of int, optional
        Dead time d_i of each input; None means none.

    """

    def __init__(self, order: int, num_inputs: int, feedthrough: bool,
                 input_delay: Any = None) -> None:
        self.order = order
        self.num_inputs = num_inputs
        self.feedthrough = feedthrough
        self.input_delay = tuple([0] * num_inputs if input_delay is None else input_delay)
        #: The oldest lag in phi(t): n + max(d_i).
        self.span = order + max(self.input_delay)
        self.history = np.zeros((self.span + 1, 1 + num_inputs))
        self.position = 0
        self.filled = 0
        self._flat = self.history.reshape(-1)
        self._index = [self._gather_index(newest) for newest in range(self.span + 1)]

    def _gather_index(self, newest: int) -> np.ndarray:
        """Return the flat indices of phi(t) when sample t sits in row ``newest``."""
        rows, width = self.span + 1, 1 + self.num_inputs
        first_lag = 0 if self.feedthrough else 1
        index = [((newest - k) % rows) * width for k in range(1, self.order + 1)]
        for i, delay in enumerate(self.input_delay):
            index.extend(((newest - k - delay) % rows) * width + 1 + i
                         for k in range(first_lag, self.order + 1))
        return np.array(index, dtype=np.intp)

    def push(self, y: float, u: np.ndarray) -> np.ndarray:
        """
        Add sample t and return phi(t), which uses y up to t-1 and u up to t.

        Parameters
        ----------
        y : float
            y(t); it enters phi only from t+1 on.
        u : numpy.ndarray, shape ``(r,)``
            u(t).

        Returns
        -------
        numpy.ndarray, shape ``(p,)``
            phi(t), a fresh array.

        """
        position = self.position
        row = self.history[position]
        row[0] = -y
        row[1:] = u
        self.position = position + 1 if position < self.span else 0
        if self.filled <= self.span:
            self.filled += 1
        return self._flat[self._index[position]]

    def push_rows(self, rows: np.ndarray) -> np.ndarray:
        """
        Add samples ``rows`` (``[y, u1, ..., ur]`` each, oldest first); return phi(t) of each.

        The same as :meth:`push` on each row in turn, ring included, with one
        gather for the block: the history in time order and the new rows are laid
        end to end, where every phi(t) sits at the same offsets from its sample's row.

        Returns
        -------
        numpy.ndarray, shape ``(k, p)``
            Row j is phi of ``rows[j]``.

        """
        rows_kept, width = self.span + 1, 1 + self.num_inputs
        position = self.position
        laid = np.empty((rows_kept + rows.shape[0], width))
        laid[:rows_kept - position] = self.history[position:]
        laid[rows_kept - position:rows_kept] = self.history[:position]
        laid[rows_kept:, 0] = -rows[:, 0]
        laid[rows_kept:, 1:] = rows[:, 1:]
        # the gather of the newest row without wrapping, as offsets from that row
        offsets = self._gather_index(self.span) - self.span * width
        starts = np.arange(rows_kept, laid.shape[0]) * width
        phis = laid.reshape(-1)[starts[:, None] + offsets]
        # the ring as push would leave it: the oldest row kept where the next one goes
        newest = laid[laid.shape[0] - rows_kept:]
        position = (position + rows.shape[0]) % rows_kept
        self.history[position:] = newest[:rows_kept - position]
        self.history[:position] = newest[rows_kept - position:]
        self.position = position
        self.filled = min(self.filled + rows.shape[0], rows_kept)
        return phis

    def peaks(self) -> np.ndarray:
        """
        Return the largest magnitude per channel (y, u_1 ... u_r) over the lags phi uses.

        That is y(t) ... y(t-n) and u_i(t-d_i) ... u_i(t-d_i-n) of the newest
        sample t: without delays, the whole history.
        """
        magnitude = np.abs(self.history)
        if not any(self.input_delay):
            return magnitude.max(axis=0)
        rows = self.span + 1
        newest = (self.position - 1) % rows
        lags = np.arange(self.order + 1)
        peaks = np.empty(1 + self.num_inputs)
        peaks[0] = magnitude[(newest - lags) % rows, 0].max()
        for i, delay in enumerate(self.input_delay):
            peaks[1 + i] = magnitude[(newest - lags - delay) % rows, 1 + i].max()
        return peaks

    @property
    def ready(self) -> bool:
        """Whether every lag in phi(t) comes from a real sample."""
        return self.filled > self.span

    def clear(self) -> None:
        """Forget the history; phi is not ready until n+1+max(d_i) new samples arrive."""
        self.history[:] = 0.0
        self.position = 0
        self.filled = 0

    def regressors(self, y: np.ndarray, u: np.ndarray) -> np.ndarray:
        """
        Return the matrix of phi(t) for t = n+max(d_i)..N-1 of whole arrays (batch form).

        Parameters
        ----------
        y : numpy.ndarray, shape ``(N,)``
            Outputs.
        u : numpy.ndarray, shape ``(N, r)``
            Inputs.

        Returns
        -------
        numpy.ndarray, shape ``(N - n - max(d_i), p)``
            Row j is phi(n + max(d_i) + j), the regressor of the (j+1)-th
            update that :meth:`push` would make ready.

        """
        n, start = self.order, self.span
        count = y.shape[0]
        columns = [-y[start - k:count - k] for k in range(1, n + 1)]
        first_lag = 0 if self.feedthrough else 1
        for i, delay in enumerate(self.input_delay):
            columns.extend(u[start - k - delay:count - k - delay, i]
                           for k in range(first_lag, n + 1))
        return np.column_stack(columns)
