"""
RPEM: the recursive prediction-error method for output-error and ARMAX models.

Ljung and Söderström (1983), *Theory and Practice of Recursive
Identification* (L&S below): the recursive prediction-error algorithm in its
Gauss-Newton form, with the output-error predictor and the recursive
maximum-likelihood (ARMAX) one, and the projection into the stability region
D_M; Ljung, *System Identification*, 2nd ed. (1999), ch. 11 (sec. 11.4, the
recursive prediction-error method) and ch. 10 (sec. 10.2, the batch
Gauss-Newton search, here started by instrumental-variable, Steiglitz-McBride,
iterations). What MATLAB's ``recursiveOE`` and ``recursiveARMAX`` run, with a
batch-refined start and the safeguards a real plant needs (docs/estimators.md,
"RPEM"). Equation numbers are not given: the books were not at hand to check
them.
"""

from __future__ import annotations

import math
from typing import Any, Callable, NamedTuple

import numpy as np

from bcid_ros.estimators.base import (power_of_two_at_least, RecursiveEstimator,
                                      weighted_square_ratio)
from bcid_ros.estimators.lti import is_stable
from bcid_ros.estimators import rules
from bcid_ros.estimators.adequacy import AdequacyMonitor
from bcid_ros.estimators.hac import HacCovariance
from bcid_ros.estimators.rls import (HEALTH_CHECK_PERIOD, load_blas, repair_covariance,
                                     residual_items, residual_reasons, residual_states)

#: Information (normalised units) of the prior that shrinks the OE initial state of a
#: fit towards 0: where a slow pole makes the start-up transient a near constant over a
#: segment, the data cannot tell it from the offset, and the level goes to the offset
#: (measured on DaISy's wall: without it a fit after one gate refusal put 1.3 units of
#: level in the offset and the validation fit fell from 76 to -40).
INITIAL_PRIOR = 10.0
#: Values of the ``model`` option.
MODELS = ('oe', 'armax')
#: Largest pole (and, for ARMAX, zero of C) radius of an estimate: the
#: stability region D_M of L&S (F, or A and C, kept inside it).
STABILITY_RADIUS = 0.999
#: Step halvings tried before a step that leaves D_M is not taken at all.
HALVINGS = 8
#: The first batch fit waits for this many usable samples (at least) ...
FIRST_FIT_SAMPLES = 50
#: ... and for this many per parameter.
FIRST_FIT_PER_PARAMETER = 10
#: The batch fit is repeated each time the stored samples grow by FIT_GROWTH, up to
#: BATCH_LIMIT samples.
FIT_GROWTH = 1.5
#: See FIT_GROWTH.
BATCH_LIMIT = 8192
#: Steiglitz-McBride (OE) or extended least-squares (ARMAX) iterations of a fit.
IV_ITERATIONS = 8
#: Gauss-Newton (or Levenberg-Marquardt) iterations of a fit.
LM_ITERATIONS = 20
#: Steps in a row that the stability projection refuses before the estimator restarts.
PROJECTION_RESTART = 50
#: Share of the steps of a validity period refused by the projection beyond which
#: the estimate is not valid (the model keeps pushing against the stability boundary).
PROJECTION_SHARE = 0.2
#: Drift: the mean square prediction error over about DRIFT_MEMORY updates exceeds
#: DRIFT_FACTOR times the variance of the last fit.
DRIFT_FACTOR = 100.0
#: See DRIFT_FACTOR.
DRIFT_MEMORY = 50
#: Undone steps in a row after which the estimator restarts from a batch fit.
UNDONE_RESTART = 3
#: Floor of the prediction-error standard deviation in normalised units.
VARIANCE_FLOOR = 2.0 ** -40
#: Annealed forgetting after a fit: lambda(t) starts at min(lambda, LAMBDA_START)
#: and approaches the user's lambda by lambda <- lambda_u - LAMBDA_RATE (lambda_u - lambda).
LAMBDA_START = 1.0
#: See LAMBDA_START.
LAMBDA_RATE = 0.99
#: A fit excludes the samples whose prediction error exceeds the gate's limit
#: (robust scale) when they are at most this share of the stored samples.
OUTLIER_SHARE = 0.05
#: Samples weighing less than this in a fit (forgetting) are not tested for outliers.
OUTLIER_WEIGHT = 0.01
#: Relative loss decrease below which the Gauss-Newton search stops.
LM_TOLERANCE = 1e-10


def inside(a: np.ndarray, radius: float = STABILITY_RADIUS) -> bool:
    r"""
    Return whether the roots of :math:`1 + a_1 z^{-1} + \dots + a_k z^{-k}` lie within ``radius``.

    One and two coefficients are tested in closed form (Jury's conditions on
    the polynomial with its roots scaled by 1/radius), more by the
    Schur-Cohn recursion of :func:`bcid_ros.estimators.lti.is_stable`.
    """
    k = a.shape[0]
    if k == 1:
        return abs(float(a[0])) < radius
    if k == 2:
        # roots of z^2 + c1 z + c2 with c1 = a1 / R, c2 = a2 / R^2 inside the unit circle
        c1 = float(a[0]) / radius
        c2 = float(a[1]) / (radius * radius)
        return abs(c2) < 1.0 and abs(c1) < 1.0 + c2
    return is_stable(np.concatenate(([1.0], a)), 1.0 - radius)


def pull_inside(a: np.ndarray, radius: float = STABILITY_RADIUS) -> np.ndarray:
    """
    Return the coefficients with their roots moved inside ``radius``.

    A root z with |z| > 1 becomes 1/conj(z) (the same magnitude response up
    to a gain), then every root at or beyond ``radius`` is moved radially
    to 0.99 ``radius``. Non-finite coefficients give all zeros.
    """
    if not np.isfinite(a).all():
        return np.zeros_like(a)
    roots = np.roots(np.concatenate(([1.0], a)))
    size = np.abs(roots)
    roots = np.where(size > 1.0, 1.0 / np.conj(roots), roots)
    size = np.abs(roots)
    roots = np.where(size >= radius, roots * (0.99 * radius / np.maximum(size, 1e-300)), roots)
    return np.real(np.poly(roots))[1:]


def signal_size(values: np.ndarray) -> float:
    """
    Return a robust size of a centred signal: 1.4826 median |x|, or its RMS if that is 0.

    The median ignores a burst of outliers (which the fits then exclude);
    for Gaussian x it is the standard deviation. 0 for an all-zero or
    non-finite signal. Multiplying x by a power of two multiplies it exactly.
    """
    size = 1.4826 * float(np.median(np.abs(values)))
    if not size > 0.0:
        size = math.sqrt(float(np.mean(values * values)))
    return size if math.isfinite(size) else 0.0


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
        """Replace x and e of the newest sample (the a-posteriori values of the step)."""
        row = self.history[self.position - 1]
        row[0] = -x
        row[-2] = e

    def load_rows_oldest_first(self, rows: np.ndarray) -> None:
        """Make ``rows`` ``[-x, u_1 ... u_r, e]`` (oldest first) the content of the ring."""
        self.clear()
        count = min(rows.shape[0], self.span + 1)
        self.history[:count, :-1] = rows[rows.shape[0] - count:]
        self.filled = count
        self.position = count % (self.span + 1)

    @property
    def ready(self) -> bool:
        """Whether every lag of phi(t) comes from a real sample."""
        return self.filled > self.span

    def clear(self) -> None:
        """Forget the history."""
        self.history[:, :-1] = 0.0
        self.position = 0
        self.filled = 0


