r"""
The predictor of one stored segment at fixed parameters: the prediction errors and their gradients.

The batch fits of RPEM (:mod:`~bcid_ros.estimators.rpem.fit`) run the same
predictor as the recursion with theta held fixed (Ljung, *System
Identification*, 2nd ed., 1999, ch. 10; Ljung and Söderström 1983 for the
predictors), over a gap-free segment ``(y, u, weights)`` of the stored
samples in normalised units:

* OE: :math:`w = \sum_i B_i u_i / F` plus the free response of F from a
  fitted initial state, :math:`\varepsilon = y - w - c`,
  :math:`\psi = \varphi(w) / F`;
* ARMAX: :math:`\varepsilon = (A y - \sum_i B_i u_i - d) / C` from rest,
  :math:`\psi = \varphi / C`.

The initial state and the offset enter linearly and are fitted by weighted
least squares at every theta (variable projection).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

#: Information (normalised units) of the prior that shrinks the OE initial state of a
#: fit towards 0: where a slow pole makes the start-up transient a near constant over a
#: segment, the data cannot tell it from the offset, and the level goes to the offset
#: (measured on DaISy's wall: without it a fit after one gate refusal put 1.3 units of
#: level in the offset and the validation fit fell from 76 to -40).
INITIAL_PRIOR = 10.0
#: |h| below which the impulse response of 1/F is taken as 0 (:func:`impulse_response`):
#: added to what the free responses meet (sizes of order 1 in normalised units) it changes
#: no bit, and it and its square stay clear of the subnormal numbers, whose arithmetic is
#: tens of times slower on x86 (a fast pole's response reaches them within a few hundred
#: samples: the loss passes of a third-order fit with a pole at 0.6 took 3 times as long, and
#: a spread fit's updates 13 ms where they take 4).
NEGLIGIBLE = 1e-150
#: The first block of :func:`impulse_response`; each next one is twice as long.
FIRST_BLOCK = 256


class Prediction(NamedTuple):
    """
    The predictor of one segment at fixed parameters (see :meth:`SegmentPredictor.predict`).

    Attributes
    ----------
    eps : numpy.ndarray, shape ``(T - span,)``
        Prediction errors of the usable samples.
    psi : numpy.ndarray, shape ``(T - span, p)``
        Their gradients with respect to theta (the nuisance held).
    x, e : numpy.ndarray, shape ``(T,)``
        The output and residual lags of every sample (for the recursion).
    nuisance : numpy.ndarray or None, shape ``(T - span, m)``
        The columns of the linear nuisance fitted at every theta (OE start-up
        transient, offset), or None.
    offset : float
        The fitted offset (0 without one).
    offset_gradient : numpy.ndarray or None, shape ``(T - span,)``
        The gradient of the prediction with respect to the offset.

    """

    eps: np.ndarray
    psi: np.ndarray
    x: np.ndarray
    e: np.ndarray
    nuisance: np.ndarray | None
    offset: float
    offset_gradient: np.ndarray | None


class SegmentPredictor:
    """
    The OE or ARMAX predictor over a segment, its regressors, at a fixed theta (normalised).

    Parameters
    ----------
    order : int
        n.
    num_inputs : int
        r.
    feedthrough : bool
        Whether the regressors hold u_i(t-d_i).
    input_delay : tuple of int
        d_i of each input.
    armax : bool
        The ARMAX predictor (else OE).
    offset : bool
        Whether the model carries an offset (``detrend: mean``).

    """

    def __init__(self, order: int, num_inputs: int, feedthrough: bool,
                 input_delay: tuple[int, ...], armax: bool, offset: bool) -> None:
        from scipy import signal  # only a fit needs it

        self._signal = signal
        self.order = order
        self.num_inputs = num_inputs
        self.first_lag = 0 if feedthrough else 1
        self.input_delay = input_delay
        self.armax = armax
        self.offset = offset
        self.span = order + max(input_delay)
        self.lags = order + 1 - self.first_lag
        self.num_b = num_inputs * self.lags
        self.num_parameters = order + self.num_b + (order if armax else 0)

    # ----------------------------------------------------------- regressors
    @staticmethod
    def lagged(x: np.ndarray, lag: int) -> np.ndarray:
        """Return x delayed by ``lag`` samples, zeros before the first."""
        out = np.zeros_like(x)
        if lag < x.shape[0]:
            out[lag:] = x[:x.shape[0] - lag]
        return out

    def input_columns(self, u: np.ndarray) -> np.ndarray:
        """Return the input lags u_i(t-d_i-k) of every t of a segment, shape ``(T, r lags)``."""
        columns = []
        for i, delay in enumerate(self.input_delay):
            columns.extend(self.lagged(u[:, i], delay + k)
                           for k in range(self.first_lag, self.order + 1))
        return np.column_stack(columns)

    def output_columns(self, x: np.ndarray) -> np.ndarray:
        """Return the output lags -x(t-1) ... -x(t-n) of every t, shape ``(T, n)``."""
        return np.column_stack([-self.lagged(x, k) for k in range(1, self.order + 1)])

    def residual_columns(self, e: np.ndarray) -> np.ndarray:
        """Return the residual lags e(t-1) ... e(t-n) of every t (ARMAX), shape ``(T, n)``."""
        return np.column_stack([self.lagged(e, k) for k in range(1, self.order + 1)])

    def with_constant(self, columns: np.ndarray) -> np.ndarray:
        """Append a column of ones when the model has an offset."""
        if not self.offset:
            return columns
        return np.column_stack((columns, np.ones(columns.shape[0])))

    # ----------------------------------------------------------- predictor
    def predict(self, theta: np.ndarray, y: np.ndarray, u: np.ndarray, weights: np.ndarray,
                inputs: np.ndarray | None = None, initial_state: bool = True,
                gradient: bool = True, prior: float = INITIAL_PRIOR) -> Prediction:
        """
        Return the :class:`Prediction` of one segment at fixed ``theta``.

        For OE the initial lags w(span-1) ... w(span-n) (and the offset) are
        the weighted least-squares fit of the free response (and a constant)
        to y - w (the initial state estimated, as Ljung 1999, ch. 10, allows), or 0
        (from rest) without ``initial_state``; before them x = y. For ARMAX
        e = 0 before span and the offset is fitted the same way. Without
        ``gradient`` psi is left empty (a loss needs only eps). ``prior``:
        the information of the prior on the initial state (INITIAL_PRIOR).
        """
        lfilter = self._signal.lfilter
        n, start = self.order, self.span
        inputs = self.input_columns(u) if inputs is None else inputs
        weights = weights[start:]
        if self.armax:
            return self._predict_armax(theta, y, inputs, weights, gradient)
        f_poly = np.concatenate(([1.0], theta[:n]))
        # w(t) = sum_i B_i(q) / F(q) u_i(t) from rest ...
        w = y.copy()
        w[start:] = lfilter([1.0], f_poly, inputs[start:].dot(theta[n:n + self.num_b]))
        # ... plus the free response of F from the initial lags (and the offset)
        nuisance = self.with_constant(self._free_responses(f_poly, y.shape[0] - start)) \
            if initial_state else None
        offset = 0.0
        if nuisance is not None:
            weighted = nuisance * weights[:, None]
            # the normal equations of the nuisance (a few columns), the initial state
            # shrunk by a prior of unit variance (normalised units): see INITIAL_PRIOR
            gram = weighted.T.dot(nuisance)
            gram[np.arange(n), np.arange(n)] += prior
            fitted = solve_regularised(gram, weighted.T.dot(y[start:] - w[start:]))
            if fitted is not None:
                # w(span - k) = fitted[k - 1]
                w[start:] += nuisance[:, :n].dot(fitted[:n])
                w[start - n:start] = fitted[n - 1::-1]
                offset = float(fitted[n]) if self.offset else 0.0
        eps = y[start:] - w[start:] - offset
        psi = np.zeros((0, self.num_parameters))
        if gradient:
            regressors = np.column_stack((self.output_columns(w), inputs))
            # psi(t) = phi(t) / F(q)
            psi = lfilter([1.0], f_poly, regressors[start:], axis=0)
        offset_gradient = np.ones(eps.shape[0]) if self.offset else None
        return Prediction(eps, psi, w, np.zeros(y.shape[0]), nuisance, offset,
                          offset_gradient)

    def _free_responses(self, f_poly: np.ndarray, count: int) -> np.ndarray:
        """
        Return the responses of 1/F to each unit initial output lag, shape ``(count, n)``.

        The lag w(-k-1) = 1 acts as the input x(t) = -f_(t+1+k), t < n - k, so
        each response is a sum of shifted impulse responses h of 1/F (one filter).
        """
        n = self.order
        h = impulse_response(self._signal.lfilter, f_poly, count)
        length = int(np.flatnonzero(h)[-1]) + 1  # (h(0) = 1) the rest is 0
        free = np.zeros((count, n))
        for k in range(n):
            for t in range(n - k):
                # free_k(s) -= f_(t+1+k) h(s - t)
                end = min(count, t + length)
                free[t:end, k] -= f_poly[t + 1 + k] * h[:end - t]
        return free

    def _predict_armax(self, theta: np.ndarray, y: np.ndarray, inputs: np.ndarray,
                       weights: np.ndarray, gradient: bool) -> Prediction:
        lfilter = self._signal.lfilter
        n, start = self.order, self.span
        p_ab = n + self.num_b
        c_poly = np.concatenate(([1.0], theta[p_ab:]))
        regressors = np.column_stack((self.output_columns(y), inputs))
        # eta(t) = A(q) y(t) - sum_i B_i(q) u_i(t), the equation error
        eta = y[start:] - regressors[start:].dot(theta[:p_ab])
        # C(q) eps(t) = eta(t) - d, from rest (e = 0 before span)
        eps = lfilter([1.0], c_poly, eta)
        offset, nuisance, offset_gradient = 0.0, None, None
        if self.offset:
            # the offset's response d / C(q), fitted by weighted least squares
            offset_gradient = lfilter([1.0], c_poly, np.ones(eta.shape[0]))
            nuisance = offset_gradient[:, None]
            weighted = offset_gradient * weights
            size = float(weighted.dot(offset_gradient))
            if size > 0.0:
                offset = float(weighted.dot(eps)) / size
                eps = eps - offset * offset_gradient
        e = np.concatenate((np.zeros(start), eps))
        psi = np.zeros((0, self.num_parameters))
        if gradient:
            regressors = np.column_stack((regressors, self.residual_columns(e)))
            # psi(t) = phi(t) / C(q)
            psi = lfilter([1.0], c_poly, regressors[start:], axis=0)
        return Prediction(eps, psi, y, e, nuisance, offset, offset_gradient)


def impulse_response(lfilter, f_poly: np.ndarray, count: int) -> np.ndarray:
    """
    Return the impulse response h of 1/F over ``count`` samples, 0 where below NEGLIGIBLE.

    Filtered a block at a time (the filter's state carried: the same arithmetic, so the same
    bits, as one call), it stops once the state and the block are below NEGLIGIBLE: a stable
    F's response decays from there. An unstable or slow F runs to the end.
    """
    h = np.zeros(count)
    state = np.zeros(f_poly.size - 1)
    first, block = 0, FIRST_BLOCK
    while first < count:
        last = min(count, first + block)
        drive = np.zeros(last - first)
        if first == 0:
            drive[0] = 1.0
        h[first:last], state = lfilter([1.0], f_poly, drive, zi=state)
        if np.all(np.abs(state) < NEGLIGIBLE) and np.all(np.abs(h[first:last]) < NEGLIGIBLE):
            break
        first, block = last, 2 * block
    h[np.abs(h) < NEGLIGIBLE] = 0.0  # (a NaN of an unstable F stays)
    return h


def solve_regularised(matrix: np.ndarray, vector: np.ndarray) -> np.ndarray | None:
    """Solve matrix x = vector, with a relative ridge of 1e-12 if singular; None if not finite."""
    if not (np.isfinite(matrix).all() and np.isfinite(vector).all()):
        return None
    try:
        return np.linalg.solve(matrix, vector)
    except np.linalg.LinAlgError:
        pass
    ridge = 1e-12 * max(float(np.abs(np.diag(matrix)).max()), 1e-300)
    try:
        return np.linalg.solve(matrix + ridge * np.eye(matrix.shape[0]), vector)
    except np.linalg.LinAlgError:
        return None
