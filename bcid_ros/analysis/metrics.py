"""
Fit and residual statistics of an identified model (pure numpy and scipy).

The model is an ARX-structure rational model
``A(q) y(t) = sum_i q^-d B_i(q) u_i(t)``, given as ``a = [1, a1, ..., an]``
and one row ``b_i = [b_i0, b_i1, ..., b_in]`` per input (``b_i0 = 0``
without feedthrough), in ascending powers of q^-1.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import linalg, signal, stats

# one AR noise model for analysis and the estimators' simulation check (layer 2)
from bcid_ros.estimators.noise_colour import ar_noise_model, autocorrelation, MAX_NOISE_ORDER
#: Directions of the test's covariance below this fraction of its largest eigenvalue
#: are left out (inputs that do not excite them: a held or narrow-band signal).
EIGENVALUE_FLOOR = 1e-10


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


def coloured_noise_covariance(psi: np.ndarray, residual: np.ndarray,
                              fitted: int) -> tuple[np.ndarray, int]:
    r"""
    Return (the sandwich covariance of an OE estimate, the AR order of its noise model).

    :math:`\mathrm{cov} = B^{-1}(\hat\sigma_w^2 G^TG)B^{-1}`, :math:`B = \psi^T\psi`,
    :math:`G = L^T\psi` (``psi`` filtered by 1/D backwards in time), with
    :math:`\hat\sigma_w^2` the AR model's innovation variance times
    N / (N - ``fitted``). Computed as :math:`K^TK` with
    :math:`K = \hat\sigma_w (L^TQ)R^{-T}` from the QR factors of the
    column-scaled ψ, so that it is positive semi-definite in floating point
    too (the product of the three matrices is not when ψ is ill-conditioned).
    """
    count = residual.size
    noise, sigma2 = ar_noise_model(residual, min(MAX_NOISE_ORDER, max(1, count // 20)))
    sigma2 *= count / max(count - fitted, 1)
    scale = np.linalg.norm(psi, axis=0)
    scale[scale == 0.0] = 1.0
    q, r = linalg.qr(psi / scale, mode='economic')
    coloured = signal.lfilter([1.0], noise, q[::-1], axis=0)[::-1]
    with np.errstate(divide='ignore', invalid='ignore', over='ignore'):
        try:
            root = linalg.solve_triangular(r, coloured.T)
        except linalg.LinAlgError:
            return np.full((psi.shape[1], psi.shape[1]), np.inf), noise.size - 1
        covariance = sigma2 * (root @ root.T) / np.outer(scale, scale)
    return covariance, noise.size - 1


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


def cross_correlation_test(residual: np.ndarray, u: np.ndarray, lags: int,
                           gradient: np.ndarray | None = None,
                           covariance: np.ndarray | None = None) -> tuple[float, float, int]:
    r"""
    Return (statistic, p-value, degrees of freedom) for "the residual is uncorrelated with u".

    The test of an output-error model's dynamics (Ljung, *System
    Identification*, 1999, ch. 16: the cross-correlation of the residual
    with past inputs). A model whose B_i/F are right leaves, in open loop, a
    residual :math:`\varepsilon = v + \psi^T(\theta - \hat\theta)` on data it
    was not fitted to: the noise v, independent of every input whatever its
    colour, and the effect of the estimate's own error. Missing dynamics or
    a wrong dead time add a part correlated with u(t - k) at some lag k.
    With φ(t) the inputs u_i(t - k), k = 0 ... ``lags`` - 1, i = 1 ... r
    (centred), the vector :math:`s = \sum_t \varphi(t)\varepsilon(t)` has
    under that hypothesis the covariance

    .. math::

        C = \hat\sigma_w^2 G^T G + \Gamma\,\mathrm{cov}(\hat\theta)\,\Gamma^T,
        \quad G = L^T\Phi,\quad \Gamma = \Phi^T\Psi

    where :math:`D(q)v = w` is the AR model of the residual chosen by AIC
    (:func:`ar_noise_model`), L the Toeplitz matrix of 1/D (so that
    :math:`\hat\sigma_w^2 LL^T` is the covariance of v, and the first term
    the textbook's :math:`N\sum_k R_v(k)R_\varphi(k)`, which a coloured
    residual makes far larger than :math:`N R_v(0)R_\varphi(0)`), Φ and Ψ
    the rows φ(t)^T and ψ(t)^T (``gradient``) and cov(θ̂) the estimate's
    covariance (``covariance``). The statistic :math:`s^TC^{-1}s` is
    :math:`\chi^2` with as many degrees of freedom as C has independent
    directions. Without the second term a consistent but inefficient
    estimate (OE under strongly coloured noise at a high signal-to-noise
    ratio) fails the test for its estimation error alone; whitening the
    residual and the inputs by D, instead of weighting by it, does the same.

    Parameters
    ----------
    residual : numpy.ndarray, shape ``(M,)``
        The residual over the last M samples of ``u``.
    u : numpy.ndarray, shape ``(N, r)``
        The inputs of the whole record (N >= M), so that the lagged inputs
        of the first residual samples are known.
    lags : int
        Lags 0 ... lags - 1 of every input, >= 1.
    gradient : numpy.ndarray, shape ``(M, p)``, optional
        ψ(t) = ∂ŷ(t)/∂θ over the residual's samples.
    covariance : numpy.ndarray, shape ``(p, p)``, optional
        The covariance of the estimate θ̂ (from other data than the residual's).

    Returns
    -------
    statistic : float
    p_value : float
        NaN when the residual is not finite or too short.
    dof : int
        Degrees of freedom.

    """
    scores, weight = _cross_scores(residual, u, lags, gradient, covariance)
    if scores is None:
        return float('nan'), float('nan'), 0
    values, vectors = np.linalg.eigh(weight)
    keep = values > values.max() * EIGENVALUE_FLOOR
    projected = vectors[:, keep].T @ scores
    statistic = float(np.sum(projected ** 2 / values[keep]))
    dof = int(np.count_nonzero(keep))
    return statistic, float(stats.chi2.sf(statistic, dof)), dof


def cross_correlation(residual: np.ndarray, u: np.ndarray, lags: int,
                      gradient: np.ndarray | None = None,
                      covariance: np.ndarray | None = None) -> np.ndarray:
    """
    Return the standardised cross-correlation of the residual with each input.

    s_j / sqrt(C_jj) of :func:`cross_correlation_test` for every input and
    lag k = 0 ... lags - 1, shape ``(r, lags)``: about N(0, 1) each under
    the test's hypothesis. NaN when the residual is not finite or too short.
    """
    scores, weight = _cross_scores(residual, u, lags, gradient, covariance)
    if scores is None:
        return np.full((u.shape[1], lags), np.nan)
    with np.errstate(divide='ignore', invalid='ignore'):
        return (scores / np.sqrt(np.diagonal(weight))).reshape(u.shape[1], lags)


def _cross_scores(residual: np.ndarray, u: np.ndarray, lags: int,
                  gradient: np.ndarray | None, covariance: np.ndarray | None
                  ) -> tuple[np.ndarray | None, np.ndarray]:
    """Return (s, C) of :func:`cross_correlation_test`, or (None, empty)."""
    count = residual.size
    start = u.shape[0] - count
    if not np.isfinite(residual).all() or lags < 1 or start < lags - 1 or \
            count < 2 * lags * u.shape[1]:
        return None, np.zeros((0, 0))
    centred = u - u[start:].mean(axis=0)
    lagged = np.column_stack([centred[start - k:u.shape[0] - k, i]
                              for i in range(u.shape[1]) for k in range(lags)])
    error = residual - residual.mean()
    noise, sigma2 = ar_noise_model(error, min(MAX_NOISE_ORDER, max(1, count // 20)))
    # G = L^T Phi: Phi filtered by 1/D backwards in time
    coloured = signal.lfilter([1.0], noise, lagged[::-1], axis=0)[::-1]
    weight = sigma2 * (coloured.T @ coloured)
    if gradient is not None and covariance is not None:
        spread = lagged.T @ gradient
        weight = weight + spread @ covariance @ spread.T
    if not (np.isfinite(weight).all() and sigma2 > 0.0):
        return None, np.zeros((0, 0))
    return lagged.T @ error, weight


def accuracy_test(error_a: np.ndarray, error_b: np.ndarray, lags: int) -> tuple[float, float]:
    r"""
    Return (z, p-value) for "model b predicts no better than model a" (one-sided).

    The Diebold-Mariano test of equal accuracy (Diebold and Mariano,
    "Comparing predictive accuracy", J. Business and Economic Statistics
    13(3), 1995) on the loss differential
    :math:`d(t) = \varepsilon_a(t)^2 - \varepsilon_b(t)^2` of two models'
    errors over the same validation samples:
    :math:`z = \bar d / \sqrt{\hat S/N}`, with :math:`\hat S` the long-run
    variance of d by the Bartlett kernel over ``lags`` lags (Newey and West
    1987), since the errors of a simulation are autocorrelated. A small p
    says that b's mean squared error is significantly lower than a's.
    NaN when an error is not finite or d is constant.
    """
    if not (np.isfinite(error_a).all() and np.isfinite(error_b).all()):
        return float('nan'), float('nan')
    differential = error_a ** 2 - error_b ** 2
    count = differential.size
    centred = differential - differential.mean()
    variance = float(centred @ centred) / count
    for k in range(1, min(lags, count - 1) + 1):
        # Bartlett weight 1 - k/(m+1) keeps the estimate non-negative
        variance += 2.0 * (1.0 - k / (lags + 1)) * float(centred[k:] @ centred[:-k]) / count
    if not variance > 0.0:
        return float('nan'), float('nan')
    z = float(differential.mean()) / math.sqrt(variance / count)
    return z, float(stats.norm.sf(z))


__all__ = ['accuracy_test', 'ar_noise_model', 'autocorrelation', 'cross_correlation',
           'cross_correlation_test', 'equation_error',
           'information_criteria', 'ljung_box', 'nrmse_fit', 'simulate',
           'whiteness_lags']