class FitResult:
    """
    A batch prediction-error fit of the stored samples, in normalised units.

    Attributes
    ----------
    theta : numpy.ndarray, shape ``(p,)``
        The estimate.
    information : numpy.ndarray, shape ``(q, q)``
        sum_t w_t psi(t) psi(t)^T at theta (q = p + 1 with the offset last).
    loss, weight : float
        sum_t w_t eps(t)^2 and sum_t w_t over the usable samples.
    arx : numpy.ndarray, shape ``(p,)``
        The least-squares ARX estimate of the same samples (c = 0 for ARMAX).
    tail_x, tail_e : numpy.ndarray
        x (w for OE, y for ARMAX) and e of the last segment's samples.
    tail_psi : numpy.ndarray, shape ``(n, q)``
        psi(t-1) ... psi(t-n) at the end (zeros where the segment is shorter;
        OE keeps the offset's column at 0, its gradient is not filtered).
    offset : float
        The output (OE) or equation (ARMAX) offset of the last segment.

    """

    def __init__(self, theta: np.ndarray, information: np.ndarray, loss: float, weight: float,
                 arx: np.ndarray, tail_x: np.ndarray, tail_e: np.ndarray,
                 tail_psi: np.ndarray, offset: float) -> None:
        self.theta = theta
        self.information = information
        self.loss = loss
        self.weight = weight
        self.arx = arx
        self.tail_x = tail_x
        self.tail_e = tail_e
        self.tail_psi = tail_psi
        self.offset = offset


