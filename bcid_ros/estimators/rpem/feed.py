r"""
What rpem gives its change detector: the one-step errors of the last fit's model, held fixed.

Each fit primes the detector with that fit's residuals (docs/tracking.md):
the reference describes the errors of the fitted model. The recursion's own
errors between fits are of another model: with forgetting its estimate
moves with a memory of about 1/(1 - lambda) samples, and on slow or
ill-conditioned plants it leaves the fit within a few hundred samples (on a
third-order plant with poles near 0.99, 17 dB: from 0.13 % off at the fit to
2-8 % off 100-200 samples later, its errors two to eight times the fit's),
so that its error variance grows on a plant that did not change. The errors
of the fit's model, the parameters held at the fit and its predictor run on
(:class:`~bcid_ros.estimators.rpem.history.RecursivePredictor` with theta
fixed), are what its residuals describe: out of the fit's samples they are
the same process, the prediction error of a fixed model, as long as the
plant does not change, and after a change they carry the whole
(G_new - G_fit) u, which the recursion would partly follow. The recursion's
own errors go to a second detector against the same reference: grown there
alone, they say that the recursion left its fit, and rpem restarts it from
a refit (docs/tracking.md).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from bcid_ros.estimators.hac import long_run_covariance, MAX_LAG
from bcid_ros.estimators.noise_colour import autocorrelation
from bcid_ros.estimators.rpem.history import PredictorHistory


class FitModelFeed:
    """
    The predictor of the last fit's model (theta held), giving its one-step errors.

    The lags of :class:`~bcid_ros.estimators.rpem.history.PredictorHistory`
    moved on as :class:`~bcid_ros.estimators.rpem.history.RecursivePredictor`
    moves them, without the gradient filter (theta does not move).

    Parameters
    ----------
    order, num_inputs, feedthrough, input_delay
        As for :class:`~bcid_ros.estimators.rpem.history.PredictorHistory`.
    armax : bool
        The ARMAX predictor (else OE).
    offset : bool
        Whether theta ends with the offset.
    size : int
        The length of theta.

    """

    def __init__(self, order: int, num_inputs: int, feedthrough: bool,
                 input_delay: tuple[int, ...], armax: bool, offset: bool, size: int) -> None:
        self._history = PredictorHistory(order, num_inputs, feedthrough, input_delay, armax,
                                         offset)
        self._theta = np.zeros(size)
        self._prediction: float | None = None

    def load(self, theta: np.ndarray, x: np.ndarray, u: np.ndarray, e: np.ndarray) -> None:
        """Hold the fit's ``theta`` and continue from its lags x, u, e (oldest first)."""
        self._theta[:] = theta
        self._history.load_rows_oldest_first(np.column_stack((-x, u, e)))

    def error(self, yn: float, un: np.ndarray) -> float | None:
        """
        Take sample t (normalised) and return y(t) minus the fit's model's prediction.

        None while the lags refill (as the recursion's predictor).
        """
        phi = self._history.regressor(yn, un)  # as the recursion's predictor's
        if phi is None:
            self._prediction = None
            return None
        prediction = float(phi.dot(self._theta))
        self._prediction = prediction
        self._history.set_prediction(yn, prediction, self._theta)
        return yn - prediction

    @property
    def theta(self) -> np.ndarray:
        """Return the fit's theta it holds (normalised; zeros before a fit). Do not change it."""
        return self._theta

    def refused(self) -> None:
        """Take the last sample as refused: ARMAX's residual lag becomes 0 (OE needs no y)."""
        if self._history.residual_lags and self._prediction is not None:
            # y(t) unknown: its prediction in its place, residual 0 (as the recursion's)
            self._history.set_newest(self._prediction, 0.0)

    def give_lags(self, history: PredictorHistory) -> None:
        """Make ``history`` (the recursion's ring, of the same layout) hold this model's lags."""
        history.history[:] = self._history.history
        history.filled, history.position = self._history.filled, self._history.position

    def clear(self) -> None:
        """Forget the lags (a restart of the regressor); the model stays."""
        self._history.clear()
        self._prediction = None

    def reset(self) -> None:
        """Forget the model and the lags (no fit yet)."""
        self.clear()
        self._theta[:] = 0.0

    def state_items(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Return (arrays, scalars) under ``feed_`` names."""
        arrays, scalars = self._history.state_items('feed_')
        return {'feed_theta': self._theta, **arrays}, scalars

    def load_state(self, arrays: dict[str, np.ndarray], scalars: dict[str, Any]) -> None:
        """Take over what :meth:`state_items` made."""
        self._theta = np.array(arrays['feed_theta'], dtype=float)
        self._history.load_state(arrays, scalars, 'feed_')
        self._prediction = None


def with_feed_items(arrays: dict[str, np.ndarray], scalars: dict[str, Any],
                    ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """
    Return a snapshot's items with the feed's, from before the feed: the recursion's own.

    The estimate of the snapshot stands for the fit's model and its
    predictor's lags for the fit's, until the next fit.
    """
    if 'feed_theta' in arrays:
        return arrays, scalars
    return ({**arrays, 'feed_theta': np.array(arrays['theta_n'], dtype=float),
             'feed_history': np.array(arrays['history'], dtype=float)},
            {**scalars, 'feed_filled': scalars['filled'],
             'feed_position': scalars['position']})


#: The paired test's false-alarm probability per hand-off (:class:`PairedErrorTest`). A false
#: return costs only the recursion's steps since the hand-off (the fit's model predicted as
#: well): no detection, no refit, no reason. On the slow plant of
#: test_rpem_return_to_fit.py (20 records) the estimate between fits was RMS 0.0267 off at
#: 1e-3, 0.0248 at 1e-2 and 0.0232 at 5e-2, the fits 0.0225 (without the test: 0.0361).
RETURN_FALSE_ALARM = 5e-2
#: 2 log(1 / alpha), the bound's constant term (:meth:`PairedErrorTest.record`).
_RETURN_LEVEL = 2.0 * math.log(1.0 / RETURN_FALSE_ALARM)
#: The paired test's longest block (samples): the noise's long-run variance ratio is capped
#: here (the HAC's AR(1) prewhitening caps its coefficient at 0.97: a ratio below 66).
RETURN_BLOCK_CAP = 64
#: The paired test's block length B: B - 1 is this many times the noise's long-run variance
#: ratio less 1 (:func:`block_length`). With 1 (B the ratio), on held tracking plants with
#: coloured noise the test crossed on 8 % of its starts, with 2 on 5 % (docs/tracking_log.md,
#: session 13).
RETURN_BLOCK_SPAN = 2.0


def block_length(residuals: np.ndarray) -> int:
    r"""
    Return the paired test's block length B for a fit, from its residuals' correlation.

    kappa, the ratio :math:`\Omega / \gamma(0)` of the residuals' long-run variance (the
    HAC's: AR(1)-prewhitened, the larger of that and none, Bartlett window with Andrews'
    bandwidth; :func:`~bcid_ros.estimators.hac.long_run_covariance`) to their variance, is 1
    for white noise and (1 + r) / (1 - r) for AR(1) noise of coefficient r; B = 1 +
    ``RETURN_BLOCK_SPAN`` (kappa - 1), rounded: 1 for white noise, (1 + 3r) / (1 - r), about
    four correlation times 1 / (1 - r), for AR(1). Block sums of B samples of AR(1) noise are
    then correlated enough that their squares understate the variance of their sum 1.35
    times (with B = kappa: 1.7 times). Capped at ``RETURN_BLOCK_CAP``; 1 for fewer than
    4 MAX_LAG residuals (too few to tell).
    """
    count = len(residuals)
    if count < 4 * MAX_LAG:
        return 1
    # the long-run variance of the autocorrelations (gamma / gamma(0)) is kappa itself
    correlation = np.concatenate([[1.0], autocorrelation(np.asarray(residuals, dtype=float),
                                                         MAX_LAG + 1)])
    omega, _ = long_run_covariance(correlation[None, :, None, None], float(count), 'larger',
                                   'bartlett', None)
    ratio = float(omega[0, 0, 0])
    return int(min(max(round(1.0 + RETURN_BLOCK_SPAN * (ratio - 1.0)), 1), RETURN_BLOCK_CAP))


class PairedErrorTest:
    r"""
    Whether the recursion predicts worse than the fit's model it started from: a paired test.

    On each sample since the last hand-off both models predict y(t): the recursion's
    a-priori error e(t) and the fit's model's f(t) (:class:`FitModelFeed`). With
    e = v + a, f = v + b (v the noise, a and b the models' errors),
    :math:`d = e^2 - f^2 = (a^2 - b^2) + 2(a - b)v`: of little noise while the two are close,
    and of mean <= 0 while the recursion only learns new samples (its estimate rests on
    more of them). A recursion that walked away from its fit makes the mean positive
    (errs.py in the session 12 notes: a-priori RMS 0.093 against the feed's 0.058).

    The test (a time-uniform, self-normalised bound; de la Peña 1999, Howard et al. 2021,
    the normal mixture) on the sums D of d over consecutive blocks of B samples: with
    :math:`S = \sum D`, :math:`V = \sum D^2` and block sums conditionally symmetric about a
    mean <= 0, :math:`\exp(\lambda S - \lambda^2 V / 2)` is a supermartingale for each
    lambda > 0; its mixture over a half-normal lambda of variance 1/rho is >= 1/alpha
    whenever S > 0 and :math:`S^2 \ge (V + \rho)[2\log(1/\alpha) + \log((V + \rho)/\rho)]`,
    so by Ville's inequality a recursion that did not leave its fit crosses it, at a block's
    end, with probability at most alpha = ``RETURN_FALSE_ALARM`` per start, at any time.
    rho sets the scale where the bound is tightest: B sigma^4 (sigma^2 the recursion's
    J / tau), i.e. an excess of a few samples' noise variance with no spread of d.

    **Blocks (batch means).** With coloured noise the d's are correlated: the sum of d's
    squares understates the spread of S by about the noise's long-run variance ratio, and the
    per-sample bound crossed on 12 starts in 2900 samples of a held tracking plant (5, 28),
    coloured noise at 29 dB (docs/tracking_log.md, session 13). Block sums of B samples, B
    from the fit's residuals (:func:`block_length`: about four correlation times of the
    noise; 1, the per-sample test, for white noise), are close to uncorrelated, and V of
    them measures S's spread; a block is cut short only by a new start (its samples are
    then not tested).
    """

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        """As new: blocks of one sample (the per-sample test) until a fit primes it."""
        self.length = 1
        self.clear()

    def prime(self, residuals: np.ndarray) -> None:
        """Start afresh after a fit, with blocks as long as its ``residuals``' correlation."""
        self.length = block_length(residuals)
        self.clear()

    def clear(self) -> None:
        """Start afresh (a hand-off, a return to the fit)."""
        self.total = 0.0
        self.squares = 0.0
        self.block = 0.0
        self.count = 0

    def record(self, recursion: float, fit: float, variance: float) -> bool:
        """Add the pair of errors; return whether the recursion predicts worse (the bound)."""
        self.block += recursion * recursion - fit * fit
        self.count += 1
        if self.count < self.length:
            return False
        block, self.block, self.count = self.block, 0.0, 0
        self.total += block
        self.squares += block * block
        if self.total <= 0.0:
            return False
        rho = self.length * variance * variance
        spread = self.squares + rho
        return self.total * self.total >= spread * (
            _RETURN_LEVEL + math.log(spread / rho))

    def state_items(self) -> dict[str, Any]:
        """Return its scalars under ``paired_`` names."""
        return {'paired_total': self.total, 'paired_squares': self.squares,
                'paired_block': self.block, 'paired_count': self.count,
                'paired_length': self.length}

    def load_state(self, scalars: dict[str, Any]) -> None:
        """Take over what :meth:`state_items` made (a snapshot from before: afresh, B = 1)."""
        self.total = float(scalars.get('paired_total', 0.0))
        self.squares = float(scalars.get('paired_squares', 0.0))
        self.block = float(scalars.get('paired_block', 0.0))
        self.count = int(scalars.get('paired_count', 0))
        self.length = int(scalars.get('paired_length', 1))
