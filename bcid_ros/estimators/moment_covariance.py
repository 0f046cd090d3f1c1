r"""
The covariance of an estimate that is a smooth function of weighted moment sums.

bciv and cl_bcls publish an estimate :math:`\hat\theta = F(\bar v)` of the
weighted means :math:`\bar v = \tau^{-1}\sum_t w_t x_t` of per-sample moment
terms :math:`x_t` (bciv: :math:`\eta_t[p_t^T, -z_t]`; cl_bcls:
:math:`\psi\psi^T, \psi y_f, y_f^2`), :math:`w_t = \lambda^{N-t}`,
:math:`\tau = \sum_t w_t`. The delta method gives

.. math::

    \mathrm{cov}\,\hat\theta = \frac{\tau_2}{\tau^2}\, J\,\Omega\,J^T, \qquad
    J = \frac{\partial F}{\partial \bar v}, \quad
    \Omega = \sum_{k=-\infty}^{\infty} \mathrm{cov}(x_t, x_{t-k}),

with :math:`\tau_2 = \sum_t w_t^2` and :math:`\Omega` the long-run
covariance of the (coloured) moment terms. :class:`MomentBlocks` estimates
:math:`\Omega` by batch means: the estimator hands it its moment sums once
per block of B updates; the block's own sum is
:math:`D_k = S_k - \lambda^B S_{k-1}`, with weights
:math:`\omega_{1,k} = \sum_{j<B}\lambda^j`, :math:`\omega_{2,k} = \sum_{j<B}\lambda^{2j}`,
and

.. math::

    \hat\Omega = \frac{K}{K - G}\,
        \frac{\sum_k (D_k - \omega_{1,k}\hat\mu_{g(k)})(D_k - \omega_{1,k}\hat\mu_{g(k)})^T}
             {\sum_k \omega_{2,k}}

over K blocks in G groups (a group: blocks of the same prefilter, whose
moments share one mean :math:`\hat\mu_g = \sum_{k\in g} D_k / \sum_{k\in g}\omega_{1,k}`).
Blocks start ``BLOCK`` updates long; at ``MAX_BLOCKS`` adjacent pairs merge
and B doubles, so B grows with the data and keeps about 32-64 blocks (with
forgetting B stops at ``1/(16(1 - lambda))`` and the oldest block is
dropped instead). A block whose sums do not follow from the previous
snapshot (a reset, a memory cut, an undone step, a new window) is skipped.

:math:`J` is a central difference of F, evaluated at the moments of a block
boundary chosen by the update count (every time the count grew by
``JACOBIAN_GROWTH``, at most ``JACOBIAN_PERIOD`` updates apart), and only
when the covariance is read: the result does not depend on when it is read.
docs/estimators.md ("Uncertainty") has the derivation and the measured
coverage.
"""

from __future__ import annotations

import math
from typing import Any, Callable

import numpy as np

from bcid_ros.estimators.base import weighted_square_ratio

#: Updates in a block at first (the block length doubles at each merge).
BLOCK = 32
#: At this many blocks adjacent pairs merge (or, with forgetting, the oldest goes).
MAX_BLOCKS = 64
#: No covariance from fewer blocks (the spread of fewer is too noisy).
MIN_BLOCKS = 16
#: The Jacobian is re-evaluated once the update count grew by this factor...
JACOBIAN_GROWTH = 1.25
#: ...or by this many updates.
JACOBIAN_PERIOD = 4096
#: Central-difference step, relative to |v_i| + the per-sample spread of v_i.
STEP = 1e-4
#: The relative mismatch of tau above which a block's sums are not one block's.
CONSISTENCY = 1e-9
#: With forgetting, blocks stop growing at this fraction of the memory 1 / (1 - lambda).
MEMORY_FRACTION = 1.0 / 16.0

#: F: mean moments (flat) -> estimate.
MomentFunction = Callable[[np.ndarray], np.ndarray]


