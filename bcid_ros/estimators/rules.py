"""
The rulebook: the safeguards every estimator shares, each written once.

Every estimator of bcid_ros runs the same rules around its own equations
(docs/estimators.md, "Estimates you can trust"): the outlier gate and its
detection of a real plant change, the warm-up before the gate tests, the
memory cut after a change, the choice of signal scales, the check and
repair of a covariance matrix, and the validity checks of a published model.
They are written here over a **leading plant axis**: arrays of shape
``(K, ...)`` for K plants, so a single-plant estimator (K = 1, in its rare
paths) and the batched estimators (K plants at once) call the same
functions and take the same decisions. The estimators keep only their own
equations and their bookkeeping (flags, regressors).

Each function is pure: it takes arrays and returns new arrays or masks; where
it says "in place" it changes the arrays it is given.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from bcid_ros.estimators.polynomials import spectral_radii

#: Normalised prediction error beyond which a sample is refused even with the
#: gate off (``outlier_threshold`` = 0): no Gaussian noise produces it, and
#: taking it would move the estimate by a million standard deviations.
IMPLAUSIBLE_ERROR = 1e6
#: The change score of the gate: +1 per refused sample, times CHANGE_DECAY per
#: tested sample; three refusals in a row (1 + 0.8 + 0.64 = 2.44) reach it.
CHANGE_SCORE = 2.4
#: See CHANGE_SCORE.
CHANGE_DECAY = 0.8
#: A decayed score below this is 0 again (about 31 accepted samples after one refusal).
SCORE_FLOOR = 1e-3
#: The share of the tested samples the gate refuses at most in the long run: beyond it the
#: limit follows the tested errors' own distribution (:func:`track_tail`).
REFUSAL_SHARE = 0.005
#: The tail's step on a log scale: a refusal raises the limit on z^2 by the factor
#: exp(TAIL_STEP (1 - REFUSAL_SHARE)) = 1.05, and every sample within the limit lowers it
#: by exp(-TAIL_STEP REFUSAL_SHARE), back to the threshold's (tail 1) in about 200 samples.
#: Small, so that the few large errors of a plant change (three in a row) barely lift it
#: and still mark the change.
TAIL_STEP = 0.05
#: The tail's factor after a sample beyond the limit.
TAIL_UP = math.exp(TAIL_STEP * (1.0 - REFUSAL_SHARE))
#: The tail's factor after a sample within the limit (down to 1 at least).
TAIL_DOWN = math.exp(-TAIL_STEP * REFUSAL_SHARE)
#: The slow change score (:func:`slow_change`): +1 per refused sample, times
#: SLOW_CHANGE_DECAY per tested sample; three refusals within about 100
#: samples reach it.
SLOW_CHANGE_SCORE = 3.0
#: See SLOW_CHANGE_SCORE.
SLOW_CHANGE_DECAY = 0.99
#: The gate tests samples once the weighted count reaches GATE_WARMUP times
#: the number of parameters (its variance estimate is then a variance).
GATE_WARMUP = 10
#: A detected plant change cuts the weighted memory to this many times p.
CHANGE_MEMORY = 4
#: Validity is re-evaluated every this many updates (its cost is amortised).
VALIDITY_PERIOD = 100
#: A model pole beyond this radius makes the model unstable.
UNSTABLE_RADIUS = 1.01
#: Output power growing by more than this between two validity checks means
#: the data are not bounded (an unstable estimate may then be right).
GROWTH = 4.0
#: A covariance whose normalised Cholesky pivots fall below this times its
#: largest diagonal entry is numerically singular (condition beyond 1e13).
CONDITION_FLOOR = 1e-13


# ------------------------------------------------------------------ the gate
def gate_limit2(outlier_threshold: float) -> float:
    """Return the squared limit of the normalised prediction error (0 = gate off)."""
    return (outlier_threshold or IMPLAUSIBLE_ERROR) ** 2


def gate(z2: Any, limit2: float, score: Any, tail: Any,
         error_z2: Any = None) -> tuple[Any, Any, Any, Any]:
    r"""
    Decide which samples are used, from their squared normalised prediction errors.

    A sample with :math:`z^2` above ``limit2`` times its plant's ``tail`` is
    refused. The tail (:func:`track_tail`) is 1 while at most
    ``REFUSAL_SHARE`` of the tested samples exceed the threshold, as on
    Gaussian errors, and otherwise lifts the limit to the errors' own upper
    quantile: heavy-tailed but genuine errors are taken, while a spike, far
    beyond any of them, is still refused. A sample beyond ``limit2`` itself
    raises a change score that decays by ``CHANGE_DECAY`` per tested sample
    (to 0 below ``SCORE_FLOOR``); when it reaches ``CHANGE_SCORE`` (three
    such samples in a row) the errors are taken as a real change of the
    plant: the sample is used, the score restarts at 0, and the caller cuts
    the memory (:func:`memory_keep`). (The score judges by the threshold,
    not the tail, which the first errors of a change would lift.) Where
    :math:`z^2` also holds a size other than the error's (cl_bcls's
    leverage of the regressor), ``error_z2`` is the error's part alone and
    the score judges by it: a changed plant shows in its errors, and a
    regressor far from the others says nothing of a change.

    Parameters
    ----------
    z2 : float or numpy.ndarray, shape ``(K,)``
        :math:`e^2 / \mathrm{var}(e)` of each plant's tested sample.
    limit2 : float
        :func:`gate_limit2` of the threshold.
    score : float or numpy.ndarray, shape ``(K,)``
        The change scores before the sample.
    tail : float or numpy.ndarray, shape ``(K,)``
        The tails before the sample (1 to start with).
    error_z2 : float or numpy.ndarray, shape ``(K,)``, optional
        The error's part of ``z2`` (<= ``z2``) for the change score; default ``z2``.

    Returns
    -------
    used, score, tail, change
        Whether each sample is used, the new scores and tails, and whether
        the sample marks a plant change (used, with the memory to be cut).
        Booleans and floats for scalar input, arrays for arrays.

    """
    within = np.less_equal(z2 if error_z2 is None else error_z2, limit2)
    accepted = np.less_equal(z2, np.multiply(limit2, tail))
    decayed = np.multiply(score, CHANGE_DECAY)
    raised = decayed + 1.0
    change = np.logical_and(np.logical_not(within), raised >= CHANGE_SCORE)
    kept = np.where(decayed > SCORE_FLOOR, decayed, 0.0)
    score = np.where(within, kept, np.where(change, 0.0, raised))
    used = np.logical_or(accepted, change)
    tail = track_tail(accepted, tail)
    if np.ndim(used) == 0:
        return bool(used), float(score), float(tail), bool(change)
    return used, score, tail, change


def track_tail(accepted: Any, tail: Any) -> Any:
    r"""
    Return the tails after a tested sample, from whether it was within the limit.

    The tail :math:`\rho \ge 1` multiplies the limit :math:`c^2` on
    :math:`z^2`. It is the stochastic approximation (Robbins and Monro
    1951) of the ``1 - REFUSAL_SHARE`` quantile of :math:`z^2/c^2`, on a log
    scale and floored at 1:

    .. math::

        \log\rho \leftarrow \max\big(0,\ \log\rho + \eta\,
            (\mathbb 1[z^2 > c^2\rho] - s)\big)

    with :math:`\eta` = ``TAIL_STEP`` and :math:`s` = ``REFUSAL_SHARE``. Summed
    over N tested samples with R refused, the steps give
    :math:`\log\rho_N \ge \eta(R - sN)`, so whatever the errors'
    distribution, :math:`R \le sN + \log(\rho_N)/\eta`: at most a share s,
    plus :math:`\log(\rho_N)/\eta` samples (about 280 for a limit lifted a
    millionfold). Errors whose share beyond the threshold is below s (5
    sigma on Gaussian errors: 6e-7) keep :math:`\rho` near 1 and the plain
    gate. The tail sees every tested sample, the refused ones too, so
    refusals cannot shrink the scale they are judged by, and a spike moves
    :math:`\log\rho` by :math:`\eta` only.
    """
    return np.where(accepted, np.maximum(np.multiply(tail, TAIL_DOWN), 1.0),
                    np.multiply(tail, TAIL_UP))


def gate_is_quiet(z2: float, limit2: float, score: float, tail: float) -> float:
    """
    Return the tail after a sample that :func:`gate` uses with nothing else to change, or 0.

    The gate's scalar fast path, on floats: a sample within ``limit2`` while
    no change score is pending is used, and only its tail moves
    (:func:`track_tail`). The estimators ask this at every tested sample and
    call :func:`gate` only when it returns 0 (the sample is not quiet).
    """
    if score or not z2 <= limit2:
        return 0.0
    return 1.0 if tail == 1.0 else lowered_tail(tail)


def lowered_tail(tail: float) -> float:
    """Return the tail after a sample within the limit (:func:`track_tail`), on floats."""
    down = tail * TAIL_DOWN
    return down if down > 1.0 else 1.0


def slow_change(refused: Any, slow: Any) -> tuple[Any, Any]:
    r"""
    Return the slow change scores after a tested sample, and whether they mark a plant change.

    The slow form of :func:`gate`'s change detection, for estimators whose
    errors after a real change pass the gate most of the time and are never
    refused three times in a row: in a closed loop a changed plant's errors
    are large mostly right after the reference moves (docs/cl_bcls.md). The
    score decays by ``SLOW_CHANGE_DECAY`` per tested sample (to 0 below
    ``SCORE_FLOOR``) and rises by 1 per refusal; a refusal that brings it to
    ``SLOW_CHANGE_SCORE`` marks a plant change: the score restarts at 0 and
    the caller cuts the memory (:func:`memory_keep`). The sample itself
    stays refused.

    Parameters
    ----------
    refused : bool or numpy.ndarray of bool, shape ``(K,)``
        Whether :func:`gate` refused each plant's tested sample.
    slow : float or numpy.ndarray, shape ``(K,)``
        The slow change scores before the sample.

    Returns
    -------
    slow, change
        The new scores, and whether the sample marks a plant change. Floats
        and booleans for scalar input, arrays for arrays.

    """
    decayed = np.multiply(slow, SLOW_CHANGE_DECAY)
    raised = np.where(decayed > SCORE_FLOOR, decayed, 0.0) + np.where(refused, 1.0, 0.0)
    change = np.logical_and(refused, raised >= SLOW_CHANGE_SCORE)
    slow = np.where(change, 0.0, raised)
    if np.ndim(change) == 0:
        return float(slow), bool(change)
    return slow, change


def memory_keep(tau: Any, count: int) -> Any:
    """
    Return the factor that cuts a weighted memory ``tau`` to CHANGE_MEMORY times ``count``.

    Below 1 where the memory is longer; 1 where it is not (nothing to cut). The
    estimator applies it as one extra forgetting step on what it learnt
    (a covariance grows by 1 / keep, sums and counts shrink by keep), which
    keeps every mean and the covariance-times-count.
    """
    tau = np.asarray(tau, dtype=float)
    with np.errstate(divide='ignore'):
        keep = np.where(tau > 0.0, CHANGE_MEMORY * count / np.where(tau > 0.0, tau, 1.0), 1.0)
    keep = np.minimum(keep, 1.0)
    return float(keep) if keep.ndim == 0 else keep


def cut_memory(p: np.ndarray, loss: np.ndarray, tau: np.ndarray, count: int) -> np.ndarray:
    """
    Cut the memories of least-squares states to CHANGE_MEMORY times ``count``, in place.

    ``p`` ``(K, p, p)`` grows by 1 / keep, ``loss`` and ``tau`` ``(K,)`` shrink
    by keep (:func:`memory_keep`): J / tau and tau P stay as they were.
    Returns the factors.
    """
    keep = memory_keep(tau, count)
    cut = keep < 1.0
    if cut.any():
        p[cut] *= (1.0 / keep[cut])[:, None, None]
        loss[cut] *= keep[cut]
        tau[cut] *= keep[cut]
    return keep


# ---------------------------------------------------------------- the units
def powers_of_two_at_least(values: Any) -> Any:
    """
    Return the smallest power of two >= each value > 0 (1.0 for 0 or non-finite).

    Scaling by such a number is exact in binary floating point, so signals
    divided by these scales keep every bit.
    """
    values = np.asarray(values, dtype=float)
    usable = (values > 0.0) & np.isfinite(values)
    mantissa, exponent = np.frexp(np.where(usable, values, 1.0))
    scale = np.where(usable, np.ldexp(1.0, np.where(mantissa == 0.5, exponent - 1, exponent)),
                     1.0)
    return float(scale) if scale.ndim == 0 else scale


def choose_scales(scales: np.ndarray, peaks: np.ndarray) -> np.ndarray:
    """
    Give each channel still without a scale (0) the scale of its peak, in place.

    ``scales`` and ``peaks`` are ``(K, channels)``; a channel whose peak is
    still 0 keeps scale 0 (it gets one when it first is not). Returns the
    mask of the channels that got a scale now.
    """
    new = (scales == 0.0) & (peaks > 0.0)
    if new.any():
        scales[new] = powers_of_two_at_least(peaks[new])
    return new


def rescale_new_channels(p: np.ndarray, new: np.ndarray, scales: np.ndarray,
                         channel: np.ndarray) -> None:
    """
    Divide the diagonal of P by the square of each new channel's scale, in place.

    Exact, and all a new scale needs: the components of a new channel were
    zero in every update so far, so their rows and columns of P are still
    p0 (times 1 / lambda^k) on the diagonal. ``p`` ``(K, p, p)``, ``new`` and
    ``scales`` ``(K, channels)``, ``channel`` ``(p,)`` the channel of each
    component.
    """
    with np.errstate(divide='ignore'):
        factor = np.where(new, 1.0 / (scales * scales), 1.0)[:, channel]
    diagonal = np.arange(p.shape[-1])
    p[:, diagonal, diagonal] *= factor


# ------------------------------------------------------------ the covariance
def definite(p: np.ndarray) -> np.ndarray:
    """Return whether each matrix of ``p`` ``(K, p, p)`` has a Cholesky factor."""
    try:
        np.linalg.cholesky(p)
        return np.ones(p.shape[0], dtype=bool)
    except np.linalg.LinAlgError:
        return np.array([_factor(matrix) is not None for matrix in p], dtype=bool)


def sound_covariances(p: np.ndarray, component_scale: np.ndarray) -> np.ndarray:
    """
    Return whether each normalised P is positive definite with a condition within 1e13.

    ``p`` ``(K, p, p)`` in the user's units, ``component_scale`` ``(K, p)``
    the scale of each component of phi: S P S is checked, whose conditioning
    does not depend on the units.
    """
    scaled = p * (component_scale[:, :, None] * component_scale[:, None, :])
    sound = np.zeros(p.shape[0], dtype=bool)
    for k, matrix in enumerate(scaled):
        factor = _factor(matrix)
        if factor is not None:
            pivots = np.diagonal(factor) ** 2
            sound[k] = pivots.min() > CONDITION_FLOOR * matrix.diagonal().max()
    return sound


def _factor(matrix: np.ndarray) -> np.ndarray | None:
    """Return the Cholesky factor of one matrix, or None."""
    try:
        return np.linalg.cholesky(matrix)
    except np.linalg.LinAlgError:
        return None


def repair_covariances(p: np.ndarray, fallback: np.ndarray,
                       weights: np.ndarray | None = None) -> np.ndarray:
    """
    Return the nearest symmetric positive definite matrices to those of ``p``.

    Per matrix ``(K, p, p)``: the symmetric part is diagonally scaled by
    ``weights`` ``(K, p)`` (the inverse signal scales, so that the eigenvalue
    floor is relative in normalised units), its eigenvalues are clipped at
    1e-12 of the largest (at least 1e-12) and the scaling is undone. A matrix
    with a non-finite entry is replaced by its ``fallback`` ``(K, p, p)``.
    """
    repaired = np.empty_like(p)
    for k, matrix in enumerate(p):
        sym = 0.5 * (matrix + matrix.T)
        if not np.isfinite(sym).all():
            repaired[k] = fallback[k]
            continue
        w = np.ones(p.shape[-1]) if weights is None else weights[k]
        values, vectors = np.linalg.eigh(sym * np.outer(w, w))
        floor = max(values.max(), 1.0) * 1e-12
        vectors = vectors / w[:, None]
        repaired[k] = (vectors * np.maximum(values, floor)) @ vectors.T
    return repaired


# -------------------------------------------------------------- the validity
def output_powers(p: np.ndarray, tau: np.ndarray, order: int) -> np.ndarray:
    """
    Return the weighted mean square of y over each memory, from P^-1 (inf where singular).

    The first n components of phi are the past outputs, so the trace of the
    a-block of the information P^-1, over n and the weighted count, is their
    weighted mean square.
    """
    try:
        information = np.linalg.inv(p)
    except np.linalg.LinAlgError:
        information = np.full(p.shape, np.inf)
        for k, matrix in enumerate(p):
            try:
                information[k] = np.linalg.inv(matrix)
            except np.linalg.LinAlgError:
                pass
    trace = information[:, :order, :order].diagonal(axis1=1, axis2=2).sum(axis=1)
    return trace / (order * np.maximum(tau, 1.0))


def unstable_models(a: np.ndarray, power: np.ndarray,
                    last_power: np.ndarray) -> list[list[str]]:
    """
    Return, per plant, the reason not to trust an unstable model of bounded data.

    ``a`` ``(K, n)`` are the published denominators, ``power`` the output
    power now and ``last_power`` at the last check (:func:`output_powers`). A
    pole beyond ``UNSTABLE_RADIUS`` is a reason unless the power grew by more
    than ``GROWTH`` (unbounded data: an unstable model may then be right).
    """
    radius = spectral_radii(a)
    # NaN compares false: an unknown radius is unstable, an unknown power bounded
    unstable = ~(radius <= UNSTABLE_RADIUS) & ~(power > GROWTH * last_power)
    return [[f'unstable model (pole radius {radius[k]:.3g}) on bounded data'] if flag else []
            for k, flag in enumerate(unstable.tolist())]


__all__ = ['CHANGE_DECAY', 'CHANGE_MEMORY', 'CHANGE_SCORE', 'CONDITION_FLOOR', 'GATE_WARMUP',
           'GROWTH', 'IMPLAUSIBLE_ERROR', 'REFUSAL_SHARE', 'SCORE_FLOOR', 'SLOW_CHANGE_DECAY',
           'SLOW_CHANGE_SCORE', 'TAIL_DOWN', 'TAIL_STEP', 'TAIL_UP', 'UNSTABLE_RADIUS',
           'VALIDITY_PERIOD', 'choose_scales', 'cut_memory', 'definite', 'gate',
           'gate_is_quiet', 'gate_limit2', 'lowered_tail', 'memory_keep', 'output_powers',
           'powers_of_two_at_least', 'repair_covariances', 'rescale_new_channels',
           'slow_change', 'sound_covariances', 'track_tail', 'unstable_models']