class Prediction(NamedTuple):
    """
    The predictor of one segment at fixed parameters (see :meth:`BatchFit.predict`).

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


class BatchFit:
    r"""
    Batch prediction-error fit of the OE or ARMAX model over stored segments (normalised).

    The same predictor as the recursion with the parameters held fixed
    (Ljung 1999, ch. 10): per segment, the first ``span`` samples fill the
    lags, then

    * OE: :math:`w = \sum_i B_i u_i / F` plus the free response of F from a
      fitted initial state, :math:`\varepsilon = y - w - c`,
      :math:`\psi = \varphi(w) / F`;
    * ARMAX: :math:`\varepsilon = (A y - \sum_i B_i u_i - d) / C` from rest,
      :math:`\psi = \varphi / C`;

    with the offset (c, or d) only with ``offset`` (``detrend: mean``: the
    sample means of a finite record of a slow plant leave the output off
    G(q) times the input by a constant). The initial state and the offset
    enter linearly and are fitted by least squares at every theta (variable
    projection), not searched.

    :meth:`fit` starts from the best of the given candidates, and from the
    best of the ARX least-squares estimate and ``IV_ITERATIONS``
    Steiglitz-McBride (OE; instruments :math:`\psi`, regressors of the data
    filtered by :math:`1/\hat F`) or extended least-squares (ARMAX) iterates,
    each pulled into the stability region; it refines both by Gauss-Newton
    steps that keep every iterate stable and returns the lower.
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
    def _lagged(self, x: np.ndarray, lag: int) -> np.ndarray:
        out = np.zeros_like(x)
        if lag < x.shape[0]:
            out[lag:] = x[:x.shape[0] - lag]
        return out

    def _input_columns(self, u: np.ndarray) -> np.ndarray:
        """Return the input lags u_i(t-d_i-k) of every t of a segment, shape ``(T, r lags)``."""
        columns = []
        for i, delay in enumerate(self.input_delay):
            columns.extend(self._lagged(u[:, i], delay + k)
                           for k in range(self.first_lag, self.order + 1))
        return np.column_stack(columns)

    def _output_columns(self, x: np.ndarray) -> np.ndarray:
        return np.column_stack([-self._lagged(x, k) for k in range(1, self.order + 1)])

    def _with_constant(self, columns: np.ndarray) -> np.ndarray:
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
        inputs = self._input_columns(u) if inputs is None else inputs
        weights = weights[start:]
        if self.armax:
            return self._predict_armax(theta, y, inputs, weights, gradient)
        f_poly = np.concatenate(([1.0], theta[:n]))
        # w(t) = sum_i B_i(q) / F(q) u_i(t) from rest ...
        w = y.copy()
        w[start:] = lfilter([1.0], f_poly, inputs[start:].dot(theta[n:n + self.num_b]))
        # ... plus the free response of F from the initial lags (and the offset)
        nuisance = self._with_constant(self._free_responses(f_poly, y.shape[0] - start)) \
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
            regressors = np.column_stack((self._output_columns(w), inputs))
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
        impulse = np.zeros(count)
        impulse[0] = 1.0
        h = self._signal.lfilter([1.0], f_poly, impulse)
        free = np.zeros((count, n))
        for k in range(n):
            for t in range(n - k):
                # free_k(s) -= f_(t+1+k) h(s - t)
                free[t:, k] -= f_poly[t + 1 + k] * h[:count - t]
        return free

    def _predict_armax(self, theta: np.ndarray, y: np.ndarray, inputs: np.ndarray,
                       weights: np.ndarray, gradient: bool) -> Prediction:
        lfilter = self._signal.lfilter
        n, start = self.order, self.span
        p_ab = n + self.num_b
        c_poly = np.concatenate(([1.0], theta[p_ab:]))
        regressors = np.column_stack((self._output_columns(y), inputs))
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
            regressors = np.column_stack((regressors, np.column_stack(
                [self._lagged(e, k) for k in range(1, n + 1)])))
            # psi(t) = phi(t) / C(q)
            psi = lfilter([1.0], c_poly, regressors[start:], axis=0)
        return Prediction(eps, psi, y, e, nuisance, offset, offset_gradient)

    # -------------------------------------------------------------- the fit
    def fit(self, segments: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
            candidates: list[np.ndarray], prior: float) -> FitResult | None:
        """
        Fit the segments ``(y, u, weights)`` (normalised); None if none is usable.

        ``prior`` is the information 1/p0 added to every diagonal entry.
        """
        usable = [(y, u, w, self._input_columns(u)) for y, u, w in segments
                  if y.shape[0] > self.span]
        if not usable:
            return None
        arx = self._arx(usable)
        # two starts: the best given candidate, and the best of ARX and its IV iterates
        starts = [self._best([theta for theta in candidates if np.isfinite(theta).all()],
                             usable), self._best(self._iv_path(arx, usable), usable)]
        best_theta, best_loss = None, math.inf
        for theta, loss in starts:
            if theta is None:
                continue
            theta, loss = self._search(theta, loss, usable, prior)
            if loss < best_loss:
                best_theta, best_loss = theta, loss
        if best_theta is None:
            return None
        return self._result(best_theta, segments, usable, arx)

    def outliers(self, theta: np.ndarray, segments: list, limit: float) -> np.ndarray:
        """
        Return the rows (over all segments) whose prediction error exceeds ``limit`` scales.

        The scale is 1.4826 times the median absolute prediction error at
        ``theta`` (the standard deviation for Gaussian errors, robust to the
        outliers themselves), over the samples weighing at least
        OUTLIER_WEIGHT.
        """
        errors, rows = [], []
        first = 0
        for y, u, weights in segments:
            if y.shape[0] > self.span:
                # the start-up transient free (no prior): a transient is no outlier
                eps = self.predict(theta, y, u, weights, gradient=False, prior=0.0).eps
                # only the samples the fit weighs (forgetting leaves the old ones out)
                weighed = weights[self.span:] >= OUTLIER_WEIGHT
                errors.append(eps[weighed])
                rows.append(np.arange(first + self.span, first + y.shape[0])[weighed])
            first += y.shape[0]
        if not errors:
            return np.zeros(0, dtype=np.intp)
        error = np.abs(np.concatenate(errors))
        scale = 1.4826 * float(np.median(error))
        if not scale > 0.0:
            return np.zeros(0, dtype=np.intp)
        return np.concatenate(rows)[~(error <= limit * scale)]

    def _best(self, thetas: list[np.ndarray],
              usable: list) -> tuple[np.ndarray | None, float]:
        """Return the one of ``thetas`` (stabilised) with the smallest loss, and its loss."""
        best_theta, best_loss = None, math.inf
        for theta in thetas:
            theta = self._stabilised(theta)
            loss = self._loss(theta, usable)
            if loss < best_loss:
                best_theta, best_loss = theta, loss
        return best_theta, best_loss

    def _iv_path(self, arx: np.ndarray, usable: list) -> list[np.ndarray]:
        """Return the ARX estimate and its IV_ITERATIONS IV iterates (each stabilised)."""
        path = [self._stabilised(arx)]
        for _ in range(IV_ITERATIONS):
            theta = self._iv_step(path[-1], usable)
            if theta is None:
                break
            path.append(self._stabilised(theta))
        return path

    def _stabilised(self, theta: np.ndarray) -> np.ndarray:
        """Return theta with F (or A and C) pulled into the stability region."""
        n = self.order
        theta = theta.copy()
        if not inside(theta[:n]):
            theta[:n] = pull_inside(theta[:n])
        if self.armax and not inside(theta[n + self.num_b:]):
            theta[n + self.num_b:] = pull_inside(theta[n + self.num_b:])
        return theta

    def _is_inside(self, theta: np.ndarray) -> bool:
        n = self.order
        return inside(theta[:n]) and (not self.armax or inside(theta[n + self.num_b:]))

    def _arx(self, usable: list) -> np.ndarray:
        """Return the weighted least-squares ARX estimate (c = 0 for ARMAX, offset dropped)."""
        start = self.span
        p_ab = self.order + self.num_b
        gram = np.zeros((p_ab + self.offset, p_ab + self.offset))
        moment = np.zeros(p_ab + self.offset)
        for y, _, weights, inputs in usable:
            regressors = self._with_constant(np.column_stack((self._output_columns(y),
                                                              inputs)))[start:]
            weighted = regressors * weights[start:, None]
            gram += weighted.T.dot(regressors)
            moment += weighted.T.dot(y[start:])
        theta = np.zeros(self.num_parameters)
        solution = solve_regularised(gram, moment)
        if solution is not None:
            theta[:p_ab] = solution[:p_ab]
        return theta

    def _loss(self, theta: np.ndarray, usable: list) -> float:
        total = 0.0
        for y, u, weights, inputs in usable:
            eps = self.predict(theta, y, u, weights, inputs, gradient=False).eps
            total += float(weights[self.span:].dot(eps * eps))
        return total if math.isfinite(total) else math.inf

    def _iv_step(self, theta: np.ndarray, usable: list) -> np.ndarray | None:
        """Return one Steiglitz-McBride (OE) or extended least-squares (ARMAX) iterate."""
        lfilter = self._signal.lfilter
        n, start = self.order, self.span
        size = self.num_parameters + self.offset
        gram = np.zeros((size, size))
        moment = np.zeros(size)
        for y, u, weights, inputs in usable:
            if self.armax:
                # regress y on [-y lags, u lags, eps lags] with eps of the current model
                e = self.predict(theta, y, u, weights, inputs, gradient=False).e
                regressors = self._with_constant(np.column_stack((
                    self._output_columns(y), inputs,
                    np.column_stack([self._lagged(e, k) for k in range(1, n + 1)]))))[start:]
                weighted = regressors * weights[start:, None]
                gram += weighted.T.dot(regressors)
                moment += weighted.T.dot(y[start:])
                continue
            f_poly = np.concatenate(([1.0], theta[:n]))
            # data filtered by 1 / F: y_f(t) = F(q)^-1 y(t), u_f(t) = F(q)^-1 u(t)
            y_filtered = lfilter([1.0], f_poly, y)
            regressors = self._with_constant(np.column_stack((
                self._output_columns(y_filtered), lfilter([1.0], f_poly, inputs, axis=0))))[
                start:]
            # instruments: psi(t) = phi(w)(t) / F(q), the noise-free regressors (from rest:
            # the initial state fitted to a poor model would carry the noise into them)
            psi = self.predict(theta, y, u, weights, inputs, False).psi
            instruments = self._with_constant(psi) * weights[start:, None]
            gram += instruments.T.dot(regressors)
            moment += instruments.T.dot(y_filtered[start:])
        new = solve_regularised(gram, moment)
        return new[:self.num_parameters] if new is not None and np.isfinite(new).all() \
            else None

    def _gradient(self, theta: np.ndarray, usable: list, prior: float,
                  concentrated: bool = True) -> tuple[float, np.ndarray, np.ndarray]:
        """
        Return the loss, the Gauss-Newton information and the gradient at theta.

        ``concentrated``: of the loss with the nuisance (initial state,
        offset) re-fitted at every theta (the search), for theta alone;
        otherwise the information of theta and the offset with the nuisance
        held (what the recursion continues with: it never re-fits the
        initial state, and it carries the offset as a parameter).
        """
        p = self.num_parameters
        size = p if concentrated else p + self.offset
        information = np.zeros((size, size))
        gradient = np.zeros(size)
        loss = 0.0
        for y, u, weights, inputs in usable:
            prediction = self.predict(theta, y, u, weights, inputs)
            psi = prediction.psi
            if concentrated and prediction.nuisance is not None:
                psi = self._without_nuisance(psi, prediction.nuisance, weights[self.span:])
            elif not concentrated and self.offset:
                psi = np.column_stack((psi, prediction.offset_gradient))
            weighted = psi * weights[self.span:, None]
            information += weighted.T.dot(psi)
            gradient += weighted.T.dot(prediction.eps)
            loss += float(weights[self.span:].dot(prediction.eps ** 2))
        information[np.diag_indices(size)] += prior
        return loss, information, gradient

    @staticmethod
    def _without_nuisance(psi: np.ndarray, nuisance: np.ndarray,
                          weights: np.ndarray) -> np.ndarray:
        r"""
        Return psi minus its weighted projection on the nuisance columns (Kaufman's VarPro).

        The nuisance (initial state, offset) is re-fitted at every theta, so
        the gradient of the concentrated loss is that of psi orthogonal to its
        columns :math:`N`: :math:`\psi - N(N^TWN)^{-1}N^TW\psi` (Golub and
        Pereyra 2003; Kaufman 1975).
        """
        weighted = nuisance * weights[:, None]
        coefficients = solve_regularised(weighted.T.dot(nuisance), weighted.T.dot(psi))
        return psi if coefficients is None else psi - nuisance.dot(coefficients)

    def _search(self, theta: np.ndarray, loss: float, usable: list,
                prior: float) -> tuple[np.ndarray, float]:
        """
        Refine theta by Gauss-Newton steps that keep it stable and lower the loss.

        Each iteration tries the Gauss-Newton step halved up to ``HALVINGS``
        times (Ljung 1999, sec. 10.2, with a line search), then, if none is
        accepted, Levenberg-Marquardt steps (H + mu diag H) with mu growing
        tenfold; it stops when no step lowers the loss by LM_TOLERANCE. The
        plain direction matters: the valley of an oversampled plant is
        conditioned like 1e10, where diagonal damping crawls (a hundred
        iterations where Gauss-Newton takes five, measured).
        """
        for _ in range(LM_ITERATIONS):
            loss, information, gradient = self._gradient(theta, usable, prior)
            step = solve_regularised(information, gradient)
            if step is None:
                break
            candidate, new_loss = self._line_search(theta, step, loss, usable)
            if candidate is None:
                candidate, new_loss = self._damped_step(theta, loss, information, gradient,
                                                        usable)
            if candidate is None:
                break
            improvement = loss - new_loss
            theta, loss = candidate, new_loss
            if not improvement > LM_TOLERANCE * loss:
                break
        return theta, loss

    def _line_search(self, theta: np.ndarray, step: np.ndarray, loss: float,
                     usable: list) -> tuple[np.ndarray | None, float]:
        """Return theta + mu step, mu = 1, 1/2, ..., the first stable one with a lower loss."""
        scale = 1.0
        for _ in range(HALVINGS + 1):
            candidate = theta + scale * step
            if self._is_inside(candidate):
                new_loss = self._loss(candidate, usable)
                if new_loss < loss:
                    return candidate, new_loss
            scale *= 0.5
        return None, loss

    def _damped_step(self, theta: np.ndarray, loss: float, information: np.ndarray,
                     gradient: np.ndarray, usable: list) -> tuple[np.ndarray | None, float]:
        """Return a Levenberg-Marquardt step (H + mu diag H) that lowers the loss, or None."""
        diagonal = np.diag(information).copy()
        damping = 1e-3
        for _ in range(8):
            step = solve_regularised(information + damping * np.diag(diagonal), gradient)
            if step is None:
                break
            candidate = theta + step
            if self._is_inside(candidate):
                new_loss = self._loss(candidate, usable)
                if new_loss < loss:
                    return candidate, new_loss
            damping *= 10.0
        return None, loss

    def _result(self, theta: np.ndarray, segments: list, usable: list,
                arx: np.ndarray) -> FitResult:
        """Return the fit at theta with the predictor state at the end of the last segment."""
        loss, information, _ = self._gradient(theta, usable, 0.0, concentrated=False)
        weight = float(sum(w[self.span:].sum() for _, _, w, _ in usable))
        n, p = self.order, self.num_parameters
        y, u, weights = segments[-1]
        tail_psi = np.zeros((n, p + self.offset))
        offset = 0.0
        if y.shape[0] > self.span:
            prediction = self.predict(theta, y, u, weights)
            x, e, offset = prediction.x, prediction.e, prediction.offset
            rows = prediction.psi[::-1][:n]
            tail_psi[:rows.shape[0], :p] = rows
            if self.armax and self.offset:  # the offset's gradient is filtered by 1 / C
                tail = prediction.offset_gradient[::-1][:n]
                tail_psi[:tail.shape[0], p] = tail
        else:
            x, e = y, np.zeros(y.shape[0])
            if usable:  # the offset of the newest usable segment
                offset = self.predict(theta, *usable[-1][:3], gradient=False).offset
        return FitResult(theta, information, loss, weight, arx, x, e, tail_psi, offset)


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


