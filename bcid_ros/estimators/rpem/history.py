r"""
The predictor state of the RPEM recursion: the lags that give phi(t) and psi(t).

Ljung and Söderström (1983) (L&S), the output-error predictor and the
recursive maximum-likelihood (ARMAX) one; Ljung, *System Identification*,
2nd ed. (1999), sec. 11.4. :class:`PredictorHistory` keeps the last samples
of the predictor (the simulated output w for OE, the measured y and the
residual for ARMAX) and gathers the regression vector
:math:`\varphi(t)`; :class:`RecursivePredictor` adds the gradient filter
:math:`\psi(t) = \varphi(t) / D(q)` (D = F for OE, C for ARMAX) with its n
lags, and moves both on with the values of each step.
"""

from __future__ import annotations

from typing import Any

import numpy as np


class PredictorHistory:
    """
    Ring buffer of the last samples that yields the regression vector phi(t) with one gather.

    Row ``k`` of ``history`` holds ``[-x, u_1, ..., u_r, e, 1]`` of one
    sample, where x is the output lag of the predictor (the simulated output
    w for OE, the measured y for ARMAX), e the residual lag (ARMAX) and 1 the
    constant of the offset. phi(t) is ``[-x(t-1) ... -x(t-n), u_i(t-d_i-k)
    ..., e(t-1) ... e(t-n), 1]``, the residual lags for ARMAX only, the 1
    with an offset only.

    Parameters
    ----------
    order : int
        n.
    num_inputs : int
        r.
    feedthrough : bool
        Whether phi(t) holds u_i(t-d_i).
    input_delay : tuple of int
        d_i of each input.
    residual_lags : bool
        Whether phi(t) holds the n residual lags (ARMAX).
    constant : bool
        Whether phi(t) ends with a 1 (the offset).

    """

    def __init__(self, order: int, num_inputs: int, feedthrough: bool,
                 input_delay: tuple[int, ...], residual_lags: bool, constant: bool) -> None:
        self.order = order
        self.residual_lags, self.constant = residual_lags, constant
        self.span = order + max(input_delay)
        self.width = 3 + num_inputs
        self.history = np.zeros((self.span + 1, self.width))
        self.history[:, -1] = 1.0
        self.position = 0
        self.filled = 0
        self._flat = self.history.reshape(-1)
        first_lag = 0 if feedthrough else 1
        rows, width = self.span + 1, self.width
        self._index = []
        for newest in range(rows):
            index = [((newest - k) % rows) * width for k in range(1, order + 1)]
            for i, delay in enumerate(input_delay):
                index.extend(((newest - k - delay) % rows) * width + 1 + i
                             for k in range(first_lag, order + 1))
            if residual_lags:
                index.extend(((newest - k) % rows) * width + width - 2
                             for k in range(1, order + 1))
            if constant:
                index.append(width - 1)
            self._index.append(np.array(index, dtype=np.intp))
        # x(t), x(t-1) ... x(t-n+1) of each newest row, for move_output_lags
        self._output_lags = [np.array([((newest - k) % rows) * width for k in range(order)],
                                      dtype=np.intp) for newest in range(rows)]

    def push(self, x: float, u: np.ndarray) -> np.ndarray:
        """Add sample t (x(t), u(t); e(t) = 0 until :meth:`set_newest`) and return phi(t)."""
        position = self.position
        row = self.history[position]
        row[0] = -x
        row[1:-2] = u
        row[-2] = 0.0
        self.position = position + 1 if position < self.span else 0
        if self.filled <= self.span:
            self.filled += 1
        return self._flat[self._index[position]]

    def level_output_lags(self) -> np.ndarray:
        """
        Set x(t-1) ... x(t-n) to their mean and return phi(t) again (OE after a restart).

        The simulated output of an oversampled OE model started from n noisy
        measured outputs takes their differences for slope and curvature and
        runs away from the data for hundreds of samples; started from their
        level it only carries one noise sample's error.
        """
        rows = self.span + 1
        newest = (self.position - 1) % rows
        lags = [(newest - k) % rows for k in range(1, self.order + 1)]
        self.history[lags, 0] = self.history[lags, 0].mean()
        return self._flat[self._index[newest]]

    def set_newest(self, x: float, e: float) -> None:
        """Replace x and e of the newest sample (the values of the step)."""
        row = self.history[self.position - 1]
        row[0] = -x
        row[-2] = e

    def move_output_lags(self, change: np.ndarray) -> None:
        """Add ``change[k]`` to x(t-k), k = 0 ... n - 1, t the newest sample."""
        self._flat[self._output_lags[self.position - 1]] -= change  # the rows hold -x

    def load_rows_oldest_first(self, rows: np.ndarray) -> None:
        """Make ``rows`` ``[-x, u_1 ... u_r, e]`` (oldest first) the content of the ring."""
        self.clear()
        count = min(rows.shape[0], self.span + 1)
        self.history[:count, :-1] = rows[rows.shape[0] - count:]
        self.filled = count
        self.position = count % (self.span + 1)

    def regressor(self, x: float, u: np.ndarray) -> np.ndarray | None:
        """
        Add sample t and return phi(t); None while the lags refill (after :meth:`clear`).

        Without residual lags (OE) the output lags are levelled when the lags are
        full again (:meth:`level_output_lags`).
        """
        filled = self.filled
        phi = self.push(x, u)
        if filled > self.span:  # full before this sample: the usual case
            return phi
        if filled < self.span:  # refilling
            return None
        # full with this sample
        return phi if self.residual_lags else self.level_output_lags()

    def set_prediction(self, y: float, prediction: float, theta: np.ndarray) -> None:
        """
        Store the lags of sample t at the model theta whose prediction phi(t)' theta is given.

        ARMAX (residual lags): e(t) = y(t) - prediction; OE: x(t) = w(t), the
        prediction without the offset (theta's last entry with a constant).
        """
        if self.residual_lags:
            self.set_newest(y, y - prediction)
        else:  # (e(t) is 0 since push)
            self.history[self.position - 1, 0] = -(
                prediction - theta[-1] if self.constant else prediction)

    def state_items(self, prefix: str = '') -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Return (arrays, scalars) of the ring: ``<prefix>history``, ``filled``, ``position``."""
        return ({f'{prefix}history': self.history},
                {f'{prefix}filled': self.filled, f'{prefix}position': self.position})

    def load_state(self, arrays: dict[str, np.ndarray], scalars: dict[str, Any],
                   prefix: str = '') -> None:
        """Take over what :meth:`state_items` made."""
        self.history[:] = arrays[f'{prefix}history']
        self.filled = int(scalars[f'{prefix}filled'])
        self.position = int(scalars[f'{prefix}position'])

    @property
    def ready(self) -> bool:
        """Whether every lag of phi(t) comes from a real sample."""
        return self.filled > self.span

    def clear(self) -> None:
        """Forget the history."""
        self.history[:, :-1] = 0.0
        self.position = 0
        self.filled = 0


class RecursivePredictor:
    r"""
    The predictor of the recursion and its gradient filter, at the current estimate.

    :meth:`regressors` gives :math:`\varphi(t)` and
    :math:`\psi(t) = \varphi(t) - d_1\psi(t-1) - \dots - d_n\psi(t-n)`;
    :meth:`advance` stores the lag of sample t at the estimate it is given
    (OE: :math:`w(t) = \varphi^T(t)\hat\theta` without the offset; ARMAX:
    :math:`\bar\varepsilon(t) = y(t) - \varphi^T(t)\hat\theta`; the
    recursion gives :math:`\hat\theta(t)`, a posteriori, or for OE under
    forgetting :math:`\hat\theta(t-1)`) and :math:`\psi(t)`. All in
    normalised units.

    Parameters
    ----------
    order, num_inputs, feedthrough, input_delay
        As for :class:`PredictorHistory`.
    armax : bool
        The ARMAX predictor (else OE).
    offset : bool
        Whether theta ends with the offset (``detrend: mean``).
    size : int
        The length of theta (and of psi).
    filter_slice : slice
        The coefficients of D in theta (F for OE, C for ARMAX).

    """

    def __init__(self, order: int, num_inputs: int, feedthrough: bool,
                 input_delay: tuple[int, ...], armax: bool, offset: bool, size: int,
                 filter_slice: slice) -> None:
        self.history = PredictorHistory(order, num_inputs, feedthrough, input_delay, armax,
                                        offset)
        self.psi_history = np.zeros((order, size))
        self._armax = armax
        self._offset = offset
        self._order = order
        self._filter = filter_slice
        # the estimate whose D coefficients (a view of it) regressors last took
        self._theta: np.ndarray | None = None
        self._coefficients = np.zeros(order)

    def fill(self, y: float, u: np.ndarray) -> None:
        """Take a sample before the first fit (no estimate yet: the lags only)."""
        self.history.push(y, u)

    def regressors(self, yn: float, un: np.ndarray,
                   theta: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """Take sample t (normalised) and return (phi(t), psi(t)); None while the lags refill."""
        phi = self.history.regressor(yn, un)
        if phi is None:  # refilling the lags after a restart
            return None
        if theta is not self._theta:  # (the view is kept: the estimate moves in place)
            self._theta, self._coefficients = theta, theta[self._filter]
        # psi(t) = phi(t) - d_1 psi(t-1) - ... - d_n psi(t-n)
        psi = phi - self._coefficients.dot(self.psi_history)
        return phi, psi

    def advance(self, yn: float, phi: np.ndarray, psi: np.ndarray, theta: np.ndarray) -> None:
        """Move the predictor on: the lags of sample t at ``theta``, and psi(t)."""
        # the lags: e(t) = y(t) - phi(t)' theta (ARMAX), w(t) = phi(t)' theta (OE)
        self.history.set_prediction(yn, float(phi.dot(theta)), theta)
        psi_history = self.psi_history
        if self._order == 2:  # (a row copied costs half of a block moved)
            psi_history[1] = psi_history[0]
        elif self._order > 2:
            psi_history[1:] = psi_history[:-1]
        psi_history[0] = psi
        if self._offset and not self._armax:
            psi_history[0, -1] = 0.0  # the OE offset's gradient is 1, not filtered by 1/F

    def follow(self, step: np.ndarray) -> None:
        r"""
        Move the simulated output lags (OE) to the estimate after a step, to first order.

        :math:`w(t-k, \hat\theta + \Delta) \approx w(t-k) + \psi^T(t-k)\Delta`,
        k = 0 ... n - 1 (psi is the gradient of the simulated output): the lags
        of phi(t + 1) are then those of the current estimate, where the
        recursion's own lags hold the estimates of their time.
        """
        self.history.move_output_lags(self.psi_history.dot(step))

    def load(self, x: np.ndarray, u: np.ndarray, e: np.ndarray, psi: np.ndarray) -> None:
        """Continue from the lags x, u, e (oldest first) and psi(t-1) ... psi(t-n) of a fit."""
        self.history.load_rows_oldest_first(np.column_stack((-x, u, e)))
        self.psi_history[:] = psi

    def clear(self) -> None:
        """Forget the lags (a reset, or a restart of the regressor)."""
        self.history.clear()
        self.psi_history[:] = 0.0

    def state_items(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Return (arrays, scalars) of the lags under the estimator's state names."""
        arrays, scalars = self.history.state_items()
        return {'psi_history': self.psi_history, **arrays}, scalars

    def load_state(self, arrays: dict[str, np.ndarray], scalars: dict[str, Any]) -> None:
        """Take over what :meth:`state_items` made."""
        self.psi_history = arrays['psi_history']
        self.history.load_state(arrays, scalars)
