r"""
Polynomial stability: the spectral radius and the stability test, in one coefficient convention.

The convention: a monic polynomial
:math:`A(q) = 1 + a_1 q^{-1} + \dots + a_n q^{-n}` (equally
:math:`q^n + a_1 q^{n-1} + \dots + a_n`) is given by its coefficients after
the leading 1, ``a = [a_1, ..., a_n]``: the a-part of θ as the estimators
hold it, with no copy on their per-sample paths. :func:`spectral_radii`
takes many of them as rows ``(K, n)``, one per plant. A polynomial written
out in descending powers, ``[c_0, c_1, ..., c_n]`` (:mod:`numpy.roots`,
:mod:`bcid_ros.estimators.lti`), enters through :func:`monic_coefficients`,
which divides by :math:`c_0` (exact for a monic one) and drops it.

The rulebook's unstable-model check, the closed-loop estimator, rpem's
stability region D_M, the batch prediction-error fits and the closed-loop
scenario all ask here.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

#: A polynomial counts as stable when all its roots have modulus below 1 - this.
STABILITY_MARGIN = 1e-6


def monic_coefficients(polynomial: Any) -> np.ndarray:
    """
    Return ``[a_1, ..., a_n]`` of ``[c_0, c_1, ..., c_n]`` (descending powers): c_i / c_0.

    Leading zeros are dropped; a constant gives no coefficients, the zero
    polynomial ``[inf]`` (it has no roots to place, and is never stable).
    """
    polynomial = np.trim_zeros(np.asarray(polynomial, dtype=float).ravel(), 'f')
    if polynomial.size == 0:
        return np.array([math.inf])
    return polynomial[1:] / polynomial[0]


def spectral_radii(a: np.ndarray) -> np.ndarray:
    """
    Return the largest root modulus of each monic polynomial, given as the rows of ``a`` (K, n).

    Closed forms for n <= 2 (a twentieth of the eigenvalues' cost), the
    companion matrix's eigenvalues above; a row with a non-finite coefficient
    has radius inf, a constant (n = 0) radius 0.
    """
    count, order = a.shape
    if order == 0:
        return np.zeros(count)
    if count == 1 and order <= 2:  # one plant: the closed forms on floats, ten times cheaper
        return np.array([_radius_of_one(a[0].tolist())])
    radius = np.full(count, math.inf)
    general = np.isfinite(a).all(axis=1)
    if order == 1:
        radius[general] = np.abs(a[general, 0])
        return radius
    if order == 2:
        with np.errstate(over='ignore', invalid='ignore'):
            discriminant = a[:, 0] * a[:, 0] - 4.0 * a[:, 1]
        closed = general & np.isfinite(discriminant)  # an overflow takes the general way
        a1, a2, d = a[closed, 0], a[closed, 1], discriminant[closed]
        # real roots (-a1 +- sqrt(d)) / 2, or a complex pair with |z|^2 = a2 (> 0 there)
        radius[closed] = np.where(d >= 0.0, 0.5 * (np.abs(a1) + np.sqrt(np.abs(d))),
                                  np.sqrt(np.abs(a2)))
        general &= ~closed
    if general.any():
        radius[general] = _companion_radii(a[general])
    return radius


def _radius_of_one(a: list[float]) -> float:
    """Return :func:`spectral_radii` of one monic polynomial of degree 1 or 2 (its a-part)."""
    if len(a) == 1:
        return abs(a[0]) if math.isfinite(a[0]) else math.inf
    a1, a2 = a
    if not (math.isfinite(a1) and math.isfinite(a2)):
        return math.inf
    discriminant = a1 * a1 - 4.0 * a2
    if not math.isfinite(discriminant):  # an overflow: the general way
        return float(_companion_radii(np.array([a]))[0])
    if discriminant >= 0.0:
        return 0.5 * (abs(a1) + math.sqrt(discriminant))
    return math.sqrt(abs(a2))


def _companion_radii(a: np.ndarray) -> np.ndarray:
    """Return the largest eigenvalue modulus of each row's companion matrix (finite rows)."""
    count, order = a.shape
    companion = np.zeros((count, order, order))
    companion[:, 0] = -a
    companion[:, 1:, :-1] = np.eye(order - 1)
    return np.abs(np.linalg.eigvals(companion)).max(axis=1)


def spectral_radius(a: Any) -> float:
    """Return the largest root modulus of one monic polynomial given as ``[a_1, ..., a_n]``."""
    return float(spectral_radii(np.asarray(a, dtype=float).reshape(1, -1))[0])


def is_stable(a: Any, margin: float = STABILITY_MARGIN) -> bool:
    r"""
    Return whether all roots of a monic polynomial lie strictly within radius 1 - ``margin``.

    With the roots scaled by :math:`1/\rho`, :math:`\rho = 1 - \text{margin}`,
    the coefficients become :math:`\alpha_i = a_i / \rho^i`. Degrees 1 and 2
    are decided by Jury's conditions, :math:`|a_1| < \rho` and
    :math:`|\alpha_2| < 1,\ |\alpha_1| < 1 + \alpha_2`, without computing a
    root (a third of the cost of comparing the radius: rpem tests every
    candidate step); higher degrees by the Schur-Cohn step-down recursion on
    :math:`[1, \alpha_1, \dots, \alpha_n]`

    .. math::

        k_j = \alpha_j, \qquad
        \alpha_i \leftarrow \frac{\alpha_i - k_j \alpha_{j-i}}{1 - k_j^2}, \quad i < j,

    for j = n, ..., 1: the roots are inside if and only if every reflection
    coefficient has :math:`|k_j| < 1`.

    Parameters
    ----------
    a : array_like, shape ``(n,)``
        ``[a_1, ..., a_n]`` of :math:`1 + a_1 q^{-1} + \dots + a_n q^{-n}`
        (:func:`monic_coefficients` of a polynomial written out).
    margin : float
        Required distance of the roots from the unit circle.

    Returns
    -------
    bool
        True for n = 0; False for any non-finite coefficient.

    """
    degree = len(a)
    radius = 1.0 - margin
    if degree == 1:
        return abs(float(a[0])) < radius
    if degree == 2:
        # roots of z^2 + c1 z + c2 with c1 = a1 / R, c2 = a2 / R^2 inside the unit circle
        c1 = float(a[0]) / radius
        c2 = float(a[1]) / (radius * radius)
        return abs(c2) < 1.0 and abs(c1) < 1.0 + c2
    # monic p(radius z) / radius^n: coefficient i becomes a_i / radius^i
    alpha = [1.0] + [float(c) / radius ** i for i, c in enumerate(a, start=1)]
    for j in range(degree, 0, -1):
        k = alpha[j]
        if not abs(k) < 1.0:
            return False
        scale = 1.0 / (1.0 - k * k)
        alpha = [(alpha[i] - k * alpha[j - i]) * scale for i in range(j)]
    return True


__all__ = ['STABILITY_MARGIN', 'is_stable', 'monic_coefficients', 'spectral_radii',
           'spectral_radius']
