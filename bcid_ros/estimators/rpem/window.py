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
still moving adds the drift between the windows' centres to the difference:
W beyond the chi-square's ``MOVE_LEVEL`` quantile says the samples the
newer fit added disagree with the older ones. The window then keeps its
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
from scipy.stats import chi2

#: The chi-square tail probability past which two nested fits are told apart.
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
        The chi-square tail probability of a move under no change.

    """
    if not weight > previous_weight > 0.0:
        return False
    spread = covariance * (weight / previous_weight - 1.0)
    try:
        factor = np.linalg.cholesky(spread)
    except np.linalg.LinAlgError:  # no honest spread to judge the move against
        return False
    whitened = np.linalg.solve(factor, step)
    statistic = float(whitened.dot(whitened))
    return statistic > float(chi2.isf(level, step.shape[0]))


__all__ = ['KEEP_SHARE', 'MOVE_LEVEL', 'moved']
