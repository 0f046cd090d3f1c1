r"""
The statistics of the residual tests: chi-square tails, whiteness, prewhitening, cross-correlation.

Pure functions over the weighted moments that
:class:`~bcid_ros.estimators.adequacy.AdequacyMonitor` keeps, with a leading
plant axis: Ljung, *System Identification*, 2nd ed. (1999), sec. 16.6 (the
whiteness and cross-correlation tests, eq. (16.63)-(16.66)), the Levinson
recursion for the prewhitening filter, and the parameter term of an
estimated model's cross test (docs/trust.md).
"""

from __future__ import annotations

import functools
import math
from typing import Any

import numpy as np

#: Starts of the profiled whiteness statistic's search besides xi = 0 (:func:`profiled_whiteness`).
PROFILE_STARTS = 2
#: Damped Gauss-Newton steps from each start, at most (a stop early only raises Q slightly:
#: 0.06 % above the minimum after 10 steps in a measured case).
PROFILE_ITERATIONS = 10
#: A start's search stops once a step lowers the statistic by less than this share of it
#: (the statistic is compared with thresholds about 2 apart).
PROFILE_TOLERANCE = 1e-6


def chi2_survival(x: float, dof: int) -> float:
    r"""
    Return :math:`P(\chi^2_\nu > x)` for an integer :math:`\nu \ge 1`.

    Abramowitz and Stegun 26.4.4 (odd :math:`\nu`) and 26.4.5 (even), finite
    sums exact to rounding; no scipy.
    """
    if x <= 0.0:
        return 1.0
    half = 0.5 * x
    if dof % 2 == 0:
        # Q = exp(-x/2) sum_{r < nu/2} (x/2)^r / r!                      (26.4.5)
        term, total = 1.0, 1.0
        for r in range(1, dof // 2):
            term *= half / r
            total += term
        return min(1.0, math.exp(-half) * total)
    # Q = 2 Q_N(chi) + 2 Z(chi) sum_{r=1}^{(nu-1)/2} chi^(2r-1) / (1 3 ... (2r-1))   (26.4.4)
    chi = math.sqrt(x)
    term, total = chi, 0.0
    for r in range(1, (dof - 1) // 2 + 1):
        total += term
        term *= x / (2 * r + 1)
    density = math.exp(-half) / math.sqrt(2.0 * math.pi)
    return min(1.0, math.erfc(chi / math.sqrt(2.0)) + 2.0 * density * total)


# (each residual monitor asks for the same few thresholds; a batched plant's restart builds
# two, some 45 bisection steps each)
@functools.lru_cache(maxsize=256)
def chi2_quantile(tail: float, dof: int) -> float:
    """Return x with :func:`chi2_survival` (x, dof) = ``tail``, by bisection (relative 1e-12)."""
    low, high = 0.0, float(dof) + 10.0
    while chi2_survival(high, dof) > tail:
        high *= 2.0
    while high - low > 1e-12 * high:
        middle = 0.5 * (low + high)
        if chi2_survival(middle, dof) > tail:
            low = middle
        else:
            high = middle
    return 0.5 * (low + high)


def whiteness_statistic(autocovariance: np.ndarray, lags: int, size: Any,
                        settling: np.ndarray | None = None
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    r"""
    Return :math:`Q = N\sum_{k=1}^M \hat\rho_k^2`, the worst lag and its :math:`\hat\rho`.

    ``autocovariance`` ``(K, L + 1)`` holds :math:`\hat R_\varepsilon(k)`,
    k = 0..L >= M; N is the effective sample size, a float or one per
    plant ``(K,)``. A residual with zero power gives Q = 0. With
    ``settling`` ``(K, M + 1, p, p)``, the means :math:`B_k` of
    :math:`\tilde\psi(t)\tilde\psi^T(t-k)`, k = 0..M, the estimate's own error enters
    the null distribution (:func:`profiled_whiteness`); a plant where
    :func:`settling_known` is false is tested without it.
    """
    power = autocovariance[:, 0]
    positive = power > 0.0
    rho = autocovariance[:, 1:lags + 1] / np.where(positive, power, 1.0)[:, None]
    rho[~positive] = 0.0
    if settling is None:
        worst = np.argmax(np.abs(rho), axis=-1)
        value = rho[np.arange(rho.shape[0]), worst]
        return size * np.einsum('ki,ki->k', rho, rho), worst + 1, value
    sizes = np.broadcast_to(np.reshape(np.asarray(size, dtype=float), (-1,)), power.shape)
    known = settling_known(settling, power) & positive
    # A_k = (B_k + B_k') / 2 / R_0, k = 1..M: rho_k = rho_v,k + xi' A_k xi
    forms = settling[:, 1:lags + 1] / np.where(positive, power, 1.0)[:, None, None, None]
    forms = 0.5 * (forms + np.swapaxes(forms, -1, -2))
    statistic = sizes * np.einsum('ki,ki->k', rho, rho)
    deviation = rho.copy()
    if known.any():
        statistic[known], deviation[known] = profiled_whiteness(rho[known], forms[known],
                                                                sizes[known])
    worst = np.argmax(np.abs(deviation), axis=-1)
    return statistic, worst + 1, rho[np.arange(rho.shape[0]), worst]


def profiled_whiteness(rho: np.ndarray, forms: np.ndarray, size: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray]:
    r"""
    Return :math:`\min_\xi F(\xi)` and :math:`\hat\rho - q(\hat\xi)` at the minimum, per plant.

    A recursive estimate's output error is
    :math:`\varepsilon(t) = v(t) + \psi^T(t)\tilde\theta(t)`. In open loop
    :math:`\psi` carries no noise, so the term linear in :math:`\tilde\theta`
    has mean zero and is of order 1/N; the quadratic one is not: with
    :math:`\tilde\theta(t) = L_t\xi`, :math:`L_tL_t^T = C(t)` the covariance
    of the estimate when the sample came, one :math:`\xi \sim N(0, I_p)` for
    the window (the estimate's error persists) and :math:`\tilde\psi = L^T\psi`,

    .. math::

        \hat\rho_k = \rho_{v,k} + q_k(\xi), \qquad q_k(\xi) = \xi^T A_k \xi, \quad
        A_k = \frac{B_k + B_k^T}{2 R_0}, \quad B_k = \overline{\tilde\psi(t)\tilde\psi^T(t-k)}.

    The statistic profiles :math:`\xi` out,

    .. math:: Q = \min_\xi\; N\,\lVert\hat\rho - q(\xi)\rVert^2 + \lVert\xi\rVert^2,

    the penalised fit whose linear counterpart (q linear in :math:`\xi`, as the
    cross test's :math:`G\xi`) is exactly :math:`N r^T(I + N G G^T)^{-1} r \sim
    \chi^2(M)` (:func:`parameter_term`); at :math:`A = 0` it is the plain
    :math:`N\lVert\hat\rho\rVert^2`. It is referred to :math:`\chi^2(M)` as
    well (the seeded Monte Carlo of test_adequacy.py measures its tail).
    Damped Gauss-Newton from :math:`\xi = 0` and from the best point along
    each leading eigenvector e of :math:`\sum_k \hat\rho_k A_k` (along e, F is
    a quadratic in :math:`u = s^2`). ``rho`` ``(K, M)``, ``forms`` ``(K, M, p, p)``
    (:math:`A_k`) and ``size`` ``(K,)`` (N) are those of K plants, searched at
    once (each plant's numbers do not depend on the others'); returns ``(K,)``
    and ``(K, M)``.
    """
    count, lags, p = forms.shape[0], forms.shape[1], forms.shape[-1]
    rows = forms.reshape(count, lags * p, p)
    identity = np.eye(p)

    def objective(xi: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        # A_k xi of every k (K, M, p), then q_k = xi' A_k xi
        spread = np.einsum('kij,kj->ki', rows, xi).reshape(count, lags, p)
        residual = rho - np.einsum('kmj,kj->km', spread, xi)
        value = size * np.einsum('km,km->k', residual, residual) + np.einsum('kj,kj->k', xi, xi)
        return value, residual, spread

    best, deviation, _ = objective(np.zeros((count, p)))
    values, vectors = np.linalg.eigh(np.einsum('km,kmij->kij', rho, forms))
    leading = np.argsort(values, axis=-1)[:, ::-1]
    for start in range(min(PROFILE_STARTS, p)):
        direction = np.take_along_axis(vectors, leading[:, None, start:start + 1], axis=2)[..., 0]
        along = np.einsum('kmj,kj->km',
                          np.einsum('kij,kj->ki', rows, direction).reshape(count, lags, p),
                          direction)
        # F(u) = N |rho - u a|^2 + u: least at u = (2 N rho.a - 1) / (2 N a.a)
        scale = ((2.0 * size * np.einsum('km,km->k', rho, along) - 1.0)
                 / np.maximum(2.0 * size * np.einsum('km,km->k', along, along), 1e-300))
        started = scale > 0.0
        xi = np.sqrt(np.where(started, scale, 0.0))[:, None] * direction
        value, residual, spread = objective(xi)
        damping = np.full(count, 1e-3)
        searching = started.copy()
        for _ in range(PROFILE_ITERATIONS):
            if not searching.any():
                break
            # F = |[sqrt(N) (rho - q); xi]|^2; the Jacobian of q is 2 A_k xi
            jacobian = -2.0 * spread
            gradient = size[:, None] * np.einsum('km,kmj->kj', residual, jacobian) + xi
            hessian = (size[:, None, None] * np.einsum('kmi,kmj->kij', jacobian, jacobian)
                       + identity)
            damped = hessian + damping[:, None, None] * (
                np.diagonal(hessian, axis1=1, axis2=2)[:, :, None] * identity)
            step = np.linalg.solve(damped, -gradient[..., None])[..., 0]
            trial, trial_residual, trial_spread = objective(xi + step)
            better = searching & (trial < value)
            converged = better & (value - trial <= PROFILE_TOLERANCE * value)
            xi = np.where(better[:, None], xi + step, xi)
            residual = np.where(better[:, None], trial_residual, residual)
            spread = np.where(better[:, None, None], trial_spread, spread)
            value = np.where(better, trial, value)
            damping = np.where(better, damping / 10.0,
                               np.where(searching, damping * 10.0, damping))
            searching &= ~converged
        lower = started & (value < best)
        best = np.where(lower, value, best)
        deviation = np.where(lower[:, None], residual, deviation)
    return best, deviation


def settling_known(settling: np.ndarray, power: np.ndarray) -> np.ndarray:
    r"""
    Return where the estimate's error enters the tests: B finite, :math:`\mathrm{tr} B_0 \le R_0`.

    A covariance the data contradict gets no term: :math:`E R_0 = \sigma^2 +
    \mathrm{tr} B_0 \ge \mathrm{tr} B_0`, so a C whose error power
    :math:`\mathrm{tr} B_0` exceeds the residual's whole power :math:`R_0`
    overstates the error (an over-specified order: the sandwich is huge along
    the cancelling pole and zero) and would explain any correlation away.
    ``settling`` ``(K, M + 1, p, p)`` (:func:`settling_sums`), ``power`` ``(K,)``.
    """
    known = np.isfinite(settling).all(axis=(1, 2, 3))
    return known & (np.einsum('kii->k', np.where(known[:, None, None], settling[:, 0], 0.0))
                    <= power)


def settling_sums(sums: np.ndarray, ring: np.ndarray, block_weights: np.ndarray,
                  lags: int) -> np.ndarray:
    r"""
    Return ``sums`` ``(K, M + 1, p, p)`` plus :math:`\sum_t w_t \tilde\psi(t)\tilde\psi^T(t-k)`.

    ``ring`` ``(K, H + B, p)`` holds H >= M earlier gradients, then the block's
    B rows; ``block_weights`` ``(B,)`` their weights; k = 0..M.
    """
    count = block_weights.shape[0]
    history = ring.shape[1] - count
    current = np.swapaxes(ring[:, history:] * block_weights[:, None], -1, -2)
    for k in range(lags + 1):
        sums[:, k] += current @ ring[:, history - k:history - k + count]
    return sums


def covariance_factors(covariance: np.ndarray) -> np.ndarray:
    """
    Return L = C^(1/2), L L' = C, of each covariance ``(K, p, p)`` (PSD part; 0 if not finite).

    The settling term takes the estimate's error as L_t xi with one xi over the
    window, so L_t must move with C_t continuously. The symmetric square root
    does; a factor of eigenvectors does not: their signs, and their directions
    at close eigenvalues, can flip from one block to the next on a last-bit
    difference.
    """
    known = np.isfinite(covariance).all(axis=(1, 2))
    symmetric = np.where(known[:, None, None],
                         0.5 * (covariance + np.swapaxes(covariance, -1, -2)), 0.0)
    values, vectors = np.linalg.eigh(symmetric)
    scaled = vectors * np.sqrt(np.maximum(values, 0.0))[:, None, :]
    return scaled @ np.swapaxes(vectors, -1, -2)


def prewhitening_filter(autocovariance: np.ndarray, order: int) -> np.ndarray:
    r"""
    Return the AR whitening filter :math:`[1, f_1, \ldots, f_q]` of each residual, ``(K, q + 1)``.

    Yule-Walker on :math:`\hat R_\varepsilon(0..q)` by the Levinson
    recursion: the filter of the order-q linear predictor. A plant whose
    recursion breaks down (a reflection coefficient not inside the unit
    circle: not minimum phase) gets no filter (``[1, 0, ...]``).
    """
    count = autocovariance.shape[0]
    result = np.zeros((count, order + 1))
    result[:, 0] = 1.0
    for k in range(count):
        coefficients = levinson(autocovariance[k, :order + 1])
        if coefficients is not None:
            result[k] = coefficients
    return result


def levinson(autocovariance: np.ndarray) -> np.ndarray | None:
    """Return the prediction-error filter of the Levinson recursion, or None if it breaks down."""
    error = float(autocovariance[0])
    if not error > 0.0:
        return None
    order = autocovariance.shape[0] - 1
    a = np.zeros(order + 1)
    a[0] = 1.0
    for m in range(1, order + 1):
        # reflection coefficient k_m = -(sum_j a_j R(m - j)) / E_{m-1}
        reflection = -float(a[:m] @ autocovariance[m:0:-1]) / error
        if not abs(reflection) < 1.0:
            return None
        # a_j <- a_j + k_m a_{m-j}, j = 1..m
        a[1:m + 1] = a[1:m + 1] + reflection * a[m - 1::-1]
        error *= 1.0 - reflection * reflection
    return a


def filter_rows(whitening: np.ndarray, rows: int, columns: int) -> np.ndarray:
    r"""
    Return :math:`\Phi` ``(K, rows, columns)`` with :math:`\Phi_{a, a + l} = f_l`.

    For x the stored lags of a signal, ``[x(t - s), x(t - s - 1), ...]``,
    row a of :math:`\Phi x` is the filtered
    :math:`\tilde x(t - s - a) = \sum_l f_l x(t - s - a - l)`.
    """
    count, order = whitening.shape[0], whitening.shape[1] - 1
    result = np.zeros((count, rows, columns))
    for a in range(rows):
        result[:, a, a:a + order + 1] = whitening
    return result


def cross_statistics(residual: np.ndarray, signals: np.ndarray, cross: np.ndarray,
                     whitening: np.ndarray, lags: int, size: Any, colour_lags: int,
                     gradient: np.ndarray | None = None, covariance: np.ndarray | None = None
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    r"""
    Return :math:`Q_i = N r^T P^{-1} r` of each input, its worst lag and correlation, ``(K, r)``.

    The weighted means are ``residual`` ``(K, q + 1, E + 1)``, of
    :math:`e(t-a)e(t-b)`, ``signals`` ``(K, r, U, U)`` of
    :math:`u_i(t-a)u_i(t-b)` and ``cross`` ``(K, r, q + 1, U)`` of
    :math:`e(t-a)u_i(t-b)` (u from lag 1); ``whitening`` is the filter f
    ``(K, q + 1)`` of both series (``[1]``: none), so that every filtered
    moment is an exact quadratic form; ``size`` N, a float or ``(K,)``;
    ``colour_lags`` J (see :class:`~bcid_ros.estimators.adequacy.AdequacyMonitor`).
    With ``gradient`` ``(K, r, q + 1, p, U)``, the means of
    :math:`\psi(t-m)u_i(t-a)`, and ``covariance`` C ``(K, p, p)`` of the
    estimate (NaN: unknown), P becomes :math:`P + N G C G^T`
    (:func:`parameter_term`).
    """
    count, inputs, stored = signals.shape[0], signals.shape[1], signals.shape[-1]
    span = lags + colour_lags
    if whitening.shape[1] == 1 and colour_lags == 0:  # a white residual: no filter
        colour = residual[:, 0, :1]
        r = cross[:, :, 0, :lags]
        products = signals[:, :, :lags, :lags]
    else:
        # e~(t - j), j = 0..J, and u~(t - a), a = 1..M + J: rows of filters on the stored lags
        residual_filter = filter_rows(whitening, colour_lags + 1, residual.shape[-1])
        input_filter = filter_rows(whitening, span, stored)
        # R_e~(j) = mean e~(t) e~(t - j) = f' [e(t - a) e(t - j - b)] f
        colour = np.einsum('ka,kab,kjb->kj', whitening, residual, residual_filter)
        # r_k = mean e~(t) u~(t - k), k = 1..M
        r = np.einsum('ka,kiac,kjc->kij', whitening, cross, input_filter[:, :lags])
        # V(a, c) = mean u~(t - a) u~(t - c), a, c = 1..M + J
        products = input_filter[:, None] @ signals @ np.swapaxes(input_filter, -1, -2)[:, None]
    # P_ab = sum_{|j| <= J} kappa_j R_e~(j) V(a, b + j), V(a, c) for c < 1 from V(a + d, c + d)
    if colour_lags == 0:
        variance = colour[:, :1, None, None] * products[:, :, :lags, :lags]
    else:
        variance = np.zeros((count, inputs, lags, lags))
        tests = np.arange(lags)
        for j in range(-colour_lags, colour_lags + 1):
            kappa = 1.0 - abs(j) / (colour_lags + 1)
            column = tests[None, :] + j
            shift = np.maximum(0, -column)
            variance += (kappa * colour[:, abs(j)])[:, None, None, None] * products[
                :, :, tests[:, None] + shift, column + shift]
    sizes = np.repeat(np.broadcast_to(np.reshape(np.asarray(size, dtype=float), (-1,)),
                                      (count,)), inputs)
    extra = None
    if gradient is not None and covariance is not None:
        extra = parameter_term(gradient, covariance, whitening, lags,
                               sizes[::inputs]).reshape(-1, lags, lags)
    statistic, standardised = quadratic_forms(variance.reshape(-1, lags, lags),
                                              r.reshape(-1, lags), sizes, extra)
    worst = np.argmax(np.abs(standardised), axis=-1)
    flat = r.reshape(-1, lags)[np.arange(count * inputs), worst].reshape(count, inputs)
    scale = np.sqrt(np.maximum(colour[:, :1] * np.einsum('kiaa->kia', products)[:, :, 0], 0.0))
    value = np.where(scale > 0.0, flat / np.where(scale > 0.0, scale, 1.0), 0.0)
    return statistic.reshape(count, inputs), worst.reshape(count, inputs) + 1, value


def quadratic_forms(variance: np.ndarray, r: np.ndarray, size: Any,
                    extra: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    r"""
    Return :math:`N r^T P^{-1} r` on the chi-square(M) scale, and :math:`r_k/\sqrt{P_{kk}}`.

    ``variance`` P ``(n, M, M)``, r ``(n, M)``, ``size`` N (a float or
    ``(n,)``). P is inverted on the directions its window can estimate: an
    eigenvalue below ``1 / N`` of the largest is below the precision of
    moments from N samples (a multisine of a few sines, or a held input,
    makes P nearly singular, and the colour terms can make it slightly
    indefinite there), and a direction the input does not excite cannot
    show a correlation anyway. On the k kept directions the statistic is
    chi-square(k) under the null; it is mapped to the chi-square(M) value of
    the same tail probability, so that one pair of thresholds serves. A P
    without power gives 0: its test cannot see anything. ``extra``
    ``(n, M, M)``, positive semi-definite (the parameter term), is added to
    P; the floor stays that of P alone, so the sum keeps every direction P
    keeps (its eigenvalues are at least P's, by Weyl's inequality).
    """
    lags = r.shape[-1]
    sizes = np.broadcast_to(np.asarray(size, dtype=float), r.shape[:1])
    statistic = np.zeros(r.shape[0])
    finite = np.isfinite(variance).all(axis=(1, 2)) & np.isfinite(r).all(axis=1)
    if extra is not None:
        finite &= np.isfinite(extra).all(axis=(1, 2))
    rows = np.flatnonzero(finite)
    # one stacked decomposition (LAPACK on each matrix, as one at a time: the same bits)
    symmetric = 0.5 * (variance[rows] + np.swapaxes(variance[rows], -1, -2))
    tops = None if extra is None else np.linalg.eigvalsh(symmetric)[:, -1]
    if extra is not None:
        symmetric = symmetric + 0.5 * (extra[rows] + np.swapaxes(extra[rows], -1, -2))
    decomposed = np.linalg.eigh(symmetric)
    for index, k in enumerate(rows.tolist()):
        values, vectors = decomposed.eigenvalues[index], decomposed.eigenvectors[index]
        top = values[-1] if tops is None else float(tops[index])
        if not top > 0.0:
            continue
        kept = values > top / max(sizes[k], 1.0)
        projected = vectors[:, kept].T @ r[k]
        value = sizes[k] * float(projected @ (projected / values[kept]))
        rank = int(kept.sum())
        statistic[k] = value if rank == lags else chi2_quantile(chi2_survival(value, rank), lags)
    diagonal = np.einsum('kii->ki', variance if extra is None else variance + extra)
    good = finite & (diagonal > 0.0).all(axis=-1)
    standardised = r / np.sqrt(np.where(good[:, None], diagonal, 1.0))
    return statistic, np.where(good[:, None], standardised, 0.0)


def parameter_term(gradient: np.ndarray, covariance: np.ndarray, whitening: np.ndarray,
                   lags: int, size: np.ndarray) -> np.ndarray:
    r"""
    Return :math:`N G_i C G_i^T`, the estimate's error in input i's cross test, ``(K, r, M, M)``.

    The residual of an estimated model is
    :math:`\varepsilon(t) = v(t) + \psi^T(t)\tilde\theta`,
    :math:`\tilde\theta = \theta - \hat\theta`, :math:`\psi = \partial\hat y/\partial\theta`
    (Ljung, *System Identification*, 2nd ed., sec. 16.6), so the whitened
    cross-correlation is :math:`r = r_v + G\tilde\theta` with

    .. math::

        G_i(k, j) = \overline{\tilde u_i(t-k)\tilde\psi_j(t)}
            = \sum_{m,a} f_m \Phi_{ka}\,\overline{\psi_j(t-m) u_i(t-a)},

    f the whitening filter, :math:`\Phi` its rows on the stored input lags
    (:func:`filter_rows`) and the bar the weighted mean (``gradient``
    ``(K, r, q + 1, p, U)``). With :math:`\tilde\theta` of covariance C
    (``covariance`` ``(K, p, p)``, in the units of :math:`\psi`) independent
    of :math:`r_v`, :math:`N\,\mathrm{cov}(r) = P + N G C G^T`, and the
    statistic stays :math:`\chi^2(M)`. A plant whose C is not finite gets
    no term (zeros); ``size`` N ``(K,)``.
    """
    input_filter = filter_rows(whitening, lags, gradient.shape[-1])
    # G_i(k, j) = sum_m sum_a f_m Phi_ka mean psi_j(t - m) u_i(t - a)
    spread = np.einsum('km,kimja,kla->kilj', whitening, gradient, input_filter)
    known = np.isfinite(covariance).all(axis=(1, 2))
    covariance = np.where(known[:, None, None], covariance, 0.0)
    # N G C G'
    term = np.einsum('kilj,kjh,kinh->kiln', spread, covariance, spread)
    return term * np.reshape(size, (-1, 1, 1, 1))
