"""
The colour of an error: AR models of it and the peak of their spectrum.

The simulation check (:mod:`~bcid_ros.estimators.simulation_check`) bounds the part of a
coloured noise that a refit can take by kappa, the largest value of the noise's spectrum
over its variance; ``bcid analyze``'s residual tests whiten with the same AR noise model.
Levinson-Durbin on the biased sample autocorrelation (Ljung 1999, ch. 10), the order
chosen by AIC (Akaike 1974). Pure numpy.
"""

from __future__ import annotations

import math

import numpy as np

#: Largest spectrum ratio kappa taken for the error's colour (a bound against a zero division
#: only: 100 made an exact rls estimate under equation noise through a pole at 0.992, whose
#: kappa is (1 + 0.992)/(1 - 0.992) = 249, fail the check on the realistic family).
MAX_COLOUR = 1e6
#: Largest order of the AR model of the error whose spectrum gives kappa (and of the AR
#: noise models of bcid_ros.analysis, which take theirs from here).
MAX_NOISE_ORDER = 30
#: Frequencies in [0, pi] on which the AR spectrum's peak is sought.
SPECTRUM_POINTS = 1024


def autocorrelation(residual: np.ndarray, lags: int) -> np.ndarray:
    """Return the sample autocorrelation r_1 ... r_lags (biased, normalised by r_0)."""
    centred = residual - residual.mean()
    denominator = float(centred @ centred)
    if denominator == 0.0:
        return np.zeros(lags)
    return np.array([centred[k:] @ centred[:-k] for k in range(1, lags + 1)]) / denominator


def ar_models(residual: np.ndarray, max_order: int) -> list[tuple[np.ndarray, float]]:
    """
    Return the AR models D(q) v = w of ``residual`` of orders 0 ... ``max_order``.

    Each is ``(D, sigma_w^2 / sigma^2)``: Levinson-Durbin on the biased sample
    autocorrelation (Ljung 1999, ch. 10); D monic and stable. The recursion stops
    before a reflection coefficient of modulus 1 (a constant residual: order 0 only).
    """
    models = [(np.ones(1), 1.0)]
    if not float(np.var(residual)) > 0.0:
        return models
    r = np.concatenate([[1.0], autocorrelation(residual, max_order)])
    polynomial = np.ones(1)
    error = 1.0
    for k in range(1, max_order + 1):
        reflection = -float(polynomial @ r[k:0:-1]) / error
        if not abs(reflection) < 1.0:
            break
        extended = np.concatenate([polynomial, [0.0]])
        polynomial = extended + reflection * extended[::-1]
        error *= 1.0 - reflection ** 2
        models.append((polynomial.copy(), error))
    return models


def ar_noise_model(residual: np.ndarray, max_order: int) -> tuple[np.ndarray, float]:
    r"""
    Return (D, sigma_w^2): the AR model D(q) v = w of ``residual`` chosen by AIC.

    Of :func:`ar_models`, the order that minimises :math:`N\ln\sigma_k^2 + 2k`
    (Akaike 1974).
    """
    count = residual.size
    centred = residual - residual.mean()
    power = float(centred @ centred) / count
    if not power > 0.0:
        return np.ones(1), 0.0
    best = (0.0, np.ones(1), 1.0)
    for k, (polynomial, error) in enumerate(ar_models(residual, max_order)[1:], start=1):
        criterion = count * math.log(error) + 2 * k
        if criterion < best[0]:
            best = (criterion, polynomial, error)
    return best[1], power * best[2]


def _spectrum_peak(polynomial: np.ndarray, error: float) -> float:
    """Return max over [0, pi] of error / |D(e^{i w})|^2 (the spectrum over the variance)."""
    frequencies = np.linspace(0.0, math.pi, SPECTRUM_POINTS)
    response = np.exp(-1j * np.outer(frequencies, np.arange(polynomial.size))) @ polynomial
    with np.errstate(divide='ignore'):
        return float(np.max(error / np.abs(response) ** 2))


def colour(error: np.ndarray, resonances: bool = True) -> float:
    r"""
    Return kappa: the largest value of the error's spectrum over its variance.

    :math:`\kappa = \max_\omega \hat\Phi(\omega)/\hat\sigma^2` of an AR spectrum
    :math:`\hat\Phi = \sigma_w^2/|D(e^{i\omega})|^2`, on ``SPECTRUM_POINTS`` frequencies in
    [0, pi], clipped to [1, MAX_COLOUR]: the AR(2) model's (the long-run colour of a slow
    noise: an exact rpem estimate under equation noise through poles 0.977 and 0.915, 1000
    samples, has its AR(2) peak at 184 and the AIC-chosen AR(5)'s at 73, and failed the
    check with the second) and, with ``resonances``, the larger of it and the peak of the
    model chosen by AIC (:func:`ar_noise_model`, orders up to ``min(MAX_NOISE_ORDER,
    L // 20)``: a resonance that two poles do not describe).
    """
    length = error.size
    models = ar_models(error, min(MAX_NOISE_ORDER, max(2, length // 20)))
    if len(models) == 1:
        return 1.0
    peak = _spectrum_peak(*models[min(2, len(models) - 1)])
    if resonances:
        chosen, _ = ar_noise_model(error, min(MAX_NOISE_ORDER, max(1, length // 20)))
        peak = max(peak, _spectrum_peak(*models[chosen.size - 1]))
    return float(min(max(peak, 1.0), MAX_COLOUR))


__all__ = ['MAX_COLOUR', 'MAX_NOISE_ORDER', 'SPECTRUM_POINTS', 'ar_models', 'ar_noise_model',
           'autocorrelation', 'colour']
