r"""
The covariance of the RPEM estimate: the sandwich of P and the long-run covariance of the scores.

The recursion's P is the inverse of the weighted information
:math:`\sum w_t\psi_t\psi_t^T`, and the estimate moves by
:math:`P\sum_t w_t\psi_t\varepsilon_t`, so its covariance is
:math:`P\,\mathrm{var}(\sum_t w_t\psi_t\varepsilon_t)\,P` (Ljung, *System
Identification*, 2nd ed., 1999, sec. 9.3, without assuming white
prediction errors). The middle is :math:`\tau_2\hat\Omega`, with
:math:`\hat\Omega` the long-run covariance per unit weight of the scores
:math:`\psi_t\varepsilon_t` that :class:`~bcid_ros.estimators.hac.HacCovariance`
estimates (prewhitened, windowed) from the scores of the last batch fit's
samples at its estimate and of every sample the recursion took after it,
and :math:`\tau_2` that of every sample the estimate learnt from (the batch
fits' included), with the small-sample factor T/(T - p). Calibrated whether
the output error of an OE model is white or coloured (docs/trust.md).
"""

from __future__ import annotations

import numpy as np

from bcid_ros.estimators.base import weighted_square_ratio
from bcid_ros.estimators.hac import HacCovariance


def parameter_covariance(hac: HacCovariance, p: np.ndarray, tau: float,
                         forgetting_factor: float, count: int,
                         unscale: np.ndarray) -> np.ndarray | None:
    """
    Return the covariance of the first ``count`` parameters in the units of theta, or None.

    Parameters
    ----------
    hac : HacCovariance
        The long-run covariance of the scores psi e (normalised units).
    p : numpy.ndarray, shape ``(q, q)``
        The recursion's P (normalised; q = ``count`` + 1 with the offset).
    tau : float
        The weighted count of the samples learnt from (> 0).
    forgetting_factor : float
        lambda.
    count : int
        p, the parameters of theta (the offset, last, is left out).
    unscale : numpy.ndarray, shape ``(count,)``
        theta_k in the user's units per normalised unit: s_y / s_channel(k).

    Returns
    -------
    numpy.ndarray or None
        ``(count, count)``; None while the HAC has no estimate or the
        effective sample size is not above q.

    """
    covariance = normalised_covariance(hac, p, tau, forgetting_factor)
    if covariance is None:
        return None
    # normalised units to theta's: theta_k s_y / s_channel(k)
    return covariance[:count, :count] * np.outer(unscale, unscale)


def normalised_covariance(hac: HacCovariance, p: np.ndarray, tau: float,
                          forgetting_factor: float) -> np.ndarray | None:
    """
    Return the covariance of every internal parameter (the offset too), in normalised units.

    The units of the recursion's gradient psi: the residual tests' parameter
    term (:class:`~bcid_ros.estimators.adequacy.AdequacyMonitor`) takes it.
    ``(q, q)``, symmetric; None as for :func:`parameter_covariance`.
    """
    long_run = hac.long_run(transform=p)
    if long_run is None:
        return None
    dimension = p.shape[0]
    tau2 = tau * weighted_square_ratio(tau, forgetting_factor)
    size = tau * tau / tau2
    if not size > dimension:
        return None
    covariance = long_run * (tau2 * size / (size - dimension))
    return 0.5 * (covariance + covariance.T)
