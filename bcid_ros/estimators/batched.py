"""
RLS and BCRLS over many plants of one structure, with one vectorised update per sample.

A robot's joints, or a fleet's actuators, are K plants with the same model
structure (order n, r inputs, feedthrough) and the same settings. Running K
:class:`~bcid_ros.estimators.rls.Rls` objects costs K Python calls per
sample, most of it call overhead at these sizes. Here the K states are
stacked (theta as ``(K, p)``, P as ``(K, p, p)``, one regressor history per
plant) and each sample of all plants is one numpy pass.

Each plant follows exactly the recursion of its single-plant estimator, with
the single-plant sample policy of the identifier (``SampleFeeder``) applied
per plant: a plant whose sample is missing or not finite restarts its own
regressor and is counted, and the other plants are not touched. Each plant's
estimate therefore equals that of a single-plant estimator fed the same
samples, to 1e-12 (bit for bit where einsum and BLAS sum the dot products in the
same order).

Every step works on the plants ``rows`` whose regressor is filled: it computes
their new state into local arrays and writes it back at the end. A per-plant
condition found on the way (s <= 0 today) narrows ``rows`` before anything is
written, which is where a per-plant gate on the prediction error or a
per-plant rollback would go.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from bcid_ros.estimators.base import (check_int, check_range, EstimatorState,
                                      parameter_names)
from bcid_ros.estimators.bcrls import COMPENSATION_MAX, DENOMINATOR_MIN
from bcid_ros.estimators.rls import HEALTH_CHECK_PERIOD

Rows = slice | np.ndarray


def _matvec(matrices: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    """Return ``matrices[k] @ vectors[k]`` for every k, shape ``(K, p)``."""
    return np.matmul(matrices, vectors[:, :, None])[:, :, 0]


def _rowdot(left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """
    Return ``left[k] . right[k]`` for every k, shape ``(K,)``.

    einsum, not numpy.vecdot: on the machines measured it sums in the order
    of the single-plant estimator's BLAS dot, so the two agree bit for bit;
    vecdot's order starts them 1e-9 apart through the ill-conditioned
    start (P(0) = 1e6 I), and that takes thousands of samples to fade.
    """
    return np.einsum('ki,ki->k', left, right)


class BatchedRls:
    r"""
    K independent RLS estimators of one structure, updated together.

    For each plant k the step is that of
    :class:`~bcid_ros.estimators.rls.Rls` (eqs. (47)-(50) of Ding et al.
    (2006) with forgetting):

    .. math::

        e_k &= y_k(t) - \varphi_k^T(t)\hat\theta_k(t-1), \qquad
        s_k = \lambda + \varphi_k^T(t) P_k(t-1)\varphi_k(t) \\
        \hat\theta_k(t) &= \hat\theta_k(t-1) + P_k(t-1)\varphi_k(t)\,e_k/s_k \\
        P_k(t) &= \frac{1}{\lambda}\big[P_k(t-1) - h_k h_k^T\big],
            \qquad h_k = P_k(t-1)\varphi_k(t)/\sqrt{s_k} \\
        J_k(t) &= \lambda J_k(t-1) + \lambda e_k^2/s_k, \qquad
        \tau_k(t) = \lambda\tau_k(t-1) + 1

    with the same safeguards, each per plant and counted per plant in
    :attr:`flags`: anti-windup (the division by :math:`\lambda` is skipped
    while :math:`\mathrm{tr}\,P_k \ge p_0 p`, ``windup_limited``); a
    Cholesky check of :math:`P_k` every ``HEALTH_CHECK_PERIOD`` of its
    updates, and whenever :math:`s_k \le 0` (then plant k makes no update),
    with a rebuild from the symmetric part and clipped eigenvalues when it
    fails (``covariance_repaired``).

    **Samples.** :meth:`update` takes one sample of every plant. Plant k's
    sample is not used when it is marked absent (counted in :attr:`missing`)
    or holds NaN or Inf (counted in :attr:`nonfinite`); its regressor then
    restarts, so no later update regresses across the gap, exactly as the
    identifier does for one plant. The other plants go on undisturbed.

    Parameters
    ----------
    num_plants : int
        K >= 1.
    order, num_inputs, feedthrough, initial_covariance, forgetting_factor
        As for :class:`~bcid_ros.estimators.base.RecursiveEstimator`, shared
        by all plants.

    Raises
    ------
    ValueError
        If a setting is out of range; the message names it.

    """

    #: The single-plant estimator whose recursion each plant follows.
    name: ClassVar[str] = 'rls'
    noise_names: ClassVar[tuple[str, ...]] = ('residual_variance',)

    def __init__(self, num_plants: int, *, order: int, num_inputs: int = 1,
                 feedthrough: bool = False, initial_covariance: float = 1e6,
                 forgetting_factor: float = 1.0) -> None:
        self.num_plants = check_int('num_plants', num_plants, 1)
        self.order = check_int('order', order, 1)
        self.num_inputs = check_int('num_inputs', num_inputs, 1)
        self.feedthrough = bool(feedthrough)
        self.initial_covariance = check_range(
            'initial_covariance', initial_covariance, 0.0, 1e15, low_open=True)
        self._forgetting_factor = check_range(
            'forgetting_factor', forgetting_factor, 0.0, 1.0, low_open=True)
        self.parameter_names = parameter_names(self.order, self.num_inputs, self.feedthrough)
        self.num_parameters = len(self.parameter_names)
        self._trace_limit = self.initial_covariance * self.num_parameters
        # history[k, j] = [-y, u_1, ..., u_r] of plant k's sample t - j (j = 0 newest);
        # phi(t) is one gather from it with a fixed index, since the rows shift.
        rows, width = self.order + 1, 1 + self.num_inputs
        self._history = np.zeros((self.num_plants, rows, width))
        self._flat_history = self._history.reshape(self.num_plants, rows * width)
        first_lag = 0 if self.feedthrough else 1
        index = [lag * width for lag in range(1, self.order + 1)]
        for i in range(self.num_inputs):
            index.extend(lag * width + 1 + i for lag in range(first_lag, self.order + 1))
        self._phi_index = np.array(index, dtype=np.intp)
        #: Samples of each plant that were missing / not finite (not used).
        self.missing = np.zeros(self.num_plants, dtype=np.int64)
        self.nonfinite = np.zeros(self.num_plants, dtype=np.int64)
        self._calls = 0
        self.reset()

    # ----------------------------------------------------------------- API
    def update(self, y: Any, u: Any, present: Any = None) -> np.ndarray:
        """
        Process one sample of every plant and return which estimates are now valid.

        Parameters
        ----------
        y : array_like, shape ``(K,)``
            Output sample y_k(t) of each plant.
        u : array_like, shape ``(K, r)`` (or ``(K,)`` when r = 1)
            Input sample u_k(t) of each plant.
        present : array_like of bool, shape ``(K,)``, optional
            False where plant k has no sample at t (its values are ignored).
            Default: all present.

        Returns
        -------
        numpy.ndarray of bool, shape ``(K,)``
            :attr:`valid` after this sample.

        Raises
        ------
        ValueError
            If an array does not have the shape above. Nothing is changed then.

        """
        y, u, present = self._checked(y, u, present)
        if present is None and np.isfinite(y).all() and np.isfinite(u).all():
            skipped = None
        else:
            usable = np.isfinite(y) & np.isfinite(u).all(axis=1)
            if present is not None:
                self.missing += ~present
                self.nonfinite += present & ~usable
                usable &= present
            else:
                self.nonfinite += ~usable
            skipped = None if usable.all() else np.flatnonzero(~usable)
        self._push(y, u)
        self._calls += 1
        if skipped is not None:
            self._clear_regressors(skipped)
        rows = self._ready_rows()
        if rows is not None:
            self._ls_step(rows, y[rows], self._flat_history[rows][:, self._phi_index])
        return self.valid

    def reset(self, plants: Any = None) -> None:
        """
        Return plants (default: all) to the state right after construction.

        The sample counters :attr:`missing` and :attr:`nonfinite` are kept.
        """
        rows = self._plant_rows(plants)
        p = self.num_parameters
        if isinstance(rows, slice):
            self.flags: dict[str, np.ndarray] = {}
            self._theta_ls = np.zeros((self.num_plants, p))
            self._p = np.zeros((self.num_plants, p, p))
            self._loss = np.zeros(self.num_plants)
            self._tau = np.zeros(self.num_plants)
            self._updates = np.zeros(self.num_plants, dtype=np.int64)
            self._cleared_at = np.zeros(self.num_plants, dtype=np.int64)
        for counts in self.flags.values():
            counts[rows] = 0
        self._theta_ls[rows] = 0.0
        self._p[rows] = self.initial_covariance * np.eye(p)
        self._loss[rows] = 0.0
        self._tau[rows] = 0.0
        self._updates[rows] = 0
        self._clear_regressors(rows)

    def restart_regressor(self, plants: Any = None) -> None:
        """
        Forget the sample history of plants (default: all) but keep what was learnt.

        Each plant's next n + 1 samples refill its regressor before it updates.
        """
        self._clear_regressors(self._plant_rows(plants))

    @property
    def forgetting_factor(self) -> float:
        """Forgetting factor lambda in (0, 1] of all plants; may be changed while running."""
        return self._forgetting_factor

    @forgetting_factor.setter
    def forgetting_factor(self, value: float) -> None:
        self._forgetting_factor = check_range('forgetting_factor', value, 0.0, 1.0,
                                              low_open=True)

    @property
    def theta(self) -> np.ndarray:
        """Compensated estimates, shape ``(K, p)`` (a copy)."""
        return self._theta().copy()

    @property
    def theta_uncompensated(self) -> np.ndarray:
        """LS estimates before compensation, shape ``(K, p)`` (a copy)."""
        return self._theta_ls.copy()

    @property
    def noise(self) -> np.ndarray:
        """Noise estimates named by :attr:`noise_names`, shape ``(K, len(noise_names))``."""
        variance = np.zeros(self.num_plants)
        np.divide(self._loss, self._tau, out=variance, where=self._tau > 0)
        return variance[:, None]

    @property
    def valid(self) -> np.ndarray:
        """Whether each plant has made at least p updates, shape ``(K,)``."""
        return self._updates >= self.num_parameters

    @property
    def samples(self) -> np.ndarray:
        """Count each plant's estimator updates (samples with a filled regressor)."""
        return self._updates.copy()

    @property
    def used(self) -> np.ndarray:
        """Count each plant's samples that went into its regressor, shape ``(K,)``."""
        return self._calls - self.missing - self.nonfinite

    @property
    def covariance(self) -> np.ndarray:
        """Return the covariances P_k(t), shape ``(K, p, p)`` (a copy)."""
        return self._p.copy()

    @property
    def covariance_trace(self) -> np.ndarray:
        """Return tr P_k(t) of each plant, shape ``(K,)``."""
        return np.trace(self._p, axis1=1, axis2=2)

    @property
    def loss(self) -> np.ndarray:
        """Return the weighted losses J_k(t) of eq. (50), shape ``(K,)`` (a copy)."""
        return self._loss.copy()

    @property
    def weighted_count(self) -> np.ndarray:
        """Return tau_k(t), shape ``(K,)`` (a copy)."""
        return self._tau.copy()

    @property
    def nbytes(self) -> int:
        """Bytes held by the per-plant state arrays (all plants), for sizing."""
        arrays = [value for value in vars(self).values()
                  if isinstance(value, np.ndarray) and value.base is None
                  and value.shape[:1] == (self.num_plants,)]
        return sum(array.nbytes for array in arrays + list(self.flags.values()))

    def plant_flags(self, plant: int) -> dict[str, int]:
        """Return the flags counted for one plant (only those that occurred)."""
        return {key: int(counts[plant]) for key, counts in self.flags.items()
                if counts[plant]}

    def plant_state(self, plant: int) -> EstimatorState:
        """
        Return plant k's state as the snapshot its single-plant estimator would make.

        :meth:`~bcid_ros.estimators.base.RecursiveEstimator.set_state` of a
        single-plant estimator of the same configuration accepts it.
        """
        arrays, scalars = self._plant_items(plant)
        rows = self.order + 1
        pushes = self._calls - int(self._cleared_at[plant])
        position = pushes % rows
        # the single-plant regressor is a ring: sample t - j sits in row position - 1 - j
        ring = np.zeros_like(self._history[plant])
        for lag in range(min(pushes, rows)):
            ring[(position - 1 - lag) % rows] = self._history[plant, lag]
        arrays['history'] = ring
        scalars.update(filled=min(pushes, rows), position=position,
                       forgetting_factor=self._forgetting_factor,
                       flags=self.plant_flags(plant))
        return EstimatorState(self.name, {k: np.array(v, copy=True) for k, v in arrays.items()},
                              scalars)

    def set_plant_state(self, plant: int, state: EstimatorState) -> None:
        """
        Load a single-plant snapshot (or one of :meth:`plant_state`) into plant k.

        The forgetting factor in the snapshot is ignored: it is shared by all plants.

        Raises
        ------
        ValueError
            If the snapshot comes from another estimator or other dimensions.

        """
        if state.estimator != self.name:
            raise ValueError(f'state is from estimator {state.estimator!r}, not {self.name!r}')
        arrays, _ = self._plant_items(plant)
        arrays['history'] = self._history[plant]
        for key, value in arrays.items():
            if key not in state.arrays or np.shape(state.arrays[key]) != np.shape(value):
                raise ValueError(f'state array {key!r} does not match this configuration')
        self._load_plant(plant, state.arrays, state.scalars)
        for counts in self.flags.values():
            counts[plant] = 0
        for key, count in dict(state.scalars.get('flags', {})).items():
            self._flag_counts(key)[plant] = count
        rows = self.order + 1
        filled, position = int(state.scalars['filled']), int(state.scalars['position'])
        pushes = filled if filled < rows else rows + position
        self._cleared_at[plant] = self._calls - pushes
        self._last_clear = max(self._last_clear, self._calls - pushes)
        history = np.zeros_like(self._history[plant])
        ring = np.asarray(state.arrays['history'], dtype=float)
        for lag in range(min(filled, rows)):
            history[lag] = ring[(position - 1 - lag) % rows]
        self._history[plant] = history

    def __repr__(self) -> str:
        return (f'{type(self).__name__}(num_plants={self.num_plants}, order={self.order}, '
                f'num_inputs={self.num_inputs}, feedthrough={self.feedthrough}, '
                f'forgetting_factor={self._forgetting_factor})')

    # ------------------------------------------------------------- the step
    def _checked(self, y: Any, u: Any,
                 present: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """Return the sample arrays as float arrays of the documented shapes, or raise."""
        plants, inputs = self.num_plants, self.num_inputs
        y = np.asarray(y, dtype=float)
        u = np.asarray(u, dtype=float)
        if inputs == 1 and u.shape == (plants,):
            u = u[:, None]
        if y.shape != (plants,):
            raise ValueError(f'y must have shape ({plants},), got {y.shape}')
        if u.shape != (plants, inputs):
            raise ValueError(f'u must have shape ({plants}, {inputs}), got {u.shape}')
        if present is not None:
            present = np.asarray(present, dtype=bool)
            if present.shape != (plants,):
                raise ValueError(f'present must have shape ({plants},), got {present.shape}')
            if present.all():
                present = None
        return y, u, present

    def _push(self, y: np.ndarray, u: np.ndarray) -> None:
        """Shift every plant's history by one sample and put sample t in row 0."""
        history = self._history
        history[:, 1:] = history[:, :-1]
        history[:, 0, 0] = -y
        history[:, 0, 1:] = u

    def _clear_regressors(self, rows: Rows) -> None:
        """Empty the histories of ``rows``; they refill from the next sample on."""
        self._history[rows] = 0.0
        self._cleared_at[rows] = self._calls
        self._last_clear = self._calls

    def _ready_rows(self) -> Rows | None:
        """Return the plants whose regressor is filled: a slice if all, else indices or None."""
        if self._calls - self._last_clear > self.order:
            return slice(None)
        ready = np.flatnonzero(self._calls - self._cleared_at > self.order)
        if ready.size == self.num_plants:
            return slice(None)
        return ready if ready.size else None

    def _ls_step(self, rows: Rows, y: np.ndarray, phi: np.ndarray) -> None:
        """Do the RLS step (47)-(50) on the plants ``rows`` with filled regressors ``phi``."""
        lam = self._forgetting_factor
        p_old = self._p[rows]
        # g = P(t-1) phi(t)
        g = _matvec(p_old, phi)
        # s = lambda + phi' P(t-1) phi
        s = lam + _rowdot(phi, g)
        if not (s > 0.0).all():
            # those plants repair P and make no update, as the single-plant step does
            bad = ~(s > 0.0)
            self._repair_covariance(self._indices(rows)[bad])
            rows, keep = self._indices(rows)[~bad], ~bad
            if not rows.size:
                return
            p_old, y, phi, g, s = p_old[keep], y[keep], phi[keep], g[keep], s[keep]
        # e = y(t) - phi'(t) theta(t-1)
        theta = self._theta_ls[rows]
        e = y - _rowdot(phi, theta)
        # theta(t) = theta(t-1) + g e / s   (a new array: nothing is written before the end)
        theta = theta + g * (e / s)[:, None]
        # P(t) = P(t-1) - h h', h = g / sqrt(s)
        h = g * (1.0 / np.sqrt(s))[:, None]
        p_new = p_old - h[:, :, None] * h[:, None, :]
        # J(t) = lambda J(t-1) + lambda e^2 / s ; tau(t) = lambda tau(t-1) + 1
        loss = lam * (self._loss[rows] + e * e / s)
        tau = lam * self._tau[rows] + 1.0
        if lam < 1.0:
            self._forget(rows, p_new)
        updates = self._updates[rows] + 1
        self._theta_ls[rows] = theta
        self._p[rows] = p_new
        self._loss[rows] = loss
        self._tau[rows] = tau
        self._updates[rows] = updates
        self._after_ls_step(rows, theta, p_new, loss, tau)
        due = updates % HEALTH_CHECK_PERIOD == 0
        if due.any():
            self._check_covariance(self._indices(rows)[due])

    def _after_ls_step(self, rows: Rows, theta_ls: np.ndarray, p: np.ndarray,
                       loss: np.ndarray, tau: np.ndarray) -> None:
        """Extend the LS step of ``rows`` (the compensation of subclasses); nothing here."""

    def _forget(self, rows: Rows, p: np.ndarray) -> None:
        """Apply P(t) <- P(t) / lambda in place, per plant unless that winds P up."""
        within = np.trace(p, axis1=1, axis2=2) < self._trace_limit
        p *= np.where(within, 1.0 / self._forgetting_factor, 1.0)[:, None, None]
        if not within.all():
            self._flag('windup_limited', rows, ~within)

    def _check_covariance(self, plants: np.ndarray) -> None:
        """Check P of ``plants`` by Cholesky; repair those that lost definiteness."""
        try:
            np.linalg.cholesky(self._p[plants])
        except np.linalg.LinAlgError:
            for plant in plants:
                try:
                    np.linalg.cholesky(self._p[plant])
                except np.linalg.LinAlgError:
                    self._repair_covariance(np.array([plant]))

    def _repair_covariance(self, plants: np.ndarray) -> None:
        """Rebuild P of ``plants`` as the nearest symmetric positive definite matrices."""
        self._flag('covariance_repaired', plants)
        for plant in plants:
            sym = 0.5 * (self._p[plant] + self._p[plant].T)
            if not np.isfinite(sym).all():
                self._p[plant] = self.initial_covariance * np.eye(self.num_parameters)
                continue
            values, vectors = np.linalg.eigh(sym)
            floor = max(values.max(), 1.0) * 1e-12
            self._p[plant] = (vectors * np.maximum(values, floor)) @ vectors.T

    # ----------------------------------------------------------- the helpers
    def _plant_rows(self, plants: Any) -> Rows:
        """Return ``plants`` (None = all, an index, indices or a mask) as rows."""
        if plants is None:
            return slice(None)
        rows = np.arange(self.num_plants)[plants]
        return np.atleast_1d(rows)

    def _indices(self, rows: Rows) -> np.ndarray:
        """Return rows as an index array."""
        return np.arange(self.num_plants)[rows]

    def _flag_counts(self, key: str) -> np.ndarray:
        """Return the per-plant counts of flag ``key``, made on first use."""
        if key not in self.flags:
            self.flags[key] = np.zeros(self.num_plants, dtype=np.int64)
        return self.flags[key]

    def _flag(self, key: str, rows: Rows, where: np.ndarray | None = None) -> None:
        """Count one occurrence of ``key`` for the plants ``rows`` (where ``where``)."""
        plants = self._indices(rows)
        if where is not None:
            plants = plants[where]
        self._flag_counts(key)[plants] += 1

    def _theta(self) -> np.ndarray:
        return self._theta_ls

    def _plant_items(self, plant: int) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Return (arrays, scalars) of plant k as in the single-plant snapshot (not copied)."""
        arrays = {'theta_ls': self._theta_ls[plant], 'p': self._p[plant]}
        scalars = {'loss': float(self._loss[plant]), 'tau': float(self._tau[plant]),
                   'updates': int(self._updates[plant])}
        return arrays, scalars

    def _load_plant(self, plant: int, arrays: dict[str, np.ndarray],
                    scalars: dict[str, Any]) -> None:
        """Take over plant k's (arrays, scalars) of a single-plant snapshot."""
        self._theta_ls[plant] = arrays['theta_ls']
        self._p[plant] = arrays['p']
        self._loss[plant] = float(scalars['loss'])
        self._tau[plant] = float(scalars['tau'])
        self._updates[plant] = int(scalars['updates'])


class BatchedBcrls(BatchedRls):
    r"""
    K independent BCRLS estimators of one structure, updated together.

    The LS part is :class:`BatchedRls`; after each plant's LS step comes the
    compensation of :class:`~bcid_ros.estimators.bcrls.Bcrls`, with
    :math:`\Lambda = \mathrm{diag}(I_n, 0)`:

    .. math::

        \hat\sigma_k^2(t) &= \frac{J_k(t)}{\tau_k(t)\,[1 + \hat\theta_{c,k}^T(t-1)
            \Lambda\hat\theta_{LS,k}(t)]} && \text{(51)} \\
        \hat\theta_{c,k}(t) &= \hat\theta_{LS,k}(t)
            + \tau_k(t)\,\hat\sigma_k^2(t)\,P_k(t)\Lambda\hat\theta_{c,k}(t-1)
            && \text{(46)}

    with the same safeguards, per plant: ``sigma2_denominator`` (the
    denominator of (51) below ``DENOMINATOR_MIN``: the previous
    :math:`\hat\sigma_k^2` is kept) and ``compensation_reset`` (a
    non-finite or runaway compensated estimate restarts from
    :math:`\hat\theta_{LS,k}(t)`). See :class:`BatchedRls` for the
    parameters and the sample policy.
    """

    name: ClassVar[str] = 'bcrls'
    noise_names: ClassVar[tuple[str, ...]] = ('sigma2',)

    def reset(self, plants: Any = None) -> None:
        """Return plants (default: all) to the state right after construction."""
        if plants is None:
            self._lambda_diagonal = np.zeros(self.num_parameters)
            self._lambda_diagonal[:self.order] = 1.0
            self._theta_c = np.zeros((self.num_plants, self.num_parameters))
            self._lambda_theta_c = np.zeros((self.num_plants, self.num_parameters))
            self._sigma2 = np.zeros(self.num_plants)
        super().reset(plants)
        rows = self._plant_rows(plants)
        self._theta_c[rows] = 0.0
        self._lambda_theta_c[rows] = 0.0
        self._sigma2[rows] = 0.0

    @property
    def sigma2(self) -> np.ndarray:
        """Return the noise variance estimates of eq. (51), shape ``(K,)`` (a copy)."""
        return self._sigma2.copy()

    @property
    def noise(self) -> np.ndarray:
        """Return the noise estimates ``sigma2``, shape ``(K, 1)``."""
        return self._sigma2[:, None].copy()

    def _after_ls_step(self, rows: Rows, theta_ls: np.ndarray, p: np.ndarray,
                       loss: np.ndarray, tau: np.ndarray) -> None:
        """Apply eqs. (51) and (46) to the plants ``rows`` after their LS step."""
        # Lambda theta_c(t-1)
        previous = self._lambda_theta_c[rows]
        # denominator of (51): 1 + theta_c(t-1)' Lambda theta_LS(t)
        denominator = 1.0 + _rowdot(previous, theta_ls)
        accepted = denominator >= DENOMINATOR_MIN
        if accepted.all():
            # sigma2(t) = J(t) / (tau(t) * denominator)          (51)
            sigma2 = loss / (tau * denominator)
        else:
            self._flag('sigma2_denominator', rows, ~accepted)
            sigma2 = self._sigma2[rows].copy()
            sigma2[accepted] = loss[accepted] / (tau[accepted] * denominator[accepted])
        self._sigma2[rows] = sigma2
        # theta_c(t) = theta_LS(t) + tau sigma2 P(t) Lambda theta_c(t-1)   (46)
        compensated = theta_ls + (tau * sigma2)[:, None] * _matvec(p, previous)
        size = _rowdot(compensated, compensated)
        limit = COMPENSATION_MAX ** 2
        # all below the absolute limit (the common case, one comparison) or each checked
        if not size.max() <= limit:
            kept = (size <= limit) | (size <= limit * (1.0 + _rowdot(theta_ls, theta_ls)))
            if not kept.all():
                self._flag('compensation_reset', rows, ~kept)
                compensated[~kept] = theta_ls[~kept]
        self._theta_c[rows] = compensated
        self._lambda_theta_c[rows] = compensated * self._lambda_diagonal

    def _theta(self) -> np.ndarray:
        return self._theta_c

    def _plant_items(self, plant: int) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        arrays, scalars = super()._plant_items(plant)
        arrays['theta_c'] = self._theta_c[plant]
        scalars['sigma2'] = float(self._sigma2[plant])
        return arrays, scalars

    def _load_plant(self, plant: int, arrays: dict[str, np.ndarray],
                    scalars: dict[str, Any]) -> None:
        super()._load_plant(plant, arrays, scalars)
        self._theta_c[plant] = arrays['theta_c']
        self._lambda_theta_c[plant] = self._theta_c[plant] * self._lambda_diagonal
        self._sigma2[plant] = float(scalars['sigma2'])


#: Registry name of the single-plant estimator -> its batched form.
BATCHED_ESTIMATORS: dict[str, type[BatchedRls]] = {'rls': BatchedRls, 'bcrls': BatchedBcrls}


def make_batched_estimator(name: str, num_plants: int, **settings: Any) -> BatchedRls:
    """
    Build the batched form of estimator ``name`` over ``num_plants`` plants.

    Raises
    ------
    ValueError
        If ``name`` has no batched form (only rls and bcrls have one).

    """
    if name not in BATCHED_ESTIMATORS:
        raise ValueError(f'estimator must be one of {", ".join(BATCHED_ESTIMATORS)} for '
                         f'many plants; got {name!r}')
    return BATCHED_ESTIMATORS[name](num_plants, **settings)


__all__ = ['BATCHED_ESTIMATORS', 'BatchedBcrls', 'BatchedRls', 'make_batched_estimator']