class Rpem(RecursiveEstimator):
    r"""
    Recursive prediction-error method for the OE or ARMAX model, with a batch-refined start.

    **Models** (``model``), with :math:`d_i` the dead time of input i:

    * ``'oe'``: :math:`y(t) = \sum_i B_i(q)/F(q)\,u_i(t) + v(t)`, v of any
      colour. Predictor: the simulated output :math:`w(t) = \varphi^T(t)\theta`,
      :math:`\varphi(t) = [-w(t-1) \dots -w(t-n), u_i(t-d_i-1) \dots]`
      (L&S, the output-error model); gradient filter :math:`D = F`.
    * ``'armax'``: :math:`A(q)y(t) = \sum_i B_i(q)u_i(t) + C(q)e(t)`, e
      white. :math:`\varphi(t) = [-y(t-1) \dots, u_i(t-d_i-1) \dots,
      \bar\varepsilon(t-1) \dots \bar\varepsilon(t-n)]` (the recursive ML
      method of L&S); gradient filter :math:`D = C`.

    **The recursion** (L&S, the Gauss-Newton direction; Ljung 1999, sec.
    11.4), in normalised units:

    .. math::

        \hat y(t) &= \varphi^T(t)\hat\theta(t-1), \qquad
            \varepsilon(t) = y(t) - \hat y(t) \\
        \psi(t) &= \varphi(t) - d_1\psi(t-1) - \dots - d_n\psi(t-n)
            && \psi = \varphi / D(q) \\
        s(t) &= \lambda(t) + \psi^T(t)P(t-1)\psi(t) \\
        \hat\theta(t) &= \big[\hat\theta(t-1) + \mu\,P(t-1)\psi(t)\,\varepsilon(t)/s(t)
            \big]_{D_M} && \text{(projected step)} \\
        P(t) &= \frac{1}{\lambda(t)}\Big[P(t-1) - \frac{P(t-1)\psi(t)\psi^T(t)P(t-1)}{s(t)}
            \Big] && \text{(Gauss-Newton P)} \\
        w(t) &= \varphi^T(t)\hat\theta(t) \ \text{(OE)}, \qquad
            \bar\varepsilon(t) = y(t) - \varphi^T(t)\hat\theta(t) \ \text{(ARMAX)} \\
        J(t) &= \lambda J(t-1) + \lambda\varepsilon^2(t)/s(t), \qquad
            \tau(t) = \lambda\tau(t-1) + 1

    :math:`[\cdot]_{D_M}`: the projection into the stability region (L&S;
    Ljung 1999, ch. 11): :math:`\mu` = 1, 1/2, ... (``HALVINGS``
    times) until every root of F (ARMAX: of A and C) lies within
    ``STABILITY_RADIUS``; if none does, :math:`\hat\theta(t) = \hat\theta(t-1)`
    (flag ``stability_projection``). So no estimate, published or internal,
    ever has an unstable F (or A, C). :math:`\sigma^2 = J/\tau` is the
    published ``sigma2``: the weighted mean square one-step prediction error
    (OE: the output error, i.e. the variance of v, coloured or not; ARMAX:
    the innovation variance of e).

    **The start.** A recursion started far from the optimum of an
    oversampled plant (poles near 1) feeds its own errors back through w and
    psi and drifts away (docs/estimators.md, "RPEM", measured), so the
    recursion never starts cold. The samples are stored; after
    ``max(FIRST_FIT_SAMPLES, FIRST_FIT_PER_PARAMETER p)`` of them, and again
    each time their count has grown by ``FIT_GROWTH`` up to ``BATCH_LIMIT``,
    :class:`BatchFit` fits the model to all stored samples (ARX least
    squares and Steiglitz-McBride or extended LS iterations, the current
    estimate too, then Gauss-Newton on the prediction error with the start-up
    transient and the offset fitted at every step; samples the gate would
    refuse are then excluded) and the recursion continues from it with
    :math:`P = (\sum_t w_t\psi\psi^T + I/p_0)^{-1}`, its :math:`J`,
    :math:`\tau`, w and psi: what the recursion would hold had it run over the
    same samples at that estimate. Beyond ``BATCH_LIMIT`` samples it is the
    plain recursion; the last ``BATCH_LIMIT`` samples stay stored for a
    restart. The estimator is not :attr:`ready` before the first fit.
    With forgetting, sample t weighs :math:`\lambda^{T-t}` in a fit.

    **Units.** Each fit takes per channel (y, each u_i) the smallest power of
    two at or above a robust size of the stored samples
    (:func:`signal_size`) as its scale, and the recursion runs on the scaled
    signals: the estimates do not depend on the units of y and u (bit for
    bit for power-of-two units), and ``initial_covariance`` p0 is the prior
    variance of the parameters of signals of unit size (the fits add
    :math:`I/p_0` to the information).

    **Offset** (``detrend: mean``). A fit re-centres the stored samples on
    the current means; the model carries an offset c, the last internal
    parameter (OE: y - m_y = G (u - m_u) + c + v; ARMAX: an equation offset
    d, c = d / A(1)), regressed on a constant 1 in phi, not published;
    :attr:`operating_point` is (m_y + c, m_u).

    **Annealed forgetting.** After each fit :math:`\lambda(t)` starts at
    :math:`\min(\lambda, \text{LAMBDA\_START})` and tends to the user's
    :math:`\lambda` by :math:`\lambda(t) \leftarrow \lambda - \text{LAMBDA\_RATE}
    (\lambda - \lambda(t-1))` (the forgetting profile of L&S). Measured after a
    batch start it only loses information, so LAMBDA_START = 1 (off).

    **Safeguards**, each counted in :attr:`flags`:

    * the transaction: a step with a non-finite or non-positive s(t) or a
      non-finite error is not taken (``update_undone``; the regressor
      restarts);
    * the gate: :math:`z^2 = \varepsilon^2/[(J/\tau)(s + 1 - \lambda)]`
      goes to the rulebook's gate once :math:`\tau \ge` ``GATE_WARMUP`` p;
      a refused sample keeps the predictor running with its prediction in
      place of y (OE: it is stored with weight 0); a plant change cuts the
      memory to ``CHANGE_MEMORY`` p (as :class:`~bcid_ros.estimators.rls.Rls`)
      and restarts the fit schedule on the samples after the change;
    * restart (``restarted``, and a validity reason until the next check):
      a new fit of the stored samples when ``PROJECTION_RESTART`` steps in a
      row left D_M, when ``UNDONE_RESTART`` steps in a row were undone, or
      when the mean square prediction error over about ``DRIFT_MEMORY``
      updates exceeds ``DRIFT_FACTOR`` times the variance of the last fit;
    * anti-windup as in Rls (no division by :math:`\lambda` while
      :math:`\mathrm{tr}\,P > p_0 p`) and a Cholesky check of P every
      ``HEALTH_CHECK_PERIOD`` updates (``covariance_repaired``).

    **Validity**, every ``VALIDITY_PERIOD`` updates: not valid after a
    restart, or when the projection refused more than ``PROJECTION_SHARE``
    of the steps (the data push the model to the stability boundary: a
    wrong order, an integrator, a plant in feedback).

    ``theta_uncompensated`` is the ARX least-squares estimate of the samples
    of the last fit (c = 0 for ARMAX), the start of its IV iterations.

    Parameters
    ----------
    model : str
        ``'oe'`` (default) or ``'armax'``.
    order, num_inputs, feedthrough, initial_covariance, forgetting_factor, outlier_threshold
        See :class:`~bcid_ros.estimators.base.RecursiveEstimator`.
    input_delay, detrend, adapt
        See :class:`~bcid_ros.estimators.base.RecursiveEstimator`.

    Raises
    ------
    ValueError
        If ``model`` or a base setting is not allowed; the message names it.

    """

    name = 'rpem'
    noise_names = ('sigma2',)

    def __init__(self, *, model: str = 'oe', **settings: Any) -> None:
        if model not in MODELS:
            raise ValueError(f"model must be 'oe' or 'armax', got {model!r}")
        self.model = model
        self._armax = model == 'armax'
        # the residual tests: an OE model's output error may be coloured (only its
        # correlation with past inputs contradicts the model); ARMAX's innovation is white
        self.adequacy_model = model
        self._blas = load_blas()
        super().__init__(**settings)
        n, r = self.order, self.num_inputs
        if self._armax:
            self.parameter_names = self.parameter_names + tuple(
                f'c{k}' for k in range(1, n + 1))
            self.num_parameters = len(self.parameter_names)
        self._lags = n + (1 if self.feedthrough else 0)
        self._num_b = r * self._lags
        # with detrend: mean the model carries an offset, the last internal parameter
        self._offset = self._means is not None
        self._size = self.num_parameters + self._offset
        # the signal channel (0 = y, i = u_i) of each parameter: b's scale with u_i / y
        self._channel = np.array([0] * n + [i for i in range(1, r + 1)
                                            for _ in range(self._lags)]
                                 + ([0] * n if self._armax else []), dtype=np.intp)
        self._filter_slice = slice(n + self._num_b, 2 * n + self._num_b) if self._armax \
            else slice(0, n)
        self._history = PredictorHistory(n, r, self.feedthrough, self.input_delay, self._armax,
                                         self._offset)
        self._first_fit = max(FIRST_FIT_SAMPLES, FIRST_FIT_PER_PARAMETER * self.num_parameters)
        self._batch: BatchFit | None = None
        self._reset()

    # ------------------------------------------------------------- the step
    def _update(self, y: float, u: np.ndarray) -> None:
        if self._fitted:
            self._step(y, u)
        else:
            self._history.push(y, u)
            self._store(y, u)

    #: _step checks before it commits: the exact form of the transaction.
    _guarded_update = _update

    def _step(self, y: float, u: np.ndarray) -> None:
        """Make one recursion step on a checked sample (the class docstring's equations)."""
        scale = self._inverse_scale
        yn = y * scale[0]
        history = self._history
        refilled = history.filled == history.span
        phi = history.push(yn, u * scale[1:])
        if not history.ready:  # refilling the lags after a restart
            self._store(y, u)
            return
        if refilled and not self._armax:
            phi = history.level_output_lags()
        theta = self._theta_n
        lam = self._lambda_t
        # psi(t) = phi(t) - d_1 psi(t-1) - ... - d_n psi(t-n)
        psi = phi - theta[self._filter_slice].dot(self._psi_history)
        # e(t) = y(t) - phi(t)' theta(t-1)
        e = yn - float(phi.dot(theta))
        # g = P(t-1) psi(t) ; s(t) = lambda + psi' P psi
        g = self._p.dot(psi)
        s = lam + float(psi.dot(g))
        if not (0.0 < s < math.inf and e * e < math.inf):
            self._refuse(s)
            return
        if self._tau >= self._gate_from:
            changes = self._changes
            # z^2 = e^2 / [(J / tau) (s + 1 - lambda)]
            z2 = e * e / ((self._loss / self._tau + VARIANCE_FLOOR ** 2) * (s + 1.0 - lam))
            self._gating = (phi, psi, y, u)
            accepted = self._gate(z2)
            self._gating = None
            if not accepted:
                return
            if self._changes != changes:  # the memory was cut: P changed
                g = self._p.dot(psi)
                s = lam + float(psi.dot(g))
                if not 0.0 < s < math.inf:
                    self._refuse(s)
                    return
        self._undone_in_row = 0
        self._move_theta(theta, g, e / s)
        self._commit_covariance(g, s, lam)
        # J(t) = lambda J(t-1) + lambda e^2 / s ; tau(t) = lambda tau(t-1) + 1
        self._loss = lam * (self._loss + e * e / s)
        self._tau = lam * self._tau + 1.0
        self._advance(yn, phi, psi)
        # recent mean square prediction error (the drift monitor)
        self._recent += (e * e - self._recent) * (1.0 / DRIFT_MEMORY)
        self._lambda_t = self._forgetting_factor - LAMBDA_RATE * (
            self._forgetting_factor - lam)
        self._updates += 1
        self._store(y, u)
        if self._tau >= self._gate_from and not self._quiet_left:
            # the residual tests take the prediction error; the HAC its score psi e
            self._monitor.record(e, u)
            self._hac.record_product(psi, e)
        if self._updates % HEALTH_CHECK_PERIOD == 0:
            self._check_covariance()
        if self._updates >= self._next_check:
            self._check_validity()

    def _advance(self, yn: float, phi: np.ndarray, psi: np.ndarray) -> None:
        """Move the predictor on: the a-posteriori lags of sample t and psi(t)."""
        theta = self._theta_n
        posterior = float(phi.dot(theta))
        if self._armax:
            # e(t) = y(t) - phi(t)' theta(t), the a-posteriori residual
            self._history.set_newest(yn, yn - posterior)
        else:
            # w(t) = phi(t)' theta(t) without the offset: the simulated output
            self._history.set_newest(posterior - theta[-1] if self._offset else posterior, 0.0)
        psi_history = self._psi_history
        psi_history[1:] = psi_history[:-1]
        psi_history[0] = psi
        if self._offset and not self._armax:
            psi_history[0, -1] = 0.0  # the OE offset's gradient is 1, not filtered by 1/F

    def _move_theta(self, theta: np.ndarray, g: np.ndarray, gain: float) -> None:
        """Take theta + mu g gain with mu = 1, 1/2, ... inside D_M, or stay (projection)."""
        n = self.order
        armax = self._armax
        noise = self._filter_slice
        for _ in range(HALVINGS + 1):
            # theta(t) = theta(t-1) + mu P psi e / s
            new = theta + g * gain
            if inside(new[:n]) and (not armax or inside(new[noise])):
                theta[:] = new
                self._projected_in_row = 0
                return
            gain *= 0.5
        self._flag('stability_projection')
        self._projected_in_row += 1
        self._projected_since_check += 1

    def _commit_covariance(self, g: np.ndarray, s: float, lam: float) -> None:
        """Apply P(t) = [P - g g' / s] / lambda in place, without winding up."""
        # h = g / sqrt(s); P <- P - h h'   (BLAS rank-1 update of the C-ordered P in place)
        h = g * (1.0 / math.sqrt(s))
        self._p = self._blas['dger'](-1.0, h, h, 1, 1, self._p.T, 0, 0, 1).T
        if lam < 1.0:
            if float(np.trace(self._p)) < self._trace_limit:
                self._p *= 1.0 / lam
            else:
                self._flag('windup_limited')

    def _refuse(self, s: float) -> None:
        """Refuse a step with a non-finite error or gain; repair P first if s <= 0."""
        if s <= 0.0:
            self._repair_covariance()
        self._undone()

    def _undone(self) -> None:
        """Refuse a step that would break the state; restart after UNDONE_RESTART in a row."""
        self._undone_in_row += 1
        if self._undone_in_row >= UNDONE_RESTART:
            self._undone_in_row = 0
            self._restart(f'{UNDONE_RESTART} steps in a row undone')
        self._undo('update_undone')

    def _undo(self, flag: str) -> None:
        """
        Refuse a step; a sample the gate refuses keeps the predictor running without its y.

        The output lag of the refused sample becomes its prediction (OE: the
        simulated output w(t), which needs no y; ARMAX: y(t) replaced by
        y^(t), residual 0), so the predictor state survives an output spike
        where a restarted one would take the following samples for outliers
        too. Other refusals restart the regressor (base class).
        """
        gating = self._gating
        if gating is None or flag != 'outlier_rejected':
            super()._undo(flag)
            return
        self._flag(flag)
        self._refused += 1
        phi, psi, y, u = gating
        # y(t) unknown: its prediction in its place, residual 0
        self._advance(float(phi.dot(self._theta_n)), phi, psi)
        if self._armax:
            self._break_pending = True  # y(t) is a lag of the next samples
        else:
            self._store(y, u, excluded=True)  # u(t) drives the simulation on

    def _hold(self, y: float, u: np.ndarray) -> None:
        """Move the predictor on with theta held: w (or the residual) and psi keep running."""
        self._break_pending = True
        history = self._history
        if not self._fitted:
            history.push(y, u)
            return
        scale = self._inverse_scale
        yn = y * scale[0]
        refilled = history.filled == history.span
        phi = history.push(yn, u * scale[1:])
        if not history.ready:
            return
        if refilled and not self._armax:
            phi = history.level_output_lags()
        psi = phi - self._theta_n[self._filter_slice].dot(self._psi_history)
        self._advance(yn, phi, psi)

    # ------------------------------------------------------- stored samples
    def _store(self, y: float, u: np.ndarray, excluded: bool = False) -> None:
        """
        Keep the sample (on the raw operating point) for the fits; fit when it is due.

        An ``excluded`` sample (OE: its output refused) keeps its input in the
        simulation and weighs 0 in the fits.
        """
        row = self._buffer[self._buffer_position]
        if self._means is None:
            row[0] = y
            row[1:] = u
        else:  # undo the running centring: a fit centres on the current means
            mean = self._means.mean
            row[0] = y + mean[0]
            row[1:] = u + mean[1:]
        self._breaks[self._buffer_position] = self._break_pending
        self._excluded[self._buffer_position] = excluded
        self._break_pending = False
        self._buffer_position = (self._buffer_position + 1) % BATCH_LIMIT
        self._stored = min(self._stored + 1, BATCH_LIMIT)
        self._since_start += 1
        self._samples += 1
        if self._since_start == self._next_fit:
            self._fit()

    def _stored_rows(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return the stored samples, their segment starts and exclusions, oldest first."""
        end, count = self._buffer_position, self._stored
        if count < BATCH_LIMIT:
            return (self._buffer[end - count:end].copy(), self._breaks[end - count:end].copy(),
                    self._excluded[end - count:end].copy())
        return (np.concatenate((self._buffer[end:], self._buffer[:end])),
                np.concatenate((self._breaks[end:], self._breaks[:end])),
                np.concatenate((self._excluded[end:], self._excluded[:end])))

    def _segments(self, rows: np.ndarray, breaks: np.ndarray, excluded: np.ndarray,
                  scale: np.ndarray) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """Split the normalised rows into gap-free segments (y, u, weights)."""
        lam = self._forgetting_factor
        count = rows.shape[0]
        # sample t of T weighs lambda^(T-1-t), an excluded one 0
        weights = lam ** np.arange(count - 1, -1, -1, dtype=float) if lam < 1.0 else np.ones(
            count)
        weights[excluded] = 0.0
        normalised = rows / scale
        starts = [0] + [int(k) for k in np.flatnonzero(breaks) if k > 0] + [count]
        return [(normalised[a:b, 0], normalised[a:b, 1:], weights[a:b])
                for a, b in zip(starts[:-1], starts[1:]) if b > a]

    # ------------------------------------------------------------- the fits
    def _fit(self) -> bool:
        """Fit the stored samples and continue the recursion from the fit (False: no fit)."""
        later = math.ceil(FIT_GROWTH * self._since_start)
        self._next_fit = later if later <= BATCH_LIMIT else 0
        rows, breaks, excluded = self._stored_rows()
        if self._means is not None:
            rows = rows - self._means.mean
        scale = self._signal_scale.copy()
        for channel in range(rows.shape[1]):
            size = signal_size(rows[:, channel])
            if size > 0.0:
                scale[channel] = power_of_two_at_least(size)
        segments = self._segments(rows, breaks, excluded, scale)
        if self._batch is None:
            self._batch = BatchFit(self.order, self.num_inputs, self.feedthrough,
                                   self.input_delay, self._armax, self._offset)
        candidates = []
        if self._fitted:
            # theta in the new scales: the b's scale with s_u / s_y
            ratio = (self._signal_scale[self._channel] / scale[self._channel]) * (
                scale[0] / self._signal_scale[0])
            candidates.append(self._theta_n[:self.num_parameters] * ratio)
        with np.errstate(all='ignore'):
            result = self._batch.fit(segments, candidates, 1.0 / self.initial_covariance)
            if result is not None and self._exclude_outliers(result.theta, segments, breaks,
                                                             excluded):
                segments = self._segments(rows, breaks, excluded, scale)
                result = self._batch.fit(segments, [result.theta],
                                         1.0 / self.initial_covariance)
        if result is None or not self._take_fit(result, segments, scale):
            return False
        self._fits += 1
        return True

    def _exclude_outliers(self, theta: np.ndarray, segments: list, breaks: np.ndarray,
                          excluded: np.ndarray) -> bool:
        """
        Take the samples that the gate would refuse at theta out of the fits.

        OE: each such sample weighs 0 from then on (its output enters nothing
        else); ARMAX: it becomes a segment of its own (a break before and
        after it: its output is a lag of the next ones). Marked in
        ``breaks`` / ``excluded`` and in the store, so that no fit uses it
        again (flag ``outlier_excluded`` per sample); False if there are none
        or more than OUTLIER_SHARE of the samples (then it is the model, not
        outliers).
        """
        batch = self._batch
        if batch is None:
            return False
        bad = batch.outliers(theta, segments, math.sqrt(self._gate_limit2))
        count = breaks.shape[0]
        if not 0 < bad.shape[0] <= OUTLIER_SHARE * count:
            return False
        first = self._buffer_position - count
        for row in bad:
            self._flag('outlier_excluded')
            if not self._armax:
                excluded[row] = True
                self._excluded[(first + row) % BATCH_LIMIT] = True
                continue
            breaks[row] = True
            self._breaks[(first + row) % BATCH_LIMIT] = True
            if row + 1 < count:
                breaks[row + 1] = True
                self._breaks[(first + row + 1) % BATCH_LIMIT] = True
            else:
                self._break_pending = True
        return True

    def _take_fit(self, result: FitResult, segments: list, scale: np.ndarray) -> bool:
        """Continue from the fit: theta, P, J, tau, the lags and psi; False if unsound."""
        information = result.information + np.eye(self._size) / self.initial_covariance
        try:
            covariance = np.linalg.inv(information)
        except np.linalg.LinAlgError:
            return False
        if not (np.isfinite(covariance).all() and np.isfinite(result.theta).all()
                and math.isfinite(result.loss) and result.weight > 0.0):
            return False
        self._p = np.ascontiguousarray(0.5 * (covariance + covariance.T))
        self._theta_n[:self.num_parameters] = result.theta
        if self._offset:
            self._theta_n[-1] = result.offset
        self._loss = result.loss
        self._tau = result.weight
        self._signal_scale = scale
        self._set_scale_dependents()
        self._arx = result.arx * self._unscale
        # the predictor's lags: those of the last segment's newest samples
        u = segments[-1][1]
        self._history.load_rows_oldest_first(np.column_stack((-result.tail_x, u,
                                                              result.tail_e)))
        self._psi_history[:] = result.tail_psi
        self._sigma2_fit = result.loss / result.weight
        self._recent = self._sigma2_fit
        self._lambda_t = min(self._forgetting_factor, LAMBDA_START)
        self._fitted = True
        self._projected_in_row = 0
        return True

    def _restart(self, reason: str) -> None:
        """Restart from a fit of the stored samples (flag ``restarted``), e.g. after a drift."""
        self._flag('restarted')
        self._restart_note = reason
        self._projected_in_row = 0
        # the residuals so far are of the model that drifted
        self._forget_residuals()
        self._fit()
        self._recent = max(self._recent, self._sigma2_fit)

    def _accept_change(self) -> None:
        """Cut the memory (rules.memory_keep) and restart the fits after the change."""
        self._changes += 1
        self._forget_residuals()
        keep = rules.memory_keep(self._tau, self.num_parameters)
        if keep < 1.0:
            # one extra forgetting step: P / kappa, kappa J, kappa tau
            self._p *= 1.0 / keep
            self._loss *= keep
            self._tau *= keep
        # the stored samples are of the old plant: the fits start again from here
        self._stored = 0
        self._since_start = 0
        self._next_fit = self._first_fit
        self._break_pending = True

    # --------------------------------------------------- health and validity
    def _check_covariance(self) -> None:
        try:
            np.linalg.cholesky(self._p)
        except np.linalg.LinAlgError:
            self._repair_covariance()

    def _repair_covariance(self) -> None:
        """Rebuild P as the nearest symmetric positive definite matrix (covariance_repaired)."""
        self._flag('covariance_repaired')
        self._p = np.ascontiguousarray(repair_covariance(
            self._p, np.eye(self._size) * self.initial_covariance))

    def _check_validity(self) -> None:
        """Re-evaluate drift and the validity reasons (every VALIDITY_PERIOD updates)."""
        steps = self._updates - self._last_check
        self._last_check = self._updates
        self._next_check = self._updates + rules.VALIDITY_PERIOD
        reasons = []
        if self._projected_in_row >= PROJECTION_RESTART:
            self._restart(f'stability projection refused {self._projected_in_row} steps '
                          f'in a row')
        elif self._recent > DRIFT_FACTOR * (self._sigma2_fit + VARIANCE_FLOOR ** 2):
            ratio = self._recent / (self._sigma2_fit + VARIANCE_FLOOR ** 2)
            self._restart(f'drift: prediction error {math.sqrt(ratio):.3g} x that of the fit')
        if self._restart_note:
            reasons.append(f'restarted ({self._restart_note})')
            self._restart_note = ''
        projected = self._projected_since_check
        self._projected_since_check = 0
        if steps > 0 and projected > PROJECTION_SHARE * steps:
            reasons.append(f'stability projection active ({projected} of the last {steps} '
                           f'updates)')
        self._reasons = tuple(reasons + residual_reasons(self._monitor))

    def _validity_reasons(self) -> tuple[str, ...]:
        return self._reasons

    # --------------------------------------------------------- the accessors
    @property
    def ready(self) -> bool:
        """Whether the first fit is made (and at least p samples were used)."""
        return self._fitted and self._samples >= self.num_parameters

    @property
    def valid(self) -> bool:
        """Whether :attr:`ready` and no :attr:`validity_reasons` (see the class docstring)."""
        return self.ready and not self._reasons

    @property
    def samples(self) -> int:
        """Count the samples used (stored for the fits or stepped on) since the last reset."""
        return self._samples

    @property
    def fits(self) -> int:
        """Count the batch fits made since the last reset (restarts included)."""
        return self._fits

    @property
    def signal_scale(self) -> np.ndarray:
        """Return the scales of y, u_1 ... u_r of the last fit (1 before the first)."""
        return self._signal_scale.copy()

    @property
    def covariance(self) -> np.ndarray:
        """Return the theta block of P(t) in the units of theta, shape ``(p, p)`` (a copy)."""
        p = self.num_parameters
        return self._p[:p, :p] * np.outer(self._unscale, self._unscale)

    @property
    def covariance_trace(self) -> float:
        """Return the trace of the theta block of P(t) in the units of theta."""
        return float(np.diagonal(self._p)[:self.num_parameters].dot(self._unscale ** 2))

    @property
    def weighted_count(self) -> float:
        """Return tau(t), the weighted count of the samples learnt from."""
        return self._tau

    def _parameter_covariance(self) -> np.ndarray | None:
        r"""
        Return the HAC covariance of the estimate in the units of theta (None before ready).

        The recursion's P is the inverse of the weighted information
        :math:`\sum w_t\psi_t\psi_t^T`, and the estimate moves by
        :math:`P\sum_t w_t\psi_t\varepsilon_t`, so its covariance is
        :math:`P\,\mathrm{var}(\sum_t w_t\psi_t\varepsilon_t)\,P` (Ljung 1999,
        sec. 9.3, without assuming white prediction errors). The middle is
        :math:`\tau_2\hat\Omega`, with :math:`\hat\Omega` the long-run covariance
        per unit weight of the scores :math:`\psi_t\varepsilon_t` that
        :class:`~bcid_ros.estimators.hac.HacCovariance` estimates from the scores
        since the gate's warm-up (prewhitened, windowed), and :math:`\tau_2` that of
        every sample the estimate learnt from (the batch fits' included), with the
        small-sample factor T/(T - p). Calibrated whether the output error of an
        OE model is white or coloured (docs/trust.md).
        """
        tau = self._tau
        if not self.ready or not tau > 0.0:
            return None
        long_run = self._hac.long_run(transform=self._p)
        if long_run is None:
            return None
        p = self.num_parameters
        tau2 = tau * weighted_square_ratio(tau, self._forgetting_factor)
        size = tau * tau / tau2
        if not size > self._size:
            return None
        covariance = long_run[:p, :p] * (tau2 * size / (size - self._size))
        # normalised units to theta's: theta_k s_y / s_channel(k)
        unscale = self._unscale
        return 0.5 * (covariance + covariance.T) * np.outer(unscale, unscale)

    def _theta(self) -> np.ndarray:
        return self._theta_n[:self.num_parameters] * self._unscale

    def _theta_uncompensated(self) -> np.ndarray:
        return self._arx

    def _noise(self) -> np.ndarray:
        if not self._tau > 0.0:
            return np.zeros(1)
        return np.array([self._loss / self._tau * self._signal_scale[0] ** 2])

    @property
    def operating_point(self) -> np.ndarray | None:
        """
        Return ``[y0, u1, ..., ur]``: the recursive means, y0 moved by the model's offset.

        With ``detrend: mean`` the model is y - m_y = G(q)(u - m_u) + c (OE;
        ARMAX: the equation offset d, c = d / A(1)), so the operating point of
        the estimate is (m_y + c, m_u): the point to simulate the model around.
        """
        point = super().operating_point
        if point is None or not self._fitted:
            return point
        offset = float(self._theta_n[-1]) * self._signal_scale[0]
        if self._armax:  # A(1) > 0 for a stable A
            offset /= 1.0 + float(self._theta_n[:self.order].sum())
        point[0] += offset
        return point

    def __repr__(self) -> str:
        return (f'Rpem(model={self.model!r}, order={self.order}, num_inputs={self.num_inputs}, '
                f'feedthrough={self.feedthrough}, '
                f'forgetting_factor={self._forgetting_factor})')

    # -------------------------------------------------------------- the state
    def _set_scale_dependents(self) -> None:
        scale = self._signal_scale
        self._inverse_scale = 1.0 / scale
        # theta in the user's units: theta_k s_y / s_channel(k)
        self._unscale = scale[0] / scale[self._channel]

    def _reset(self) -> None:
        p, n, size = self.num_parameters, self.order, self._size
        self._history.clear()
        # theta in normalised units, and the offset last with detrend: mean
        self._theta_n = np.zeros(size)
        self._p = self.initial_covariance * np.eye(size)
        self._psi_history = np.zeros((n, size))
        self._arx = np.zeros(p)
        self._signal_scale = np.ones(1 + self.num_inputs)
        self._set_scale_dependents()
        self._trace_limit = self.initial_covariance * size
        self._buffer = np.zeros((BATCH_LIMIT, 1 + self.num_inputs))
        self._breaks = np.zeros(BATCH_LIMIT, dtype=bool)
        self._excluded = np.zeros(BATCH_LIMIT, dtype=bool)
        self._buffer_position = 0
        self._stored = 0
        self._since_start = 0
        self._next_fit = self._first_fit
        self._break_pending = False
        self._fitted = False
        self._fits = 0
        self._samples = 0
        self._updates = 0
        self._loss = 0.0
        self._tau = 0.0
        self._lambda_t = self._forgetting_factor
        self._sigma2_fit = 0.0
        self._recent = 0.0
        self._gate_from = rules.GATE_WARMUP * p
        self._changes = 0
        self._undone_in_row = 0
        self._projected_in_row = 0
        self._projected_since_check = 0
        self._next_check = rules.VALIDITY_PERIOD
        self._last_check = 0
        self._restart_note = ''
        self._reasons: tuple[str, ...] = ()
        # (phi, psi, y, u) of the step whose sample the gate is testing
        self._gating: tuple[np.ndarray, np.ndarray, float, np.ndarray] | None = None
        self._forget_residuals()

    def _forget_residuals(self) -> None:
        """Start the residual tests and the HAC afresh (at a reset and at a plant change)."""
        self._monitor = AdequacyMonitor(num_inputs=self.num_inputs, model=self.adequacy_model,
                                        forgetting_factor=self._forgetting_factor)
        self._hac = HacCovariance(dimension=self._size,
                                  forgetting_factor=self._forgetting_factor)

    def _restart_regressor(self) -> None:
        self._history.clear()
        self._psi_history[:] = 0.0
        self._break_pending = True

    _ARRAYS = ('theta_n', 'p', 'psi_history', 'arx', 'signal_scale', 'buffer', 'breaks',
               'excluded')
    _SCALARS = ('buffer_position', 'stored', 'since_start', 'next_fit', 'break_pending',
                'fitted', 'fits', 'samples', 'updates', 'loss', 'tau', 'lambda_t',
                'sigma2_fit', 'recent', 'changes', 'undone_in_row', 'projected_in_row',
                'projected_since_check', 'next_check', 'last_check', 'restart_note',
                'forgetting_factor')

    def _state_items(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        arrays = {name: getattr(self, '_' + name) for name in self._ARRAYS}
        arrays['history'] = self._history.history
        scalars = {name: getattr(self, '_' + name) for name in self._SCALARS}
        scalars.update(filled=self._history.filled, position=self._history.position,
                       reasons=list(self._reasons))
        residual_arrays, residual_scalars = residual_items(self._monitor.get_state(),
                                                           self._hac.get_state())
        return {**arrays, **residual_arrays}, {**scalars, **residual_scalars}

    def _load_state(self, arrays: dict[str, np.ndarray], scalars: dict[str, Any]) -> None:
        for name in self._ARRAYS:
            setattr(self, '_' + name, arrays[name])
        self._p = np.ascontiguousarray(self._p)
        self._history.history[:] = arrays['history']
        self._history.filled = int(scalars['filled'])
        self._history.position = int(scalars['position'])
        kinds: dict[str, Callable[[Any], Any]] = {
            'loss': float, 'tau': float, 'lambda_t': float, 'sigma2_fit': float,
            'recent': float, 'forgetting_factor': float, 'break_pending': bool, 'fitted': bool,
            'restart_note': str}
        for name in self._SCALARS:
            setattr(self, '_' + name, kinds.get(name, int)(scalars[name]))
        self._reasons = tuple(scalars['reasons'])
        self._set_scale_dependents()
        monitor, hac = residual_states(arrays, scalars)
        self._monitor.set_state(monitor)
        self._hac.set_state(hac)
