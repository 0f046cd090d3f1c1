r"""
Closed-loop bias-compensated least squares with iterative prefilter redesign.

Ikeda (2008), "Bias-compensated least squares method in closed loop
environment", IFAC World Congress. The plant

.. math::

    y[k] = \frac{b_p(q)}{a_p(q)} u[k] + \nu[k], \qquad
    a_p(q) = q^n + a_1 q^{n-1} + \dots + a_n, \quad
    b_p(q) = b_1 q^{n-1} + \dots + b_n          \qquad (1)-(3)

runs under a known linear controller with white observation noise
:math:`\nu` of variance :math:`\sigma_\nu^2` (no process noise). The
module holds

* the pieces of the paper's Algorithm 1 as functions: the prefiltered LS
  (eqs. 10-17), the closed-loop realisation (eqs. 8, 29-33, 54), the Lyapunov
  and Sylvester equations (eqs. 36, 43, 44, solved with :mod:`scipy.linalg`),
  the noise variance (eqs. 50-53, 58) and the compensated estimate (eq. 59);
* :func:`closed_loop_bcls`, the batch Algorithm 1 with prefilter redesign
  (Remark 3 for unstable plant estimates);
* :class:`ClosedLoopBcls`, the per-sample (online) form the identifier node runs.

**Sign convention.** Eq. (4) prints u = (b_c/a_c)(y - r), but eqs. (8),
(22), (23) and the example (60) all use negative feedback (PAPER_NOTES.md).
``controller_sign='negative'`` (the default) means u = (b_c/a_c)(r - y);
``'positive'`` means u = (b_c/a_c)(y - r). Internally a positive-feedback
controller is the negative-feedback controller -b_c/a_c, so everything
below is written for u = (b_c/a_c)(r - y) and d_cl = a_p a_c + b_p b_c.

**Parametrisation.** With the prefilter f(q) = q^n + f_1 q^{n-1} + ... + f_n
(monic, stable), the regression vector is theta = [f_1 - a_1, ..., f_n - a_n |
b_1, ..., b_n] (eq. 13). Published vectors use the base naming
``a1..an, b1_1..b1_n`` with a_i the coefficients of a_p(q), so the paper's
plant 0.5/(q - 0.8) is ``a1 = -0.8, b1_1 = 0.5``.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Sequence

import numpy as np
import scipy.linalg
from scipy import signal

from bcid_ros.estimators.base import check_int, check_range, RecursiveEstimator

#: A polynomial counts as stable when all its roots have modulus below 1 - this.
STABILITY_MARGIN = 1e-6
#: Default cap on the redesign window (samples); the paper's N.
DEFAULT_WINDOW = 4096
#: Default number of samples between two compensations + prefilter redesigns.
DEFAULT_REDESIGN_PERIOD = 1000
#: Default cap on the prefilter iterations of one redesign.
DEFAULT_MAX_ITERATIONS = 20
#: Default stopping tolerance on the change of the plant estimate (the paper's 0.001).
DEFAULT_TOLERANCE = 1e-3
#: Allowed values of ``controller_sign``.
CONTROLLER_SIGNS = ('negative', 'positive')
#: Regression rows per parameter that the window must hold before a redesign.
ROWS_PER_PARAMETER = 10
#: The first redesign waits for ``window // FIRST_WINDOW_DIVISOR`` samples: its estimate
#: then has at most about twice the variance of a full-window one, and Algorithm 1 is
#: not started from a window too short to hold a fixed point near the plant (see
#: :class:`ClosedLoopBcls`, Safety).
FIRST_WINDOW_DIVISOR = 2


class CompensationFailure(ArithmeticError):
    """
    One step of Algorithm 1 could not be carried out.

    Attributes
    ----------
    flag : str
        The :attr:`ClosedLoopBcls.flags` key that reports it:
        ``unstable_closed_loop``, ``unstable_prefilter``, ``lyapunov_failed``,
        ``negative_variance_argument`` or ``singular_information``.

    """

    def __init__(self, flag: str, message: str) -> None:
        super().__init__(message)
        self.flag = flag


# --------------------------------------------------------------- polynomials
def _finite_vector(name: str, value: Any) -> np.ndarray:
    try:
        vector = np.atleast_1d(np.asarray(value, dtype=float))
    except (TypeError, ValueError):
        raise ValueError(f'{name} must be a list of finite floats, got {value!r}') from None
    if vector.ndim != 1 or vector.size == 0 or not np.isfinite(vector).all():
        raise ValueError(f'{name} must be a non-empty list of finite floats, got {value!r}')
    return vector


def spectral_radius(polynomial: np.ndarray) -> float:
    """Return the largest root modulus of a polynomial in descending powers (0 if constant)."""
    polynomial = np.trim_zeros(np.asarray(polynomial, dtype=float), 'f')
    if polynomial.size <= 1:
        return 0.0
    return float(np.abs(np.roots(polynomial)).max())


def is_stable(polynomial: np.ndarray, margin: float = STABILITY_MARGIN) -> bool:
    """
    Return whether all roots lie inside the circle of radius 1 - ``margin``.

    Uses the Schur-Cohn step-down recursion on the polynomial with its roots
    scaled by 1/(1 - margin): the roots are inside the unit circle if and
    only if every reflection coefficient has modulus below 1. Exact in
    floating point terms for the small degrees here, and far cheaper than
    computing the roots.

    Parameters
    ----------
    polynomial : array_like, shape ``(k + 1,)``
        Coefficients in descending powers, first one non-zero.
    margin : float
        Required distance of the roots from the unit circle.

    """
    coefficients = [float(c) for c in polynomial]
    while coefficients and coefficients[0] == 0.0:
        coefficients.pop(0)
    if not coefficients:
        return False
    radius = 1.0 - margin
    lead = coefficients[0]
    # monic p(radius z) / radius^k: coefficient i becomes c_i / (c_0 radius^i)
    a = [c / (lead * radius ** i) for i, c in enumerate(coefficients)]
    for j in range(len(a) - 1, 0, -1):
        k = a[j]
        if not abs(k) < 1.0:
            return False
        scale = 1.0 / (1.0 - k * k)
        a = [(a[i] - k * a[j - i]) * scale for i in range(j)]
    return True


def stable_reflection(a_p: np.ndarray) -> np.ndarray:
    """
    Return the monic polynomial ā_p of Remark 3: roots outside the unit circle mirrored.

    Each root p with ``|p| > 1`` is replaced by ``1 / conj(p)``, so that
    a_p / ā_p is all-pass (an inner function up to a constant). For a stable
    a_p this returns a_p itself.

    Parameters
    ----------
    a_p : numpy.ndarray, shape ``(n + 1,)``
        Monic polynomial in descending powers of q.

    Returns
    -------
    numpy.ndarray, shape ``(n + 1,)``

    """
    a_p = np.asarray(a_p, dtype=float)
    if is_stable(a_p, 0.0):
        return a_p.copy()
    roots = np.roots(a_p)
    outside = np.abs(roots) > 1.0
    if not outside.any():
        return a_p.copy()
    roots = np.where(outside, 1.0 / np.conj(roots), roots)
    return np.real(np.poly(roots))


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
    values = _finite_vector(name, prefilter)
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


def controller_canonical(polynomial: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """
    Return (A, b), the controller canonical form of 1 / polynomial.

    For ``polynomial = [1, d_1, ..., d_k]`` the state X[j] = q^(k-j)/d(q) w,
    j = 1..k, obeys X[k+1] = A X[k] + b w[k] with A's first row
    ``[-d_1, ..., -d_k]``, ones on the sub-diagonal and b = e_1. An output
    C X realises c(q)/d(q) where C lists c's coefficients of q^(k-1) ... 1.

    Returns
    -------
    A : numpy.ndarray, shape ``(k, k)``
    b : numpy.ndarray, shape ``(k,)``

    """
    size = polynomial.size - 1
    a = np.zeros((size, size))
    a[0, :] = -polynomial[1:]
    a[1:, :-1] = np.eye(size - 1)
    b = np.zeros(size)
    b[0] = 1.0
    return a, b


@dataclasses.dataclass(frozen=True)
class Controller:
    """
    The known feedback controller, normalised.

    Attributes
    ----------
    numerator : numpy.ndarray, shape ``(m + 1,)``
        b_c(q) as given (scaled by a_c's leading coefficient, left-padded with zeros).
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
        """Return b_c for the negative-feedback form u = (b_c/a_c)(r - y) of eq. (60)."""
        return self.numerator if self.sign == 'negative' else -self.numerator


def make_controller(numerator: Any, denominator: Any, sign: str = 'negative') -> Controller:
    """
    Check and normalise the controller parameters (ROS names in the messages).

    Raises
    ------
    ValueError
        If a polynomial is empty or not finite, a_c's leading coefficient is
        0, the controller is improper (deg b_c > deg a_c) or the sign is unknown.

    """
    if sign not in CONTROLLER_SIGNS:
        raise ValueError(f'controller_sign must be one of {", ".join(CONTROLLER_SIGNS)}, '
                         f'got {sign!r}')
    den = _finite_vector('controller_denominator', denominator)
    num = _finite_vector('controller_numerator', numerator)
    if den[0] == 0.0:
        raise ValueError('controller_denominator must have a non-zero first (highest power) '
                         f'coefficient, got {den.tolist()}')
    if num.size > den.size:
        raise ValueError(
            f'controller_numerator must have at most len(controller_denominator) = {den.size} '
            f'coefficients (a proper controller), got {num.size}')
    padded = np.concatenate((np.zeros(den.size - num.size), num)) / den[0]
    return Controller(padded, den / den[0], sign)


# ------------------------------------------------------- realisations (31)-(54)
def closed_loop_realisation(a_p: np.ndarray, b_p: np.ndarray, controller: Controller
                            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """
    Return d_cl and (A_cl, b_cl, C_cl) of eqs. (8), (31), (32) and (54).

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
        Eq. (54): shifted rows of a_c and of -b_c.

    """
    n = a_p.size - 1
    a_c = controller.denominator
    b_c = controller.feedback_numerator
    m = a_c.size - 1
    # d_cl(q) = a_p(q) a_c(q) + b_p(q) b_c(q)                               (8)
    d_cl = np.convolve(a_p, a_c) + np.convolve(np.concatenate(([0.0], b_p)), b_c)
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


def solve_stein(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """
    Solve the discrete Sylvester (Stein) equation X = A X B + C with scipy.linalg.

    Uses vec(A X B) = (B^T kron A) vec(X) and :func:`scipy.linalg.solve`; the
    sizes here are (n + m) n, so the Kronecker system is small.

    Raises
    ------
    numpy.linalg.LinAlgError
        If the system is singular (A and B have eigenvalues with product 1).

    """
    rows, cols = c.shape
    # (I - B' kron A) vec(X) = vec(C), column-major vec; the Kronecker product
    # is formed as an outer product (np.kron's generality costs more than the solve)
    kron = np.multiply.outer(b.T, a).transpose(0, 2, 1, 3).reshape(rows * cols, rows * cols)
    lhs = np.eye(rows * cols) - kron
    x = scipy.linalg.solve(lhs, c.reshape(-1, order='F'), check_finite=False)
    return x.reshape((rows, cols), order='F')


def solve_p22(f_matrix: np.ndarray, g: np.ndarray) -> np.ndarray:
    """
    Solve eq. (44), P22 = F P22 F' + g g' (a Lyapunov equation).

    Solved as the Stein equation of :func:`solve_stein`, which is what
    :func:`scipy.linalg.solve_discrete_lyapunov` does for small sizes, at a
    quarter of its call overhead; the tests check the two agree.
    """
    return solve_stein(f_matrix, f_matrix.T, np.outer(g, g))


def solve_p12(a_cl: np.ndarray, b_cl: np.ndarray, f_matrix: np.ndarray, g: np.ndarray,
              h: np.ndarray, p22: np.ndarray) -> np.ndarray:
    """Solve eq. (43), P12 = A_cl P12 F' + b_cl h P22 F' + b_cl g' (Remark 4)."""
    constant = np.outer(b_cl, h @ p22 @ f_matrix.T) + np.outer(b_cl, g)
    return solve_stein(a_cl, f_matrix.T, constant)


def augmented_system(a_cl: np.ndarray, b_cl: np.ndarray, f_matrix: np.ndarray,
                     g: np.ndarray, h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return (Ā, b̄) of eqs. (29) and (30)."""
    k, n = a_cl.shape[0], f_matrix.shape[0]
    a_bar = np.zeros((k + n, k + n))
    a_bar[:k, :k] = a_cl
    a_bar[:k, k:] = np.outer(b_cl, h)
    a_bar[k:, k:] = f_matrix
    return a_bar, np.concatenate((b_cl, g))


def noise_state_covariance(a_cl: np.ndarray, b_cl: np.ndarray, f_matrix: np.ndarray,
                           g: np.ndarray, h: np.ndarray) -> np.ndarray:
    """Solve eq. (36), P = Ā P Ā' + b̄ b̄', with scipy.linalg.solve_discrete_lyapunov."""
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
    """
    Return (Phi, target, next phi) of eqs. (10), (14), (18) and (19).

    The filters q^n/f(q) start from rest at the first sample. Row j of Phi is
    phi[n + j] = [y_f[n+j-1] ... y_f[j], u_f[n+j-1] ... u_f[j]] and the target
    is y[n + j]: only rows whose lags all lie in the record are used.
    """
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
    """
    Solve the prefiltered LS problem (eqs. 16, 17) over a record.

    Raises
    ------
    CompensationFailure
        ``singular_information`` if Phi' Phi is not positive definite.

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


# ------------------------------------------------ the compensation (50)-(59)
def bias_terms(theta_plant: np.ndarray, prefilter: np.ndarray, controller: Controller
               ) -> tuple[np.ndarray, float]:
    """
    Return (c, beta): the bias direction C_cl P12 h' and 1 + h P22 h' (steps 3 and 4).

    E{phi[k] eps[k]} = c sigma^2 (eq. 37) and E{eps^2} = beta sigma^2 (eq. 48)
    for the plant ``theta_plant`` = [a | b] under ``controller`` with prefilter f.

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
    """
    Apply eqs. (56), (58) and (59) to an LS solution; return (theta_BC, sigma2).

    theta_BC is in the regression form [f - a | b].

    Raises
    ------
    CompensationFailure
        ``negative_variance_argument`` if beta^2 - 4 alpha gamma < 0 in (58).

    """
    return _compensate(ls.theta, ls.information_inverse, ls.loss, float(ls.count),
                       direction, beta)


def _compensate(theta: np.ndarray, inverse: np.ndarray, loss: float, count: float,
                direction: np.ndarray, beta: float) -> tuple[np.ndarray, float]:
    pc = inverse @ direction
    # gamma = e'e / N                                                        (53)
    gamma = loss / count
    # alpha = N c' (Phi'Phi)^-1 c                                            (51), (56)
    alpha = count * float(direction @ pc)
    discriminant = beta * beta - 4.0 * alpha * gamma
    if not discriminant >= 0.0:
        raise CompensationFailure('negative_variance_argument',
                                  f'beta^2 - 4 alpha gamma = {discriminant:.4g} < 0 in eq. (58)')
    # sigma2 = 2 gamma / (beta + sqrt(beta^2 - 4 alpha gamma))               (58)
    sigma2 = 2.0 * gamma / (beta + math.sqrt(discriminant))
    # theta_BC = theta_LS - N (Phi'Phi)^-1 c sigma2                          (59)
    return theta - (count * sigma2) * pc, sigma2


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
        Whether the last change of ``theta`` was below the tolerance.
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
    """
    Return whether a fixed-point iteration's last step is shorter than its first.

    The steps are s_i = ||theta^(i) - theta^(i-1)|| of the plant-form
    iterates [a | b] (what would be published). For an iteration that
    converges linearly with factor rho, s_last / s_first = rho^(k-2) < 1;
    ``False`` means the iteration did not contract over the redesign (on
    average rho >= 1): it was drifting, not converging, and its last iterate
    is no estimate of a fixed point. With fewer than three iterates (fewer
    than two steps) there is nothing to compare, and the answer is ``True``.

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
    """
    Run Algorithm 1 of Ikeda (2008): prefilter redesign with BCLS at each iteration.

    For i = 0, 1, ...:

    (2) LS on the data prefiltered by f^(i) (eqs. 10-17) and gamma (eq. 53);
    (3) A_cl, h, Ā from theta_LS^(i) (eqs. 29-33, 54);
    (4) P12 and P22 from eqs. (43) and (44) (equivalent to eq. 55), alpha and beta
        (eqs. 56, 57);
    (5) sigma^2 from eq. (58) and theta_BC^(i) from eq. (59);
    (6), (7) f^(i+1) = â_p^(i), with the unstable roots mirrored (Remark 3).

    The iteration stops when the estimate theta^(i) in the regression form of
    eq. (13), [f^(i) - a^(i) | b^(i)], moves by less than ``tolerance``
    (2-norm) from one iteration to the next ("the norm of the parameter
    improvement", section 7.3), or after ``max_iterations`` LS solves. This
    literal reading gives the paper's iteration counts; measuring the change
    of [a | b] instead costs about 0.2 (with BC) and 0.6 (without) more
    iterations on the section 7.3 example. Without ``bias_compensation`` steps 3-5 are
    skipped (the plain iterative prefilter redesign of section 7.3).

    If a step fails (see :class:`CompensationFailure`) after the first
    iteration, the last good iterate is returned with ``failure`` set; if it
    fails in the first iteration the failure is raised.

    Parameters
    ----------
    y, u : array_like, shape ``(N,)``
        Measured output and input of the plant in the loop.
    order : int
        n.
    controller_numerator, controller_denominator, controller_sign
        See :func:`make_controller`.
    prefilter_initial : float or sequence of float
        f^(0), see :func:`prefilter_polynomial`; 0 gives f = q^n (step 1).
    max_iterations : int
        Cap on the LS solves.
    tolerance : float
        Stopping threshold on the change of theta in the form of eq. (13).
    bias_compensation : bool
        Apply steps 3-5 (the proposed method) or not.

    Returns
    -------
    ClosedLoopResult

    Raises
    ------
    ValueError
        On bad arguments.
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
    return _algorithm1(y, u, controller, prefilter, max_iterations, tolerance,
                       bias_compensation)


def _algorithm1(y: np.ndarray, u: np.ndarray, controller: Controller, prefilter: np.ndarray,
                max_iterations: int, tolerance: float, bias_compensation: bool
                ) -> ClosedLoopResult:
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


# -------------------------------------------------------- the online form
class ClosedLoopBcls(RecursiveEstimator):
    r"""
    Online closed-loop BCLS: per-sample prefiltered RLS, windowed Algorithm 1.

    **What is assumed.** The estimator sees only the measured (y[k], u[k]).
    It never needs the reference r: the LS uses y and u alone, and the bias
    term (eq. 37) depends on how the *noise* travels round the loop, which
    the plant estimate and the known controller fix (r only has to be
    independent of the noise, assumption A5). It does assume that

    * u[k] is exactly the output of the LTI controller
      ``controller_numerator/controller_denominator`` with ``controller_sign``
      acting on the same measured y (no saturation, no input noise, no
      controller change while running: a retuned or adaptive controller
      invalidates the compensation);
    * the noise is white observation noise on y (A3), with no process noise;
    * the true closed loop is stable (A4) and the plant is strictly proper of
      order at most n (A2).

    **Per sample** k (samples counted since the last redesign's window start):

    .. math::

        y_f[k] &= \frac{q^n}{f(q)} y[k], \quad u_f[k] = \frac{q^n}{f(q)} u[k]
            && \text{(10)} \\
        \varphi[k] &= [y_f[k-1] \dots y_f[k-n], u_f[k-1] \dots u_f[k-n]]^T
            && \text{(14)} \\
        s &= 1 + \varphi^T P \varphi, \quad e = y[k] - \varphi^T\hat\theta_{LS} \\
        \hat\theta_{LS} &\leftarrow \hat\theta_{LS} + P\varphi\, e / s, \quad
        P \leftarrow P - P\varphi\varphi^T P / s, \quad
        J \leftarrow J + e^2/s, \quad N \leftarrow N + 1 && \text{(17), recursively} \\
        \gamma &= J / N, \quad \alpha = N c^T P c && \text{(53), (56)} \\
        \hat\sigma_\nu^2 &= \frac{2\gamma}{\beta + \sqrt{\beta^2 - 4\alpha\gamma}}
            && \text{(58)} \\
        \hat\theta_{BC} &= \hat\theta_{LS} - N \hat\sigma_\nu^2 P c && \text{(59)} \\
        \hat a_i &= f_i - \hat\theta_{BC,i}, \quad \hat b_i = \hat\theta_{BC,n+i}
            && \text{(13)}

    where f, :math:`c = C_{cl}P_{12}h^T` (eq. 37) and
    :math:`\beta = 1 + h P_{22} h^T` (eq. 57) are frozen at the last redesign.

    **Every** ``redesign_period`` **samples** (once the window holds at least
    ``10 * 2n + n`` samples, and before the first successful redesign since
    the last reset at least :attr:`first_window` = max(``window`` // 2,
    ``10 * 2n + n``) samples), :func:`closed_loop_bcls` (Algorithm 1) runs on
    the raw samples of the window, the last min(samples since reset or
    restart, ``window``) of them, starting from the prefilter in use and
    stopping after ``max_iterations`` LS solves or when the estimate (in the
    form of eq. 13) moves by less than ``tolerance``. On success the prefilter
    becomes the one of its last LS solve, P, theta_LS, J, N are set to that LS
    solution
    (:math:`P = (\Phi^T\Phi)^{-1}`), phi continues from the filtered window,
    and c, beta are taken from its last compensation.

    **The estimate published at sample N** is therefore, exactly (to
    rounding): with s the first sample of the window of the last successful
    redesign (at sample R <= N), f its prefilter and c, beta its bias
    terms, eqs. (56), (58), (59) applied to the LS solution (17) over
    samples s..N prefiltered by f from rest at s. At N = R it equals the
    result of Algorithm 1 on the window. Between redesigns the LS window grows
    by one sample per sample (up to ``window + redesign_period - 1``).
    Exceptions: values held after a failed redesign or a failed eq. (58) (see
    Safety), and after :meth:`restart_regressor`, which empties the window
    and restarts the prefilter state from rest while the running LS keeps its
    statistics until the next redesign replaces them.
    ``theta_uncompensated`` is that LS solution in the same plant form.
    Before the first successful redesign the LS runs from
    :math:`P(0) = p_0 I`, :math:`\hat\theta(0) = 0` with the initial prefilter,
    ``theta`` equals ``theta_uncompensated`` and :attr:`valid` is False.

    **Safety** (each counted in :attr:`flags`; nothing here ever yields NaN):

    * ``unstable_closed_loop``, ``unstable_prefilter``, ``lyapunov_failed``,
      ``singular_information``, ``negative_variance_argument`` at a
      redesign: if the first iteration of Algorithm 1 fails, the redesign is
      dropped: the prefilter and the running LS stay as they were, and the
      compensated estimate and sigma^2 are *held* at their last good values
      (:attr:`holding`) until a redesign succeeds; if a later iteration fails,
      its last good iterate is used as the redesign's result;
    * ``negative_variance_argument`` at a sample (beta^2 - 4 alpha gamma < 0
      in eq. 58 with the running LS): the last good compensated estimate and
      sigma^2 are kept for that sample;
    * ``nonfinite_estimate``: a compensated estimate that is not finite is
      never published; the last good one is kept;
    * ``not_converged``: a redesign used all ``max_iterations``; its result
      is used if the iteration was contracting (see below);
    * ``not_contracting``: a redesign stopped without meeting ``tolerance``
      (``not_converged`` or a failure in a later iteration), and its last step
      was not shorter than its first (:func:`is_contracting`, plant form): the
      iteration was drifting, not converging, so its last iterate is no
      estimate. The redesign is dropped as if it had failed: the prefilter
      and the running LS stay as they were, and the compensated estimate and
      sigma^2 are held (or stay invalid before the first good redesign). The
      next redesign starts again from the same prefilter on a longer window.
      On the paper's loop, a 1000-sample first window can hold no fixed point
      near the true pole; accepting the drift's end point there moved the
      prefilter past a repelling fixed point, and later redesigns went on to a
      spurious one at pole -1.01 (seed 1082 of the ``ikeda_closed_loop``
      scenario);
    * the same spurious point (a plant pole just outside -1 with the mirrored
      prefilter of Remark 3 just inside: a fixed point of Algorithm 1 that,
      once reached, later windows keep) can also be reached by a *converging*
      iteration on a short window. Hence the first redesign waits for
      :attr:`first_window` samples. On the paper's loop, over 100 runs of 4096
      samples, the final pole ended below 0.3 in 3 to 19 runs (depending on
      ``prefilter_initial`` and ``redesign_period``) with a 1000- or 200-sample
      first window, and in none with 2048;
    * ``covariance_repaired``: P lost definiteness and was rebuilt.

    Parameters
    ----------
    order : int
        Plant order n.
    num_inputs : int
        Must be 1 (SISO).
    feedthrough : bool
        Must be False: b_p has degree < n (eq. 3).
    initial_covariance : float
        p0 of P(0) = p0 I, used only before the first redesign.
    forgetting_factor : float
        Must be 1: the estimator forgets through its finite ``window``.
    controller_numerator, controller_denominator : sequence of float
        b_c(q) and a_c(q) in descending powers of q (eqs. 5, 6); b_c is
        left-padded with zeros to the length of a_c. The paper's (60) is
        ``[0.2289]`` over ``[1, -0.09004]``.
    controller_sign : str
        ``'negative'`` (default): u = (b_c/a_c)(r - y); ``'positive'``:
        u = (b_c/a_c)(y - r).
    prefilter_initial : float or sequence of float
        f^(0): a pole p giving f(q) = (q - p)^n (default 0: f = q^n, the
        paper's step 1), or ``[1, f_1, ..., f_n]``; must be stable. A rough
        guess of the plant poles is better than the default: from f = q^n and a
        short first window, Algorithm 1 can run to a spurious fixed point (on
        the paper's loop, a pole near -1 in some runs of 200-1000 samples).
    window : int
        Cap on the samples kept for a redesign (default 4096, the paper's N).
        The first redesign also waits until half of it is filled
        (:attr:`first_window`).
    redesign_period : int
        Samples between redesigns (default 1000).
    max_iterations : int
        Cap on the LS solves of one redesign (default 20).
    tolerance : float
        Stop a redesign when the estimate moves by less (default 1e-3, as in
        section 7.3).

    Raises
    ------
    ValueError
        If a setting is out of range; the message names it.

    """

    name = 'cl_bcls'
    noise_names = ('sigma2',)
    #: Extra constructor keywords (ROS parameter names) beyond the base ones.
    options: tuple[str, ...] = ('controller_numerator', 'controller_denominator',
                                'controller_sign', 'prefilter_initial', 'window',
                                'redesign_period', 'max_iterations', 'tolerance')

    def __init__(self, *, order: int, num_inputs: int = 1, feedthrough: bool = False,
                 initial_covariance: float = 1e6, forgetting_factor: float = 1.0,
                 controller_numerator: Sequence[float], controller_denominator: Sequence[float],
                 controller_sign: str = 'negative', prefilter_initial: Any = 0.0,
                 window: int = DEFAULT_WINDOW, redesign_period: int = DEFAULT_REDESIGN_PERIOD,
                 max_iterations: int = DEFAULT_MAX_ITERATIONS,
                 tolerance: float = DEFAULT_TOLERANCE) -> None:
        super().__init__(order=order, num_inputs=num_inputs, feedthrough=feedthrough,
                         initial_covariance=initial_covariance,
                         forgetting_factor=forgetting_factor)
        if self.num_inputs != 1:
            raise ValueError(f'num_inputs must be 1 for cl_bcls (a SISO loop), got {num_inputs}')
        if self.feedthrough:
            raise ValueError('feedthrough must be False for cl_bcls (b_p(q) has degree < n, '
                             'eq. (3)), got True')
        self._check_forgetting(self._forgetting_factor)
        self.controller = make_controller(controller_numerator, controller_denominator,
                                          controller_sign)
        self.prefilter_initial = prefilter_polynomial(prefilter_initial, self.order)
        self.min_window = ROWS_PER_PARAMETER * 2 * self.order + self.order
        self.window = check_int('window', window, self.min_window)
        self.first_window = max(self.window // FIRST_WINDOW_DIVISOR, self.min_window)
        self.redesign_period = check_int('redesign_period', redesign_period, 1)
        self.max_iterations = check_int('max_iterations', max_iterations, 1)
        self.tolerance = check_range('tolerance', tolerance, 0.0, math.inf, low_open=True)
        self._reset()

    @staticmethod
    def _check_forgetting(value: float) -> None:
        if value != 1.0:
            raise ValueError('forgetting_factor must be 1 for cl_bcls (it forgets through its '
                             f'finite window), got {value!r}')

    @property
    def forgetting_factor(self) -> float:
        """Return the forgetting factor; cl_bcls only accepts 1."""
        return self._forgetting_factor

    @forgetting_factor.setter
    def forgetting_factor(self, value: float) -> None:
        value = check_range('forgetting_factor', value, 0.0, 1.0, low_open=True)
        self._check_forgetting(value)
        self._forgetting_factor = value

    # ------------------------------------------------------------- the step
    def _update(self, y: float, u: np.ndarray) -> None:
        u0 = float(u[0])
        # keep the raw sample for the redesign window
        pos = self._pos
        if pos == self._buffer.shape[0]:
            self._buffer[:self.window] = self._buffer[self.window:]
            pos = self.window
        self._buffer[pos] = (y, u0)
        self._pos = pos + 1
        if self._filled < self.window:
            self._filled += 1
        self._samples += 1
        phi = self._phi
        if self._lags >= self.order:
            self._ls_step(y, phi)
        else:
            self._lags += 1
        # phi[k+1] = blockdiag(F, F) phi[k] + [g y[k]; g u[k]]        (10), (14)
        phi = self._shift.dot(phi)
        phi[0] += y
        phi[self.order] += u0
        self._phi = phi
        self._since_redesign += 1
        if (self._since_redesign >= self.redesign_period and self._filled >= (
                self.min_window if self._direction is not None else self.first_window)):
            self._since_redesign = 0
            self._redesign()

    def _ls_step(self, y: float, phi: np.ndarray) -> None:
        """Do the RLS step and, once a redesign has succeeded, eqs. (56)-(59)."""
        theta = self._theta_ls
        # g = P phi
        g = self._p.dot(phi)
        # s = 1 + phi' P phi
        s = 1.0 + phi.dot(g)
        if not s > 0.0:
            self._repair_covariance()
            return
        # e = y[k] - phi' theta_LS
        e = y - phi.dot(theta)
        # theta_LS += P phi e / s
        theta += g * (e / s)
        # P -= P phi phi' P / s, written as h h' with h = g / sqrt(s)
        h = g * (1.0 / math.sqrt(s))
        self._p -= h[:, None] * h
        # J += e^2 / s ; N += 1
        self._loss += e * e / s
        self._count += 1.0
        if self._direction is None or self._holding:
            return
        count = self._count
        direction = self._direction
        pc = self._p.dot(direction)
        # gamma = J / N                                                      (53)
        gamma = self._loss / count
        # alpha = N c' P c                                                   (56)
        alpha = count * direction.dot(pc)
        beta = self._beta
        discriminant = beta * beta - 4.0 * alpha * gamma
        if not discriminant >= 0.0:
            self._flag('negative_variance_argument')
            return
        # sigma2 = 2 gamma / (beta + sqrt(beta^2 - 4 alpha gamma))           (58)
        sigma2 = 2.0 * gamma / (beta + math.sqrt(discriminant))
        # theta_BC = theta_LS - N sigma2 P c                                 (59)
        compensated = theta - (count * sigma2) * pc
        if not math.isfinite(compensated.dot(compensated) + sigma2):
            self._flag('nonfinite_estimate')
            return
        self._theta_bc = compensated
        self._sigma2 = sigma2

    def _repair_covariance(self) -> None:
        """Rebuild P as the nearest symmetric positive definite matrix."""
        self._flag('covariance_repaired')
        sym = 0.5 * (self._p + self._p.T)
        if not np.isfinite(sym).all():
            self._p = self.initial_covariance * np.eye(self.num_parameters)
            return
        values, vectors = np.linalg.eigh(sym)
        floor = max(values.max(), 1.0) * 1e-12
        self._p = (vectors * np.maximum(values, floor)) @ vectors.T

    def _redesign(self) -> None:
        """Run Algorithm 1 on the window and take over its result."""
        data = self._buffer[self._pos - self._filled:self._pos]
        try:
            result = _algorithm1(data[:, 0], data[:, 1], self.controller, self._prefilter,
                                 self.max_iterations, self.tolerance, True)
        except CompensationFailure as error:
            self._flag(error.flag)
            self._holding = self._direction is not None
            return
        if result.failure is not None:
            self._flag(result.failure)
        elif not result.converged:
            self._flag('not_converged')
        if not result.converged and not is_contracting(result.history):
            # the iteration drifted without converging: no fixed point of this window
            # near the prefilter in use; drop the redesign like a failed one
            self._flag('not_contracting')
            self._holding = self._direction is not None
            return
        self._redesigns += 1
        self._last_iterations = result.iterations
        self._set_prefilter(result.prefilter)
        self._phi = result.ls.next_regressor.copy()
        self._lags = self.order
        self._theta_ls = result.ls.theta.copy()
        self._p = result.ls.information_inverse.copy()
        self._loss = result.ls.loss
        self._count = float(result.ls.count)
        self._direction = result.direction.copy()
        self._beta = float(result.beta)
        self._theta_bc = regression_from_plant(result.theta, result.prefilter)
        self._sigma2 = float(result.sigma2)
        self._holding = False

    def _set_prefilter(self, prefilter: np.ndarray) -> None:
        n = self.order
        self._prefilter = np.array(prefilter, dtype=float)
        f_matrix, _ = controller_canonical(self._prefilter)
        shift = np.zeros((2 * n, 2 * n))
        shift[:n, :n] = f_matrix
        shift[n:, n:] = f_matrix
        self._shift = shift

    # --------------------------------------------------------- the accessors
    @property
    def valid(self) -> bool:
        """Whether a compensation (redesign) has succeeded since the last reset."""
        return self._direction is not None

    @property
    def samples(self) -> int:
        """Count the samples processed since the last reset."""
        return self._samples

    @property
    def prefilter(self) -> np.ndarray:
        """Return the prefilter in use, [1, f_1, ..., f_n] (a copy)."""
        return self._prefilter.copy()

    @property
    def sigma2(self) -> float:
        """Return the noise variance estimate of eq. (58) (0 before the first redesign)."""
        return self._sigma2

    @property
    def redesigns(self) -> int:
        """Count the successful redesigns since the last reset."""
        return self._redesigns

    @property
    def last_iterations(self) -> int:
        """Return the LS solves of the last successful redesign (0 before)."""
        return self._last_iterations

    @property
    def holding(self) -> bool:
        """Whether the compensated estimate is held after a failed redesign."""
        return self._holding

    @property
    def window_length(self) -> int:
        """Return the number of samples the next redesign would use."""
        return self._filled

    @property
    def covariance(self) -> np.ndarray:
        """Return P, the inverse information matrix of the running LS (a copy)."""
        return self._p.copy()

    @property
    def covariance_trace(self) -> float:
        """Return tr P."""
        return float(np.trace(self._p))

    def _theta(self) -> np.ndarray:
        if self._direction is None:
            return self._theta_uncompensated()
        # a_i = f_i - theta_i ; b_i = theta_(n+i)                            (13)
        return plant_from_regression(self._theta_bc, self._prefilter)

    def _theta_uncompensated(self) -> np.ndarray:
        return plant_from_regression(self._theta_ls, self._prefilter)

    def _noise(self) -> np.ndarray:
        return np.array([self._sigma2])

    def __repr__(self) -> str:
        return (f'{type(self).__name__}(order={self.order}, '
                f'controller={self.controller.numerator.tolist()}/'
                f'{self.controller.denominator.tolist()} ({self.controller.sign} feedback), '
                f'window={self.window}, redesign_period={self.redesign_period}, '
                f'max_iterations={self.max_iterations}, tolerance={self.tolerance:g})')

    # -------------------------------------------------------------- the state
    def _reset(self) -> None:
        p = self.num_parameters
        self._set_prefilter(self.prefilter_initial)
        self._buffer = np.zeros((2 * self.window, 2))
        self._pos = 0
        self._filled = 0
        self._phi = np.zeros(p)
        self._lags = 0
        self._theta_ls = np.zeros(p)
        self._p = self.initial_covariance * np.eye(p)
        self._loss = 0.0
        self._count = 0.0
        self._direction: np.ndarray | None = None
        self._beta = 1.0
        self._theta_bc = np.zeros(p)
        self._sigma2 = 0.0
        self._holding = False
        self._samples = 0
        self._since_redesign = 0
        self._redesigns = 0
        self._last_iterations = 0

    def _restart_regressor(self) -> None:
        self._filled = 0
        self._phi = np.zeros(self.num_parameters)
        self._lags = 0

    def _state_items(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        compensated = self._direction is not None
        arrays = {'prefilter': self._prefilter, 'buffer': self._buffer, 'phi': self._phi,
                  'theta_ls': self._theta_ls, 'p': self._p, 'theta_bc': self._theta_bc,
                  'direction': (self._direction if compensated
                                else np.zeros(self.num_parameters))}
        scalars = {'pos': self._pos, 'filled': self._filled, 'lags': self._lags,
                   'loss': self._loss, 'count': self._count, 'beta': self._beta,
                   'sigma2': self._sigma2, 'samples': self._samples,
                   'since_redesign': self._since_redesign, 'redesigns': self._redesigns,
                   'last_iterations': self._last_iterations, 'compensated': compensated,
                   'holding': self._holding}
        return arrays, scalars

    def _load_state(self, arrays: dict[str, np.ndarray], scalars: dict[str, Any]) -> None:
        self._set_prefilter(arrays['prefilter'])
        self._buffer = arrays['buffer']
        self._phi = arrays['phi']
        self._theta_ls = arrays['theta_ls']
        self._p = arrays['p']
        self._theta_bc = arrays['theta_bc']
        self._direction = arrays['direction'] if scalars['compensated'] else None
        self._pos = int(scalars['pos'])
        self._filled = int(scalars['filled'])
        self._lags = int(scalars['lags'])
        self._loss = float(scalars['loss'])
        self._count = float(scalars['count'])
        self._beta = float(scalars['beta'])
        self._sigma2 = float(scalars['sigma2'])
        self._samples = int(scalars['samples'])
        self._since_redesign = int(scalars['since_redesign'])
        self._redesigns = int(scalars['redesigns'])
        self._last_iterations = int(scalars['last_iterations'])
        self._holding = bool(scalars['holding'])