class MomentBlocks:
    """
    Block sums of an estimator's moment terms, and the covariance of its estimate from them.

    The estimator calls :meth:`close` when its update count reaches
    :attr:`next_boundary` (a single comparison per sample) and
    :meth:`covariance` when the covariance is read. Not part of the
    estimator's saved state: after :meth:`clear` (or a restored state) the
    covariance is None again until ``MIN_BLOCKS`` blocks are taken.
    """

    def __init__(self) -> None:
        self.clear()

    def clear(self) -> None:
        """Forget every block and the Jacobian."""
        self.next_boundary = 0
        self._length = BLOCK
        self._base: np.ndarray | None = None
        self._base_count = 0
        self._base_tau = 0.0
        self._sums: list[np.ndarray] = []
        self._weights: list[tuple[int, float, float]] = []  # rows, omega_1, omega_2
        self._tags: list[Any] = []
        self._function: MomentFunction | None = None
        self._point = np.zeros(0)
        self._jacobian_count = 0
        self._jacobian: np.ndarray | None = None
        self._cache: np.ndarray | None = None

    @property
    def blocks(self) -> int:
        """Count the blocks held."""
        return len(self._sums)

    @property
    def block_length(self) -> int:
        """Return the current block length B in updates."""
        return self._length

    def close(self, count: int, sums: np.ndarray, tau: float, forgetting_factor: float,
              tag: Any, function: Callable[[], MomentFunction]) -> None:
        """
        Take the moment sums at a block boundary.

        Parameters
        ----------
        count : int
            The estimator's update count (the clock of the blocks).
        sums : numpy.ndarray
            The weighted moment sums S (any shape; copied, flattened).
        tau : float
            The weighted count of S, sum of lambda^(N-t).
        forgetting_factor : float
            lambda since the previous boundary.
        tag : hashable
            Blocks with equal tags share one mean (the prefilter in use).
        function : callable
            Returns F for the moments now; called only when a Jacobian is due.

        """
        flat = np.array(sums, dtype=float).reshape(-1)
        lam = forgetting_factor
        rows = count - self._base_count
        if self._base is not None and rows > 0 and self._base.shape == flat.shape:
            decay = lam ** rows
            omega1 = float(rows) if lam == 1.0 else (1.0 - decay) / (1.0 - lam)
            omega2 = float(rows) if lam == 1.0 else (1.0 - decay * decay) / (1.0 - lam * lam)
            if abs(tau - (decay * self._base_tau + omega1)) <= CONSISTENCY * max(tau, 1.0):
                self._add(flat - decay * self._base, rows, omega1, omega2, tag, lam)
        elif self._base is not None and self._base.shape != flat.shape:
            self.clear()
        self._base, self._base_count, self._base_tau = flat, count, tau
        if tau > 0.0 and (self._function is None or count >= min(
                JACOBIAN_GROWTH * self._jacobian_count, self._jacobian_count + JACOBIAN_PERIOD)):
            self._function = function()
            self._point = flat / tau
            self._jacobian_count = count
            self._jacobian = None
            self._cache = None
        self.next_boundary = count + self._length

    def _add(self, block: np.ndarray, rows: int, omega1: float, omega2: float, tag: Any,
             lam: float) -> None:
        self._sums.append(block)
        self._weights.append((rows, omega1, omega2))
        self._tags.append(tag)
        self._cache = None
        if len(self._sums) < MAX_BLOCKS:
            return
        memory = math.inf if lam == 1.0 else 1.0 / (1.0 - lam)
        if 2 * self._length > MEMORY_FRACTION * memory:
            del self._sums[0], self._weights[0], self._tags[0]
            return
        sums, weights, tags = [], [], []
        for first in range(0, len(self._sums) - 1, 2):
            (rows_a, w1_a, w2_a), (rows_b, w1_b, w2_b) = self._weights[first:first + 2]
            decay = lam ** rows_b
            sums.append(decay * self._sums[first] + self._sums[first + 1])
            weights.append((rows_a + rows_b, decay * w1_a + w1_b,
                            decay * decay * w2_a + w2_b))
            tags.append(self._tags[first + 1])
        self._sums, self._weights, self._tags = sums, weights, tags
        self._length *= 2

    def covariance(self, tau: float, forgetting_factor: float) -> np.ndarray | None:
        r"""
        Return :math:`(\tau_2/\tau^2) J\hat\Omega J^T`, or None before ``MIN_BLOCKS`` blocks.

        None as well if F fails or is not finite near the moments.
        """
        if len(self._sums) < MIN_BLOCKS or self._function is None or not tau > 0.0:
            return None
        if self._cache is None:
            self._cache = self._long_run()
        if self._cache is None:
            return None
        return self._cache * (weighted_square_ratio(tau, forgetting_factor) / tau)

    def _residuals(self) -> tuple[np.ndarray, float]:
        """Return the centred block sums (K, d) and the denominator of Omega."""
        sums = np.array(self._sums)
        omega1 = np.array([w[1] for w in self._weights])
        omega2 = np.array([w[2] for w in self._weights])
        residuals = np.empty_like(sums)
        groups = {}
        for index, tag in enumerate(self._tags):
            groups.setdefault(tag, []).append(index)
        for members in groups.values():
            mean = sums[members].sum(axis=0) / omega1[members].sum()
            residuals[members] = sums[members] - omega1[members, None] * mean
        count = len(self._sums)
        return residuals, float(omega2.sum()) * (count - len(groups)) / count

    def _long_run(self) -> np.ndarray | None:
        """Return J Omega J^T (per sample), or None."""
        residuals, denominator = self._residuals()
        if not denominator > 0.0:
            return None
        if self._jacobian is None:
            spread = np.sqrt((residuals * residuals).sum(axis=0) / denominator)
            jacobian = central_jacobian(self._function, self._point,
                                        STEP * (np.abs(self._point) + spread))
            # a failed F is not retried at every read: no covariance until the next Jacobian
            self._jacobian = np.zeros((0, 0)) if jacobian is None else jacobian
        if self._jacobian.size == 0:
            return None
        projected = residuals @ self._jacobian.T
        covariance = projected.T @ projected / denominator
        if not np.isfinite(covariance).all():
            return None
        return 0.5 * (covariance + covariance.T)


