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

from typing import Any

import numpy as np

from bcid_ros.estimators.rpem.history import RecursivePredictor


class FitModelFeed:
    """
    The predictor of the last fit's model (theta held), giving its one-step errors.

    Parameters
    ----------
    order, num_inputs, feedthrough, input_delay, armax, offset, size, filter_slice
        As for :class:`~bcid_ros.estimators.rpem.history.RecursivePredictor`.

    """

    def __init__(self, order: int, num_inputs: int, feedthrough: bool,
                 input_delay: tuple[int, ...], armax: bool, offset: bool, size: int,
                 filter_slice: slice) -> None:
        self._predictor = RecursivePredictor(order, num_inputs, feedthrough, input_delay,
                                             armax, offset, size, filter_slice)
        self._theta = np.zeros(size)
        self._armax = armax
        self._step: tuple[np.ndarray, np.ndarray] | None = None

    def load(self, theta: np.ndarray, x: np.ndarray, u: np.ndarray, e: np.ndarray,
             psi: np.ndarray) -> None:
        """Hold the fit's ``theta`` and continue from its lags (as the recursion does)."""
        self._theta[:] = theta
        self._predictor.load(x, u, e, psi)

    def error(self, yn: float, un: np.ndarray) -> float | None:
        """
        Take sample t (normalised) and return y(t) minus the fit's model's prediction.

        None while the lags refill (as the recursion's predictor).
        """
        theta = self._theta
        regressors = self._predictor.regressors(yn, un, theta)
        self._step = regressors
        if regressors is None:
            return None
        phi, psi = regressors
        self._predictor.advance(yn, phi, psi, theta)
        return yn - float(phi.dot(theta))

    def refused(self) -> None:
        """Take the last sample as refused: ARMAX's residual lag becomes 0 (OE needs no y)."""
        if self._armax and self._step is not None:
            # y(t) unknown: its prediction in its place, residual 0 (as the recursion's)
            phi = self._step[0]
            self._predictor.history.set_newest(float(phi.dot(self._theta)), 0.0)

    def clear(self) -> None:
        """Forget the lags (a restart of the regressor); the model stays."""
        self._predictor.clear()
        self._step = None

    def reset(self) -> None:
        """Forget the model and the lags (no fit yet)."""
        self.clear()
        self._theta[:] = 0.0

    def state_items(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Return (arrays, scalars) under ``feed_`` names."""
        arrays, scalars = self._predictor.state_items()
        return ({'feed_theta': self._theta, **{f'feed_{k}': v for k, v in arrays.items()}},
                {f'feed_{k}': v for k, v in scalars.items()})

    def load_state(self, arrays: dict[str, np.ndarray], scalars: dict[str, Any]) -> None:
        """Take over what :meth:`state_items` made."""
        self._theta = np.array(arrays['feed_theta'], dtype=float)
        self._predictor.load_state(
            {'psi_history': np.array(arrays['feed_psi_history'], dtype=float),
             'history': arrays['feed_history']},
            {'filled': scalars['feed_filled'], 'position': scalars['feed_position']})
        self._step = None


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
             'feed_psi_history': np.array(arrays['psi_history'], dtype=float),
             'feed_history': np.array(arrays['history'], dtype=float)},
            {**scalars, 'feed_filled': scalars['filled'],
             'feed_position': scalars['position']})
