r"""
The uncertainty of the BCIV estimate: the delta method on the moments of Step 2.

Ikenoue et al. (2008) give no covariance for the estimate; this one follows
from its form. The estimate is a smooth function of the weighted means of
Step 2, :math:`\hat\theta = F(\bar S/\tau)`, :math:`\bar S = [\bar R, -\bar r]`
(K alternations of eqs. (75)/(53) from eq. (38) colored, the fixed point of
eqs. (65)-(67) white). So

.. math::

    \mathrm{cov}\,\hat\theta = \frac{\tau_2}{\tau^2} J\Omega J^T, \qquad
    J = \partial F/\partial(\bar S/\tau),

with :math:`\Omega` the long-run covariance of the per-sample terms
:math:`\eta_t[p_t^T, -z_t]` (coloured through u, d and e), from the spread of
the sums over blocks of updates, and J by central differences of F (a
separate :class:`~bcid_ros.estimators.bciv.solver.BcivSolver`, built here) at
a block boundary (:mod:`bcid_ros.estimators.moment_covariance`). The
estimator publishes none before it is ready, before 16 blocks (512 updates),
with ``bciv_update='printed'`` (its estimate is not a function of the
moments) and after a restored state until 16 new blocks.

Not exact: the share of true parameters within +-2 std, measured over 200
runs (docs/estimators.md, "Uncertainty"), is 90-94 % per parameter on
Ikenoue's colored example at N = 1000 and 10000 (b1_1: 89.5 % at 10000),
94-97 % white at N = 10000, but 85.5 % for b1_2 white at N = 1000, where the
alternation can end at a spurious fixed point (b near 0) and the std is far
too small; 96 % on the runs still valid.
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np

from bcid_ros.estimators.bciv.solver import BcivSolver


def moment_function(settings: dict[str, Any], shape: tuple[int, ...],
                    regularisation: np.ndarray, mode: str, iterations: int, tolerance: float,
                    start_noise: float) -> Callable[[np.ndarray], np.ndarray]:
    """
    Return F: the estimate from the weighted means of [R | -r], as the estimator computes it.

    Parameters
    ----------
    settings : dict
        The :class:`~bcid_ros.estimators.bciv.solver.BcivSolver` keywords of
        the estimator (its solver is built at the first call of F, not here).
    shape : tuple of int
        ``(m, p + 1)``, the shape of the moments.
    regularisation : numpy.ndarray, shape ``(p,)``
        The M_0 term of Step 1 for the means: rho^-1 lambda^2N S^2 / tau^2.
    mode, iterations, tolerance, start_noise
        As the estimator passes them to
        :meth:`~bcid_ros.estimators.bciv.solver.BcivSolver.estimate`.

    """
    solvers: list[BcivSolver] = []  # built at the first read, not at the boundary

    def estimate(means: np.ndarray) -> np.ndarray:
        if not solvers:
            solvers.append(BcivSolver(**settings))
        return solvers[0].estimate(means.reshape(shape), regularisation, mode=mode,
                                   iterations=iterations, tolerance=tolerance,
                                   start_noise=start_noise).theta.copy()
    return estimate
