r"""
The bias of the prefiltered LS in the loop: Theorem 1 of Ikeda (2008), eqs. (29)-(57).

The noise reaches the regressor of eq. (14) through the closed loop and the
prefilter. With the realisations of the closed loop (eqs. 8, 31, 32, 54) and
of a_p(q)/f(q) (eq. 33), the augmented system of eqs. (29), (30) has the
state covariance of eq. (36), whose blocks P_12 and P_22 solve the smaller
eqs. (43), (44). They give the bias direction c of
:math:`E\{\varphi\varepsilon\} = c\,\sigma_\nu^2` (eq. 37) and
:math:`\beta` of :math:`E\{\varepsilon^2\} = \beta\,\sigma_\nu^2` (eqs. 48, 57):
:func:`bias_terms`, steps 3 and 4 of Algorithm 1.
"""

from __future__ import annotations

import math

import numpy as np

from bcid_ros.estimators.cl_bcls.regression import CompensationFailure
from bcid_ros.estimators.lti import (closed_loop_polynomial, Controller, controller_canonical,
                                     solve_stein)
from bcid_ros.estimators.polynomials import is_stable, monic_coefficients, spectral_radius


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
    if not is_stable(monic_coefficients(d_cl)):
        raise CompensationFailure('unstable_closed_loop',
                                  f'estimated closed loop has a pole of modulus '
                                  f'{spectral_radius(monic_coefficients(d_cl)):.4g}')
    if not is_stable(monic_coefficients(prefilter)):
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
