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
estimates (prewhitened with ``PREWHITENING``, windowed) from the profiled scores
of the last batch fit's samples at its estimate (:func:`fitted_scores`) and of
every sample the recursion took after it,
and :math:`\tau_2` that of every sample the estimate learnt from (the batch
fits' included), with the small-sample factor T/(T - p). Calibrated whether
the output error of an OE model is white or coloured (docs/trust.md).

**The fitted initial state.** The recursion continues from a batch fit with
:math:`P_f = I_h^{-1}`, the information of the fit's samples with each
segment's initial state held, as the recursion holds it. But the fit chose
that state (and the offset) at every theta: what the samples tell about theta
is the profiled information :math:`I_c \le I_h`, psi projected off the
nuisance columns (Golub and Pereyra 2003). On a slow plant the free response
of a held state carries "information" about the poles that the fitted state
absorbs: on tracking plant (1, 5) (poles 0.98, 0.97, 0.83) the variances of
:math:`I_h^{-1}` were 5-200 times below :math:`I_c^{-1}`'s after its change.
The sandwich of the profiled scores gives the fit's honest covariance
:math:`C_c`; :math:`D = C_c - C_h \succeq 0` (its positive part) is what the
held one leaves out. The recursion carries the fit's error on linearly: with
exponential forgetting :math:`\theta(t) - \theta^* \approx
\lambda^k P(t) P_f^{-1} (\theta_f - \theta^*) + \ldots` after k steps (the
information form of the recursion, Ljung and Söderström 1983, sec. 2.6), so
:math:`\lambda^{2k} P(t) E P(t)`, :math:`E = P_f^{-1} D P_f^{-1}`, joins the
sandwich (:func:`fitted_state_excess`, :func:`parameter_covariance`). E is kept as
its square root :math:`R = P_f^{-1} D^{1/2}` (:math:`E = RR^T`) and the share
computed as :math:`(P R)(P R)^T`: the information behind :math:`P_f^{-1}` spans
ten and more decades on a slow plant, and the product P E P lost them twice,
where P R loses them once (:func:`carried_excess`).

**Between fits.** The recursion's estimate leaves its fit (on a slow plant its error was
1.6-1.9 times a batch fit's of the same samples, 150-280 samples after its fit): the move
since the fit, d, joins the sandwich as d d^T (:func:`whole_covariance`).

**Ends the data cannot tell apart.** The sandwich is the curvature at the
estimate. On a plant whose data determine its response but not its
parameters (an input that barely excites a fast pole, poles near 1), the loss
has a long curved valley, and the curvature at a point of it says nothing of
how far the valley goes: on tracking plant (2, 23) with lambda 0.999, after its
drift ended, the estimate was 14-41 % off with 2 sqrt(tr C) 7-21 % of its size
(the error 4-7000 in its Mahalanobis units), while its simulated output was the
true model's (squared error 0.91-1.04 of it over the last 1000 samples) and the
window's information at the truth put 2 std at 36-45 %, the error at 2-11 in
its units. The fit's two starts (:class:`~bcid_ros.estimators.rpem.fit.BatchFit`)
end apart along such a valley (there: up to 112 % apart, thousands of std, the
losses within the likelihood-ratio region): the other end's distance d joins
the fit's covariance as d d^T, carried on by the recursion as the initial
state's share (:func:`with_unresolved`).
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np

from bcid_ros.estimators.base import weighted_square_ratio
from bcid_ros.estimators.hac import HacCovariance
from bcid_ros.estimators.noise_colour import colour, MAX_COLOUR
from bcid_ros.estimators.residual_statistics import chi2_quantile

#: The HAC's prewhitening for rpem (:class:`~bcid_ros.estimators.hac.HacCovariance`): the
#: larger of the diagonal AR(1) one and none, in every direction. After a fit the scores are
#: the profiled ones, whose smallest principal axis the diagonal one understated half
#: (docs/trust.md, "rpem's std after a fit").
PREWHITENING = 'larger'

#: The likelihood-ratio region's tail probability within which the fit's other end is one
#: the data do not tell from its estimate (:func:`with_unresolved`).
UNRESOLVED_LEVEL = 0.05


def parameter_covariance(hac: HacCovariance, p: np.ndarray, tau: float,
                         forgetting_factor: float, count: int,
                         unscale: np.ndarray, excess: np.ndarray | None = None,
                         decay: float = 1.0, moved: np.ndarray | None = None
                         ) -> np.ndarray | None:
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
    excess : numpy.ndarray, shape ``(q, q)``, optional
        R, the square root of E of the last fit (:func:`fitted_state_excess`):
        decay² P E P joins the sandwich (:func:`whole_covariance`); NaN (the share
        not known): no covariance.
    decay : float
        The weight the last fit's samples keep now: lambda^k after k steps.
    moved : numpy.ndarray, shape ``(q,)``, optional
        theta_n now less the last fit's (normalised): its outer product joins the
        sandwich (:func:`whole_covariance`).

    Returns
    -------
    numpy.ndarray or None
        ``(count, count)``; None while the HAC has no estimate, the
        effective sample size is not above q, or ``excess`` is not known.

    """
    if excess is not None and not np.isfinite(excess).all():
        return None  # the last fit's share is not known, nor the std
    covariance = whole_covariance(hac, p, tau, forgetting_factor, excess, decay, moved)
    if covariance is None:
        return None
    # normalised units to theta's: theta_k s_y / s_channel(k)
    return covariance[:count, :count] * np.outer(unscale, unscale)


def whole_covariance(hac: HacCovariance, p: np.ndarray, tau: float, forgetting_factor: float,
                     excess: np.ndarray | None, decay: float,
                     moved: np.ndarray | None = None) -> np.ndarray | None:
    r"""
    Return :func:`normalised_covariance` with the last fit's share and the move since it.

    decay² P E P (:func:`carried_excess`) is what the recursion carries on of the states the
    fit chose; ``excess`` None or not finite (the share not known): the HAC's alone. The
    estimate's error is the fit's plus the move :math:`d = \theta(t) - \theta_f` the
    recursion made since: ``moved``, known, joins as d d^T (as the fit's other end does,
    :func:`with_unresolved`). The std (:func:`parameter_covariance`) takes it; rpem's
    residual tests' parameter term takes it without d.

    Between fits the recursion's estimate leaves its fit: on the slow plant of
    test_rpem_fitted_state.py (poles 0.98, 0.97, 0.83), over 40 seeds at 900-1600
    samples, its error was 1.6-1.9 times the batch fit's 150-280 samples after a fit
    (median), and beyond 2 std of a_1..a_3 in 19 % of the readings (z rms 2.4) without
    d d^T; 5.0 % with it (z rms 0.97).
    """
    covariance = normalised_covariance(hac, p, tau, forgetting_factor)
    if covariance is None:
        return None
    if excess is not None and np.isfinite(excess).all():
        covariance = covariance + decay * decay * carried_excess(p, excess)
    if moved is not None:
        covariance = covariance + np.outer(moved, moved)
    return covariance


def carried_excess(p: np.ndarray, root: np.ndarray) -> np.ndarray:
    r"""
    Return P E P as (P R)(P R)^T, from the square root R of E (:func:`fitted_state_excess`).

    R is P_f^-1 D^1/2 and the recursion's P is near P_f after a fit, so P R is near D^1/2,
    computed to about cond(P_f) times the rounding error. The plain product P E P of
    E = R R^T loses cond(P_f) squared: on tracking plant (1, 17) (poles 0.995 to 0.997),
    at fits with cond(P_f) 1e12-1e13, its variances were negative where D's were 0.4-254
    (no std at all, and the window test after a change, :mod:`.window`, judged nothing),
    and a root taken from E's eigenvalues was positive but 2.5-15,000 times D.
    """
    carried = p @ root
    return carried @ carried.T


def excess_root(excess: np.ndarray) -> np.ndarray:
    """Return a square root R of E, R R^T = E (E's negative eigenvalues at 0; NaN stays NaN)."""
    if not np.isfinite(excess).all():
        return np.full_like(excess, np.nan)
    values, vectors = np.linalg.eigh(0.5 * (excess + excess.T))
    return vectors * np.sqrt(np.maximum(values, 0.0))


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


def fitted_scores(scores: np.ndarray, profiled: np.ndarray) -> np.ndarray:
    r"""
    Return a fit's scores ``(m, q)`` for the HAC, theta's columns the profiled ones.

    The fit solved theta's profiled equations (each segment's initial state re-fitted at
    every theta), so the profiled scores ``(m, p)`` sum to about zero at its estimate;
    the held ones :math:`\psi_h\varepsilon` do not: they carry each segment's start-up
    transient (on early-run plant 12, 92 % of their power in the first 10 of 381 samples),
    which overstated the std 2-6 times (docs/trust.md, "rpem's std after a fit"). The
    offset's column (q > p) stays. Rows that do not match (none profiled): ``scores``.
    """
    if profiled.shape[0] != scores.shape[0]:
        return scores
    fitted = scores.copy()
    fitted[:, :profiled.shape[1]] = profiled
    return fitted


def score_hac(dimension: int, forgetting_factor: float) -> HacCovariance:
    """Return an empty HAC of rpem's scores psi e: the recursion's, and a fit's (profiled)."""
    return HacCovariance(dimension=dimension, forgetting_factor=forgetting_factor,
                         prewhitening=PREWHITENING)


def fitted_state_excess(held: np.ndarray | None, information: np.ndarray,
                        profiled_information: np.ndarray, profiled_scores: np.ndarray,
                        prior: float, tau: float, forgetting_factor: float) -> np.ndarray:
    """
    Return R = P_f^-1 D^1/2 of a fit, E = R R^T: what its held-state covariance leaves out.

    :func:`profiled_excess` with the profiled scores recorded whole in a HAC here
    (``HacCovariance.complete``, as rpem/store.py's ``_recorded`` records a fit's).

    Parameters
    ----------
    held : numpy.ndarray or None, shape ``(q, q)``
        C_h, the sandwich of the fit (:func:`normalised_covariance` of its scores
        and P_f); None: not known (R is NaN).
    information : numpy.ndarray, shape ``(q, q)``
        I_h, the fit's information with the nuisance held (P_f is the inverse of
        it plus ``prior`` I).
    profiled_information, profiled_scores : numpy.ndarray
        I_c ``(p, p)`` and the scores ``(m, p)`` of theta with the nuisance
        profiled out (:attr:`~bcid_ros.estimators.rpem.fit.FitResult.profiled`).
    prior : float
        1 / p0, the information every diagonal entry starts with.
    tau, forgetting_factor : float
        The fit's weighted count and lambda, as for :func:`normalised_covariance`.

    Returns
    -------
    numpy.ndarray
        ``(q, q)``, its columns outside theta's block zero (R R^T is E: symmetric
        positive semi-definite); zeros where nothing was profiled; NaN where either
        covariance is not known (``held`` None, or fewer scores than parameters): the
        share is then unknown, not zero. Taken as zero, a short fit of a slow plant had
        the held covariance alone once the recursion's scores gave the HAC an
        estimate: on tracking plant (2, 10) (a pole at 0.992, 200 samples after
        its change) 2 sqrt(tr C) was 8 % of the estimate's size while it was 49 %
        off, and ``valid`` took it as precise.

    """
    hac = score_hac(profiled_information.shape[0], forgetting_factor)
    hac.record_all(profiled_scores)
    hac.complete()
    return profiled_excess(held, information, profiled_information, hac, prior, tau,
                           forgetting_factor)


def profiled_excess(held: np.ndarray | None, information: np.ndarray,
                    profiled_information: np.ndarray, profiled_hac: HacCovariance,
                    prior: float, tau: float, forgetting_factor: float) -> np.ndarray:
    """
    Return :func:`fitted_state_excess` from the HAC of the profiled scores, ``profiled_hac``.

    (A fit spread over updates records them a pass at a time: rpem/store.py, FitJob.)
    """
    size, count = information.shape[0], profiled_information.shape[0]
    if not profiled_hac.samples:
        return np.zeros((size, size))
    if held is None:
        return np.full((size, size), np.nan)
    try:
        p_profiled = np.linalg.inv(profiled_information + prior * np.eye(count))
    except np.linalg.LinAlgError:
        return np.zeros((size, size))
    profiled = normalised_covariance(profiled_hac, p_profiled, tau, forgetting_factor)
    if profiled is None or not np.isfinite(profiled).all():
        return np.full((size, size), np.nan)
    # D: the positive part of C_c - C_h (the held one can be larger in a direction by
    # the noise of the two HAC estimates; it is never less honest there); its root
    values, vectors = np.linalg.eigh(profiled - held[:count, :count])
    root = np.zeros((size, size))
    root[:count, :count] = vectors * np.sqrt(np.maximum(values, 0.0))
    return (information + prior * np.eye(size)) @ root  # P_f^-1 D^1/2


def unresolved_limit(parameters: int, square_ratio: float) -> float:
    r"""
    Return the ``UNRESOLVED_LEVEL`` quantile of the likelihood-ratio statistic at the truth.

    :math:`(\tau_2/\tau)\chi^2_p` under white errors, ``square_ratio`` the weights'
    :math:`\tau_2/\tau` (1 without forgetting): a statistic :math:`N(V_2/V_1 - 1)` within
    it is one the data do not tell from chance (:func:`with_unresolved`, and the ranking of
    a fit's ends after a change, :meth:`~bcid_ros.estimators.rpem.fit.BatchFit._ranked`).
    """
    return chi2_quantile(UNRESOLVED_LEVEL, parameters) * square_ratio


def with_unresolved(root: np.ndarray, theta: np.ndarray,
                    alternative: tuple[np.ndarray, float] | None, weight: float,
                    forgetting_factor: float, residuals: Callable[[], np.ndarray],
                    inverse: np.ndarray) -> np.ndarray:
    r"""
    Return the root of E + P_f^-1 d d^T P_f^-1 where the fit's other end is as good, else R.

    The likelihood-ratio statistic of a parameter vector against the estimate,
    :math:`N(V_2/V_1 - 1)` (V the weighted losses, N the weight), is at the truth
    :math:`(\tau_2/\tau)\chi^2_p` under white errors (the weighted estimate's covariance
    is :math:`\sigma^2(\tau_2/\tau)H^{-1}` for the weighted curvature H; 1 without
    forgetting) and at most :math:`\kappa` times that with coloured ones (kappa the peak of
    the residuals' spectrum over their variance,
    :func:`~bcid_ros.estimators.noise_colour.colour`; the simulation check's bound). The
    other end within its ``UNRESOLVED_LEVEL`` quantile is in the likelihood-ratio
    confidence region: the data do not prefer the estimate to it, and the estimate's error
    can be as large as d = theta_2 - theta_1, which joins the fit's covariance as d d^T (as
    :func:`fitted_state_excess`'s D, carried on by the recursion with the fit's weight).

    Parameters
    ----------
    root : numpy.ndarray, shape ``(q, q)``
        R of the fit (:func:`fitted_state_excess`); NaN (not known) stays NaN.
    theta : numpy.ndarray, shape ``(p,)``
        The fit's estimate.
    alternative : tuple or None
        ``(theta_2, V_2 / V_1)`` of its other start (None: one start).
    weight, forgetting_factor : float
        N and lambda (the fit's weights lambda^k).
    residuals : callable
        Returns the fit's residuals (asked only where kappa decides).
    inverse : numpy.ndarray, shape ``(q, q)``
        P_f^-1 (q >= p: the offset last).

    Returns
    -------
    numpy.ndarray
        ``(q, q)``: R' with R' R'^T = R R^T + P_f^-1 d d^T P_f^-1 (from the QR
        factorisation of [R, P_f^-1 d]^T, which keeps the columns' accuracy), or R where
        the ends agree or the data prefer the estimate.

    """
    if alternative is None or not weight > 0.0 or not np.isfinite(root).all():
        return root
    other, ratio = alternative
    step = np.zeros(root.shape[0])
    step[:theta.shape[0]] = other - theta
    if not (np.isfinite(step).all() and math.isfinite(ratio)) or not step.any():
        return root
    statistic = weight * (ratio - 1.0)
    limit = unresolved_limit(theta.shape[0], weighted_square_ratio(weight, forgetting_factor))
    # kappa is in [1, MAX_COLOUR]: the residuals are asked only where it decides
    if statistic > limit and (statistic > MAX_COLOUR * limit
                              or statistic > colour(residuals()) * limit):
        return root
    stacked = np.vstack((root.T, (inverse @ step)[None]))
    return np.linalg.qr(stacked, mode='r').T
