r"""
Small discrete-time LTI helpers: polynomials in q, realisations, the Stein equation.

Polynomials are numpy arrays of coefficients in descending powers of the
forward shift q, ``[c_0, c_1, ..., c_k]`` for
:math:`c_0 q^k + c_1 q^{k-1} + \dots + c_k`, the convention of
:mod:`bcid_ros.estimators.polynomials`, which tests their stability. The closed-loop estimator
(:mod:`bcid_ros.estimators.cl_bcls`) and the closed-loop scenario
(:mod:`bcid_ros.simulation.ikeda`) share them.

The feedback convention is the one of Ikeda (2008), eqs. (8), (22), (23) and
(60): negative feedback, :math:`u = (b_c/a_c)(r - y)`. The paper's eq. (4)
prints the opposite sign; docs/papers.md lists that misprint. A controller
given with ``sign='positive'`` is stored as the negative-feedback controller
:math:`-b_c/a_c` (:attr:`Controller.feedback_numerator`).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import scipy.linalg

from bcid_ros.estimators.polynomials import is_stable, monic_coefficients

#: Allowed values of a controller's ``sign``.
CONTROLLER_SIGNS = ('negative', 'positive')


def finite_vector(name: str, value: Any) -> np.ndarray:
    """Return ``value`` as a non-empty 1-D array of finite floats; ValueError names ``name``."""
    try:
        vector = np.atleast_1d(np.asarray(value, dtype=float))
    except (TypeError, ValueError):
        raise ValueError(f'{name} must be a list of finite floats, got {value!r}') from None
    if vector.ndim != 1 or vector.size == 0 or not np.isfinite(vector).all():
        raise ValueError(f'{name} must be a non-empty list of finite floats, got {value!r}')
    return vector


def stable_reflection(polynomial: Any) -> np.ndarray:
    r"""
    Return the polynomial with its roots outside the unit circle mirrored inside.

    Each root p with :math:`|p| > 1` becomes :math:`1/\bar p`, so that
    :math:`a(q)/\bar a(q)` is all-pass. This is :math:`\bar a_p` of Remark 3 of
    Ikeda (2008). A polynomial with no root outside the unit circle is
    returned unchanged (as a copy).

    Parameters
    ----------
    polynomial : array_like, shape ``(k + 1,)``
        Monic, in descending powers.

    Returns
    -------
    numpy.ndarray, shape ``(k + 1,)``
        Monic, in descending powers.

    """
    polynomial = np.asarray(polynomial, dtype=float)
    if is_stable(monic_coefficients(polynomial), 0.0):
        return polynomial.copy()
    roots = np.roots(polynomial)
    outside = np.abs(roots) > 1.0
    if not outside.any():
        return polynomial.copy()
    roots = np.where(outside, 1.0 / np.conj(roots), roots)
    return np.real(np.poly(roots))


def controller_canonical(polynomial: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    r"""
    Return (A, b), the controller canonical form of 1 / d(q).

    For :math:`d(q) = q^k + d_1 q^{k-1} + \dots + d_k` the state
    :math:`X_j[t] = q^{k-j}/d(q)\, w[t]`, j = 1..k, obeys

    .. math::

        X[t+1] = A X[t] + b\, w[t], \qquad
        A = \begin{bmatrix} -d_1 & \cdots & -d_{k-1} & -d_k \\
                            1 & & & 0 \\ & \ddots & & \vdots \\ & & 1 & 0 \end{bmatrix},
        \qquad b = e_1,

    and :math:`C X` realises c(q)/d(q), C listing the coefficients of
    :math:`q^{k-1}, \dots, 1` in c.

    Parameters
    ----------
    polynomial : numpy.ndarray, shape ``(k + 1,)``
        d(q), monic, degree k >= 1.

    Returns
    -------
    A : numpy.ndarray, shape ``(k, k)``
    b : numpy.ndarray, shape ``(k,)``

    Raises
    ------
    ValueError
        If the polynomial is not 1-D, has degree < 1 or is not monic.

    """
    if polynomial.ndim != 1 or polynomial.size < 2 or polynomial[0] != 1.0:
        raise ValueError('polynomial must be monic of degree >= 1 in descending powers of q, '
                         f'got {polynomial.tolist()}')
    size = polynomial.size - 1
    a = np.zeros((size, size))
    a[0, :] = -polynomial[1:]
    a[1:, :-1] = np.eye(size - 1)
    b = np.zeros(size)
    b[0] = 1.0
    return a, b


def solve_stein(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    r"""
    Solve the discrete Sylvester (Stein) equation X = A X B + C.

    With column-major vec, :math:`\operatorname{vec}(AXB) = (B^T \otimes A)
    \operatorname{vec}(X)`, so

    .. math::

        (I - B^T \otimes A)\, \operatorname{vec}(X) = \operatorname{vec}(C),

    solved with :func:`scipy.linalg.solve`. The Kronecker system has
    ``rows * cols`` unknowns: meant for the small sizes of a plant and its
    controller. With ``B = A^T`` this is the discrete Lyapunov equation
    :math:`X = A X A^T + C`.

    Parameters
    ----------
    a : numpy.ndarray, shape ``(r, r)``
        A.
    b : numpy.ndarray, shape ``(c, c)``
        B.
    c : numpy.ndarray, shape ``(r, c)``
        C.

    Returns
    -------
    numpy.ndarray, shape ``(r, c)``

    Raises
    ------
    ValueError
        If the shapes do not match.
    numpy.linalg.LinAlgError
        If the system is singular: an eigenvalue of A times one of B equals 1.

    """
    rows, cols = c.shape
    if a.shape != (rows, rows) or b.shape != (cols, cols):
        raise ValueError(f'solve_stein needs A (r, r), B (c, c) and C (r, c); got A {a.shape}, '
                         f'B {b.shape}, C {c.shape}')
    # (I - B' kron A) vec(X) = vec(C), column-major vec; the Kronecker product
    # is formed as an outer product (np.kron's generality costs more than the solve)
    kron = np.multiply.outer(b.T, a).transpose(0, 2, 1, 3).reshape(rows * cols, rows * cols)
    lhs = np.eye(rows * cols) - kron
    x = scipy.linalg.solve(lhs, c.reshape(-1, order='F'), check_finite=False)
    return x.reshape((rows, cols), order='F')


@dataclasses.dataclass(frozen=True)
class Controller:
    """
    A known linear feedback controller b_c(q)/a_c(q), normalised.

    Attributes
    ----------
    numerator : numpy.ndarray, shape ``(m + 1,)``
        b_c(q) as given, divided by a_c's leading coefficient and left-padded
        with zeros to the length of a_c.
    denominator : numpy.ndarray, shape ``(m + 1,)``
        a_c(q), monic.
    sign : str
        ``'negative'``: u = (b_c/a_c)(r - y); ``'positive'``: u = (b_c/a_c)(y - r).

    """

    numerator: np.ndarray
    denominator: np.ndarray
    sign: str

    @property
    def order(self) -> int:
        """Return m, the degree of a_c."""
        return self.denominator.size - 1

    @property
    def feedback_numerator(self) -> np.ndarray:
        """Return b_c of the negative-feedback form u = (b_c/a_c)(r - y)."""
        return self.numerator if self.sign == 'negative' else -self.numerator


def make_controller(numerator: Any, denominator: Any, sign: str = 'negative') -> Controller:
    """
    Check and normalise a controller given as ROS parameters.

    Parameters
    ----------
    numerator : sequence of float
        ``controller_numerator``: b_c(q), descending powers of q, at most as
        many coefficients as ``denominator`` (a proper controller).
    denominator : sequence of float
        ``controller_denominator``: a_c(q), descending powers of q, first one non-zero.
    sign : str
        ``controller_sign``, one of :data:`CONTROLLER_SIGNS`.

    Returns
    -------
    Controller

    Raises
    ------
    ValueError
        If a polynomial is empty or not finite, a_c's leading coefficient is
        0, the controller is improper (deg b_c > deg a_c) or the sign is
        unknown. The message names the ROS parameter.

    """
    if sign not in CONTROLLER_SIGNS:
        raise ValueError(f'controller_sign must be one of {", ".join(CONTROLLER_SIGNS)}, '
                         f'got {sign!r}')
    den = finite_vector('controller_denominator', denominator)
    num = finite_vector('controller_numerator', numerator)
    if den[0] == 0.0:
        raise ValueError('controller_denominator must have a non-zero first (highest power) '
                         f'coefficient, got {den.tolist()}')
    if num.size > den.size:
        raise ValueError(
            f'controller_numerator must have at most len(controller_denominator) = {den.size} '
            f'coefficients (a proper controller), got {num.size}')
    padded = np.concatenate((np.zeros(den.size - num.size), num)) / den[0]
    return Controller(padded, den / den[0], sign)


def closed_loop_polynomial(a_p: np.ndarray, b_p: np.ndarray, controller: Controller
                           ) -> np.ndarray:
    r"""
    Return the characteristic polynomial of the loop, eq. (8) of Ikeda (2008).

    .. math::

        d_{cl}(q) = a_p(q)\, a_c(q) + b_p(q)\, b_c(q),

    with :math:`b_c` of the negative-feedback form
    (:attr:`Controller.feedback_numerator`).

    Parameters
    ----------
    a_p : numpy.ndarray, shape ``(n + 1,)``
        Plant denominator, monic.
    b_p : numpy.ndarray, shape ``(n,)``
        Plant numerator b_1 ... b_n of a strictly proper plant
        (:math:`b_1 q^{n-1} + \dots + b_n`).
    controller : Controller
        The known controller, a_c(q) of degree m.

    Returns
    -------
    numpy.ndarray, shape ``(n + m + 1,)``
        Monic when a_p and a_c are.

    """
    b_c = controller.feedback_numerator
    return np.convolve(a_p, controller.denominator) + np.convolve(
        np.concatenate(([0.0], b_p)), b_c)
