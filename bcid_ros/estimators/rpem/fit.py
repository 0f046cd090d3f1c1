r"""
The batch prediction-error fit of RPEM's stored samples: its starts and its Gauss-Newton search.

Ljung, *System Identification*, 2nd ed. (1999), ch. 10 (sec. 10.2, the
Gauss-Newton search with a line search, started here by instrumental-variable
iterations): the ARX least-squares estimate, ``IV_ITERATIONS``
Steiglitz-McBride (OE) or extended least-squares (ARMAX) iterates, and the
given candidates are each pulled into the stability region D_M
(:mod:`~bcid_ros.estimators.rpem.stability`); the best are refined by
Gauss-Newton (or Levenberg-Marquardt) steps on the loss of the predictor of
:mod:`~bcid_ros.estimators.rpem.segment`, with the nuisance (initial state,
offset) projected out (Kaufman's variable projection). :class:`FitResult`
carries what the recursion continues with.
"""

from __future__ import annotations

import math
from typing import Any, Generator

import numpy as np

from bcid_ros.estimators.polynomials import is_stable
from bcid_ros.estimators.rpem.segment import INITIAL_PRIOR, SegmentPredictor, solve_regularised
from bcid_ros.estimators.rpem.stability import (edge_mode_cancelled, HALVINGS, pull_inside,
                                                REGION_MARGIN)
from bcid_ros.estimators.rpem.uncertainty import unresolved_limit

#: Steiglitz-McBride (OE) or extended least-squares (ARMAX) iterations of a fit.
IV_ITERATIONS = 8
#: Gauss-Newton (or Levenberg-Marquardt) iterations of a fit.
LM_ITERATIONS = 20
#: Samples weighing less than this in a fit (forgetting) are not tested for outliers.
OUTLIER_WEIGHT = 0.01
#: Relative loss decrease below which the Gauss-Newton search stops.
LM_TOLERANCE = 1e-10


#: The fixed cost of a pass in sample-columns (its calls: about 0.05 ms, as 2000 columns).
PASS_COST = 4096
#: A fit spread over passes: announces each pass's cost before it runs it (a pass runs at
#: the next ``next``), returns its value (see BatchFit.steps).
Steps = Generator[int, None, Any]


