"""
The ARX information vector phi(t) of Ding et al. (2006), eqs. (53)-(55).

phi(t) = [-y(t-1) ... -y(t-n), u_1(t) ... u_1(t-n), ..., u_r(t) ... u_r(t-n)],
with the lag-0 input terms only when the model has direct feedthrough.
"""

from __future__ import annotations

import numpy as np


class ArxRegressor:
    """
    Sliding window of past samples that yields phi(t) with one fancy index.

    The window ``history`` has one row per lag k = 0..n holding
    ``[-y(t-k), u_1(t-k), ..., u_r(t-k)]``; pushing a sample shifts it by
    one row. phi(t) is then a fixed gather over that array, which costs the
    same whatever n and r are.

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
        self.filled = 0
        width = 1 + num_inputs
        first_lag = 0 if feedthrough else 1
        index = [k * width for k in range(1, order + 1)]
        for i in range(num_inputs):
            index.extend(k * width + 1 + i for k in range(first_lag, order + 1))
        self._index = np.array(index, dtype=np.intp)
        self._flat = self.history.reshape(-1)

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
        history = self.history
        history[1:] = history[:-1]
        history[0, 0] = -y
        history[0, 1:] = u
        if self.filled <= self.order:
            self.filled += 1
        return self._flat[self._index]

    @property
    def ready(self) -> bool:
        """Whether every lag in phi(t) comes from a real sample."""
        return self.filled > self.order

    def clear(self) -> None:
        """Forget the history; phi is not ready until n+1 new samples arrive."""
        self.history[:] = 0.0
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
