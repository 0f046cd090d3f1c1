r"""
The online RPEM estimator: the recursion, its gate, its hand-over from the fits, and its state.

Ljung and Söderström (1983), *Theory and Practice of Recursive
Identification* (L&S): the recursive prediction-error algorithm in its
Gauss-Newton form with the output-error and the recursive
maximum-likelihood (ARMAX) predictors, projected into D_M; Ljung, *System
Identification*, 2nd ed. (1999), sec. 11.4. :class:`Rpem` holds theta, P,
J and tau; the predictor's lags, the stored samples with their fits and the
restart monitors are its collaborators (``history``, ``store``, ``watch``);
the gate, warm-up, memory cut, covariance check and repair and validity
period are the rulebook's. Equation numbers are not given: the books were
not at hand to check them.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from bcid_ros.estimators import rules
from bcid_ros.estimators.adequacy import AdequacyMonitor
from bcid_ros.estimators.base import RecursiveEstimator
from bcid_ros.estimators.change_detection import (BLOCK_LENGTH, BLOCK_SHARE, BlockMeanDetector,
                                                  ChangeDetector, FALSE_ALARM, WARMUP)
from bcid_ros.estimators.polynomials import is_stable
from bcid_ros.estimators.recursion import (downdate, HEALTH_CHECK_PERIOD, repair_covariance,
                                           VARIANCE_FLOOR)
from bcid_ros.estimators.rpem.feed import FitModelFeed, PairedErrorTest
from bcid_ros.estimators.rpem.fit import FitResult
from bcid_ros.estimators.rpem.history import RecursivePredictor
from bcid_ros.estimators.rpem.stability import HALVINGS, REGION_MARGIN
from bcid_ros.estimators.rpem.state import RpemState
from bcid_ros.estimators.rpem.store import (BATCH_LIMIT, FitUncertainty, SampleStore, Segment,
                                            StoredFit)
from bcid_ros.estimators.rpem.uncertainty import (parameter_covariance, score_hac,
                                                  whole_covariance)
from bcid_ros.estimators.rpem.watch import on_boundary, RestartWatch
from bcid_ros.estimators.rpem.window import KEEP_SHARE, moved
from bcid_ros.estimators.simulation_check import change_rate
from bcid_ros.estimators.validity import doubt_the_model, imprecision, STANDING_PRECISION

#: Values of the ``model`` option.
MODELS = ('oe', 'armax')
#: The change's reason again, after a change taken as done, when a fit finds another estimate
#: as good as its own farther away than PRECISION allows (:meth:`Rpem._fitted_now`).
UNRESOLVED_NOTE = 'plant changed: a refit of its samples found another estimate as good'
#: What the change's reason adds when the simulation check found it
#: (:meth:`~bcid_ros.estimators.simulation_check.SimulationWindow.contradicted_twice`).
SIMULATION_NOTE = ': the simulated output contradicted on two disjoint windows'
#: What the change's reason adds when the block-mean test found it (the errors grown at low
#: frequencies; its change point is placed at whole blocks, late rather than early).
BLOCK_NOTE = f': the means of the errors over blocks of {BLOCK_LENGTH} samples grew'
#: Annealed forgetting after a fit: lambda(t) starts at min(lambda, LAMBDA_START)
#: and approaches the user's lambda by lambda <- lambda_u - LAMBDA_RATE (lambda_u - lambda).
LAMBDA_START = 1.0
#: See LAMBDA_START.
LAMBDA_RATE = 0.99
#: Not valid while the change detector's CUSUM S is at or past this share w of its threshold
#: h: under no change S(t), the largest sum of its last k increments, is >= w h on at
#: most exp(-w h) (Ville's inequality for the increments' likelihood ratios) =
#: (0.7 FALSE_ALARM)^w of the samples (0.26 %; docs/tracking.md, "What a detection does");
#: the block-mean test's CUSUM warns at the same level w h (Rpem._live_reasons)
CHANGE_WARNING = 0.5
#: The floor of the gate's variance, squared (a power of two: exact)
_VARIANCE_FLOOR2 = VARIANCE_FLOOR ** 2


class Rpem(RpemState, RecursiveEstimator):
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
        w(t) &= \varphi^T(t)\hat\theta(t) \ \text{(OE; under forgetting: below)}, \qquad
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

    **The start.** A recursion started far from the optimum of an oversampled
    plant (poles near 1) feeds its own errors back through w and psi and drifts
    away (docs/estimators.md, "RPEM", measured), so the recursion never starts
    cold. The samples are stored; after ``max(FIRST_FIT_SAMPLES,
    FIRST_FIT_PER_PARAMETER p)`` of them, and again each time their count has
    grown by ``FIT_GROWTH`` up to ``BATCH_LIMIT``,
    :class:`~bcid_ros.estimators.rpem.fit.BatchFit` fits the model to all
    stored samples (ARX least squares and Steiglitz-McBride or extended LS
    iterations, the current estimate too, then Gauss-Newton on the prediction
    error with the start-up transient and the offset fitted at every step;
    samples the gate would refuse are then excluded) and the recursion
    continues from it with :math:`P = (\sum_t w_t\psi\psi^T + I/p_0)^{-1}`, its
    :math:`J`, :math:`\tau`, w and psi: what the recursion would hold had it
    run over the same samples at that estimate. Each fit is spread over the
    next updates, a bounded amount of work each, and taken where its work
    ends, a few to tens of samples later, its predictor
    run on over them (:class:`~bcid_ros.estimators.rpem.store.FitJob`): no
    update waits on a whole fit. Beyond ``BATCH_LIMIT`` samples it is the
    plain recursion (with forgetting, fits on a sliding schedule). Not
    :attr:`ready` before the first fit; with forgetting, sample t weighs
    :math:`\lambda^{T-t}` in a fit.

    **Units.** Each fit scales each channel by a power of two at or above its
    robust size (:mod:`.store`): the estimates do not depend on the units of
    y and u, and p0 is the prior variance for signals of unit size.

    **Offset** (``detrend: mean``): the model carries an offset c, the last
    internal parameter, not published; m are the means each fit centres its
    samples on, and the recursion goes on in that frame until the next fit
    (:meth:`_normalised`); :attr:`operating_point` is (m_y + c, m_u)
    (OE: y - m_y = G (u - m_u) + c + v; ARMAX: c = d / A(1)).

    **Predictor lags.** Without forgetting the lags of sample t are those of
    the estimate after the step (a posteriori, L&S). For OE under forgetting
    (lambda < 1) or a random walk (``adaptation: kalman``, whose gain does not
    vanish either: on realistic seed 2's 60 plants its restarts fell 178 -> 5
    and its stability projections 11,346 -> 1,952 with this) the newest is
    the simulated output of the estimate before it,
    :math:`\hat y(t) = \varphi^T(t)\hat\theta(t-1)`, and after the step the
    last n move to the new estimate along their gradient,
    :math:`w(t-k) \mathrel{+}= \psi^T(t-k)\,\Delta\hat\theta` (k < n): the lags of
    :math:`\varphi(t+1)` are then those of :math:`\hat\theta(t)` to first order,
    as the Gauss-Newton direction assumes, where the recursion's own lags
    hold the estimates of their time. The a-posteriori w(t) adds
    :math:`\kappa\varepsilon(t)`, :math:`\kappa = \varphi^T P\psi/s`, which
    1/F carries on: the predictor is then an observer whose error is
    F/(F + kappa) times the output error, blind where
    :math:`|F(e^{i\omega})| < \kappa`, while psi = phi / F is the gradient of
    the plain simulation. Without forgetting kappa and the steps fall as 1/t
    and both effects vanish (L&S); with forgetting neither does: on a plant
    with poles 0.995, 0.95, 0.57 (F(1) = 1.1e-4) kappa was 1.3e-3 at lambda
    0.999, and the recursion ran from fits 0.04 % off to 75 % off (median;
    0.16 % now: docs/estimators.md). ARMAX keeps the a-posteriori residual of
    recursive ML (no such loss measured).

    **Annealed forgetting.** After each fit :math:`\lambda(t)` starts at
    min(lambda, LAMBDA_START) and tends to the user's by lambda(t) <- lambda -
    LAMBDA_RATE (lambda - lambda(t-1)) (L&S); LAMBDA_START = 1 (off: after a
    batch start it only loses information); it smooths a live change.

    **Safeguards**, each counted in :attr:`flags`:

    * the transaction: a step with a non-finite or non-positive s(t) or a
      non-finite error is not taken (``update_undone``; the regressor
      restarts);
    * the gate: :math:`z^2 = \varepsilon^2/[(J/\tau)(s + 1 - \lambda)]`
      goes to the rulebook's gate once :math:`\tau \ge` ``GATE_WARMUP`` p;
      a refused sample keeps the predictor running with its prediction in
      place of y (OE: it is stored with weight 0); a plant change cuts the
      memory to ``CHANGE_MEMORY`` p (as :class:`~bcid_ros.estimators.rls.Rls`)
      and restarts the fit schedule on the samples after the change; after it
      (lambda = 1) a fit that moved from the last one of the same start by more
      than their nested windows explain keeps the newest half of the window
      (``window_moved``: the plant still moves, :mod:`.window`), and while the
      change is pending the simulation check contradicting the new model on two
      disjoint windows keeps its last window (:meth:`_window_contradicted`);
    * restart (``restarted``) and the reasons of every ``VALIDITY_PERIOD``:
      :mod:`.watch` (a stuck projection a refit can move, undone steps; a
      projection active on many steps), and a recursion that left its fit
      (its errors grown against the fit's residuals, by a second
      :class:`~bcid_ros.estimators.change_detection.ChangeDetector`, while
      the fit's model's errors did not: :mod:`.feed`); a changing plant is
      the detector's, which tests the errors of the last fit's model, and
      of their means over blocks of 100 samples (a change seen at low
      frequencies only:
      :class:`~bcid_ros.estimators.change_detection.BlockMeanDetector`);
    * the return to the fit (``returned_to_fit``): the recursion's a-priori squared
      errors since the hand-off against the fit's model's on the same samples, a paired
      test with a stated false-alarm rate per hand-off
      (:class:`~bcid_ros.estimators.rpem.feed.PairedErrorTest`), at every stage; past its
      bound theta and the predictor's lags are the fit's again (on a slow plant the
      recursion walked from a fit 1.3 % off to 34 % in 100 samples);
    * anti-windup as in Rls (no division by :math:`\lambda` while
      :math:`\mathrm{tr}\,P > p_0 p`) and a Cholesky check of P every
      ``HEALTH_CHECK_PERIOD`` updates (``covariance_repaired``).

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
    tracks = True
    #: The simulation check at every validity decision, not every CHECK_PERIOD samples: a
    #: verdict kept between checks let a drift's lag or a new fit go unjudged (docs/trust.md)
    _SIMULATION_CHECK_PERIOD = 1
    #: a change the detector misses, from the check's runs of contradictions
    _SIMULATION_CHANGES = True
    #: the change detector's warning (CHANGE_WARNING) moves with every sample
    _LIVE_REASONS = True

    def __init__(self, *, model: str = 'oe', **settings: Any) -> None:
        if model not in MODELS:
            raise ValueError(f"model must be 'oe' or 'armax', got {model!r}")
        self.model = model
        self._armax = model == 'armax'
        # the residual tests: an OE model's output error may be coloured (only its
        # correlation with past inputs contradicts the model); ARMAX's innovation is white
        self.adequacy_model = model
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
        # the lags of the predictor and of its gradient, and the samples kept for the fits
        self._predictor = RecursivePredictor(n, r, self.feedthrough, self.input_delay,
                                             self._armax, self._offset, self._size,
                                             self._filter_slice)
        # the detector's errors: those of the last fit's model (rpem/feed.py)
        self._feed = FitModelFeed(n, r, self.feedthrough, self.input_delay, self._armax,
                                  self._offset, self._size)
        self._store = SampleStore(n, r, self.feedthrough, self.input_delay, self._armax,
                                  self._offset, self._channel)
        self._watch = RestartWatch()
        # the stated false-alarm rate is shared: the block test takes BLOCK_SHARE of it, the
        # simulation check's two disjoint contradictions their 2 alpha^2 a check, and the
        # detector the rest, so that a plant_change of any of them stays within FALSE_ALARM
        self._detector = ChangeDetector(false_alarm=(1.0 - BLOCK_SHARE) * FALSE_ALARM
                                        - change_rate(rules.VALIDITY_PERIOD))
        # the same errors' slow part: their means over blocks (change_detection.py)
        self._block_test = BlockMeanDetector()
        self._warning_level = CHANGE_WARNING * self._detector.threshold
        self._left_fit = ChangeDetector()
        # the recursion's errors against the fit's model's on the same samples (feed.py)
        self._paired = PairedErrorTest()
        self._reset()

    # ------------------------------------------------------------- the step
    def _update(self, y: float, u: np.ndarray) -> None:
        if self._decide_pending:  # the fit handed over at the last update, judged now
            self._decide_now()
        if self._fitted:
            self._step(y, u)
        else:
            self._predictor.fill(y, u)
            self._keep(y, u)

    #: _step checks before it commits: the exact form of the transaction.
    _guarded_update = _update

    def _step(self, y: float, u: np.ndarray) -> None:
        """Make one recursion step on a checked sample (the class docstring's equations)."""
        yn, un = self._normalised(y, u)
        theta = self._theta_n
        predictor = self._predictor
        # phi(t) and psi(t) = phi(t) - d_1 psi(t-1) - ... - d_n psi(t-n)
        regressors = predictor.regressors(yn, un, theta)
        fed = self._feed.error(yn, un)
        if regressors is None:  # refilling the lags after a restart
            self._keep(y, u)
            return
        phi, psi = regressors
        lam = self._lambda_t
        # e(t) = y(t) - phi(t)' theta(t-1)
        e = yn - float(phi.dot(theta))
        # g = P(t-1) psi(t) ; s(t) = lambda + psi' P psi
        g = self._p.dot(psi)
        s = lam + float(psi.dot(g))
        if not (0.0 < s < math.inf and e * e < math.inf):
            self._refuse(s)
            return
        if self._tau >= self._gate_from:
            # z^2 = e^2 / [(J / tau) (s + 1 - lambda)]
            z2 = e * e / ((self._loss / self._tau + _VARIANCE_FLOOR2) * (s + 1.0 - lam))
            # the gate's quiet case (rules.gate_is_quiet) on floats, as Rls's: used, and only
            # a lifted tail moves; any other tested sample goes to the rules (_gate)
            if self._change_score or not z2 <= self._gate_limit2:
                changes = self._changes
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
            elif self._gate_tail != 1.0:
                self._gate_tail = rules.lowered_tail(self._gate_tail)
        # the lags of sample t: of theta(t-1) (a priori, then moved to theta(t) along psi)
        # for OE whose gain does not vanish (forgetting, a random walk), else of theta(t)
        # (a posteriori); the class docstring, "Predictor lags"
        a_priori = not self._armax and (self._forgetting_factor < 1.0
                                        or self.adaptation == 'kalman')
        if a_priori:
            predictor.advance(yn, phi, psi, theta)
            prior = theta.copy()
        taken = self._move_theta(theta, g, e / s)
        if a_priori and taken:  # the output lags moved to theta(t) along psi
            predictor.follow(theta - prior)
        self._commit_covariance(g, s, lam)
        # J(t) = lambda J(t-1) + lambda e^2 / s ; tau(t) = lambda tau(t-1) + 1
        self._loss = lam * (self._loss + e * e / s)
        self._tau = lam * self._tau + 1.0
        if not a_priori:
            predictor.advance(yn, phi, psi, theta)
        self._watch.stepped(taken)
        self._lambda_t = self._forgetting_factor - LAMBDA_RATE * (
            self._forgetting_factor - lam)
        self._updates += 1
        self._keep(y, u)
        if self._change_detection and self._settled and fed is not None:
            # the one-step error of the last fit's model (rpem/feed.py), against the
            # reference of that fit's residuals (both on the fit's means), once the
            # estimate has been valid since the last change: before, the errors are those
            # of a model still converging, and a detection would only restart it from
            # fewer samples
            age, note = self._detector.record(fed), ''
            if not age:
                # the block means see an error grown at low frequencies, which the
                # detector's centring and whitening remove (a slow pole or gain moved:
                # docs/tracking.md)
                age = self._block_test.record(fed, self._samples)
                note = BLOCK_NOTE
            if age:
                self._plant_changed(age, note)
                return
            # the recursion's own normalised error e / sqrt(s) against the same reference:
            # detected where the fit's model's are not, the recursion left its fit (its
            # estimate moves between fits), and a refit of the stored samples restarts it
            if self._left_fit.record(e / math.sqrt(s)):
                self._restart('the recursion left its fit')
        # (after a fit only: before the first the feed's model is zero)
        if self._fitted and fed is not None and self._paired.record(
                e, fed, self._loss / self._tau + _VARIANCE_FLOOR2):
            # the recursion predicts the samples since the hand-off worse than the fit's
            # model does, beyond the paired test's bound: back to the fit (feed.py), at
            # every stage (the wander comes early too, before the detector runs)
            self._return_to_fit()
        if self._tau >= self._gate_from and not self._quiet_left:
            # the residual tests take the prediction error (and, OE, psi); the HAC psi e
            self._monitor.record(e, u, psi)
            self._hac.record_product(psi, e)
            self._simulation.record(y, u)
        else:  # a sample the window does not take is a gap in it (docs/trust.md)
            self._simulation.gap()
        if self._updates % HEALTH_CHECK_PERIOD == 0:
            self._check_covariance()
        if self._updates >= self._watch.next_check:
            self._check_validity()

    def _move_theta(self, theta: np.ndarray, g: np.ndarray, gain: float) -> bool:
        """Take theta + mu g gain with mu = 1, 1/2, ... inside D_M, or stay (False)."""
        # on Python floats (each sum rounds as numpy's would), written back once
        old, step = theta.tolist(), g.tolist()
        n = self.order
        noise = self._filter_slice if self._armax else None
        for _ in range(HALVINGS + 1):
            # theta(t) = theta(t-1) + mu P psi e / s
            new = [value + change * gain for value, change in zip(old, step)]
            if is_stable(new[:n], REGION_MARGIN) and (
                    noise is None or is_stable(new[noise], REGION_MARGIN)):
                theta[:] = new
                return True
            gain *= 0.5
        self._flag('stability_projection')
        return False

    def _commit_covariance(self, g: np.ndarray, s: float, lam: float) -> None:
        """Apply P(t) = [P - g g' / s] / lambda in place, without winding up."""
        # P <- P - h h', h = g / sqrt(s) (the shared step's; g is overwritten), then propagate
        self._p = downdate(self._p, g, s)
        if self._propagation.propagate_one(self._p, lam):
            self._flag('windup_limited')

    def _refuse(self, s: float) -> None:
        """Refuse a step with a non-finite error or gain (repair P first if s <= 0)."""
        if s <= 0.0:
            self._repair_covariance()
        reason = self._watch.undone()  # UNDONE_RESTART in a row restart from a fit
        if reason:
            self._restart(reason)
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
        self._feed.refused()
        self._decide_now()
        phi, psi, y, u = gating
        # y(t) unknown: its prediction in its place, residual 0
        theta = self._theta_n
        self._predictor.advance(float(phi.dot(theta)), phi, psi, theta)
        if self._armax:
            self._store.break_pending = True  # y(t) is a lag of the next samples
        else:
            self._keep(y, u, excluded=True)  # u(t) drives the simulation on
        self._simulation.gap()  # the refused sample is not recorded

    def _hold(self, y: float, u: np.ndarray) -> None:
        """Move the predictor on with theta held: w (or the residual) and psi keep running."""
        self._store.break_pending = True
        self._simulation.gap()  # the held samples are not recorded
        if not self._fitted:
            self._predictor.fill(y, u)
            return
        yn, un = self._normalised(y, u)
        theta = self._theta_n
        regressors = self._predictor.regressors(yn, un, theta)
        self._feed.error(yn, un)
        if regressors is not None:
            self._predictor.advance(yn, *regressors, theta)

    def _normalised(self, y: float, u: np.ndarray) -> tuple[float, np.ndarray]:
        """
        Return a sample in the recursion's units: on the last fit's means, scaled.

        With ``detrend: mean`` the base class centres each sample on the
        running means of its time; the last fit centred all its samples on
        the means when it started, and its offset c is of that frame. The
        recursion goes on in the fit's frame: its errors are then those of
        the fitted model (the detector's reference is the fit's residuals),
        where in the running frame they would carry
        -(m_y(t) - m_y') + G (m_u(t) - m_u'), an offset that grows as the
        means move early in a record and that c follows only slowly. A
        constant centring is no loss to a model with an offset.
        """
        if self._means is not None:
            shift = self._means.mean - self._fit_mean
            y, u = y + float(shift[0]), u + shift[1:]
        return y * self._output_factor, u * self._input_factors

    # ------------------------------------------------------------- the fits
    def _keep(self, y: float, u: np.ndarray, excluded: bool = False) -> None:
        """Store the sample, do a slice of the fit on its way; start a fit if one is due."""
        self._samples += 1
        store = self._store
        due = store.add(y, u, None if self._means is None else self._means.mean, excluded)
        job = store.job
        ended = None if job is None else store.advance()  # (None: no fit on its way)
        if ended is not None:  # its last pass ended: the predictor run on to this sample
            self._fitted_now(*ended, job.mean)
            due = self._window_moved(ended[1]) or due
        if due:
            self._fit()

    def _fit(self, fresh: bool = True) -> None:
        """Fit the stored samples, spread over the next updates; fresh: no restart's refit."""
        arguments = (None if self._means is None else self._means.mean, self._signal_scale,
                     self._theta_n[:self.num_parameters] if self._fitted else None,
                     self._forgetting_factor, 1.0 / self.initial_covariance,
                     math.sqrt(self._gate_limit2))
        # after a plant change the stored samples are the new plant's (restart_schedule)
        self._store.start(*arguments, fresh, after_change=self._changes > 0)

    def _fitted_now(self, fitted: StoredFit, fresh: bool, mean: np.ndarray | None) -> None:
        """Continue the recursion from a fit (if it is sound) centred on ``mean``."""
        for _ in range(fitted.outliers):
            self._flag('outlier_excluded')
        result, uncertainty = fitted.result, fitted.uncertainty
        if result is not None and self._take_fit(result, uncertainty, fitted.segments,
                                                 fitted.scale, fresh, mean):
            self._fits += 1
            # the other start's end, where the data cannot tell it apart (:mod:`.uncertainty`;
            # the job's with_unresolved)
            self._excess = uncertainty.unresolved
            if self._changes and not self._change_note and (
                    uncertainty.unresolved is not uncertainty.root) and (
                    imprecision(self._theta(), lambda: self.parameter_covariance)):
                # the new plant's estimate was taken as known to PRECISION, and a refit of
                # its samples found another as good farther away: the change is not done
                self._change_note = UNRESOLVED_NOTE
            # a new estimate: judged at the next update, not at the period's end; not in
            # this one, whose hand-over and the simulation check took 8-10 ms together
            # (benchmarks/rpem_stall.py; the bound is 10 ms), the last verdict holding for
            # that sample. The first fit has none (it makes rpem ready): judged at once
            # (a short fit, a window too short to check)
            if self._fits == 1:
                self._decide_now()
            else:
                self._decide_pending = True

    def _window_moved(self, fresh: bool) -> bool:
        """
        After a change, keep the newest half of the fits' window if the plant still moves.

        The fit just taken is compared with the last fresh one of the same window start
        (nested windows, both of at least the detector's warm-up; the sliding schedule's
        are not nested) by :func:`~bcid_ros.estimators.rpem.window.moved`. A move keeps the
        newest half of the samples since the start (at least WARMUP; flag ``window_moved``)
        and returns True: a fit of them is due now. Before any change the fits are never
        compared: a stationary record's schedule is as it was. Without forgetting only: the
        variance of the move is that of nested windows of equally weighted samples, and
        forgetting lets a drift's samples go by itself.
        """
        if (not fresh or not self._changes or self._forgetting_factor < 1.0
                or self._fit_sample != self._samples):
            return False
        store = self._store
        start = self._samples - store.since_start
        nested = start == self._window_start and store.since_start <= BATCH_LIMIT
        previous, previous_weight = self._window_theta.copy(), self._window_weight
        theta, weight = self._theta(), self._tau
        self._window_theta[:], self._window_weight, self._window_start = theta, weight, start
        if not nested or previous_weight < WARMUP:
            return False
        covariance = self._parameter_covariance()
        if covariance is None or not moved(theta - previous, covariance, weight,
                                           previous_weight):
            return False
        return self._keep_newest(max(int(KEEP_SHARE * store.since_start), WARMUP))

    def _window_contradicted(self, age: int) -> None:
        """
        After a change, fit only the last ``age`` samples (the check's last window).

        While the change is pending, or until the new plant's model passed the check on a
        full window (it may pass the other checks on a shorter one and be valid for a
        while), the model, fitted to every sample since the change point, contradicted by
        the simulation check on two disjoint windows with none passing in between
        (:meth:`~bcid_ros.estimators.simulation_check.SimulationWindow.contradicted_across`,
        ``age`` the samples of the last: 0, not so): the window still holds samples of
        another plant, a drift that went on after its detection or a change point placed
        early. The fits restart from the last window's samples (flag ``window_moved``, as
        :meth:`_window_moved`; no memory cut, no new change: the one pending stays). Under a
        plant that does not move, at most at the rate alpha^2 per check, as the change the
        check finds after a model passed; a false one costs the fits their older samples.
        """
        if not age:
            return
        self._simulation.new_run()
        if self._store.since_start <= age:  # the window holds no sample before the last one's
            return
        if self._keep_newest(age):
            self._fit()

    def _keep_newest(self, keep: int) -> bool:
        """
        Move the fits' window to the newest ``keep`` samples (flag ``window_moved``).

        The nested-window comparison starts again from the next fit; returns whether a fit
        of the kept samples is due now.
        """
        self._flag('window_moved')
        self._window_weight = 0.0
        return self._store.restart_schedule(keep)

    def _take_fit(self, result: FitResult, uncertainty: FitUncertainty | None,
                  segments: list[Segment], scale: np.ndarray, fresh: bool,
                  mean: np.ndarray | None) -> bool:
        """
        Continue from the fit: theta, P, J, tau, its lags, psi and means; False if unsound.

        ``uncertainty`` is its P, HAC and R as its job made them before the hand-off
        (FitJob._uncertainty); None: no P.
        """
        if uncertainty is None:
            return False
        p = uncertainty.covariance
        if mean is not None:  # the frame of the fit's samples, its offset and its lags
            self._fit_mean[:] = mean
        # the errors to come, its model's and the recursion's, are judged against this fit's
        # residuals (its own model's)
        residuals = result.residuals(segments[-1], self._armax)
        self._detector.prime(residuals)
        self._left_fit.prime(residuals)
        self._paired.prime(residuals)
        self._block_test.prime(residuals)
        # after a change, a fit of WARMUP samples starts the detector valid or not: a drift
        # goes on after its detection, and a model that blends it may never pass the tests
        self._settled = self._settled or (self._changes > 0 and result.weight >= WARMUP)
        self._p = p
        self._theta_n[:self.num_parameters] = result.theta
        if self._offset:
            self._theta_n[-1] = result.offset
        self._loss = result.loss
        self._tau = result.weight
        self._signal_scale = scale
        self._set_scale_dependents()
        self._arx = result.arx * self._unscale
        # the predictor's lags: those of the last segment's newest samples
        self._predictor.load(result.tail_x, segments[-1][1], result.tail_e, result.tail_psi)
        self._feed.load(self._theta_n, result.tail_x, segments[-1][1], result.tail_e)
        theta = self._theta_n
        self._watch.fitted(on_boundary([theta[:self.order]] + (
            [theta[self._filter_slice]] if self._armax else [])), fresh)
        # the scores recorded so far are of the estimates before the fit, whose errors
        # would swell the HAC (hundreds of times on a fit that moved far): the fit's own,
        # theta's profiled (the equations the fit solved; the held ones carry each segment's
        # start-up transient, which overstated the std 2-6 times: docs/trust.md)
        self._hac = uncertainty.hac
        # made with the job's factor: the recursion's HAC follows the one now in force, as
        # _follow_forgetting_factor keeps it through a live change (the same bits otherwise)
        self._hac.forgetting_factor = self._forgetting_factor
        # what the covariance of P leaves out: the fit chose each segment's initial state
        self._excess = uncertainty.root
        self._fit_sample = self._samples
        self._lambda_t = min(self._forgetting_factor, LAMBDA_START)
        self._fitted = True
        return True

    def _return_to_fit(self) -> None:
        """
        Take the fit's estimate and its model's lags back (flag ``returned_to_fit``).

        theta_n becomes the fit's (the feed holds it), the predictor's output lags its
        model's (the feed ran them on); P, J and tau stay (P has only shrunk since the
        hand-off: smaller steps), and psi, the gradient of the estimate it left, fades in
        the filter's time. The paired test starts again on the samples to come.
        """
        self._flag('returned_to_fit')
        self._theta_n[:] = self._feed.theta  # (in place: the predictor holds a view)
        self._feed.give_lags(self._predictor.history)
        self._paired.clear()

    def _restart(self, reason: str) -> None:
        """Restart from a fit of the stored samples (flag ``restarted``), e.g. after a drift."""
        self._flag('restarted')
        self._watch.restarting(reason)
        # the residuals so far are of the model that drifted; the simulation check's window
        # holds the same plant's samples: the estimate is judged on it at once, the refit
        # once handed over
        self._forget_residuals(keep_window=True)
        self._fit(fresh=False)
        self._decide_now()

    def _accept_change(self) -> None:
        """
        Restart after a plant change the gate found (three refusals): from its first refusal.

        The outputs it refused in a row before this one are the new plant's
        first (OE stores them, weighing 0; ARMAX none): they start the fits.
        """
        self._restart_after_change(self._store.refused_run())

    def _plant_changed(self, age: int, note: str = '') -> None:
        """Flag a plant change a test found ``age`` samples ago (``note`` its), and restart."""
        self._flag('plant_change')
        self._restart_after_change(age, note=note)

    def _simulation_changed(self, age: int) -> None:
        """
        Flag a plant change the simulation check found, and restart from its last ``age``.

        The model had passed the check on a full window since the last change, and two
        disjoint windows since contradict it
        (:meth:`~bcid_ros.estimators.simulation_check.SimulationWindow.contradicted_twice`):
        the change is at least ``age`` samples old, and a fit of those samples, the new
        plant's alone, starts at once and is taken within tens of samples. The memory is not
        cut: the cut only lets the recursion's last few samples pull it around until that
        fit (tracking plant (0, 22), a drift's end: from 0.8 % to 1.1 % off for 8 samples,
        then the fit's 0.2 %).
        """
        self._flag('plant_change')
        self._restart_after_change(age, cut=False, note=SIMULATION_NOTE)

    def _restart_after_change(self, age: int, cut: bool = True, note: str = '') -> None:
        """
        Cut the memory and restart the fits from the last ``age`` samples (the new plant's).

        The memory cut (rules.cut_memory) lets the recursion move at once; the
        stored samples before the change point leave the fits, and a fit of
        the ones after it starts once there are enough. Not valid from this
        sample on, until a fit of the new samples passed the checks. ``cut``
        False: no memory cut (a change whose fit starts at once); ``note`` ends
        the change's reason.
        """
        self._changes += 1
        first = self._samples - age + 1 if age else self._samples + 1
        self._change_note = f'plant changed (sample {first}){note}'
        self._settled = False
        self._forget_residuals()
        self._detector.clear()
        self._left_fit.clear()
        self._block_test.clear()
        if cut:  # one extra forgetting step: P / kappa, kappa J, kappa tau (P in place)
            loss, tau = np.array([self._loss]), np.array([self._tau])
            keep = rules.cut_memory(self._p[None], loss, tau, self.num_parameters)
            self._excess *= float(keep[0])  # E's root: the old fit's weight, cut as P's
            self._loss, self._tau = float(loss[0]), float(tau[0])
        if self._store.restart_schedule(age):
            self._fit()
        self._decide_now()

    # --------------------------------------------------- health and validity
    def _check_covariance(self) -> None:
        """Repair P if it lost definiteness (every HEALTH_CHECK_PERIOD updates)."""
        if not rules.definite(self._p[None])[0]:
            self._repair_covariance()

    def _repair_covariance(self) -> None:
        """Rebuild P as the nearest symmetric positive definite matrix (covariance_repaired)."""
        self._flag('covariance_repaired')
        self._p = np.ascontiguousarray(repair_covariance(
            self._p, np.eye(self._size) * self.initial_covariance))

    def _check_validity(self) -> None:
        """Re-evaluate drift and the validity reasons (every VALIDITY_PERIOD updates)."""
        watch = self._watch
        steps = watch.start_period(self._updates)
        reason = watch.restart_reason()
        if reason:
            self._restart(reason)
        self._period_reasons = watch.reasons(steps)
        if not self._decide_pending:  # else a fit came in this update: decided at the next
            self._decide_now()
        # a model that passed the simulation check, contradicted on two disjoint windows
        # since: the plant changed where the detector did not see it (docs/tracking.md);
        # not while a change is pending (its model has not passed the checks yet)
        age = (self._simulation.contradicted_twice()
               if self._change_detection and not self._change_note else 0)
        if age:
            self._simulation_changed(age)
        elif self._change_detection and self._changes and (
                self._change_note or not self._simulation.passed):
            # the new plant's model, not yet passed on a full window (valid on a shorter
            # one or not): its fits may blend another plant
            self._window_contradicted(self._simulation.contradicted_across())

    def _decide_now(self) -> None:
        """
        Decide the reasons now: a plant change, a restart, the last period's, the tests'.

        Called at every validity period and on every event (a detection, a
        restart, a refusal), so that ``~/valid`` follows them at that sample.
        The change's reason stays until a fit of the samples after it passes
        the residual tests.
        """
        self._decide_pending = False
        notes = []
        if self._watch.restart_note:  # a restart since the last period (reported there too)
            notes.append(f'restarted ({self._watch.restart_note})')
        # the change is done once a fit of the samples after it passes the checks
        self._change_note = self._decide_validity(
            notes + self._period_reasons, self._change_note,
            ready_again=self._store.since_start < self._samples)
        # the detector runs once the model passed its checks (with forgetting, and is pinned
        # down); a std judged too small or an estimate not yet precise after a change is the
        # covariance's matter, and holds no detection back
        self._settled = self._settled or (not doubt_the_model(self._reasons)
                                          and self._pinned_down())
        if not (self._change_note or doubt_the_model(self._reasons)):
            self._simulation.vouch()  # the model passed every check: its changes are judged

    def _live_reasons(self) -> tuple[str, ...]:
        """
        Return the change tests' warning: a CUSUM past ``CHANGE_WARNING`` of the detector's h.

        Until a detection the old model is valid, though the detector's evidence
        has been growing for h over its mean increment samples; past w h a change
        is suspected. With S >= w h on at most e^(-w h) of the samples of no
        change (S(t) is the largest sum of its last k increments: Ville's inequality),
        the warning costs that share of a stationary record's valid samples. The
        block-mean test's CUSUM, a log-likelihood ratio too, warns at the same level
        c = w h: past it on at most e^-c of its blocks (0.26 %), so that together
        they cost at most 0.53 % (a drift its blocks see first: tracking plant
        (1, 17) with lambda 0.999, valid 10-15 % off for the 100 samples before its
        detection with S_b at 0.94 of its threshold).
        """
        statistic = self._detector.statistic_of()
        # (once a sample: valid is asked at each update)
        if statistic >= self._warning_level:
            return (f'change suspected: the change detector at '
                    f'{statistic / self._detector.threshold:.2f} of its threshold',)
        block = self._block_test.statistic_of()
        if block >= self._warning_level:
            return (f'change suspected: the block-mean test at '
                    f'{block / self._block_test.threshold:.2f} of its threshold',)
        return ()

    # --------------------------------------------------------- the accessors
    @property
    def ready(self) -> bool:
        """Whether the first fit is made (and at least p samples were used)."""
        return self._fitted and self._samples >= self.num_parameters

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
        """Return the HAC covariance of the estimate (:mod:`.uncertainty`; None before ready)."""
        if not self.ready or not self._tau > 0.0:
            return None
        return parameter_covariance(self._hac, self._p, self._tau, self._forgetting_factor,
                                    self.num_parameters, self._unscale, self._excess,
                                    self._fit_decay(), self._moved())

    def _fit_decay(self) -> float:
        """Return the weight the last fit's samples keep now: lambda^k after k steps."""
        return self._forgetting_factor ** (self._samples - self._fit_sample)

    def _moved(self) -> np.ndarray:
        """Return theta_n less the last fit's (the feed holds it): where the recursion went."""
        return self._theta_n - self._feed.theta

    def _pinned_down(self) -> bool:
        """
        Whether the estimate is known to ``STANDING_PRECISION`` (always, at lambda = 1).

        With forgetting the fits rest on a window that stops growing, and the detector's
        reference, the fit's residuals, describes the errors to come only for a model its
        samples pin down: one known to several times its size predicts new samples worse
        than it fitted its own (tracking plant (3, 2) with lambda 0.999, armed at 2 sqrt(tr C)
        529 % of |theta|: three false detections before its change, each 50-150 samples
        after a fit). Without forgetting the fits' windows grow, and no such detection was
        seen (docs/tracking_log.md, "Limits", session 10).
        """
        if self._forgetting_factor >= 1.0:
            return True
        return not imprecision(self._theta(), lambda: self.parameter_covariance,
                               self._standing_precision())

    def _standing_precision(self) -> float | None:
        """
        Return ``STANDING_PRECISION``, at every lambda.

        With forgetting the estimate rests on a window that stops growing: where it does not
        pin the estimate to a third of its size it never will, and a drift moves the estimate
        within that looseness unseen (tracking plant (2, 19) with lambda 0.999: 20-34 % off
        with 2 sqrt(tr C) 15-143 % of it). Without, a stationary estimate 95 % off with
        2 sqrt(tr C) 96 % of it (tracking plant (0, 13) before its gain change) is no
        model either. Asked at lambda 1 since the std after a fit is calibrated (the fit's
        profiled scores; the held ones overstated it 2-6 times early in a run: docs/trust.md,
        "Precision at all times").
        """
        return STANDING_PRECISION

    def _covariance_count(self) -> float | None:
        """Return tau, the samples the estimate rests on (``oe``: an output-error covariance)."""
        return None if self._armax else self._tau

    def _internal_covariance(self, plants: np.ndarray) -> np.ndarray | None:
        """Return the HAC covariance of theta_n, offset included, for the residual tests."""
        if not self._tau > 0.0:
            return None
        # the estimate's error, as the std's (the last fit's initial states too), but for the
        # move since the fit: it is no error of the samples' (a known one), and it would
        # excuse the residuals of an estimate that moved away (tracking plant (2, 19), lambda
        # 0.999: valid while 20-40 % off 5.8 % -> 29 % of the 2000 samples after its change)
        return whole_covariance(self._hac, self._p, self._tau, self._forgetting_factor,
                                self._excess, self._fit_decay())

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
        Return ``[y0, u1, ..., ur]``: the last fit's means, y0 moved by the model's offset.

        With ``detrend: mean`` the model is y - m_y = G(q)(u - m_u) + c (OE;
        ARMAX: the equation offset d, c = d / A(1)), m the means the last fit
        centred on (the recursion's frame), so the operating point of the
        estimate is (m_y + c, m_u): the point to simulate the model around.
        Before the first fit, the running means.
        """
        point = super().operating_point
        if point is None or not self._fitted:
            return point
        point[:] = self._fit_mean
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
        # _normalised's factors 1 / scale, y's on a Python float
        inverse = 1.0 / scale
        self._output_factor, self._input_factors = float(inverse[0]), inverse[1:]
        # theta in the user's units: theta_k s_y / s_channel(k)
        self._unscale = scale[0] / scale[self._channel]

    def _forget_residuals(self, keep_window: bool = False) -> None:
        """
        Start the residual tests, the HAC and the simulation check afresh (reset, change).

        ``keep_window``: the simulation check's window stays (a restart: its samples are
        the same plant's).

        OE: the cross test counts the estimate's own error (the parameter
        term, with the HAC covariance of every internal parameter in the
        normalised units of psi): consistent but not efficient under coloured
        noise, the estimate alone fails the plain test at a high SNR
        (docs/trust.md). ARMAX is efficient for its white innovation: its
        error stays within the plain test's margin.
        """
        oe = not self._armax
        self._monitor = AdequacyMonitor(
            num_inputs=self.num_inputs, model=self.adequacy_model,
            forgetting_factor=self._forgetting_factor,
            num_parameters=self._size if oe else 0,
            parameter_covariance=self._internal_covariance if oe else None)
        self._hac = score_hac(self._size, self._forgetting_factor)
        if not keep_window:
            self._start_simulation_check()

    def _restart_regressor(self) -> None:
        self._predictor.clear()
        self._feed.clear()
        self._store.break_pending = True
        self._simulation.clear()  # (a gap in its window)
