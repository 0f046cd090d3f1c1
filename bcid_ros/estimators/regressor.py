"""
The ARX information vector phi(t) of Ding et al. (2006), eqs. (53)-(55).

phi(t) = [-y(t-1) ... -y(t-n), u_1(t) ... u_1(t-n), ..., u_r(t) ... u_r(t-n)],
with the lag-0 input terms only when the model has direct feedthrough.
"""

from __future__ import annotations

import numpy as np


class ArxRegressor:
    """
    Ring buffer of the last n+1 samples that yields phi(t) with one gather.

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
        Whether phi(t) includes u_i(t).

    """

    def __init__(self, order: int, num_inputs: int, feedthrough: bool) -> None:
        self.order = order
        self.num_inputs = num_inputs
        self.feedthrough = feedthrough
        self.history = np.zeros((order + 1, 1 + num_inputs))
        self.position = 0
        self.filled = 0
        self._flat = self.history.reshape(-1)
        self._index = [self._gather_index(newest) for newest in range(order + 1)]

    def _gather_index(self, newest: int) -> np.ndarray:
        """Return the flat indices of phi(t) when sample t sits in row ``newest``."""
        rows, width = self.order + 1, 1 + self.num_inputs
        first_lag = 0 if self.feedthrough else 1
        index = [((newest - k) % rows) * width for k in range(1, self.order + 1)]
        for i in range(self.num_inputs):
            index.extend(((newest - k) % rows) * width + 1 + i
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
        self.position = position + 1 if position < self.order else 0
        if self.filled <= self.order:
            self.filled += 1
        return self._flat[self._index[position]]

    @property
    def ready(self) -> bool:
        """Whether every lag in phi(t) comes from a real sample."""
        return self.filled > self.order

    def clear(self) -> None:
        """Forget the history; phi is not ready until n+1 new samples arrive."""
        self.history[:] = 0.0
        self.position = 0
        self.filled = 0

    def regressors(self, y: np.ndarray, u: np.ndarray) -> np.ndarray:
        """
        Return the matrix of phi(t) for t = n..N-1 of whole arrays (batch form).

        Parameters
        ----------
        y : numpy.ndarray, shape ``(N,)``
            Outputs.
        u : numpy.ndarray, shape ``(N, r)``
            Inputs.

        Returns
        -------
        numpy.ndarray, shape ``(N - n, p)``
            Row j is phi(n + j), the regressor of the (j+1)-th update that
            :meth:`push` would make ready.

        """
        n = self.order
        count = y.shape[0]
        columns = [-y[n - k:count - k] for k in range(1, n + 1)]
        first_lag = 0 if self.feedthrough else 1
        for i in range(self.num_inputs):
            columns.extend(u[n - k:count - k, i] for k in range(first_lag, n + 1))
        return np.column_stack(columns)
