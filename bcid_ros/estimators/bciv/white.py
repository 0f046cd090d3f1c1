r"""
The white-input-noise fixed point of the BCIV alternation (eqs. 65-67), by the secant method.

With white input noise Q~(b) = b~ (eq. 66) and the noise vector is the one
variance sigma_d^2 (eq. 67). The alternation of eqs. (75) and (53) then has a
fixed point that the plain alternation reaches slowly, if at all
(``docs/bciv.md``); for a given sigma = N sigma_d^2 the b-part of a fixed
point solves an n x n system, so eq. (75) becomes one scalar equation
sigma = f(sigma), solved here. :class:`~bcid_ros.estimators.bciv.solver.BcivSolver`
hands over the per-sample numbers of Step 1 and falls back to the plain
alternation where the scalar equation breaks down.
"""

from __future__ import annotations

import math
from typing import Any, Callable

import numpy as np
from scipy.linalg.lapack import dgesv


class WhiteFixedPoint:
    r"""
    Find the fixed point of Steps 3-4 with white input noise (eqs. 65-67).

    With :math:`\tilde Q = \tilde b` (eq. 66) and :math:`\sigma = N\sigma_d^2`,
    a fixed point satisfies :math:`\theta = \hat\theta_{IV} + \sigma\,GEb`
    (eq. 53), so for a given :math:`\sigma` its b-part solves an n x n
    system, and eq. (75) becomes a scalar equation :math:`\sigma = f(\sigma)`:

    .. math::

        (I - \sigma [GE]_b)\, b(\sigma) = \hat b_{IV}, \qquad
        f(\sigma) = \frac{c_0^Tb + \sigma\, b^TK_1b}{b^TE^TXE\,b}, \quad
        c_0 = E^TX(\bar R\hat\theta_{IV} - \bar r), \ K_1 = E^TX\bar R\,GE.

    Its buffers, bordered for :math:`u = [b; 1]`: the forms,
    ``(3, nb + 1, nb + 1)``: :math:`E^TXE` (constant), :math:`K_1`, and
    :math:`c_0` in the last row (both set per sample), so that
    :math:`u^T F_0 u = b^TE^TXEb`, :math:`u^T F_1 u = b^TK_1b` and
    :math:`u^T F_2 u = c_0^Tb`; the system, ``(2, nb + 1, nb + 1)``: the
    identity and :math:`[GE]_b` (set per sample) with a zero border, so that
    :math:`(I - \sigma [GE]_b)\,b = \hat b_{IV}` bordered by :math:`1 = 1`
    has the solution u.

    Parameters
    ----------
    order : int
        n.
    num_parameters : int
        p = n + nb.
    gram : numpy.ndarray, shape ``(nb, nb)``
        :math:`E^TXE`.

    """

    def __init__(self, order: int, num_parameters: int, gram: np.ndarray) -> None:
        self.order, self.num_parameters = order, num_parameters
        nb = num_parameters - order
        self._forms = np.zeros((3, nb + 1, nb + 1))
        self._forms[0, :nb, :nb] = gram
        self._system = np.zeros((2, nb + 1, nb + 1))
        self._system[0] = np.eye(nb + 1)
        #: [theta_IV; 1]
        self._x = np.ones(num_parameters + 1)

    def solve(self, theta_iv: np.ndarray, gain: np.ndarray, noise_moments: np.ndarray,
              start: float, max_steps: int, tolerance: float
              ) -> tuple[np.ndarray, np.ndarray, int, bool] | None:
        r"""
        Return the fixed point by the secant method on :math:`\phi(\sigma) = \sigma - f(\sigma)`.

        The root is searched from ``start`` (the previous
        :math:`N\hat\sigma_d^2`, or 0, whose first step is one alternation
        from theta_IV). The estimate is
        :math:`\hat\theta_{IV} + f(\sigma_k)\,GE\,b(\sigma_k)`.

        Parameters
        ----------
        theta_iv : numpy.ndarray, shape ``(p,)``
            theta_IV of eq. (38).
        gain : numpy.ndarray, shape ``(p, nb)``
            G E of Step 1.
        noise_moments : numpy.ndarray, shape ``(nb, p + 1)``
            :math:`E^TX[\bar R, -\bar r]`.
        start : float
            :math:`\sigma` to start from.
        max_steps : int
            Cap on the evaluations of f.
        tolerance : float
            Stop once a change of :math:`\sigma` moves theta by less than this.

        Returns
        -------
        tuple or None
            (theta, gamma = [sigma], steps, converged), or None where the
            scalar equation breaks down (a singular system, a denominator not
            positive, a non-finite value): the caller iterates the plain
            alternation instead.

        """
        n, p = self.order, self.num_parameters
        nb = p - n
        forms = self._forms
        forms[1, :nb, :nb] = noise_moments[:, :p].dot(gain)  # K_1
        x = self._x  # [theta_IV; 1]
        x[:p] = theta_iv
        forms[2, nb, :nb] = noise_moments.dot(x)  # c_0
        # bordered by a unit row, one solve gives u = [b(sigma); 1]:
        # [[I - sigma [GE]_b, 0], [0, 1]] u = [b_IV; 1]
        identity, gain_b = self._system
        gain_b[:nb, :nb] = gain[n:]
        b_iv = x[n:].copy()
        # a change of sigma moves theta by |G E b| times it, and b starts at b_IV
        direction = gain.dot(theta_iv[n:])
        scale = math.sqrt(direction.dot(direction))
        tolerance_sigma = tolerance / scale if scale > 0.0 else math.inf

        def by_lapack(sigma: float) -> tuple[float | None, Any]:
            """Return the value of f and [b; 1] at sigma, or None if either is undefined."""
            _, _, u, info = dgesv(identity - sigma * gain_b, b_iv)
            if info != 0:
                return None, None
            denominator, curvature, linear = forms.dot(u).dot(u).tolist()
            if not denominator > 0.0:
                return None, None
            return (linear + sigma * curvature) / denominator, u

        # for n <= 2 the same f on Python floats: there the calls cost more than the sums
        f = by_lapack if nb > 2 else _small_white_function(
            gain_b[:nb, :nb].tolist(), b_iv[:nb].tolist(), forms[0, :nb, :nb].tolist(),
            forms[1, :nb, :nb].tolist(), forms[2, nb, :nb].tolist())
        # secant steps on phi(sigma) = sigma - f(sigma)
        s_0 = float(start)
        f_1, u = f(s_0)
        done = 1
        if f_1 is None:
            return None
        s_1, phi_0 = f_1, s_0 - f_1
        converged = abs(phi_0) <= tolerance_sigma
        while not converged and done < max_steps:
            f_1, u = f(s_1)
            done += 1
            if f_1 is None or not math.isfinite(f_1):
                return None
            phi_1 = s_1 - f_1
            if abs(phi_1) <= tolerance_sigma:
                converged = True
                break
            slope = phi_1 - phi_0
            s_next = f_1 if slope == 0.0 else s_1 - phi_1 * (s_1 - s_0) / slope
            s_0, phi_0, s_1 = s_1, phi_1, s_next
        # Step 4, eq. (53): theta = theta_IV + sigma G E b
        theta = theta_iv + gain.dot(u[:nb]) * f_1
        return theta, np.array([f_1]), done, converged


