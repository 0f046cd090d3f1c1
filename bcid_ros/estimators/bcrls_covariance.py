"""
The sandwich covariance of BCRLS: lagged moments of z = [phi; y] and H^-1 S H^-T.

The estimating equations of the BCLS fixed point (Ding, Chen and Qiu 2006,
eqs. (24) and (39)) have MA(n) scores on output-error data; their sandwich
needs the lagged moments of the extended regressor z = [phi; y], kept here
per plant and summed a block at a time (docs/estimators.md, "Uncertainty").
:class:`~bcid_ros.estimators.bcrls.Bcrls` holds one plant's, the batched form K.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from bcid_ros.estimators.recursion import rows_view

#: The extended regressors z = [phi; y] of this many updates are kept, then
#: added to the lagged moments of the covariance in one product per lag.
MOMENT_BLOCK = 64


class LaggedMoments:
    """
    The lagged moments of z = [phi; y] of K plants, kept for the sandwich covariance.

    Per plant: a ring holding the lag context (the last n rows already summed)
    and up to ``MOMENT_BLOCK`` rows not yet summed; the weighted sums of
    z_t z_{t-k}' (k = 0..n) and of the weights; the estimates and scales at
    the last flush; and the sandwich of that block once computed. A full
    block is summed at once (:func:`add_lagged_moments`); the sandwich
    (:func:`block_sandwich`) is evaluated only when read. Bcrls holds one
    with K = 1 (its hot path collects the rows in lists, then hands over a
    full block), BatchedBcrls one over its plants.
    """

    def __init__(self, plants: int, order: int, num_parameters: int) -> None:
        self.order = order
        width = num_parameters + 1
        self.ring = np.zeros((plants, order + MOMENT_BLOCK, width))
        self.pending = np.zeros(plants, dtype=np.intp)
        self.sums = np.zeros((plants, order + 1, width, width))
        self.weight = np.zeros(plants)
        self.snapshot = np.zeros((plants, 2, width))
        self.sandwich = np.full((plants, num_parameters, num_parameters), np.nan)
        self.due = np.zeros(plants, dtype=bool)

    def clear(self, rows: Any) -> None:
        """Forget the moments of ``rows``."""
        for array in (self.ring, self.pending, self.sums, self.weight, self.snapshot):
            array[rows] = 0
        self.sandwich[rows] = np.nan
        self.due[rows] = False

    def record(self, rows: np.ndarray, y: np.ndarray, phi: np.ndarray) -> np.ndarray:
        """Keep z = [phi; y] of ``rows``; return the plants whose block is now full."""
        at = rows_view(rows, self.pending.shape[0])  # (every plant's: no copies)
        pending = self.pending[at]
        slots = self.order + pending
        self.ring[rows, slots, :-1] = phi
        self.ring[rows, slots, -1] = y
        pending += 1
        self.pending[at] = pending
        return rows[pending == MOMENT_BLOCK]

    def flush(self, rows: np.ndarray | slice, forgetting_factor: float, theta_c: np.ndarray,
              sigma2: np.ndarray, component_scale: np.ndarray, y_scale: np.ndarray) -> None:
        """Sum the full blocks of ``rows``; keep their estimates and scales for the sandwich."""
        n, ring = self.order, self.ring[rows]
        self.sums[rows], self.weight[rows] = add_lagged_moments(
            self.sums[rows], self.weight[rows], ring, n, forgetting_factor)
        # the last n rows are the lag context of the next block
        self.ring[rows, :n] = ring[:, MOMENT_BLOCK:]
        self.pending[rows] = 0
        self.snapshot[rows, 0, :-1] = theta_c
        self.snapshot[rows, 0, -1] = sigma2
        self.snapshot[rows, 1, :-1] = component_scale
        self.snapshot[rows, 1, -1] = np.where(y_scale > 0.0, y_scale, 1.0)
        self.due[rows] = True

    def sandwiches(self, known: np.ndarray) -> np.ndarray:
        """
        Return H^-1 S H^-T of each plant's last block, ``(K, p, p)``; NaN where ``known`` is not.

        All plants whose block ended since the last read are evaluated in one
        batched call; a singular one (LinAlgError) is evaluated alone and
        stays NaN.
        """
        due = np.flatnonzero(known & self.due)
        if due.size:
            try:
                self.sandwich[due] = block_sandwich(self.sums[due], self.weight[due],
                                                    self.snapshot[due], self.order)
            except np.linalg.LinAlgError:
                for plant in due.tolist():
                    self.sandwich[plant] = sandwich_or_nan(
                        self.sums[plant], self.weight[plant], self.snapshot[plant], self.order)
            self.due[due] = False
        return np.where(known[:, None, None], self.sandwich, np.nan)

    def plant_items(self, plant: int) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Return plant k's moments as a single-plant snapshot's (arrays, scalars)."""
        ring = self.ring[plant].copy()
        ring[self.order + int(self.pending[plant]):] = 0.0
        return ({'moment_ring': ring, 'moment_sums': self.sums[plant],
                 'moment_snapshot': self.snapshot[plant]},
                {'moment_pending': int(self.pending[plant]),
                 'moment_weight': float(self.weight[plant])})

    def load_plant(self, plant: int, arrays: dict[str, np.ndarray],
                   scalars: dict[str, Any]) -> None:
        """Take over plant k's moments from a snapshot made by :meth:`plant_items`."""
        self.ring[plant] = arrays['moment_ring']
        self.pending[plant] = int(scalars['moment_pending'])
        self.sums[plant] = arrays['moment_sums']
        self.weight[plant] = float(scalars['moment_weight'])
        self.snapshot[plant] = arrays['moment_snapshot']
        self.sandwich[plant] = np.nan
        self.due[plant] = self.weight[plant] > 0.0


