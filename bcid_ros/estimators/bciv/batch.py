"""
The batch BCIV reference: the moments over the whole record, then the same solver.

Ikenoue et al. (2008), eqs. (37)-(75): for each data length t the moments of
Step 2 (eqs. 54, 68-70) are summed at once over the first t samples and
:class:`~bcid_ros.estimators.bciv.solver.BcivSolver` gives the estimate (eq.
38, then eqs. 75 and 53 alternated, or the white fixed point of eqs. 65-67).
This is what :class:`~bcid_ros.estimators.bciv.online.Bciv` with
``bciv_update='converged'`` computes recursively; the tests hold the two
against each other.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Sequence

import numpy as np

from bcid_ros.estimators.bciv.solver import (BcivSolver, check_structure, DEFAULT_TOLERANCE,
                                             INPUT_NOISE)
from bcid_ros.estimators.bciv.units import regularisation_weights, window_scales


@dataclasses.dataclass(frozen=True)
class BcivBatch:
    """
    Batch BCIV estimates at one or more sample counts.

    Attributes
    ----------
    samples : numpy.ndarray, shape ``(k,)``
        The sample counts t (data length) of each row.
    theta, theta_iv : numpy.ndarray, shape ``(k, p)``
        theta_BCIV and theta_IV (eq. 38) from the data up to t.
    noise : numpy.ndarray, shape ``(k, q)``
        gamma~ normalised by the weighted count.
    iterations : numpy.ndarray, shape ``(k,)``
    status : tuple of str
        ``''`` or the fallback reason, per row.

    """

    samples: np.ndarray
    theta: np.ndarray
    theta_iv: np.ndarray
    noise: np.ndarray
    iterations: np.ndarray
    status: tuple[str, ...]


def bciv_batch(y: Any, u: Any, *, order: int, iv_lag: int = 5, input_noise: str = 'colored',
               feedthrough: bool = False, bciv_iterations: int = 20,
               tolerance: float = DEFAULT_TOLERANCE, initial_covariance: float = 1e6,
               forgetting_factor: float = 1.0, idle_samples: int = 0,
               checkpoints: Sequence[int] | None = None, allow_underdetermined: bool = False,
               iv_weight: Any = None, noise_weight: Any = None) -> BcivBatch:
    r"""
    Return the batch BCIV reference: moments over the data, then the same solver.

    For each checkpoint t the moments of the first t samples are summed at
    once, :math:`\bar S = \sum \lambda^{N-i}\eta_i[p_i^T, -z_i]`, and
    :meth:`BcivSolver.estimate` gives the estimate: K alternations from
    theta_IV (colored) or the fixed point from theta_IV (white). This is what
    :class:`~bcid_ros.estimators.bciv.online.Bciv` with
    ``bciv_update='converged'`` computes recursively.

    Parameters
    ----------
    y, u : array_like, shape ``(N,)``
        Noisy output z and noisy input w.
    order, iv_lag, input_noise, feedthrough, bciv_iterations, tolerance
        As for :class:`~bcid_ros.estimators.bciv.online.Bciv`.
    initial_covariance, forgetting_factor
        rho and lambda, as for :class:`~bcid_ros.estimators.bciv.online.Bciv`
        (M_0 = rho S^-2 with the scales of
        :func:`~bcid_ros.estimators.bciv.units.window_scales`).
    idle_samples : int
        Below this many updates the estimate is theta_IV.
    checkpoints : sequence of int or None
        Data lengths t at which to estimate; None means only t = N.
    allow_underdetermined : bool
        As for :class:`~bcid_ros.estimators.bciv.online.Bciv`.
    iv_weight, noise_weight : array_like or None
        W and X (identity if None).

    Returns
    -------
    BcivBatch
        One row per checkpoint.

    """
    if input_noise not in INPUT_NOISE:
        raise ValueError(f"input_noise must be 'colored' or 'white', got {input_noise!r}")
    check_structure(order, iv_lag, feedthrough, input_noise, allow_underdetermined)
    solver = BcivSolver(order=order, iv_lag=iv_lag, feedthrough=feedthrough,
                        input_noise=input_noise, iv_weight=iv_weight,
                        noise_weight=noise_weight)
    z = np.asarray(y, dtype=float).reshape(-1)
    w = np.asarray(u, dtype=float).reshape(-1)
    count = z.shape[0]
    checkpoints = [count] if checkpoints is None else [int(t) for t in checkpoints]
    eta, pz = solver.data_windows(z, w)
    weights_s = regularisation_weights(*window_scales(z, w, solver.m), order,
                                       solver.num_parameters)
    mode = 'fixed_point' if input_noise == 'white' else 'steps'
    rows = []
    lam = forgetting_factor
    for t in checkpoints:
        updates = max(t - solver.m + 1, 0)
        weights = lam ** np.arange(updates - 1, -1, -1, dtype=float)
        moments = eta[:updates].T @ (pz[:updates] * weights[:, None])
        tau = float(weights.sum())
        row_mode = mode if updates >= max(idle_samples, 1) else 'idle'
        result = solver.estimate(moments, lam ** (2 * updates) / initial_covariance * weights_s,
                                 mode=row_mode, iterations=bciv_iterations, tolerance=tolerance)
        gamma = result.gamma / tau if tau > 0 else result.gamma
        rows.append((result.theta, result.theta_iv, gamma, result.iterations, result.status))
    return BcivBatch(np.array(checkpoints), np.array([r[0] for r in rows]),
                     np.array([r[1] for r in rows]), np.array([r[2] for r in rows]),
                     np.array([r[3] for r in rows]), tuple(r[4] for r in rows))