def _small_white_function(gain: list[list[float]], b_iv: list[float], gram: list[list[float]],
                          curvature_form: list[list[float]], linear_form: list[float]
                          ) -> Callable[[float], tuple[float | None, list[float] | None]]:
    r"""
    Return f(sigma) of :meth:`WhiteFixedPoint.solve` for nb <= 2, on Python floats.

    The same function as there: b solves :math:`(I - \sigma [GE]_b)\,b = \hat b_{IV}`,
    here by Cramer's rule (an n x n system with n <= 2), and the three forms are
    written out; LAPACK and numpy calls cost more than this arithmetic. Returns
    (None, None) where the system is singular or the denominator not positive.
    """
    size = len(b_iv)

    def f(sigma: float) -> tuple[float | None, list[float] | None]:
        if size == 1:
            determinant = 1.0 - sigma * gain[0][0]
            if determinant == 0.0:
                return None, None
            b = [b_iv[0] / determinant]
        else:
            (g00, g01), (g10, g11) = gain
            a00, a01, a10, a11 = 1.0 - sigma * g00, -sigma * g01, -sigma * g10, 1.0 - sigma * g11
            determinant = a00 * a11 - a01 * a10
            if determinant == 0.0:
                return None, None
            b = [(a11 * b_iv[0] - a01 * b_iv[1]) / determinant,
                 (a00 * b_iv[1] - a10 * b_iv[0]) / determinant]
        denominator = curvature = linear = 0.0
        for i in range(size):
            linear += linear_form[i] * b[i]
            for j in range(size):
                product = b[i] * b[j]
                denominator += gram[i][j] * product
                curvature += curvature_form[i][j] * product
        if not denominator > 0.0:
            return None, None
        return (linear + sigma * curvature) / denominator, b
    return f
