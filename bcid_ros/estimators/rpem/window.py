r"""
After a plant change: whether the plant still moves within the window of the fits.

A detection part of the way through a drift restarts the fits from a change
point inside the drift, and the fits of the samples since it grow (by
``FIT_GROWTH``): the rest of the drift stays in every later fit, its weight
falling only as 1/N (docs/tracking_log.md, "Limits and what is left",
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
The test takes W over the principal directions of C_2's correlation
matrix whose eigenvalue is at least ``CONDITION_FLOOR`` times the largest
(the combinations of the parameters whose std is at least about 1/18 of
the loosest one's), with as many degrees of freedom as directions
kept. Not over all of them: on a slow plant C_2 spans ten decades (cond
4.5e10 on tracking plant (1, 5) after its change, 500-760 samples, nine
parameters), and its tightest directions, which W weighs most, are not
what a fit of a few hundred samples honours (the curvature at the
estimate, where the loss has valleys). There W was 62.6 against a limit
of 27.9 with every parameter within 1.4 of its std: the window kept half
its samples of a plant that no longer moved, and the recursion, left
with 500 of them, ran 12-72 % off. Nor parameter by parameter (the test
of session 8, Bonferroni over the :math:`z_k = \Delta_k /
\sqrt{[C_2]_{kk}(N_2/N_1 - 1)}`): a drift moves several parameters
together (a gain every numerator coefficient; a pole the denominator and,
through their correlation, the numerator), and W adds up their evidence
where the largest single :math:`|z_k|` sees a part of it. During the
drifts of tracking plants (0, 17) and (2, 21) the largest :math:`|z_k|` was
1.3-3.3 (the limit 3.59) while W was 18-93 against 16.3: their
recoveries went 505 -> 1777 and 261 -> 2052 samples when the test went
per parameter. On the tracking family's fits after its abrupt changes
(three seeds, 190 comparisons of one plant) W passed its limit only
through directions at 7e-4 of the largest eigenvalue or below ((1, 5) 7e-4
and 1e-11, (0, 7) 3e-6 to 7e-6, (1, 1) 6e-7), and the drifts' moves showed
mostly in directions at 4e-3 to 0.3 ("Limits and what is left",
2026-11-28, session 9). The window then keeps its
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

#: The probability under no change past which two nested fits are told apart.
MOVE_LEVEL = 1e-3
#: The smallest eigenvalue of the covariance's correlation matrix, over its largest, whose
#: direction the test weighs (fits of a few hundred samples do not honour tighter ones: above).
CONDITION_FLOOR = 3e-3
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
        The probability of a move under no change.

    """
    if not weight > previous_weight > 0.0:
        return False
    spread = np.diagonal(covariance) * (weight / previous_weight - 1.0)
    if not (np.isfinite(step).all() and np.isfinite(covariance).all() and (spread > 0.0).all()):
        return False  # no honest spread to judge the move against
    scale = np.sqrt(np.diagonal(covariance))
    z = step / np.sqrt(spread)
    values, vectors = np.linalg.eigh(covariance / np.outer(scale, scale))
    kept = values >= CONDITION_FLOOR * values[-1]  # (ascending: the last is the largest)
    along = vectors[:, kept].T @ z
    statistic = float(np.sum(along * along / values[kept]))
    return statistic > float(chi2.isf(level, int(kept.sum())))


__all__ = ['CONDITION_FLOOR', 'KEEP_SHARE', 'MOVE_LEVEL', 'moved']