def finish(steps: Steps) -> Any:
    """Run the passes of ``steps`` to the end; return its value."""
    while True:
        try:
            next(steps)
        except StopIteration as done:
            return done.value


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
    scores : numpy.ndarray, shape ``(m, q)``
        psi(t) eps(t) at theta of the m samples with a weight, oldest first:
        the estimating-equation scores of the estimate (the HAC's input).
    profiled : tuple of numpy.ndarray or None
        The information ``(p, p)`` and the scores ``(m, p)`` of theta alone with
        the nuisance (each segment's initial state, the offset) fitted, psi
        projected off its columns: what the samples tell about theta
        (:mod:`~bcid_ros.estimators.rpem.uncertainty`). ``information`` holds the
        nuisance instead, as the recursion does, and on a slow plant's short
        segments claims far more (tracking plant (1, 5): variances 5-200 times
        smaller).
    alternative : tuple or None
        ``(theta, ratio)``: where the fit's other start ended, and the ratio of its
        loss to the estimate's (the search's criterion, after a change the loss with
        the state free, below 1 where the data did not tell the ends apart and the
        current estimate's stayed; None: one start), for
        :func:`~bcid_ros.estimators.rpem.uncertainty.with_unresolved`.

    """

    def __init__(self, theta: np.ndarray, information: np.ndarray, loss: float, weight: float,
                 arx: np.ndarray, tail_x: np.ndarray, tail_e: np.ndarray,
                 tail_psi: np.ndarray, offset: float, scores: np.ndarray,
                 profiled: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        self.theta = theta
        self.information = information
        self.loss = loss
        self.weight = weight
        self.arx = arx
        self.tail_x = tail_x
        self.tail_e = tail_e
        self.tail_psi = tail_psi
        self.offset = offset
        self.scores = scores
        self.profiled = profiled
        #: (theta, loss ratio) where the fit's other start ended (None: one start)
        self.alternative: tuple[np.ndarray, float] | None = None

    def residuals(self, segment: tuple[np.ndarray, np.ndarray, np.ndarray],
                  armax: bool) -> np.ndarray:
        """Return the one-step errors of the last segment ``(y, u, weights)``, weighted ones."""
        y, _, weights = segment
        # OE: the output minus the simulated output and the offset
        residuals = self.tail_e if armax else y - self.tail_x - self.offset
        return residuals[weights > 0.0]

    def covariance(self, initial_covariance: float) -> np.ndarray | None:
        """
        Return the P to continue the recursion with: (information + I / p0)^-1, C-ordered.

        Symmetrised; None if it cannot be inverted or it or the fit is not finite.
        """
        information = self.information + np.eye(self.information.shape[0]) / initial_covariance
        try:
            covariance = np.linalg.inv(information)
        except np.linalg.LinAlgError:
            return None
        if not (np.isfinite(covariance).all() and np.isfinite(self.theta).all()
                and math.isfinite(self.loss) and self.weight > 0.0):
            return None
        return np.ascontiguousarray(0.5 * (covariance + covariance.T))


class BatchFit:
    r"""
    Batch prediction-error fit of the OE or ARMAX model over stored segments (normalised).

    The same predictor as the recursion with the parameters held fixed
    (Ljung 1999, ch. 10; :class:`~bcid_ros.estimators.rpem.segment.SegmentPredictor`):
    per segment, the first ``span`` samples fill the lags, then

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
    steps that keep every iterate stable and returns the lower end; after a
    plant change (``after_change``), the searches and their comparison with each
    segment's initial state free (OE; elsewhere the searches' loss shrinks it
    towards 0, which charges samples that start where the old plant left the
    output for their true state): the end of lower loss where the losses tell
    the ends apart, else the current estimate's (:meth:`_ranked`). An OE end with a
    mode on the region's edge that a zero of every B_i cancels comes after the other
    whatever its loss (:func:`~bcid_ros.estimators.rpem.stability.edge_mode_cancelled`),
    and stays the fit's alternative. The fit the recursion continues with
    (:meth:`_result`) keeps the prior.
    """

    def __init__(self, order: int, num_inputs: int, feedthrough: bool,
                 input_delay: tuple[int, ...], armax: bool, offset: bool) -> None:
        from scipy import signal  # only a fit needs it

        self._signal = signal
        self._predictor = predictor = SegmentPredictor(order, num_inputs, feedthrough,
                                                       input_delay, armax, offset)
        self.order = order
        self.armax = armax
        self.offset = offset
        self.span = predictor.span
        self.num_b = predictor.num_b
        self.num_inputs = num_inputs
        self.num_parameters = predictor.num_parameters
        #: the information of the prior on each segment's initial state in the fit under way
        #: (:meth:`steps`: none after a plant change)
        self._state_prior = INITIAL_PRIOR
        #: The columns a pass of the predictor without its gradient counts (the loss, the
        #: outlier test): n + 2, not 1. Per counted unit against the gradient pass (2 (p + 1)
        #: columns), a loss pass counted as 1 column took 1.8 times as long at n = 1 and
        #: 2.4-3.3 times at n = 3, as n + 1 columns 1.3-1.4 times (tracking plants (0, 1),
        #: (1, 27), (2, 5), (3, 2)): its recursion over F's n lags, not its one output, sets
        #: its cost
        self.loss_columns = order + 2

    # -------------------------------------------------------------- the fit
    def fit(self, segments: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
            candidates: list[np.ndarray], prior: float,
            after_change: bool = False) -> FitResult | None:
        """
        Fit the segments ``(y, u, weights)`` (normalised); None if none is usable.

        ``prior`` is the information 1/p0 added to every diagonal entry. The
        whole of :meth:`steps` at once.
        """
        return finish(self.steps(segments, candidates, prior, after_change))

    def steps(self, segments: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
              candidates: list[np.ndarray], prior: float, after_change: bool = False) -> Steps:
        """
        Fit as :meth:`fit` does, one pass over the samples at a time; return the fit.

        A generator: before each pass of the predictor (or a regression)
        over the segments it yields the pass's cost, the samples times the
        columns it computes (:meth:`_cost`), and runs the pass when resumed,
        so that a caller can spread the fit over updates by a deterministic
        amount of work each and know a pass's cost before it runs it
        (:class:`~bcid_ros.estimators.rpem.store.FitJob`).
        """
        usable = [(y, u, w, self._predictor.input_columns(u)) for y, u, w in segments
                  if y.shape[0] > self.span]
        if not usable:
            return None
        # after a plant change the searches too with each segment's initial state free (OE):
        # its samples start where the old plant left the output, and the prior that shrinks
        # the state towards 0 charges the true state for it, a slow plant's most: drift (2,
        # 19) 2250 samples after its change, the searches' minimum with the prior 40 % off
        # (its criterion 1.403 against the truth's 1.622), free the search from it ends
        # 1.7 % off, the batch OE fit's (0.4 %) basin (free 1.1318 against 1.1575)
        self._state_prior = 0.0 if after_change and not self.armax else INITIAL_PRIOR
        yield self._cost(usable, self.num_parameters)
        arx = self._arx(usable)
        # two starts: the best given candidate, and the best of ARX and its IV iterates
        path = yield from self._iv_path(arx, usable)
        starts = [(yield from self._best([theta for theta in candidates
                                          if np.isfinite(theta).all()], usable)),
                  (yield from self._best(path, usable))]
        ends = []
        for theta, loss in starts:
            if theta is None:
                continue
            ends.append((yield from self._search(theta, loss, usable, prior)))
        if not ends:
            return None
        if after_change and len(ends) > 1 and not self.armax:
            # the ends compared with each segment's initial state free (Ljung 1999, ch. 10:
            # estimated): the prior that keeps the level out of the offset in the search
            # also charges the samples after a plant change, which start where the old
            # plant left the output, for their true state (tracking plant (2, 0), 135
            # samples after its change: the truth's loss 5 times that free, and the end
            # 110 % off the lower by it; free, the truth's end is). Not before any change:
            # free, an integrator's loop (test_rpem_projection_reason) took an end nearer
            # the boundary, and a stationary plant of realistic_family(60, 2) two false
            # detections. (The searches' losses are free after a change too; the ends are
            # scored again here, one pass each, as they were when only the comparison was.)
            free = yield from self._scored([theta for theta, _ in ends], usable, prior=0.0)
            ends = self._ranked(free, usable)
        else:
            ends.sort(key=lambda end: end[1])  # stable: a tie goes to the first start
        if not self.armax:  # (ARMAX's A is the noise's too: a cancelled pole is its pole)
            # an end whose mode on the edge serves only the initial state goes last, whatever
            # its loss: the free state's share of it is the disturbance's (edge_mode_cancelled)
            ends.sort(key=lambda end: self._cancelled_at_edge(end[0]))
        yield self._cost(usable, 2 * (self.num_parameters + 1))
        result = self._result(ends[0][0], segments, usable, arx)
        # the other start's end: where the data may not tell it from the estimate, its
        # distance is an error no covariance at the estimate shows (rpem/uncertainty.py)
        if len(ends) > 1 and ends[0][1] > 0.0:
            result.alternative = (ends[1][0], ends[1][1] / ends[0][1])
        return result

    def _ranked(self, ends: list[tuple[np.ndarray, float]],
                usable: list) -> list[tuple[np.ndarray, float]]:
        r"""
        Return ``ends`` best first where their losses tell them apart, else as they started.

        The likelihood-ratio statistic of the worse end against the better,
        :math:`N(V_2/V_1 - 1)` (V the losses, N the weight), is at most
        :math:`(\tau_2/\tau)\chi^2_p` at the truth under white errors
        (:func:`~bcid_ros.estimators.rpem.uncertainty.with_unresolved`). Within its
        ``UNRESOLVED_LEVEL`` quantile the data do not prefer either end, and the first
        start's end stays first: that of the search from the current estimate (the
        given candidate). A switch between minima the data do not tell apart moves the
        estimate by their distance for nothing, and the next fits, started from it,
        stay in its basin (tracking plant (0, 5), 311 samples after its change: losses
        0.35 % apart, a statistic of 1.1 against 12.6, and the fit took the end 35 % off
        over the one 12 % off for the next 1500 samples; docs/tracking_log.md, "Limits",
        session 9). The other end still joins the covariance where it is as good
        (:attr:`FitResult.alternative`, its loss ratio then possibly below 1).
        """
        ranked = sorted(ends, key=lambda end: end[1])
        weights = np.concatenate([w[self.span:] for _, _, w, _ in usable])
        weight = float(weights.sum())
        best, second = ranked[0][1], ranked[1][1]
        if not (weight > 0.0 and best > 0.0 and math.isfinite(second)):
            return ranked
        statistic = weight * (second / best - 1.0)
        # tau_2 / tau of the fit's weights (1 without forgetting)
        limit = unresolved_limit(self.num_parameters, float(weights.dot(weights)) / weight)
        return ranked if statistic > limit else ends

    def _cost(self, usable: list, columns: int) -> int:
        """Return the cost of a pass: samples times columns, and PASS_COST for its calls."""
        return sum(y.shape[0] for y, _, _, _ in usable) * columns + PASS_COST

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
                eps = self._predictor.predict(theta, y, u, weights, gradient=False,
                                              prior=0.0).eps
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

    def _best(self, thetas: list[np.ndarray], usable: list) -> Steps:
        """Return the one of ``thetas`` (stabilised) with the smallest loss, and its loss."""
        best_theta, best_loss = None, math.inf
        for theta, loss in (yield from self._scored(thetas, usable)):
            if loss < best_loss:
                best_theta, best_loss = theta, loss
        return best_theta, best_loss

    def _scored(self, thetas: list[np.ndarray], usable: list,
                prior: float | None = None) -> Steps:
        """Return each of ``thetas`` stabilised, with its loss (the initial states' ``prior``)."""
        scored = []
        for theta in thetas:
            theta = self._stabilised(theta)
            scored.append((theta, (yield from self._loss_steps(theta, usable, prior))))
        return scored

    def _iv_path(self, arx: np.ndarray, usable: list) -> Steps:
        """Return the ARX estimate and its IV_ITERATIONS IV iterates (each stabilised)."""
        path = [self._stabilised(arx)]
        for _ in range(IV_ITERATIONS):
            yield self._cost(usable, 2 * (self.num_parameters + 1))
            theta = self._iv_step(path[-1], usable)
            if theta is None:
                break
            path.append(self._stabilised(theta))
        return path

    def _stabilised(self, theta: np.ndarray) -> np.ndarray:
        """Return theta with F (or A and C) pulled into the stability region."""
        n = self.order
        theta = theta.copy()
        if not is_stable(theta[:n], REGION_MARGIN):
            theta[:n] = pull_inside(theta[:n])
        if self.armax and not is_stable(theta[n + self.num_b:], REGION_MARGIN):
            theta[n + self.num_b:] = pull_inside(theta[n + self.num_b:])
        return theta

    def _cancelled_at_edge(self, theta: np.ndarray) -> bool:
        """Return whether a root of F on the region's edge is cancelled by every B_i's zeros."""
        n = self.order
        return edge_mode_cancelled(theta[:n], np.split(theta[n:n + self.num_b], self.num_inputs))

    def _is_inside(self, theta: np.ndarray) -> bool:
        n = self.order
        return is_stable(theta[:n], REGION_MARGIN) and (
            not self.armax or is_stable(theta[n + self.num_b:], REGION_MARGIN))

    def _arx(self, usable: list) -> np.ndarray:
        """Return the weighted least-squares ARX estimate (c = 0 for ARMAX, offset dropped)."""
        start = self.span
        p_ab = self.order + self.num_b
        gram = np.zeros((p_ab + self.offset, p_ab + self.offset))
        moment = np.zeros(p_ab + self.offset)
        predictor = self._predictor
        for y, _, weights, inputs in usable:
            regressors = predictor.with_constant(np.column_stack((predictor.output_columns(y),
                                                                  inputs)))[start:]
            weighted = regressors * weights[start:, None]
            gram += weighted.T.dot(regressors)
            moment += weighted.T.dot(y[start:])
        theta = np.zeros(self.num_parameters)
        solution = solve_regularised(gram, moment)
        if solution is not None:
            theta[:p_ab] = solution[:p_ab]
        return theta

    def _loss_steps(self, theta: np.ndarray, usable: list, prior: float | None = None) -> Steps:
        """Return :meth:`_loss`, a pass announced."""
        yield self._cost(usable, self.loss_columns)
        return self._loss(theta, usable, prior)

    def _loss(self, theta: np.ndarray, usable: list, prior: float | None = None) -> float:
        """Return sum w eps^2 at theta, the initial states' prior of information ``prior``."""
        prior = self._state_prior if prior is None else prior
        total = 0.0
        for y, u, weights, inputs in usable:
            eps = self._predictor.predict(theta, y, u, weights, inputs, gradient=False,
                                          prior=prior).eps
            total += float(weights[self.span:].dot(eps * eps))
        return total if math.isfinite(total) else math.inf

    def _iv_step(self, theta: np.ndarray, usable: list) -> np.ndarray | None:
        """Return one Steiglitz-McBride (OE) or extended least-squares (ARMAX) iterate."""
        lfilter = self._signal.lfilter
        predictor = self._predictor
        n, start = self.order, self.span
        size = self.num_parameters + self.offset
        gram = np.zeros((size, size))
        moment = np.zeros(size)
        for y, u, weights, inputs in usable:
            if self.armax:
                # regress y on [-y lags, u lags, eps lags] with eps of the current model
                e = predictor.predict(theta, y, u, weights, inputs, gradient=False).e
                regressors = predictor.with_constant(np.column_stack((
                    predictor.output_columns(y), inputs, predictor.residual_columns(e))))[start:]
                weighted = regressors * weights[start:, None]
                gram += weighted.T.dot(regressors)
                moment += weighted.T.dot(y[start:])
                continue
            f_poly = np.concatenate(([1.0], theta[:n]))
            # data filtered by 1 / F: y_f(t) = F(q)^-1 y(t), u_f(t) = F(q)^-1 u(t)
            y_filtered = lfilter([1.0], f_poly, y)
            regressors = predictor.with_constant(np.column_stack((
                predictor.output_columns(y_filtered), lfilter([1.0], f_poly, inputs, axis=0))))[
                start:]
            # instruments: psi(t) = phi(w)(t) / F(q), the noise-free regressors (from rest:
            # the initial state fitted to a poor model would carry the noise into them)
            psi = predictor.predict(theta, y, u, weights, inputs, False).psi
            instruments = predictor.with_constant(psi) * weights[start:, None]
            gram += instruments.T.dot(regressors)
            moment += instruments.T.dot(y_filtered[start:])
        new = solve_regularised(gram, moment)
        return new[:self.num_parameters] if new is not None and np.isfinite(new).all() \
            else None

    def _gradient(self, theta: np.ndarray, usable: list, prior: float,
                  concentrated: bool = True, scores: list | None = None,
                  profiled: list | None = None,
                  state_prior: float | None = None) -> tuple[float, np.ndarray, np.ndarray]:
        """
        Return the loss, the Gauss-Newton information and the gradient at theta.

        ``scores``, a list: each segment's psi eps of its samples with a
        weight is appended to it. ``profiled``, a list: each segment's
        information and scores of theta with psi projected off the nuisance
        (:attr:`FitResult.profiled`) are appended to it. ``state_prior``: the information
        of the initial states' prior (None: the search's).

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
            prediction = self._predictor.predict(
                theta, y, u, weights, inputs,
                prior=self._state_prior if state_prior is None else state_prior)
            psi = prediction.psi
            if profiled is not None:
                clean = psi[:, :self.num_parameters]
                if prediction.nuisance is not None:
                    clean = self._without_nuisance(clean, prediction.nuisance,
                                                   weights[self.span:])
                kept = weights[self.span:] > 0.0
                profiled.append(((clean * weights[self.span:, None]).T.dot(clean),
                                 (clean * prediction.eps[:, None])[kept]))
            if concentrated and prediction.nuisance is not None:
                psi = self._without_nuisance(psi, prediction.nuisance, weights[self.span:])
            elif not concentrated and self.offset:
                psi = np.column_stack((psi, prediction.offset_gradient))
            weighted = psi * weights[self.span:, None]
            information += weighted.T.dot(psi)
            gradient += weighted.T.dot(prediction.eps)
            loss += float(weights[self.span:].dot(prediction.eps ** 2))
            if scores is not None:
                scores.append((psi * prediction.eps[:, None])[weights[self.span:] > 0.0])
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

    def _search(self, theta: np.ndarray, loss: float, usable: list, prior: float) -> Steps:
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
            yield self._cost(usable, 2 * (self.num_parameters + 1))
            loss, information, gradient = self._gradient(theta, usable, prior)
            step = solve_regularised(information, gradient)
            if step is None:
                break
            candidate, new_loss = yield from self._line_search(theta, step, loss, usable)
            if candidate is None:
                candidate, new_loss = yield from self._damped_step(theta, loss, information,
                                                                   gradient, usable)
            if candidate is None:
                break
            improvement = loss - new_loss
            theta, loss = candidate, new_loss
            if not improvement > LM_TOLERANCE * loss:
                break
        return theta, loss

    def _line_search(self, theta: np.ndarray, step: np.ndarray, loss: float,
                     usable: list) -> Steps:
        """Return theta + mu step, mu = 1, 1/2, ..., the first stable one with a lower loss."""
        scale = 1.0
        for _ in range(HALVINGS + 1):
            candidate = theta + scale * step
            if self._is_inside(candidate):
                new_loss = yield from self._loss_steps(candidate, usable)
                if new_loss < loss:
                    return candidate, new_loss
            scale *= 0.5
        return None, loss

    def _damped_step(self, theta: np.ndarray, loss: float, information: np.ndarray,
                     gradient: np.ndarray, usable: list) -> Steps:
        """Return a Levenberg-Marquardt step (H + mu diag H) that lowers the loss, or None."""
        diagonal = np.diag(information).copy()
        damping = 1e-3
        for _ in range(8):
            step = solve_regularised(information + damping * np.diag(diagonal), gradient)
            if step is None:
                break
            candidate = theta + step
            if self._is_inside(candidate):
                new_loss = yield from self._loss_steps(candidate, usable)
                if new_loss < loss:
                    return candidate, new_loss
            damping *= 10.0
        return None, loss

    def _result(self, theta: np.ndarray, segments: list, usable: list,
                arx: np.ndarray) -> FitResult:
        """Return the fit at theta with the predictor state at the end of the last segment."""
        scores: list[np.ndarray] = []
        profiled: list[tuple[np.ndarray, np.ndarray]] = []
        # what the recursion continues with, and its std: with the state's prior, after a
        # change too (the searches alone go free): free here as well, the std of tracking
        # plant (0, 13) (11 dB) after its change fell below 10 % of |theta| with the
        # estimate 16-24 % off (valid on 64 % of its 2000 samples); with the prior it says
        # 11-16 %
        loss, information, _ = self._gradient(theta, usable, 0.0, concentrated=False,
                                              scores=scores, profiled=profiled,
                                              state_prior=INITIAL_PRIOR)
        weight = float(sum(w[self.span:].sum() for _, _, w, _ in usable))
        x, e, tail_psi, offset = self._tails(theta, segments, usable)
        p = self.num_parameters
        return FitResult(theta, information, loss, weight, arx, x, e, tail_psi, offset,
                         np.concatenate(scores) if scores else np.zeros((0, information.shape[0])),
                         (sum((i for i, _ in profiled), np.zeros((p, p))),
                          np.concatenate([c for _, c in profiled]) if profiled
                          else np.zeros((0, p))))

    def continued(self, result: FitResult, segments: list) -> FitResult:
        """
        Return ``result`` with the predictor state at the end of ``segments`` instead.

        For a fit taken some samples after the ones it fitted (a fit spread
        over updates, :class:`~bcid_ros.estimators.rpem.store.FitJob`): the
        same estimate, information, loss and scores; the lags, psi and offset
        those of its predictor run at its estimate over the samples stored now.
        """
        usable = [(y, u, w, self._predictor.input_columns(u)) for y, u, w in segments
                  if y.shape[0] > self.span]
        tail_x, tail_e, tail_psi, offset = self._tails(result.theta, segments, usable)
        continued = FitResult(result.theta, result.information, result.loss, result.weight,
                              result.arx, tail_x, tail_e, tail_psi, offset, result.scores,
                              result.profiled)
        continued.alternative = result.alternative
        return continued

    def _tails(self, theta: np.ndarray, segments: list,
               usable: list) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """Return the predictor's x, e, psi lags and offset at theta at the end of the segments."""
        n, p = self.order, self.num_parameters
        y, u, weights = segments[-1]
        tail_psi = np.zeros((n, p + self.offset))
        offset = 0.0
        if y.shape[0] > self.span:
            prediction = self._predictor.predict(theta, y, u, weights)
            x, e, offset = prediction.x, prediction.e, prediction.offset
            rows = prediction.psi[::-1][:n]
            tail_psi[:rows.shape[0], :p] = rows
            if self.armax and self.offset:  # the offset's gradient is filtered by 1 / C
                tail = prediction.offset_gradient[::-1][:n]
                tail_psi[:tail.shape[0], p] = tail
        else:
            x, e = y, np.zeros(y.shape[0])
            if usable:  # the offset of the newest usable segment
                offset = self._predictor.predict(theta, *usable[-1][:3], gradient=False).offset
        return x, e, tail_psi, offset
