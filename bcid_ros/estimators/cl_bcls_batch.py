r"""
Batch closed-loop BCLS: Algorithm 1 of Ikeda (2008) and its pieces.

Ikeda (2008), "Bias-compensated least squares method in closed loop
environment", IFAC World Congress. The plant

.. math::

    y[k] = \frac{b_p(q)}{a_p(q)} u[k] + \nu[k], \qquad
    a_p(q) = q^n + a_1 q^{n-1} + \dots + a_n, \quad
    b_p(q) = b_1 q^{n-1} + \dots + b_n                \qquad (1)-(3)

runs under a known linear controller :math:`u = (b_c/a_c)(r - y)` (eqs. 5,
6, 8; see :mod:`bcid_ros.estimators.lti` for the sign), with white
observation noise :math:`\nu` of variance :math:`\sigma_\nu^2` (A3) and no
process noise. With the monic stable prefilter
:math:`f(q) = q^n + f_1 q^{n-1} + \dots + f_n` (eq. 9) the LS regresses
y[k] on the prefiltered signals (eqs. 10-17) with

.. math::

    \theta = [f_1 - a_1, \dots, f_n - a_n \mid b_1, \dots, b_n]^T. \qquad (13)

Published vectors use the plant form ``[a1..an, b1_1..b1_n]``, the
coefficients of a_p and b_p: the paper's plant 0.5/(q - 0.8) is
``a1 = -0.8, b1_1 = 0.5``.

The module holds the prefiltered LS (:func:`prefiltered_ls`), the bias terms
of Theorem 1 (:func:`bias_terms`, eqs. 29-57), the compensation
(:func:`compensated_estimate`, eqs. 56-59) and Algorithm 1 with prefilter
redesign (:func:`closed_loop_bcls`). The online form is
:class:`bcid_ros.estimators.cl_bcls.ClosedLoopBcls`; docs/cl_bcls.md explains
both.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Sequence

import numpy as np

from bcid_ros.estimators.base import check_int, check_range
from bcid_ros.estimators.lti import (closed_loop_polynomial, Controller, controller_canonical,
                                     finite_vector, is_stable, make_controller, solve_stein,
                                     spectral_radius, stable_reflection)

#: Default stopping tolerance on the change of the estimate (the paper's 0.001, section 7.3).
DEFAULT_TOLERANCE = 1e-3


class CompensationFailure(ArithmeticError):
    """
    One step of Algorithm 1 could not be carried out.

    Attributes
    ----------
    flag : str
        The :attr:`~bcid_ros.estimators.base.RecursiveEstimator.flags` key
        that reports it: ``unstable_closed_loop``, ``unstable_prefilter``,
        ``lyapunov_failed``, ``negative_variance_argument`` or
        ``singular_information``.

    """

    def __init__(self, flag: str, message: str) -> None:
        super().__init__(message)
        self.flag = flag


def prefilter_polynomial(prefilter: Any, order: int, name: str = 'prefilter_initial'
                         ) -> np.ndarray:
    """
    Return the monic prefilter f(q) of eq. (9) from a pole or a coefficient list.

    Parameters
    ----------
    prefilter : float or sequence of float
        Either one pole p (a float or a one-element list): f(q) = (q - p)^n,
        so the paper's "f = 0.5" is ``0.5``; or the n + 1 coefficients of
        f(q) in descending powers of q, ``[1, f_1, ..., f_n]`` (scaled to
        monic if the first is not 1).
    order : int
        n.
    name : str
        Argument name for the error message.

    Returns
    -------
    numpy.ndarray, shape ``(n + 1,)``
        ``[1, f_1, ..., f_n]``.

    Raises
    ------
    ValueError
        If the value has the wrong length, is not finite, or f(q) has a root
        on or outside the unit circle (the prefilter 1/f must be stable).

    """
    values = finite_vector(name, prefilter)
    if values.size == 1:
        polynomial = np.real(np.poly(np.full(order, values[0])))
    elif values.size == order + 1 and values[0] != 0.0:
        polynomial = values / values[0]
    else:
        raise ValueError(
            f'{name} must be a pole (one float) or the n + 1 = {order + 1} coefficients of '
            f'f(q) in descending powers of q with a non-zero first one, got {values.tolist()}')
    if not is_stable(polynomial):
        raise ValueError(
            f'{name} must have all roots of f(q) strictly inside the unit circle, got roots '
            f'{np.roots(polynomial).round(6).tolist()}')
    return polynomial


# ------------------------------------------------------- realisations (29)-(54)
def closed_loop_realisation(a_p: np.ndarray, b_p: np.ndarray, controller: Controller
                            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    r"""
    Return d_cl and (A_cl, b_cl, C_cl) of eqs. (8), (31), (32) and (54).

    :math:`(A_{cl}, b_{cl})` is the controller canonical form of
    :math:`1/d_{cl}` and :math:`C_{cl}` maps its state to the lagged
    :math:`[y \mid u]` noise responses:

    .. math::

        C_{cl} = \begin{bmatrix} \text{rows of } q^{n-1-i} a_c(q) \\
                                 \text{rows of } -q^{n-1-i} b_c(q) \end{bmatrix},
        \quad i = 0, \dots, n - 1. \qquad (54)

    Parameters
    ----------
    a_p : numpy.ndarray, shape ``(n + 1,)``
        Monic plant denominator.
    b_p : numpy.ndarray, shape ``(n,)``
        Plant numerator coefficients b_1 ... b_n.
    controller : Controller
        The known controller (its sign folded into the numerator).

    Returns
    -------
    d_cl : numpy.ndarray, shape ``(n + m + 1,)``
        a_p a_c + b_p b_c (eq. 8, negative-feedback form).
    A_cl : numpy.ndarray, shape ``(n + m, n + m)``
    b_cl : numpy.ndarray, shape ``(n + m,)``
    C_cl : numpy.ndarray, shape ``(2n, n + m)``

    """
    n = a_p.size - 1
    a_c = controller.denominator
    b_c = controller.feedback_numerator
    m = a_c.size - 1
    # d_cl(q) = a_p(q) a_c(q) + b_p(q) b_c(q)                               (8)
    d_cl = closed_loop_polynomial(a_p, b_p, controller)
    a_cl, b_cl = controller_canonical(d_cl)
    c_cl = np.zeros((2 * n, n + m))
    for i in range(n):
        # row i: coefficients of q^(n-1-i) a_c(q); row n+i: of -q^(n-1-i) b_c(q)   (54)
        c_cl[i, i:i + m + 1] = a_c
        c_cl[n + i, i:i + m + 1] = -b_c
    return d_cl, a_cl, b_cl, c_cl


def prefilter_realisation(prefilter: np.ndarray, a_p: np.ndarray
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """
    Return (F, g, h) with (F, g, h, 1) realising a_p(q)/f(q), eq. (33).

    In controller canonical form h is the coefficient vector of a_p - f
    (Remark 2), i.e. h = -theta_1.

    Returns
    -------
    F : numpy.ndarray, shape ``(n, n)``
    g : numpy.ndarray, shape ``(n,)``
    h : numpy.ndarray, shape ``(n,)``

    """
    f_matrix, g = controller_canonical(prefilter)
    return f_matrix, g, a_p[1:] - prefilter[1:]


def solve_p22(f_matrix: np.ndarray, g: np.ndarray) -> np.ndarray:
    r"""
    Solve eq. (44), :math:`P_{22} = F P_{22} F^T + g g^T`, a Lyapunov equation.

    Solved as the Stein equation of :func:`~bcid_ros.estimators.lti.solve_stein`.
    """
    return solve_stein(f_matrix, f_matrix.T, np.outer(g, g))


def solve_p12(a_cl: np.ndarray, b_cl: np.ndarray, f_matrix: np.ndarray, g: np.ndarray,
              h: np.ndarray, p22: np.ndarray) -> np.ndarray:
    r"""
    Solve eq. (43), a Sylvester equation (Remark 4).

    .. math::

        P_{12} = A_{cl} P_{12} F^T + b_{cl} h P_{22} F^T + b_{cl} g^T. \qquad (43)
    """
    constant = np.outer(b_cl, h @ p22 @ f_matrix.T) + np.outer(b_cl, g)
    return solve_stein(a_cl, f_matrix.T, constant)


def augmented_system(a_cl: np.ndarray, b_cl: np.ndarray, f_matrix: np.ndarray,
                     g: np.ndarray, h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    r"""
    Return :math:`(\bar A, \bar b)` of eqs. (29) and (30).

    .. math::

        \bar A = \begin{bmatrix} A_{cl} & b_{cl} h \\ 0 & F \end{bmatrix}, \qquad
        \bar b = \begin{bmatrix} b_{cl} \\ g \end{bmatrix}.
    """
    k, n = a_cl.shape[0], f_matrix.shape[0]
    a_bar = np.zeros((k + n, k + n))
    a_bar[:k, :k] = a_cl
    a_bar[:k, k:] = np.outer(b_cl, h)
    a_bar[k:, k:] = f_matrix
    return a_bar, np.concatenate((b_cl, g))


def noise_state_covariance(a_cl: np.ndarray, b_cl: np.ndarray, f_matrix: np.ndarray,
                           g: np.ndarray, h: np.ndarray) -> np.ndarray:
    r"""
    Solve eq. (36), :math:`P = \bar A P \bar A^T + \bar b \bar b^T`, in one piece.

    Uses :func:`scipy.linalg.solve_discrete_lyapunov`. Its blocks are
    :math:`P_{12}` and :math:`P_{22}` of eqs. (43) and (44); the estimator
    solves those smaller equations instead, and the tests check the two agree.
    """
    import scipy.linalg

    a_bar, b_bar = augmented_system(a_cl, b_cl, f_matrix, g, h)
    return scipy.linalg.solve_discrete_lyapunov(a_bar, np.outer(b_bar, b_bar))


# ---------------------------------------------------------- the LS (10)-(17)
@dataclasses.dataclass(frozen=True)
class PrefilteredLs:
    """
    The prefiltered LS solution of eqs. (10)-(17) and (53) over a data record.

    Attributes
    ----------
    theta : numpy.ndarray, shape ``(2n,)``
        theta_LS in the regression form [f - a | b] (eq. 17).
    information : numpy.ndarray, shape ``(2n, 2n)``
        Phi' Phi.
    information_inverse : numpy.ndarray, shape ``(2n, 2n)``
        (Phi' Phi)^-1.
    loss : float
        e' e, the residual sum of squares (eqs. 45, 46).
    count : int
        N, the number of regression rows (samples n .. end of the record).
    next_regressor : numpy.ndarray, shape ``(2n,)``
        phi of the sample right after the record, for an online continuation.

    """

    theta: np.ndarray
    information: np.ndarray
    information_inverse: np.ndarray
    loss: float
    count: int
    next_regressor: np.ndarray


def prefiltered_regression(y: np.ndarray, u: np.ndarray, prefilter: np.ndarray
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    r"""
    Return (Phi, target, next phi) of eqs. (10), (14), (18) and (19).

    .. math::

        y_f[k] = \frac{q^n}{f(q)} y[k], \quad u_f[k] = \frac{q^n}{f(q)} u[k], \qquad (10)

        \varphi[k] = [y_f[k-1], \dots, y_f[k-n], u_f[k-1], \dots, u_f[k-n]]^T. \qquad (14)

    The filters start from rest at the first sample. Row j of Phi is
    :math:`\varphi[n + j]^T` and the target is y[n + j]: only rows whose lags
    all lie in the record are used.
    """
    from scipy import signal

    n = prefilter.size - 1
    count = y.shape[0]
    # y_f = q^n/f(q) y, u_f = q^n/f(q) u (both columns in one call)          (10)
    filtered = signal.lfilter([1.0], prefilter, np.column_stack((y, u)), axis=0)
    # phi[k] = [y_f[k-1..k-n], u_f[k-1..k-n]]                                (14)
    if n == 1:
        phi = filtered[:-1]
    else:
        phi = np.empty((count - n, 2 * n))
        for k in range(1, n + 1):
            phi[:, k - 1] = filtered[n - k:count - k, 0]
            phi[:, n + k - 1] = filtered[n - k:count - k, 1]
    next_phi = np.concatenate((filtered[::-1][:n, 0], filtered[::-1][:n, 1]))
    return phi, y[n:], next_phi


def prefiltered_ls(y: np.ndarray, u: np.ndarray, prefilter: np.ndarray) -> PrefilteredLs:
    r"""
    Solve the prefiltered LS problem over a record, eqs. (16), (17) and (45).

    .. math::

        \hat\theta_{LS} = (\Phi^T \Phi)^{-1} \Phi^T y, \qquad
        e = y - \Phi \hat\theta_{LS}.

    Raises
    ------
    CompensationFailure
        ``singular_information`` if :math:`\Phi^T\Phi` is not positive definite.

    """
    phi, target, next_phi = prefiltered_regression(y, u, prefilter)
    information = phi.T @ phi
    try:
        np.linalg.cholesky(information)
        inverse = np.linalg.inv(information)
    except np.linalg.LinAlgError:
        raise CompensationFailure('singular_information',
                                  'Phi\'Phi is not positive definite') from None
    # theta_LS = (Phi' Phi)^-1 Phi' y                                        (17)
    theta = np.linalg.solve(information, phi.T @ target)
    # e = y - Phi theta_LS                                                   (45)
    residual = target - phi @ theta
    if not (np.isfinite(theta).all() and np.isfinite(inverse).all()):
        raise CompensationFailure('singular_information', 'the LS solution is not finite')
    return PrefilteredLs(theta, information, inverse, float(residual @ residual),
                         target.shape[0], next_phi)


def plant_from_regression(theta: np.ndarray, prefilter: np.ndarray) -> np.ndarray:
    """Return [a_1..a_n, b_1..b_n] from the regression form [f - a | b] (eq. 13)."""
    n = prefilter.size - 1
    return np.concatenate((prefilter[1:] - theta[:n], theta[n:]))


def regression_from_plant(theta_plant: np.ndarray, prefilter: np.ndarray) -> np.ndarray:
    """Return the regression form [f - a | b] (eq. 13) of a plant vector [a | b]."""
    n = prefilter.size - 1
    return np.concatenate((prefilter[1:] - theta_plant[:n], theta_plant[n:]))


# ------------------------------------------------ the compensation (37)-(59)
def bias_terms(theta_plant: np.ndarray, prefilter: np.ndarray, controller: Controller
               ) -> tuple[np.ndarray, float]:
    r"""
    Return the bias direction c and beta of Theorem 1 (steps 3 and 4 of Algorithm 1).

    For the plant ``theta_plant`` = [a | b] under ``controller`` with
    prefilter f, with the realisations of :func:`closed_loop_realisation` and
    :func:`prefilter_realisation`:

    .. math::

        E\{\varphi[k]\varepsilon[k]\} &= c\, \sigma_\nu^2, &
        c &= C_{cl} P_{12} h^T, && (37) \\
        E\{\varepsilon[k]^2\} &= \beta\, \sigma_\nu^2, &
        \beta &= 1 + h P_{22} h^T, && (48), (57)

    with :math:`P_{22}` from eq. (44) and :math:`P_{12}` from eq. (43).

    Raises
    ------
    CompensationFailure
        ``unstable_closed_loop`` if d_cl has a root on or outside the unit
        circle (the Lyapunov solution would be meaningless),
        ``unstable_prefilter`` if f does, ``lyapunov_failed`` if a solve fails
        or gives non-finite values.

    """
    n = prefilter.size - 1
    a_p = np.concatenate(([1.0], theta_plant[:n]))
    d_cl, a_cl, b_cl, c_cl = closed_loop_realisation(a_p, theta_plant[n:], controller)
    if not is_stable(d_cl):
        raise CompensationFailure('unstable_closed_loop',
                                  f'estimated closed loop has a pole of modulus '
                                  f'{spectral_radius(d_cl):.4g}')
    if not is_stable(prefilter):
        raise CompensationFailure('unstable_prefilter', 'prefilter f(q) is not stable')
    f_matrix, g, h = prefilter_realisation(prefilter, a_p)
    try:
        # P22 = F P22 F' + g g'                                              (44)
        p22 = solve_p22(f_matrix, g)
        # P12 = A_cl P12 F' + b_cl h P22 F' + b_cl g'                        (43)
        p12 = solve_p12(a_cl, b_cl, f_matrix, g, h, p22)
    except (np.linalg.LinAlgError, ValueError) as error:
        raise CompensationFailure('lyapunov_failed', str(error)) from None
    # c = C_cl P12 h'                                                        (37)
    direction = c_cl @ (p12 @ h)
    # beta = 1 + h P22 h'                                                    (52), (57)
    beta = 1.0 + float(h @ p22 @ h)
    if not (np.isfinite(direction).all() and math.isfinite(beta)):
        raise CompensationFailure('lyapunov_failed', 'Lyapunov/Sylvester solution not finite')
    return direction, beta


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


# ----------------------------------------------------- Algorithm 1 (batch)
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
    order = check_int('order', order, 1)
    max_iterations = check_int('max_iterations', max_iterations, 1)
    tolerance = check_range('tolerance', tolerance, 0.0, math.inf, low_open=True)
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
        stable_next = is_stable(next_prefilter)
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
