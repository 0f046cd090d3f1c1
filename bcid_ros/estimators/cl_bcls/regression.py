r"""
The model of Ikeda (2008) and its prefiltered regression form; the LS over a record.

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

The module holds the prefilter (:func:`prefilter_polynomial`, eq. 9), the
two forms of theta (eq. 13), the prefiltered LS over a record
(:func:`prefiltered_ls`, eqs. 10-17, 45) and :class:`CompensationFailure`,
which every step of Algorithm 1 raises when it cannot be carried out.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from bcid_ros.estimators.lti import finite_vector
from bcid_ros.estimators.polynomials import is_stable, monic_coefficients


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
    if not is_stable(monic_coefficients(polynomial)):
        raise ValueError(
            f'{name} must have all roots of f(q) strictly inside the unit circle, got roots '
            f'{np.roots(polynomial).round(6).tolist()}')
    return polynomial


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


def definite_inverse(information: np.ndarray, name: str) -> np.ndarray:
    """
    Return the inverse of an information matrix that has a Cholesky factor.

    Raises
    ------
    CompensationFailure
        ``singular_information``, naming the matrix ``name``, if it is not
        positive definite.

    """
    try:
        np.linalg.cholesky(information)
        return np.linalg.inv(information)
    except np.linalg.LinAlgError:
        raise CompensationFailure('singular_information',
                                  f'{name} is not positive definite') from None


def moment_loss(information: np.ndarray, cross: np.ndarray, energy: float,
                theta: np.ndarray) -> float:
    r"""
    Return the residual sum of squares of ``theta`` from the moments M, sum psi y and sum y^2.

    .. math::

        J(\theta) = \sum y^2 - 2\theta^T \sum\psi y + \theta^T M \theta

    is quadratic in an error of theta, where the usual
    :math:`\sum y^2 - \theta^T\sum\psi y` is linear in it: with M ill
    conditioned (the lags of a slowly moving output, cond 1e10 on a 1 kHz
    position loop) theta's rounding error alone made that form cancel to a
    negative loss (clipped to 0: no noise, and every later row refused).
    This form's rounding error is of order eps times the terms (about
    eps sum y^2), and it is the loss of the theta actually used. Floored at 0.
    """
    return max(float(energy - 2.0 * theta.dot(cross) + theta.dot(information.dot(theta))), 0.0)


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
    inverse = definite_inverse(information, "Phi'Phi")
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