def add_lagged_moments(sums: np.ndarray, weight: Any, ring: np.ndarray, order: int,
                       forgetting_factor: float) -> tuple[np.ndarray, Any]:
    """
    Return the lagged moment sums and their weight with the new rows of ``ring`` added.

    ``ring`` ``(..., n + m, p + 1)`` holds the lag context (the last n rows z
    already summed) then m new rows z = [phi; y], oldest first; ``sums``
    ``(..., n + 1, p + 1, p + 1)`` are the sums of w_t z_t z_{t-k}' (k = 0..n)
    and ``weight`` ``(...)`` the sum of w_t. Old sums decay by lambda^m, the
    newest row has weight 1. Leading dimensions are plants (the batched
    estimators).
    """
    n, lam = order, forgetting_factor
    count = ring.shape[-2] - n
    decay = lam ** count
    sums = sums * decay
    weight = weight * decay
    if count:
        newest = ring[..., n:, :]
        if lam == 1.0:  # all weights 1: no product to form
            weight = weight + float(count)
        else:
            # w = lambda^(age): the newest row has weight 1
            weights = lam ** np.arange(count - 1, -1, -1, dtype=float)
            newest = newest * weights[:, None]
            weight = weight + float(weights.sum())
        newest = np.swapaxes(newest, -1, -2)
        for k in range(n + 1):
            sums[..., k, :, :] += newest @ ring[..., n - k:n - k + count, :]
    return sums, weight


def block_sandwich(sums: np.ndarray, weight: Any, snapshot: np.ndarray,
                   order: int) -> np.ndarray:
    """
    Return H^-1 S H^-T in the user's units from the moments and estimates of a block.

    ``sums`` ``(..., n + 1, p + 1, p + 1)`` are the weighted sums of
    z_t z_{t-k}' (k = 0..n) over ``weight`` ``(...)``; ``snapshot``
    ``(..., 2, p + 1)`` holds ``[theta_c, sigma2]`` and ``[scales of phi,
    scale of y]`` at the block's end. Leading dimensions are plants (the
    batched estimators). The sandwich is evaluated in normalised units
    (z / scale), where its conditioning does not depend on the user's units.
    """
    estimates, scale = snapshot[..., 0, :], snapshot[..., 1, :]
    p = estimates.shape[-1] - 1
    # normalised units: z~ = z / scale, theta~_k = theta_k s_k / s_y, sigma2~ = sigma2 / s_y^2
    y_scale = scale[..., p:]
    outer = scale[..., :, None] * scale[..., None, :]
    gamma_z = sums / (np.asarray(weight)[..., None, None, None] * outer[..., None, :, :])
    theta = estimates[..., :p] * scale[..., :p] / y_scale
    sigma2 = estimates[..., p] / (y_scale[..., 0] * y_scale[..., 0])
    back = y_scale / scale[..., :p]
    return (bcls_sandwich(gamma_z, theta, sigma2, order)
            * (back[..., :, None] * back[..., None, :]))


