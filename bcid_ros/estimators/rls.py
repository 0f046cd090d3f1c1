"""
Recursive least squares on the ARX regressor: the baseline estimator.

The recursion is eqs. (47)-(50) of Ding, Chen and Qiu (2006) with an
exponential forgetting factor, written so that the covariance P stays
symmetric positive definite and cannot wind up when the data stop being
exciting.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from bcid_ros.estimators.base import RecursiveEstimator
from bcid_ros.estimators.regressor import ArxRegressor

#: How often (in updates) the covariance is checked by a Cholesky factorisation.
HEALTH_CHECK_PERIOD = 1000

#: BLAS level-1/2 kernels, loaded from scipy on first use (see :func:`rls_step`).
_BLAS: dict[str, Any] = {}


def _load_blas() -> dict[str, Any]:
    """Import the scipy BLAS wrappers only when an RLS step is first made."""
    if not _BLAS:
        from scipy.linalg.blas import daxpy, dgemv, dger
        _BLAS.update(daxpy=daxpy, dgemv=dgemv, dger=dger)
    return _BLAS


def rls_innovation(theta: np.ndarray, p: np.ndarray, phi: np.ndarray, y: float,
                   lam: float) -> tuple[float, np.ndarray, float]:
    r"""
    Return the a-priori quantities of one RLS step, eqs. (47)-(48).

    Parameters
    ----------
    theta : numpy.ndarray, shape ``(p,)``
        :math:`\hat\theta(t-1)`.
    p : numpy.ndarray, shape ``(p, p)``
        :math:`P(t-1)`, symmetric positive definite.
    phi : numpy.ndarray, shape ``(p,)``
        :math:`\varphi(t)`.
    y : float
        :math:`y(t)`.
    lam : float
        Forgetting factor :math:`\lambda`.

    Returns
    -------
    e : float
        :math:`e(t) = y(t) - \varphi^T(t)\hat\theta(t-1)`.
    g : numpy.ndarray, shape ``(p,)``
        :math:`g = P(t-1)\varphi(t)`.
    s : float
        :math:`s(t) = \lambda + \varphi^T(t) P(t-1)\varphi(t)`; not finite or
        :math:`\le 0` means the step must not be made.

    """
    # ndarray.dot: half the call overhead of @ at this size
    g = p.dot(phi)
    return y - phi.dot(theta), g, lam + phi.dot(g)


def rls_step(theta: np.ndarray, p: np.ndarray, g: np.ndarray, s: float,
             e: float) -> np.ndarray:
    r"""
    Make the RLS step (47)-(49) in place, without the division by :math:`\lambda`.

    :math:`\hat\theta \leftarrow \hat\theta + g e/s` and
    :math:`P \leftarrow P - h h^T` with :math:`h = g/\sqrt{s}`, which is
    symmetric to the last bit. ``g``, ``s`` and ``e`` come from
    :func:`rls_innovation` and ``s`` must be finite and positive.

    Returns
    -------
    numpy.ndarray, shape ``(p, p)``
        The downdated P (the memory of ``p``, updated in place when ``p``
        is C-contiguous).

    """
    blas = _BLAS or _load_blas()
    # theta(t) = theta(t-1) + g e / s   (BLAS axpy, in place)
    blas['daxpy'](g, theta, a=e / s)
    h = g * (1.0 / math.sqrt(s))
    # BLAS rank-1 update in place (P is C-ordered, so P.T is the Fortran view)
    return blas['dger'](-1.0, h, h, a=p.T, overwrite_a=True).T


def repair_covariance(p: np.ndarray, fallback: np.ndarray,
                      weights: np.ndarray | None = None) -> np.ndarray:
    """
    Return the nearest symmetric positive definite matrix to ``p``.

    The symmetric part is diagonally scaled by ``weights`` (the inverse
    signal scales, so that the eigenvalue floor is relative in normalised
    units), its eigenvalues are clipped at 1e-12 of the largest (at least
    1e-12) and the scaling is undone. A non-finite ``p`` is replaced by
    ``fallback`` (a copy).
    """
    sym = 0.5 * (p + p.T)
    if not np.isfinite(sym).all():
        return fallback.copy()
    w = np.ones(p.shape[0]) if weights is None else weights
    values, vectors = np.linalg.eigh(sym * np.outer(w, w))
    floor = max(values.max(), 1.0) * 1e-12
    vectors = vectors / w[:, None]
    return (vectors * np.maximum(values, floor)) @ vectors.T


class Rls(RecursiveEstimator):
    r"""
    Recursive least squares with forgetting, anti-windup and a guarded covariance.

    For the ARX regressor :math:`\varphi(t)` of Ding et al. (2006), eqs. (53)-(55):

    .. math::

        e(t) &= y(t) - \varphi^T(t)\hat\theta(t-1) \\
        s(t) &= \lambda + \varphi^T(t) P(t-1) \varphi(t) \\
        \hat\theta(t) &= \hat\theta(t-1) + P(t-1)\varphi(t)\, e(t) / s(t)
            && \text{(47), (48)} \\
        P(t) &= \frac{1}{\lambda}\Big[P(t-1) - \frac{P(t-1)\varphi(t)\varphi^T(t)P(t-1)}{s(t)}\Big]
            && \text{(49)} \\
        J(t) &= \lambda J(t-1) + \lambda e^2(t) / s(t) && \text{(50)} \\
        \tau(t) &= \lambda \tau(t-1) + 1

    With :math:`\lambda = 1` this is exactly the paper's recursion and
    :math:`\tau(t) = t`. :math:`\tau` is the weighted sample count and
    :math:`J/\tau` the published residual variance.

    Numerical safeguards:

    * the downdate is written as :math:`P - h h^T` with :math:`h = P\varphi/\sqrt{s}`,
      which is symmetric to the last bit;
    * anti-windup: the division by :math:`\lambda` is skipped while
      :math:`\mathrm{tr}\,P` exceeds its initial value :math:`p_0 p`, so P stays
      bounded when the input stops exciting the plant (flag ``windup_limited``);
    * every ``HEALTH_CHECK_PERIOD`` updates, and whenever :math:`s \le 0`, P is
      checked by a Cholesky factorisation and, if it has lost definiteness,
      rebuilt from its symmetric part with eigenvalues clipped (flag
      ``covariance_repaired``).

    Parameters
    ----------
    order, num_inputs, feedthrough, initial_covariance, forgetting_factor
        See :class:`~bcid_ros.estimators.base.RecursiveEstimator`.

    """

    name = 'rls'
    noise_names = ('residual_variance',)
    #: Extra constructor keywords (ROS parameter names) beyond the base ones.
    options: tuple[str, ...] = ()

    def __init__(self, **settings: Any) -> None:
        super().__init__(**settings)
        self._regressor = ArxRegressor(self.order, self.num_inputs, self.feedthrough)
        self._trace_limit = self.initial_covariance * self.num_parameters
        self._reset()

    # ------------------------------------------------------------- the step
    def _update(self, y: float, u: np.ndarray) -> None:
        phi = self._regressor.push(y, u)
        if self._regressor.ready and self._ls_step(y, phi):
            self._after_ls_step()

    def _after_ls_step(self) -> None:
        """Extend the LS step (the bias compensation of subclasses); nothing here."""

    def _ls_step(self, y: float, phi: np.ndarray) -> bool:
        """Do the RLS step (47)-(50) on a ready regressor ``phi``; return whether it did."""
        lam = self._forgetting_factor
        e, g, s = rls_innovation(self._theta_ls, self._p, phi, y, lam)
        if not s > 0.0:
            self._repair_covariance()
            return False
        self._p = rls_step(self._theta_ls, self._p, g, s, e)
        # J(t) = lambda J(t-1) + lambda e^2 / s ; tau(t) = lambda tau(t-1) + 1
        self._loss = lam * (self._loss + e * e / s)
        self._tau = lam * self._tau + 1.0
        if lam < 1.0:
            self._forget()
        self._updates += 1
        if self._updates % HEALTH_CHECK_PERIOD == 0:
            self._check_covariance()
        return True

    def _forget(self) -> None:
        """Apply P(t) <- P(t) / lambda unless that would wind P up past its start."""
        if np.trace(self._p) < self._trace_limit:
            self._p *= 1.0 / self._forgetting_factor
        else:
            self._flag('windup_limited')

    def _check_covariance(self) -> None:
        try:
            np.linalg.cholesky(self._p)
        except np.linalg.LinAlgError:
            self._repair_covariance()

    def _repair_covariance(self) -> None:
        """Rebuild P as the nearest symmetric positive definite matrix."""
        self._flag('covariance_repaired')
        self._p = repair_covariance(
            self._p, self.initial_covariance * np.eye(self.num_parameters))

    # --------------------------------------------------------- the accessors
    @property
    def valid(self) -> bool:
        """Whether phi(t) is filled and at least p updates have been made."""
        return self._updates >= self.num_parameters

    @property
    def samples(self) -> int:
        """Count the estimator updates (samples with a filled regressor)."""
        return self._updates

    @property
    def covariance(self) -> np.ndarray:
        """Return the covariance matrix P(t), shape ``(p, p)`` (a copy)."""
        return self._p.copy()

    @property
    def covariance_trace(self) -> float:
        """Return tr P(t)."""
        return float(np.trace(self._p))

    @property
    def loss(self) -> float:
        """Return the weighted loss J(t) of eq. (50)."""
        return self._loss

    @property
    def weighted_count(self) -> float:
        """Return tau(t) = sum of lambda^(t-i); equals t when lambda = 1."""
        return self._tau

    def _theta(self) -> np.ndarray:
        return self._theta_ls

    def _theta_uncompensated(self) -> np.ndarray:
        return self._theta_ls

    def _noise(self) -> np.ndarray:
        return np.array([self._loss / self._tau if self._tau > 0 else 0.0])

    # -------------------------------------------------------------- the state
    def _reset(self) -> None:
        p = self.num_parameters
        self._regressor.clear()
        self._theta_ls = np.zeros(p)
        self._p = self.initial_covariance * np.eye(p)
        self._loss = 0.0
        self._tau = 0.0
        self._updates = 0

    def _restart_regressor(self) -> None:
        self._regressor.clear()

    def _state_items(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        arrays = {'theta_ls': self._theta_ls, 'p': self._p,
                  'history': self._regressor.history}
        scalars = {'loss': self._loss, 'tau': self._tau, 'updates': self._updates,
                   'filled': self._regressor.filled,
                   'position': self._regressor.position,
                   'forgetting_factor': self._forgetting_factor}
        return arrays, scalars

    def _load_state(self, arrays: dict[str, np.ndarray], scalars: dict[str, Any]) -> None:
        self._theta_ls = arrays['theta_ls']
        self._p = arrays['p']
        self._regressor.history[:] = arrays['history']
        self._regressor.filled = int(scalars['filled'])
        self._regressor.position = int(scalars['position'])
        self._loss = float(scalars['loss'])
        self._tau = float(scalars['tau'])
        self._updates = int(scalars['updates'])
        self._forgetting_factor = float(scalars['forgetting_factor'])


def ls_batch(y: np.ndarray, u: np.ndarray, *, order: int, num_inputs: int = 1,
             feedthrough: bool = False, initial_covariance: float | None = None,
             forgetting_factor: float = 1.0) -> tuple[np.ndarray, np.ndarray, float, float]:
    r"""
    Solve the (weighted, regularised) least-squares problem that :class:`Rls` solves recursively.

    .. math::

        \hat\theta_{LS}(N) = \Big[\lambda^{N'} P_0^{-1} + \sum_i \lambda^{N'-i}\varphi(i)
            \varphi^T(i)\Big]^{-1} \sum_i \lambda^{N'-i}\varphi(i) y(i)

    over the N' = N - n updates that have a filled regressor. With
    ``initial_covariance=None`` the :math:`P_0^{-1}` term is dropped (plain LS).

    Parameters
    ----------
    y : numpy.ndarray, shape ``(N,)``
        Outputs.
    u : numpy.ndarray, shape ``(N,)`` or ``(N, r)``
        Inputs.
    order, num_inputs, feedthrough, initial_covariance, forgetting_factor
        As for :class:`Rls`.

    Returns
    -------
    theta : numpy.ndarray, shape ``(p,)``
        The LS estimate.
    p : numpy.ndarray, shape ``(p, p)``
        The inverse of the (regularised) weighted information matrix.
    loss : float
        J = weighted sum of squared residuals at theta.
    tau : float
        Weighted sample count sum(lambda^(N'-i)).

    """
    y = np.asarray(y, dtype=float).reshape(-1)
    u = np.asarray(u, dtype=float).reshape(y.shape[0], -1)
    phi = ArxRegressor(order, num_inputs, feedthrough).regressors(y, u)
    target = y[order:]
    weights = forgetting_factor ** np.arange(phi.shape[0] - 1, -1, -1, dtype=float)
    information = (phi * weights[:, None]).T @ phi
    if initial_covariance is not None:
        information += forgetting_factor ** phi.shape[0] / initial_covariance * np.eye(
            phi.shape[1])
    theta = np.linalg.solve(information, (phi * weights[:, None]).T @ target)
    residual = target - phi @ theta
    return theta, np.linalg.inv(information), float(weights @ residual ** 2), float(
        weights.sum())
