r"""
After a plant change: whether the plant still moves within the window of the fits.

A detection part of the way through a drift restarts the fits from a change
point inside the drift, and the fits of the samples since it grow (by
``FIT_GROWTH``): the rest of the drift stays in every later fit, its weight
falling only as 1/N (docs/tracking.md, "Limits and what is left",
2026-11-28, session 7). The fits themselves show it: two fits of nested
windows from the same start, :math:`\hat\theta_1` of :math:`N_1` samples and
:math:`\hat\theta_2` of :math:`N_2 > N_1` (the newer samples added), differ
under no change by the older fit's extra error only. With both fits
efficient, :math:`\mathrm{Cov}(\hat\theta_2 - \hat\theta_1) = C_1 - C_2`
(Hausman 1978: the efficient estimate is uncorrelated with its difference
from any other consistent one), and with :math:`C_1 = C_2 N_2/N_1` that is
:math:`C_2 (N_2/N_1 - 1)`, so

.. math::

    W = (\hat\theta_2 - \hat\theta_1)^T [C_2 (N_2/N_1 - 1)]^{-1}
        (\hat\theta_2 - \hat\theta_1) \sim \chi^2_p

(C_2 the HAC covariance of the newer fit, the published one). A plant
still moving adds the drift between the windows' centres to the difference.
The test takes it parameter by parameter, :math:`z_k = \Delta_k /
\sqrt{[C_2]_{kk}(N_2/N_1 - 1)}`, and calls it a move when the largest
:math:`|z_k|` passes the normal quantile of ``MOVE_LEVEL``/(2p) (Bonferroni:
at most ``MOVE_LEVEL`` under no change, whatever the correlation), not by W
itself: on a slow plant C_2 spans ten decades (cond 4.5e10 on tracking plant
(1, 5) after its change, 500-760 samples, nine parameters), and its weakest
direction, which W weighs most, is not what a fit of a few hundred samples
honours. There W was 62.6 against a limit of 27.9 with every z_k within 1.4
(5.2 in the weakest direction): the window kept half its samples of a plant
that no longer moved, and the recursion, left with 500 of them, ran 12-72 %
off. The simulation check's covariance test is per parameter for the same
reason (:func:`~bcid_ros.estimators.simulation_check.understatement`). The window then keeps its
newest half (at least the detector's warm-up), and the fits grow again from
there: a drift's samples leave the window while they can be told apart
from the newer ones. Without forgetting only (rpem's default): with
lambda < 1 two fits weigh their common samples differently, the formula
does not hold, and forgetting lets a drift's samples go by itself (on the
tracking family, seed 0, moves there slowed four recoveries by 800-3000
samples and left two never recovered).
"""

from __future__ import annotations

import numpy as np
from scipy.stats import norm

#: The probability under no change past which two nested fits are told apart.
MOVE_LEVEL = 1e-3
#: The share of the window's samples (the newest) a move keeps.
KEEP_SHARE = 0.5


def moved(step: np.ndarray, covariance: np.ndarray, weight: float,
          previous_weight: float, level: float = MOVE_LEVEL) -> bool:
    """
    Return whether the fit moved from the last one by more than their windows explain.

    Parameters
    ----------
    step : numpy.ndarray, shape ``(p,)``
        The newer fit's estimate less the older one's (nested windows, one start).
    covariance : numpy.ndarray, shape ``(p, p)``
        The newer fit's covariance C_2, in the units of ``step``.
    weight, previous_weight : float
        The fits' (weighted) sample counts N_2 > N_1.
    level : float
        The probability of a move under no change (Bonferroni over the parameters).

    """
    if not weight > previous_weight > 0.0:
        return False
    spread = np.diagonal(covariance) * (weight / previous_weight - 1.0)
    if not (np.isfinite(step).all() and (spread > 0.0).all()):
        return False  # no honest spread to judge the move against
    largest = float(np.max(np.abs(step) / np.sqrt(spread)))
    return largest > float(norm.isf(level / (2.0 * step.shape[0])))


__all__ = ['KEEP_SHARE', 'MOVE_LEVEL', 'moved']