def sandwich_or_nan(sums: np.ndarray, weight: float, snapshot: np.ndarray,
                    order: int) -> np.ndarray:
    """Return one plant's :func:`block_sandwich`, or NaN where its bread is singular."""
    try:
        return block_sandwich(sums, weight, snapshot, order)
    except np.linalg.LinAlgError:  # no covariance for this block
        return np.full((snapshot.shape[-1] - 1,) * 2, np.nan)


def bcls_sandwich(gamma_z: np.ndarray, theta: np.ndarray, sigma2: Any,
                  order: int) -> np.ndarray:
    r"""
    Return :math:`H^{-1} S H^{-T}` of the BCLS fixed point, the p x p block of theta.

    Parameters
    ----------
    gamma_z : numpy.ndarray, shape ``(..., n + 1, p + 1, p + 1)``
        :math:`\Gamma_z(k)`, the mean of :math:`z_t z_{t-k}^T` with
        :math:`z = [\varphi; y]`, k = 0..n.
    theta : numpy.ndarray, shape ``(..., p)``
        :math:`\hat\theta_c` (its first n entries are :math:`a_1 \ldots a_n`).
    sigma2 : float or numpy.ndarray, shape ``(...)``
        :math:`\hat\sigma^2`.
    order : int
        n.

    Returns
    -------
    numpy.ndarray, shape ``(..., p, p)``
        The covariance of one sample's worth: divide by the (effective) count.
        Leading dimensions (plants) are computed at once.

    """
    n, p = order, theta.shape[-1]
    sigma2 = np.asarray(sigma2, dtype=float)[..., None]
    lead = theta.shape[:-1]
    a = np.concatenate((np.ones(lead + (1,)), theta[..., :n]), axis=-1)
    # gamma_w(k) = sigma2 sum_i a_i a_{i+k}, k = 0..n
    gamma_w = sigma2 * np.stack([(a[..., :n + 1 - k] * a[..., k:]).sum(axis=-1)
                                 for k in range(n + 1)], axis=-1)
    # c_k = E[zeta_t w_{t-k}], d_k = E[w_t zeta_{t-k}] (rows k); zeta = [-v(t-1..t-n), 0, v(t)]
    padded = np.zeros(lead + (3 * n + 1,))
    padded[..., n:2 * n + 1] = a  # padded[m + n] = a_m, zero outside 0..n
    lags = np.arange(1, n + 1) + n - np.arange(n + 1)[:, None]
    c = np.zeros(lead + (n + 1, p + 1))
    d = np.zeros(lead + (n + 1, p + 1))
    c[..., :n] = -sigma2[..., None] * padded[..., lags]
    d[..., :n] = -sigma2[..., None] * padded[..., lags + 2 * np.arange(n + 1)[:, None]]
    c[..., 0, p] = sigma2[..., 0]
    d[..., p] = sigma2 * a
    # S = S_0 + sum_{k>=1} (S_k + S_k'), S_k = Gamma_z(k) gamma_w(k) + c_k d_k'
    lagged = (np.einsum('...k,...kij->...ij', gamma_w, gamma_z)
              + np.swapaxes(c, -1, -2) @ d)
    first = (gamma_z[..., 0, :, :] * gamma_w[..., :1, None]
             + c[..., 0, :, None] * d[..., 0, None, :])
    meat = lagged + np.swapaxes(lagged, -1, -2) - first
    lam = np.zeros(p)
    lam[:n] = 1.0
    bread = np.empty(lead + (p + 1, p + 1))
    bread[..., :p, :p] = sigma2[..., None] * np.diag(lam) - gamma_z[..., 0, :p, :p]
    bread[..., :p, p] = lam * theta
    bread[..., p, :p] = -gamma_z[..., 0, p, :p]
    bread[..., p, p] = -1.0
    half = np.linalg.solve(bread, meat)
    covariance = np.linalg.solve(bread, np.swapaxes(half, -1, -2))
    return 0.5 * (covariance + np.swapaxes(covariance, -1, -2))[..., :p, :p]
