r"""
Batch closed-loop BCLS: the compensation (eqs. 53-59) and Algorithm 1 of Ikeda (2008).

Algorithm 1 iterates on a data record: the prefiltered LS (step 2,
:func:`~bcid_ros.estimators.cl_bcls.regression.prefiltered_ls`), the bias
terms of Theorem 1 (steps 3, 4,
:func:`~bcid_ros.estimators.cl_bcls.bias.bias_terms`), the compensation
(step 5, :func:`compensated_estimate`, eqs. 53, 56, 58, 59) and the
prefilter redesign from the compensated estimate (steps 6, 7, Remark 3).
:func:`closed_loop_bcls` is the entry point; the online
:class:`~bcid_ros.estimators.cl_bcls.online.ClosedLoopBcls` runs
:func:`algorithm1` on a window of samples. docs/cl_bcls.md explains both.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Sequence

import numpy as np

from bcid_ros.estimators.cl_bcls.bias import bias_terms
from bcid_ros.estimators.cl_bcls.regression import (CompensationFailure, plant_from_regression,
                                                    prefilter_polynomial, PrefilteredLs,
                                                    prefiltered_ls)
from bcid_ros.estimators.lti import Controller, make_controller, stable_reflection
from bcid_ros.estimators.polynomials import is_stable, monic_coefficients
from bcid_ros.estimators.settings import CL_BCLS_OPTIONS, option, SHARED_SETTINGS

#: Default stopping tolerance on the change of the estimate (the paper's 0.001, section 7.3).
DEFAULT_TOLERANCE = 1e-3


def compensated_estimate(ls: PrefilteredLs, direction: np.ndarray, beta: float
                         ) -> tuple[np.ndarray, float]:
    r"""
    Apply eqs. (53), (56), (58) and (59) to an LS solution; return (theta_BC, sigma2).

    .. math::

        \gamma &= e^T e / N, \qquad \alpha = N c^T (\Phi^T\Phi)^{-1} c,
            && (53), (56) \\
        \hat\sigma_\nu^2 &= \frac{2\gamma}{\beta + \sqrt{\beta^2 - 4\alpha\gamma}},
            && (58) \\
        \hat\theta_{BC} &= \hat\theta_{LS} - N \hat\sigma_\nu^2 (\Phi^T\Phi)^{-1} c.
            && (59)

    theta_BC is in the regression form [f - a | b].

    Raises
    ------
    CompensationFailure
        ``negative_variance_argument`` if :math:`\beta^2 - 4\alpha\gamma < 0` in (58).

    """
    count = float(ls.count)
    pc = ls.information_inverse @ direction
    # gamma = e'e / N                                                        (53)
    gamma = ls.loss / count
    # alpha = N c' (Phi'Phi)^-1 c                                            (51), (56)
    alpha = count * float(direction @ pc)
    discriminant = beta * beta - 4.0 * alpha * gamma
    if not discriminant >= 0.0:
        raise CompensationFailure('negative_variance_argument',
                                  f'beta^2 - 4 alpha gamma = {discriminant:.4g} < 0 in eq. (58)')
    # sigma2 = 2 gamma / (beta + sqrt(beta^2 - 4 alpha gamma))               (58)
    sigma2 = 2.0 * gamma / (beta + math.sqrt(discriminant))
    # theta_BC = theta_LS - N (Phi'Phi)^-1 c sigma2                          (59)
    return ls.theta - (count * sigma2) * pc, sigma2


@dataclasses.dataclass(frozen=True)
class ClosedLoopResult:
    """
    The outcome of :func:`closed_loop_bcls`.

    Attributes
    ----------
    theta : numpy.ndarray, shape ``(2n,)``
        Final estimate [a_1..a_n, b_1..b_n] (compensated when
        ``bias_compensation``, else the LS estimate of the last iteration).
    theta_ls : numpy.ndarray, shape ``(2n,)``
        The LS estimate of the last iteration, same form.
    sigma2 : float or None
        sigma_nu^2 of eq. (58) of the last iteration (None without compensation).
    prefilter : numpy.ndarray, shape ``(n + 1,)``
        f(q) of the last iteration's LS.
    next_prefilter : numpy.ndarray, shape ``(n + 1,)``
        f(q) redesigned from ``theta`` (step 7), equal to ``prefilter`` if the
        redesign was refused.
    iterations : int
        Number of LS solves (iterations of steps 2-7) carried out and accepted.
    converged : bool
        Whether the last change of the estimate was below the tolerance.
    failure : str or None
        Flag of the failure that stopped the iteration early, if any.
    ls : PrefilteredLs
        The last iteration's LS solution (regression form).
    direction : numpy.ndarray or None
        c = C_cl P12 h' of the last iteration.
    beta : float or None
        1 + h P22 h' of the last iteration.
    history : tuple of numpy.ndarray
        ``theta`` after each iteration.

    """

    theta: np.ndarray
    theta_ls: np.ndarray
    sigma2: float | None
    prefilter: np.ndarray
    next_prefilter: np.ndarray
    iterations: int
    converged: bool
    failure: str | None
    ls: PrefilteredLs
    direction: np.ndarray | None
    beta: float | None
    history: tuple[np.ndarray, ...]


def is_contracting(history: Sequence[np.ndarray]) -> bool:
    r"""
    Return whether a fixed-point iteration's last step is shorter than its first.

    With the steps :math:`s_i = \|\theta^{(i)} - \theta^{(i-1)}\|` of the
    plant-form iterates [a | b], this is :math:`s_{last} < s_1`. A linearly
    converging iteration with factor :math:`\rho < 1` passes; False means the
    iteration drifted instead of converging. Fewer than three iterates
    (two steps) give True.

    Parameters
    ----------
    history : sequence of numpy.ndarray
        The iterates, as :attr:`ClosedLoopResult.history`.

    """
    if len(history) < 3:
        return True
    first = float(np.linalg.norm(history[1] - history[0]))
    last = float(np.linalg.norm(history[-1] - history[-2]))
    return last < first


def closed_loop_bcls(y: Any, u: Any, *, order: int, controller_numerator: Any,
                     controller_denominator: Any, controller_sign: str = 'negative',
                     prefilter_initial: Any = 0.0, max_iterations: int = 50,
                     tolerance: float = DEFAULT_TOLERANCE,
                     bias_compensation: bool = True) -> ClosedLoopResult:
    r"""
    Run Algorithm 1 of Ikeda (2008): prefilter redesign with BCLS at each iteration.

    For i = 0, 1, ...:

    2. LS on the data prefiltered by :math:`f^{(i)}` (eqs. 10-17) and
       :math:`\gamma` (eq. 53), :func:`prefiltered_ls`;
    3. :math:`A_{cl}, h, \bar A` from :math:`\hat\theta_{LS}^{(i)}` (eqs. 29-33, 54);
    4. :math:`P_{12}, P_{22}` from eqs. (43), (44) (equivalent to eq. 55),
       :math:`\alpha, \beta` (eqs. 56, 57), :func:`bias_terms`;
    5. :math:`\hat\sigma_\nu^2` from eq. (58) and :math:`\hat\theta_{BC}^{(i)}`
       from eq. (59), :func:`compensated_estimate`;
    6. and 7. :math:`f^{(i+1)} = \hat a_p^{(i)}` with the roots outside the
       unit circle mirrored (Remark 3, :func:`~bcid_ros.estimators.lti.stable_reflection`).

    The iteration stops when the estimate in the regression form of eq. (13),
    :math:`[f^{(i)} - a^{(i)} \mid b^{(i)}]`, moves by less than ``tolerance``
    (2-norm) from one iteration to the next ("the norm of the parameter
    improvement", section 7.3), or after ``max_iterations`` LS solves.
    Without ``bias_compensation`` steps 3-5 are skipped (the plain iterative
    prefilter redesign of section 7.3).

    If a step fails after the first iteration, the last good iterate is
    returned with ``failure`` set; if it fails in the first iteration the
    failure is raised. A redesigned prefilter that is not stable stops the
    iteration with ``failure = 'unstable_prefilter'``.

    Parameters
    ----------
    y, u : array_like, shape ``(N,)``
        Measured output and input of the plant in the loop.
    order : int
        n.
    controller_numerator, controller_denominator, controller_sign
        See :func:`~bcid_ros.estimators.lti.make_controller`.
    prefilter_initial : float or sequence of float
        :math:`f^{(0)}`, see :func:`prefilter_polynomial`; 0 gives
        :math:`f = q^n` (step 1).
    max_iterations : int
        Cap on the LS solves.
    tolerance : float
        Stopping threshold on the change of the estimate in the form of eq. (13).
    bias_compensation : bool
        Apply steps 3-5 (the proposed method) or not.

    Returns
    -------
    ClosedLoopResult

    Raises
    ------
    ValueError
        On bad arguments; the message names the argument.
    CompensationFailure
        If the first iteration cannot be carried out.

    """
    order = SHARED_SETTINGS['order'].check_argument(order)
    max_iterations = option(CL_BCLS_OPTIONS, 'max_iterations').check_argument(max_iterations)
    tolerance = option(CL_BCLS_OPTIONS, 'tolerance').check_argument(tolerance)
    controller = make_controller(controller_numerator, controller_denominator, controller_sign)
    prefilter = prefilter_polynomial(prefilter_initial, order)
    y = np.asarray(y, dtype=float).reshape(-1)
    u = np.asarray(u, dtype=float).reshape(-1)
    if u.shape != y.shape:
        raise ValueError(f'u must have as many samples as y ({y.size}), got {u.size}')
    return algorithm1(y, u, controller, prefilter, max_iterations, tolerance, bias_compensation)


def algorithm1(y: np.ndarray, u: np.ndarray, controller: Controller, prefilter: np.ndarray,
               max_iterations: int, tolerance: float, bias_compensation: bool = True
               ) -> ClosedLoopResult:
    """
    Run :func:`closed_loop_bcls` on checked arguments.

    ``y`` and ``u`` are float arrays of one length, ``controller`` comes from
    :func:`~bcid_ros.estimators.lti.make_controller` and ``prefilter`` from
    :func:`prefilter_polynomial`.
    """
    history: list[np.ndarray] = []
    previous = None
    last = None
    failure = None
    converged = False
    for _ in range(max_iterations):
        try:
            # step (2): prefiltered LS with f^(i)                           (10)-(17)
            ls = prefiltered_ls(y, u, prefilter)
            theta_ls = plant_from_regression(ls.theta, prefilter)
            direction, beta, sigma2 = None, None, None
            theta_regression, theta = ls.theta, theta_ls
            if bias_compensation:
                # steps (3), (4): realisation from theta_LS, P12, P22, beta   (29)-(57)
                direction, beta = bias_terms(theta_ls, prefilter, controller)
                # step (5): sigma^2 and theta_BC                            (58), (59)
                theta_regression, sigma2 = compensated_estimate(ls, direction, beta)
                theta = plant_from_regression(theta_regression, prefilter)
                if not np.isfinite(theta).all():
                    raise CompensationFailure('lyapunov_failed', 'compensated estimate '
                                              'is not finite')
        except CompensationFailure as error:
            if last is None:
                raise
            failure = error.flag
            break
        # steps (6), (7): f^(i+1) = â_p^(i), unstable roots mirrored (Remark 3)
        next_prefilter = stable_reflection(np.concatenate(([1.0], theta[:prefilter.size - 1])))
        stable_next = is_stable(monic_coefficients(next_prefilter))
        last = (theta, theta_ls, sigma2, prefilter, next_prefilter if stable_next else prefilter,
                ls, direction, beta)
        history.append(theta)
        # stop when ||theta^(i) - theta^(i-1)|| < tolerance, theta as in eq. (13)
        if previous is not None and np.linalg.norm(theta_regression - previous) < tolerance:
            converged = True
            break
        previous = theta_regression
        if not stable_next:
            failure = 'unstable_prefilter'
            break
        prefilter = next_prefilter
    theta, theta_ls, sigma2, used, redesigned, ls, direction, beta = last
    return ClosedLoopResult(theta, theta_ls, sigma2, used, redesigned, len(history), converged,
                            failure, ls, direction, beta, tuple(history))
