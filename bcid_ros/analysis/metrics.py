"""
Fit and residual statistics of an identified model (pure numpy and scipy).

The model is an ARX-structure rational model
``A(q) y(t) = sum_i q^-d B_i(q) u_i(t)``, given as ``a = [1, a1, ..., an]``
and one row ``b_i = [b_i0, b_i1, ..., b_in]`` per input (``b_i0 = 0``
without feedthrough), in ascending powers of q^-1.
"""

from __future__ import annotations

import numpy as np
from scipy import signal, stats


def simulate(a: np.ndarray, b: np.ndarray, u: np.ndarray) -> np.ndarray:
    r"""
    Return the simulated output :math:`\hat y_s = \sum_i B_i/A\,u_i` from rest.

    Parameters
    ----------
    a : numpy.ndarray, shape ``(n + 1,)``
        A = [1, a1, ..., an].
    b : numpy.ndarray, shape ``(r, n + 1)``
        One row [b_i0, ..., b_in] per input.
    u : numpy.ndarray, shape ``(N, r)``
        Inputs, already delayed.

    Returns
    -------
    numpy.ndarray, shape ``(N,)``
        Non-finite where an unstable model overflowed.

    """
    with np.errstate(over='ignore', invalid='ignore'):
        return sum(signal.lfilter(b[i], a, u[:, i]) for i in range(b.shape[0]))


def equation_error(a: np.ndarray, b: np.ndarray, y: np.ndarray, u: np.ndarray) -> np.ndarray:
    r"""
    Return :math:`\varepsilon(t) = A(q) y(t) - \sum_i B_i(q) u_i(t)`, the LS residual.

    It is also the one-step prediction error of the model read as ARX,
    :math:`y(t) - \hat y(t|t-1)`. The first n samples (incomplete regressor)
    are left out: shape ``(N - n,)``.
    """
    n = a.size - 1
    error = signal.lfilter(a, [1.0], y)
    for i in range(b.shape[0]):
        error = error - signal.lfilter(b[i], [1.0], u[:, i])
    return error[n:]


def nrmse_fit(y: np.ndarray, estimate: np.ndarray) -> float:
    r"""
    Return the NRMSE fit :math:`100\,(1 - \|y - \hat y\| / \|y - \bar y\|)` in percent.

    100 is a perfect fit, 0 is no better than the mean, and it is negative
    for a model worse than the mean; ``-inf`` when ``estimate`` is not
    finite (an unstable simulation).
    """
    if not np.isfinite(estimate).all():
        return float('-inf')
    spread = np.linalg.norm(y - y.mean())
    with np.errstate(over='ignore', invalid='ignore'):
        fit = float(100.0 * (1.0 - np.linalg.norm(y - estimate) / spread))
    return fit if np.isfinite(fit) else float('-inf')


def information_criteria(residual: np.ndarray, num_parameters: int) -> tuple[float, float]:
    r"""
    Return (AIC, MDL) of a least-squares fit from its residual.

    With :math:`V = \frac1N\sum\varepsilon^2` over N residuals and p parameters,
    :math:`\mathrm{AIC} = N\ln V + 2p` and
    :math:`\mathrm{MDL} = N\ln V + p\ln N` (Akaike 1974; Rissanen 1978), the
    forms of Ljung, *System Identification* (1999), eqs. (16.33)-(16.34)
    multiplied by N. Smaller is better.
    """
    count = residual.size
    with np.errstate(over='ignore', invalid='ignore'):
        loss = float(np.mean(residual ** 2))
    if not loss > 0 or not np.isfinite(loss):
        return float('nan'), float('nan')
    return (count * np.log(loss) + 2 * num_parameters,
            count * np.log(loss) + num_parameters * np.log(count))


def autocorrelation(residual: np.ndarray, lags: int) -> np.ndarray:
    """Return the sample autocorrelation r_1 ... r_lags (biased, normalised by r_0)."""
    centred = residual - residual.mean()
    denominator = float(centred @ centred)
    if denominator == 0.0:
        return np.zeros(lags)
    return np.array([centred[k:] @ centred[:-k] for k in range(1, lags + 1)]) / denominator


def whiteness_lags(count: int) -> int:
    """Return the number of lags the whiteness test uses: 20, fewer for short records."""
    return int(max(1, min(20, count // 5)))


def ljung_box(residual: np.ndarray, lags: int) -> tuple[float, float]:
    r"""
    Return the Ljung-Box statistic and its p-value for "the residual is white".

    :math:`Q = N(N+2)\sum_{k=1}^{m} r_k^2/(N-k)`, asymptotically
    :math:`\chi^2_m` under whiteness (Ljung and Box 1978). The residuals
    tested here are computed on validation data the model was not fitted
    to, so no degrees of freedom are subtracted for the parameters.
    """
    count = residual.size
    with np.errstate(over='ignore', invalid='ignore'):
        r = autocorrelation(residual, lags)
    if not np.isfinite(r).all():
        return float('nan'), float('nan')
    statistic = float(count * (count + 2) * np.sum(r ** 2 / (count - np.arange(1, lags + 1))))
    return statistic, float(stats.chi2.sf(statistic, lags))


def is_stable(a: np.ndarray) -> bool:
    """Return whether every root of A lies strictly inside the unit circle."""
    return bool(a.size == 1 or np.abs(np.roots(a)).max() < 1.0)


__all__ = ['autocorrelation', 'equation_error', 'information_criteria', 'is_stable',
           'ljung_box', 'nrmse_fit', 'simulate', 'whiteness_lags']
