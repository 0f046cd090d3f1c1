r"""
The uncertainty of the closed-loop BCLS estimate: the delta method on the moments.

Ikeda (2008) gives no covariance for the estimate; this one follows from
its form. The compensated estimate is, to first order, the fixed point of
Algorithm 1 on the weighted means
:math:`\bar v = [M, \sum w\psi y_f, \sum w y_f^2]/\tau` (``window`` 0;
with a window, the same sums of the running regression-form LS, recovered
from P, theta_LS and J):

.. math::

    \theta = G(\theta, \bar v) = \hat\theta_{LS} - \hat\sigma_\nu^2 P C(\theta),
    \quad C = \sum_e \frac{W_e}{\tau} D c_e(\theta), \
    B = \sum_e \frac{W_e}{\tau}\beta_e(\theta)

(eqs. (37), (57)-(59); the prefilters held fixed: their error moves the
estimate only at second order). The delta method gives
:math:`\mathrm{cov}\,\hat\theta = (\tau_2/\tau^2) J\Omega J^T`,
:math:`J = (I - \partial G/\partial\theta)^{-1}\partial G/\partial\bar v`
at the published estimate (the implicit function theorem, central
differences, :func:`~bcid_ros.estimators.moment_covariance.implicit_step`,
on the F of :func:`moment_function`), and :math:`\Omega` the long-run
covariance of the per-row terms (coloured by the closed loop), from the
spread of their sums over blocks of samples, centred per prefilter
(:mod:`bcid_ros.estimators.moment_covariance`). The estimator publishes none
before it is ready, while it holds a failed redesign, before 16 blocks (512
samples) since the last reset or controller change, and after a restored
state until 16 new blocks.

Not exact: the share of true parameters within +-2 std, measured over 200
runs on Ikeda's loop (docs/estimators.md, "Uncertainty"), is 93-94 % per
parameter with ``window`` 0 (N = 1000 and 10000) and 91-92 % with
``window`` 4096 (N = 10000; the std of b about 15 % small).
"""

from __future__ import annotations

import math
from typing import Callable, Sequence

import numpy as np

from bcid_ros.estimators.cl_bcls.bias import bias_terms
from bcid_ros.estimators.cl_bcls.regression import moment_loss, plant_from_regression
from bcid_ros.estimators.lti import Controller
from bcid_ros.estimators.moment_covariance import fixed_point_system, implicit_step


def moment_function(controller: Controller, prefilter: np.ndarray,
                    epochs: Sequence[tuple[float, np.ndarray]], start: np.ndarray,
                    window: bool) -> Callable[[np.ndarray], np.ndarray]:
    """
    Return F: the fixed point of Algorithm 1 from the weighted mean moments.

    Parameters
    ----------
    controller : Controller
        The controller in the loop.
    prefilter : numpy.ndarray, shape ``(n + 1,)``
        The prefilter in use (with a window, the regression form's f).
    epochs : sequence of (float, numpy.ndarray)
        (W_e / tau, f_e) of every epoch with a weight.
    start : numpy.ndarray, shape ``(2n,)``
        The published estimate, where the fixed point is linearised.
    window : bool
        Whether the sums are those of a windowed estimator's regression-form LS.

    """
    n = prefilter.shape[0] - 1
    p = 2 * n
    system: list[np.ndarray] = []

    def step(theta: np.ndarray, means: np.ndarray) -> np.ndarray:
        information = means[:p * p].reshape(p, p)
        inverse = np.linalg.inv(0.5 * (information + information.T))
        cross = means[p * p:p * p + p]
        theta_ls = inverse.dot(cross)
        loss = moment_loss(information, cross, means[-1], theta_ls)
        direction, beta = np.zeros(p), 0.0
        for share, f in epochs:
            c_e, beta_e = bias_terms(theta, f, controller)
            if not window:
                c_e = np.concatenate((-c_e[:n], c_e[n:]))
            direction += share * c_e
            beta += share * beta_e
        pc = inverse.dot(direction)
        discriminant = beta * beta - 4.0 * direction.dot(pc) * loss
        if not discriminant >= 0.0:
            raise ArithmeticError('negative discriminant')
        compensated = theta_ls - (2.0 * loss / (beta + math.sqrt(discriminant))) * pc
        return plant_from_regression(compensated, prefilter) if window else compensated

    def estimate(means: np.ndarray) -> np.ndarray:
        def at(theta: np.ndarray) -> np.ndarray:
            return step(theta, means)
        if not system:  # (the first call is at the moments themselves)
            system.append(fixed_point_system(at, start))
        return implicit_step(at, start, system[0])
    return estimate
