"""
Nonlinear least squares for the batch prediction-error fits: trust region or Levenberg-Marquardt.

:func:`best_run` runs the chosen solver from several starts and keeps the
lowest end; the trust-region solver is :func:`scipy.optimize.least_squares`,
the Levenberg-Marquardt one (:func:`levenberg_marquardt`) solves the damped
normal equations, several times cheaper per iteration at these sizes.
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np
from scipy import linalg, optimize

#: Most function evaluations of one least-squares run.
MAX_EVALUATIONS = 200
#: Values of the ``solver`` argument of :func:`fit_oe`.
SOLVERS = ('trf', 'lm')
#: Levenberg-Marquardt (``solver='lm'``): first damping (relative to the scaled
#: diagonal of J^T J), its factor down after a step that lowers the cost and up
#: after one that does not, and the damping at which no step is left to try.
LM_DAMPING = 1e-3
LM_FACTOR = 10.0
LM_MAX_DAMPING = 1e16
#: Both solvers stop when an accepted step lowers the cost by less than this
#: fraction, or moves the scaled x by less than this fraction of its norm
#: (scipy.optimize.least_squares' default ftol and xtol).
STOP_TOLERANCE = 1e-8


def best_run(residual: Callable[[np.ndarray], np.ndarray],
             jacobian: Callable[[np.ndarray], np.ndarray], candidates: list[np.ndarray],
             losses: list[float], starts: int, max_evaluations: int,
             solver: str = 'trf') -> optimize.OptimizeResult:
    """
    Return the run that ends lowest, of at most ``starts`` runs from the lowest start losses.

    The lowest start does not always lead to the lowest minimum (an
    over-parametrised OE model has several), so every start given is run.
    """
    return min(runs(residual, jacobian, candidates, losses, starts, max_evaluations, solver),
               key=lambda run: run.cost)


def runs(residual: Callable[[np.ndarray], np.ndarray],
         jacobian: Callable[[np.ndarray], np.ndarray], candidates: list[np.ndarray],
         losses: list[float], starts: int, max_evaluations: int,
         solver: str = 'trf') -> list[optimize.OptimizeResult]:
    """Return the runs from the ``starts`` lowest start losses, in that order."""
    ended = []
    for index in np.argsort(losses, kind='stable')[:starts]:
        if solver == 'lm':
            ended.append(levenberg_marquardt(residual, jacobian, candidates[index],
                                             max_evaluations))
        else:
            ended.append(minimise_trf(residual, jacobian, candidates[index], max_evaluations))
    return ended


def kept_start(residual: Callable[[np.ndarray], np.ndarray], x: np.ndarray,
               why: str) -> optimize.OptimizeResult:
    """Return a start as a run that did not move (status 0, no evaluations counted)."""
    fun = residual(x)
    return optimize.OptimizeResult(x=x.copy(), fun=fun, cost=0.5 * float(fun @ fun), status=0,
                                   nfev=0, message=why)


def minimise_trf(residual: Callable[[np.ndarray], np.ndarray],
                 jacobian: Callable[[np.ndarray], np.ndarray], x0: np.ndarray,
                 max_evaluations: int) -> optimize.OptimizeResult:
    """Run trust-region-reflective least squares from ``x0`` with scaled variables."""
    return optimize.least_squares(residual, x0, jac=jacobian, method='trf', x_scale='jac',
                                  max_nfev=max_evaluations)


def levenberg_marquardt(residual: Callable[[np.ndarray], np.ndarray],
                        jacobian: Callable[[np.ndarray], np.ndarray], x0: np.ndarray,
                        max_evaluations: int = MAX_EVALUATIONS) -> optimize.OptimizeResult:
    r"""
    Minimise :math:`\frac12\|r(x)\|^2` by Levenberg-Marquardt on the normal equations.

    With the Jacobian's columns scaled to unit norm, :math:`J_s = J S^{-1}`,
    each iteration solves

    .. math::

        (J_s^T J_s + \mu I)\,\delta = -J_s^T r, \qquad x \leftarrow x + S^{-1}\delta

    (Marquardt's scaling: the damping acts alike on every parameter whatever
    its units; Ljung 1999, ch. 10, the damped Gauss-Newton search). A step
    that lowers the cost is taken and μ divided by ``LM_FACTOR``; otherwise
    (also when the residual is not finite, e.g. F unstable) μ is multiplied
    by it and the step tried again. It stops when a step lowers the cost by
    less than ``STOP_TOLERANCE`` of it, or moves the scaled x by less than
    ``STOP_TOLERANCE`` of its norm, or no step is left to try (status > 0),
    or after ``max_evaluations`` residuals (status 0). Forming the p x p
    matrix costs a few per cent of the SVD of the N x p Jacobian that the
    trust-region solver of :func:`scipy.optimize.least_squares` computes at
    every iteration; the squared condition number of the normal equations
    matters only far from the minimum, where μ dominates.

    Returns
    -------
    scipy.optimize.OptimizeResult
        ``x``, ``fun`` (the residual at x), ``cost``, ``nfev``, ``status``
        and ``message``, as :func:`scipy.optimize.least_squares` returns.

    """
    x = np.array(x0, dtype=float)
    fun = residual(x)
    cost = 0.5 * float(fun @ fun)
    evaluations, damping = 1, LM_DAMPING
    status, message = 0, 'the most residual evaluations were reached'
    while evaluations < max_evaluations and status == 0:
        columns = jacobian(x)
        scale = np.linalg.norm(columns, axis=0)
        scale[scale == 0.0] = 1.0
        scaled = columns / scale
        normal = scaled.T @ scaled
        gradient = scaled.T @ fun
        step = None
        while evaluations < max_evaluations:
            if damping > LM_MAX_DAMPING:
                status, message = 2, 'no step lowers the cost'
                break
            try:
                # (J_s^T J_s + mu I) delta = -J_s^T r
                delta = -linalg.cho_solve(linalg.cho_factor(
                    normal + damping * np.eye(normal.shape[0])), gradient)
            except (linalg.LinAlgError, ValueError):
                damping *= LM_FACTOR
                continue
            trial = x + delta / scale
            trial_fun = residual(trial)
            evaluations += 1
            trial_cost = 0.5 * float(trial_fun @ trial_fun)
            if math.isfinite(trial_cost) and trial_cost < cost:
                step = delta
                break
            damping *= LM_FACTOR
        if step is None:
            break
        reduction = (cost - trial_cost) / cost if cost > 0.0 else 0.0
        moved = float(np.linalg.norm(step)) / max(float(np.linalg.norm(x * scale)), 1e-300)
        x, fun, cost = trial, trial_fun, trial_cost
        damping = max(damping / LM_FACTOR, 1e-300)
        if reduction < STOP_TOLERANCE:
            status, message = 2, 'the cost fell by less than the tolerance'
        elif moved < STOP_TOLERANCE:
            status, message = 3, 'the step was below the tolerance'
    return optimize.OptimizeResult(x=x, fun=fun, cost=cost, nfev=evaluations, status=status,
                                   message=message, success=status > 0)


__all__ = ['MAX_EVALUATIONS', 'SOLVERS', 'best_run', 'levenberg_marquardt', 'minimise_trf']