def central_jacobian(function: MomentFunction, point: np.ndarray,
                     steps: np.ndarray) -> np.ndarray | None:
    """Return dF/dv at ``point`` by central differences (zero steps: zero columns), or None."""
    columns = []
    try:
        with np.errstate(all='ignore'):
            size = np.asarray(function(point)).shape[0]
            for index, step in enumerate(steps.tolist()):
                if not step > 0.0 or not math.isfinite(step):
                    columns.append(np.zeros(size))
                    continue
                shifted = point.copy()
                shifted[index] += step
                upper = np.array(function(shifted), dtype=float)
                shifted[index] = point[index] - step
                lower = np.asarray(function(shifted), dtype=float)
                columns.append((upper - lower) / (2.0 * step))
    except (ArithmeticError, ValueError, np.linalg.LinAlgError):
        return None
    jacobian = np.array(columns).T
    return jacobian if np.isfinite(jacobian).all() else None


def fixed_point_system(step: Callable[[np.ndarray], np.ndarray],
                       start: np.ndarray) -> np.ndarray:
    r"""Return :math:`I - \partial G/\partial\theta` at ``start`` (central differences)."""
    size = start.shape[0]
    scale = 1e-6 * (np.abs(start) + 1e-3)
    gradient = np.empty((size, size))
    for index in range(size):
        shifted = start.copy()
        shifted[index] += scale[index]
        upper = step(shifted)
        shifted[index] = start[index] - scale[index]
        gradient[:, index] = (upper - step(shifted)) / (2.0 * scale[index])
    return np.eye(size) - gradient


def implicit_step(step: Callable[[np.ndarray], np.ndarray], start: np.ndarray,
                  system: np.ndarray) -> np.ndarray:
    r"""
    Return :math:`\theta_0 - A^{-1}(\theta_0 - G(\theta_0))`, one chord step from ``start``.

    With :math:`A` = ``system`` = :math:`I - \partial G/\partial\theta` at
    :math:`(\theta_0, \bar v_0)` (:func:`fixed_point_system`), its derivative
    in :math:`\bar v` is :math:`A^{-1}\partial G/\partial\bar v`: that of the
    fixed point :math:`\theta = G(\theta, \bar v)` by the implicit function
    theorem, evaluated at the published :math:`\theta_0` whether or not the
    iteration itself has converged there.
    """
    return start - np.linalg.solve(system, start - step(start))
