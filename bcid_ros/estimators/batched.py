"""
RLS and BCRLS over many plants of one structure, with one vectorised update per sample.

A robot's joints, or a fleet's actuators, are K plants with the same model
structure (order n, r inputs, feedthrough) and the same settings. Running K
:class:`~bcid_ros.estimators.rls.Rls` objects costs K Python calls per
sample, most of it call overhead at these sizes. Here the K states are
stacked (theta as ``(K, p)``, P as ``(K, p, p)``, one regressor history per
plant) and each sample of all plants is one numpy pass.

Each plant follows exactly the recursion of its single-plant estimator, with
its units (signal scales per plant and channel), its transaction, its outlier
gate and plant-change rule, and its validity, all per plant; and with the
single-plant sample policy of the identifier (``SampleFeeder``) applied per
plant: a plant whose sample is missing or not finite restarts its own
regressor and is counted, and the other plants are not touched. Each plant's
estimate therefore equals that of a single-plant estimator fed the same
samples, to 1e-12. The dot products go to the same BLAS kernels as the
single plant's, on rows laid out the same way, so the LS part agrees bit for
bit. BCRLS's compensation (46) is one BLAS gemv with beta = 1 in the single
plant, whose kernel rounds the final sum its own way when p is not a multiple
of 4 (measured here): last-bit differences there, which the contraction of
(46) keeps from growing.

Every step computes the a-priori quantities of all plants ``rows`` whose
regressor is filled, in one pass. The plants whose step is ordinary (a
moderate gain s/lambda, a finite error, s > 0 and a prediction error the gate
accepts) are committed together; the few others (a step that may break P, a
refused sample, a plant change) go one by one through the single-plant logic
(:meth:`BatchedRls._plant_step`), which the one pass has not touched yet.
"""

from __future__ import annotations

import math
from typing import Any, ClassVar

import numpy as np

from bcid_ros.estimators.base import (CHANGE_DECAY, CHANGE_SCORE, check_int, check_range,
                                      EstimatorState, HUGE_SCREEN, IMPLAUSIBLE_ERROR,
                                      parameter_names, weighted_square_ratio)
from bcid_ros.estimators.bcrls import (add_lagged_moments, block_sandwich, COMPENSATION_MAX,
                                       CONTRACTION_MAX, DENOMINATOR_MIN, MOMENT_BLOCK,
                                       RUNAWAY, sandwich_or_nan)
from bcid_ros.estimators.rls import (CAREFUL_GAIN, CHANGE_MEMORY, GATE_WARMUP, GROWTH,
                                     HEALTH_CHECK_PERIOD, repair_covariance, rls_step,
                                     UNSTABLE_RADIUS, VALIDITY_PERIOD, VARIANCE_FLOOR)

Rows = slice | np.ndarray


def _matvec(matrices: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    """
    Return ``matrices[k] @ vectors[k]`` for every k, shape ``(K, p)``.

    numpy's matmul hands each product to BLAS gemv, the kernel of the
    single-plant estimator's ``P.dot(phi)``, so both sum in the same order.
    """
    return np.matmul(matrices, vectors[:, :, None])[:, :, 0]


def _rowdot(left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """
    Return ``left[k] . right[k]`` for every k, shape ``(K,)``.

    numpy.vecdot: its inner loop is BLAS ddot, the kernel of the single-plant
    estimator's ``phi.dot(g)``, so the two sum in the same order and agree
    bit for bit. einsum has its own loop, which on some machines sums with
    two accumulators (measured: one dot product of 4 terms in 4 differed in
    the last bit), and the ill-conditioned start amplifies that to 1e-10.
    """
    return np.vecdot(left, right)


def _powers_of_two_at_least(values: np.ndarray) -> np.ndarray:
    """Return the smallest power of two >= each value > 0 (1.0 for 0), elementwise."""
    mantissa, exponent = np.frexp(values)
    return np.ldexp(1.0, np.where(mantissa == 0.5, exponent - 1, exponent))


def _spectral_radii(a: np.ndarray) -> np.ndarray:
    """Return the largest pole magnitude of each A_k(q) = 1 + a_k1 q^-1 + ..., rows of ``a``."""
    count, order = a.shape
    if order == 1:
        return np.abs(a[:, 0])
    radius = np.full(count, math.inf)
    finite = np.isfinite(a).all(axis=1)
    if finite.any():
        companion = np.zeros((int(finite.sum()), order, order))
        companion[:, 0] = -a[finite]
        companion[:, 1:, :-1] = np.eye(order - 1)
        radius[finite] = np.abs(np.linalg.eigvals(companion)).max(axis=1)
    return radius


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

    with everything around it per plant, as in the single-plant estimator
    (docs/estimators.md, "Estimates you can trust"), and counted per plant in
    :attr:`flags`:

    * **units**: :math:`P_k(0) = p_0 S_k^{-2}`, with the power-of-two scales
      :math:`S_k` of plant k's channels (y, u_1 ... u_r) taken from the
      samples in its regressor at its first update (:attr:`signal_scale`);
    * **transaction**: a step with a non-finite :math:`s_k` or
      :math:`e_k^2`, or a risky one (:math:`s_k/\lambda >` ``CAREFUL_GAIN``)
      that leaves :math:`S_k P_k S_k` indefinite or ill-conditioned, is
      undone on plant k only (``update_undone``) and its regressor restarts;
      three in a row start plant k afresh with new scales (``rescaled``);
    * **gate**: plant k's squared normalised prediction error
      :math:`z_k^2 = e_k^2 / [(J_k/\tau_k)(1 + \varphi_k^T P_k\varphi_k)]` above
      ``outlier_threshold``:math:`^2` (or above 1e6 with the gate off)
      refuses the sample on plant k (``outlier_rejected``); three refusals in
      a row are taken as a change of plant k (``plant_change``) and cut its
      memory;
    * anti-windup (``windup_limited``), the Cholesky check of :math:`P_k`
      every ``HEALTH_CHECK_PERIOD`` of its updates and whenever
      :math:`s_k \le 0` (``covariance_repaired``);
    * **validity** (:attr:`valid`, :meth:`plant_validity_reasons`), re-evaluated
      every ``VALIDITY_PERIOD`` of the plant's updates: an unstable model on
      bounded data.

    **Samples.** :meth:`update` takes one sample of every plant. Plant k's
    sample is not used when it is marked absent (counted in :attr:`missing`)
    or holds NaN or Inf (counted in :attr:`nonfinite`); its regressor then
    restarts, so no later update regresses across the gap, exactly as the
    identifier does for one plant. The other plants go on undisturbed.

    Parameters
    ----------
    num_plants : int
        K >= 1.
    order, num_inputs, feedthrough, initial_covariance, forgetting_factor, outlier_threshold
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
                 forgetting_factor: float = 1.0, outlier_threshold: float = 0.0) -> None:
        self.num_plants = check_int('num_plants', num_plants, 1)
        self.order = check_int('order', order, 1)
        self.num_inputs = check_int('num_inputs', num_inputs, 1)
        self.feedthrough = bool(feedthrough)
        self.initial_covariance = check_range(
            'initial_covariance', initial_covariance, 0.0, 1e15, low_open=True)
        self._forgetting_factor = check_range(
            'forgetting_factor', forgetting_factor, 0.0, 1.0, low_open=True)
        self.outlier_threshold = outlier_threshold
        self.parameter_names = parameter_names(self.order, self.num_inputs, self.feedthrough)
        self.num_parameters = len(self.parameter_names)
        self._trace_limit = self.initial_covariance * self.num_parameters
        self._gate_from = GATE_WARMUP * self.num_parameters
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
        # the signal channel (0 = y, i = u_i) of each component of phi
        lags = self.order + (1 if self.feedthrough else 0)
        self._channel = np.array([0] * self.order + [
            i for i in range(1, self.num_inputs + 1) for _ in range(lags)], dtype=np.intp)
        self._diagonal = np.arange(self.num_parameters)
        # a value at or above this may overflow in a step: see RecursiveEstimator.update
        self._huge = 1.0 / (HUGE_SCREEN * width)
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
        huge = self._huge
        # one comparison each screens for NaN, Inf and values that could overflow
        if present is None and np.abs(y).max() < huge and np.abs(u).max() < huge:
            skipped = None
        else:
            skipped = self._screen(y, u, present)
        self._push(y, u)
        self._calls += 1
        if skipped is not None:
            self._clear_regressors(skipped)
        rows = self._ready_rows()
        if rows is not None:
            # take, not [:, index]: fancy indexing lays the result out by columns, and
            # BLAS ddot sums a strided row in another order than the single plant's phi
            phi = self._flat_history[rows].take(self._phi_index, axis=1)
            if self._quiet_left:
                # a huge value is in some regressor: its overflow is refused, not warned about
                self._quiet_left -= 1
                with np.errstate(all='ignore'):
                    self._step(rows, y[rows], phi)
            else:
                self._step(rows, y[rows], phi)
        elif self._quiet_left:
            self._quiet_left -= 1
        return self.valid

    def reset(self, plants: Any = None) -> None:
        """
        Return plants (default: all) to the state right after construction.

        The sample counters :attr:`missing` and :attr:`nonfinite` are kept.
        """
        rows = self._plant_rows(plants)
        if isinstance(rows, slice):
            self.flags: dict[str, np.ndarray] = {}
            self._allocate()
            self._quiet_left = 0
        for counts in self.flags.values():
            counts[rows] = 0
        self._change_score[rows] = 0.0
        self._scoring = bool(self._change_score.any())
        self._reset_learning(rows)
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
    def outlier_threshold(self) -> float:
        """Gate of the normalised prediction error, >= 0 (0 = off); may change while running."""
        return self._outlier_threshold

    @outlier_threshold.setter
    def outlier_threshold(self, value: float) -> None:
        self._outlier_threshold = check_range('outlier_threshold', value, 0.0,
                                              IMPLAUSIBLE_ERROR)
        self._gate_limit2 = (self._outlier_threshold or IMPLAUSIBLE_ERROR) ** 2

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
    def ready(self) -> np.ndarray:
        """Whether each plant has made at least p updates, shape ``(K,)``."""
        return self._updates >= self.num_parameters

    @property
    def valid(self) -> np.ndarray:
        """Whether each plant is :attr:`ready` with no validity reasons, shape ``(K,)``."""
        return (self._updates >= self.num_parameters) & ~self._has_reasons

    @property
    def validity_reasons(self) -> tuple[tuple[str, ...], ...]:
        """Return the reasons not to trust each plant's estimate, one tuple per plant."""
        return tuple(self._reasons.get(plant, ()) for plant in range(self.num_plants))

    def plant_validity_reasons(self, plant: int) -> tuple[str, ...]:
        """Return why plant k's estimate is not trustworthy now (empty when it is)."""
        return self._reasons.get(range(self.num_plants)[plant], ())

    @property
    def samples(self) -> np.ndarray:
        """Count each plant's estimator updates (samples with a filled regressor)."""
        return self._updates.copy()

    @property
    def used(self) -> np.ndarray:
        """Count each plant's samples that went into its regressor, shape ``(K,)``."""
        return self._calls - self.missing - self.nonfinite

    @property
    def signal_scale(self) -> np.ndarray:
        """Return the scales of y, u_1 ... u_r per plant, shape ``(K, 1 + r)`` (0: not yet)."""
        return self._signal_scale.copy()

    @property
    def initial_covariance_diagonal(self) -> np.ndarray:
        """Return the diagonal of each P_k(0) = p0 S_k^-2 in the user's units, ``(K, p)``."""
        return self.initial_covariance / self._component_scale ** 2

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
    def parameter_covariance(self) -> np.ndarray:
        """
        Return each plant's covariance of :attr:`theta`, shape ``(K, p, p)``.

        Plant k's is that of its single-plant estimator
        (``parameter_covariance``, docs/estimators.md "Uncertainty"); all NaN
        where that one is None (not ready, no data for one yet, not finite
        or a negative variance).
        """
        covariance = self._parameter_covariance()
        diagonal = np.diagonal(covariance, axis1=1, axis2=2)
        unknown = ~(np.isfinite(covariance).all(axis=(1, 2)) & (diagonal >= 0.0).all(axis=1))
        covariance[unknown] = np.nan
        return covariance

    @property
    def parameter_std(self) -> np.ndarray:
        """Return each plant's standard deviations of :attr:`theta`, ``(K, p)``; NaN where none."""
        return np.sqrt(np.diagonal(self.parameter_covariance, axis1=1, axis2=2))

    def _parameter_covariance(self) -> np.ndarray:
        """Return sigma_e^2 P_k tau_2 / tau per plant (``Rls._parameter_covariance``)."""
        p, tau = self.num_parameters, self._tau
        ratio = weighted_square_ratio(tau, self._forgetting_factor)
        dof = tau - p * ratio
        known = (self._updates >= p) & (tau > 0.0) & (dof > 0.0)
        factor = np.full(self.num_plants, np.nan)
        factor[known] = self._loss[known] / dof[known] * ratio[known]
        return factor[:, None, None] * self._p

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
        plant = range(self.num_plants)[plant]
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
                       flags=self.plant_flags(plant),
                       change_score=float(self._change_score[plant]))
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
        plant = range(self.num_plants)[plant]
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
        self._change_score[plant] = float(state.scalars.get('change_score', 0.0))
        self._scoring = bool(self._change_score.any())
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

    # ------------------------------------------------------------ the samples
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

    def _screen(self, y: np.ndarray, u: np.ndarray,
                present: np.ndarray | None) -> np.ndarray | None:
        """Count the samples not used; return their plants (None if all are used)."""
        usable = np.isfinite(y) & np.isfinite(u).all(axis=1)
        if present is not None:
            self.missing += ~present
            self.nonfinite += present & ~usable
            usable &= present
        else:
            self.nonfinite += ~usable
        with np.errstate(invalid='ignore'):
            huge = usable & ~((np.abs(y) < self._huge) & (np.abs(u) < self._huge).all(axis=1))
        if huge.any():
            # the order + 2 steps whose regressors can hold it run with warnings off
            self._quiet_left = self.order + 2
        return None if usable.all() else np.flatnonzero(~usable)

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

    # ------------------------------------------------------------- the step
    def _step(self, rows: Rows, y: np.ndarray, phi: np.ndarray) -> None:
        """Do one step of the plants ``rows``, whose regressors ``phi`` are filled."""
        if self._pending_any:
            self._choose_scales(self._indices(rows))
        lam = self._forgetting_factor
        p_old = self._p[rows]
        theta = self._theta_ls[rows]
        loss = self._loss[rows]
        tau = self._tau[rows]
        # g = P(t-1) phi(t); s = lambda + phi' g; e = y(t) - phi' theta(t-1)
        g = _matvec(p_old, phi)
        s = lam + _rowdot(phi, g)
        e = y - _rowdot(phi, theta)
        e2 = e * e
        # the ordinary steps: no risk to P, and an error the gate accepts (or does not test)
        ordinary = (s < CAREFUL_GAIN * lam) & (e2 < math.inf) & (s > 0.0)
        tested = tau >= self._gate_from
        # z^2 = e^2 / [(J / tau + floor)(s + 1 - lambda)], only read where tested (tau > 0)
        z2 = e2 / ((loss / np.maximum(tau, 1.0) + self._variance_floor[rows]) * (s + 1.0 - lam))
        ordinary &= ~tested | (z2 <= self._gate_limit2)
        if self._scoring:
            self._decay_scores(self._indices(rows)[ordinary & tested])
        if ordinary.all():
            theta, p_new, loss, tau, updates = self._commit(rows, theta, p_old, g, s, e, loss,
                                                            tau)
            self._after_ls_step(rows, theta, p_new, loss, tau, y, phi)
        else:
            plants = self._indices(rows)
            if ordinary.any():
                self._commit(plants[ordinary], theta[ordinary], p_old[ordinary], g[ordinary],
                             s[ordinary], e[ordinary], loss[ordinary], tau[ordinary])
            others = [plant for plant, y_k, phi_k in zip(
                plants[~ordinary], y[~ordinary].tolist(), phi[~ordinary])
                if self._plant_step(plant, y_k, phi_k)]
            stepped = np.sort(np.r_[np.flatnonzero(ordinary), np.searchsorted(
                plants, np.array(others, dtype=np.intp))])
            rows = plants[stepped]
            if not rows.size:
                return
            theta, p_new = self._theta_ls[rows], self._p[rows]
            loss, tau, updates = self._loss[rows], self._tau[rows], self._updates[rows]
            self._after_ls_step(rows, theta, p_new, loss, tau, y[stepped], phi[stepped])
        due = updates >= self._next_check[rows]
        if due.any():
            self._check_validity(self._indices(rows)[due])

    def _commit(self, rows: Rows, theta: np.ndarray, p_old: np.ndarray, g: np.ndarray,
                s: np.ndarray, e: np.ndarray, loss: np.ndarray,
                tau: np.ndarray) -> tuple[np.ndarray, ...]:
        """Make the step (47)-(50) of ``rows``; return their theta, P, J, tau and counts."""
        lam = self._forgetting_factor
        # theta(t) = theta(t-1) + g e / s   (a new array: nothing is written before the end)
        theta = theta + g * (e / s)[:, None]
        # P(t) = P(t-1) - h h', h = g / sqrt(s)
        h = g * (1.0 / np.sqrt(s))[:, None]
        p_new = p_old - h[:, :, None] * h[:, None, :]
        # J(t) = lambda J(t-1) + lambda e^2 / s ; tau(t) = lambda tau(t-1) + 1
        loss = lam * (loss + e * e / s)
        tau = lam * tau + 1.0
        if lam < 1.0:
            self._forget(rows, p_new)
        updates = self._updates[rows] + 1
        self._theta_ls[rows] = theta
        self._p[rows] = p_new
        self._loss[rows] = loss
        self._tau[rows] = tau
        self._updates[rows] = updates
        if self._undone_any:
            self._undone_in_row[rows] = 0
            self._undone_any = bool(self._undone_in_row.any())
        due = updates % HEALTH_CHECK_PERIOD == 0
        if due.any():
            self._check_covariance(self._indices(rows)[due])
            p_new = self._p[rows]
        return theta, p_new, loss, tau, updates

    def _after_ls_step(self, rows: Rows, theta_ls: np.ndarray, p: np.ndarray,
                       loss: np.ndarray, tau: np.ndarray, y: np.ndarray,
                       phi: np.ndarray) -> None:
        """Extend the LS step of ``rows`` on (y, phi) (the compensation of subclasses)."""

    def _forget(self, rows: Rows, p: np.ndarray) -> None:
        """Apply P(t) <- P(t) / lambda in place, per plant unless that winds P up."""
        weighted = _rowdot(np.diagonal(p, axis1=1, axis2=2), self._trace_weights[rows])
        within = weighted < self._trace_limit
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
            scale = self._component_scale[plant]
            self._p[plant] = repair_covariance(
                self._p[plant], np.diag(self.initial_covariance / scale ** 2), scale)

    # ----------------------------------------- one plant's step, when not ordinary
    def _plant_step(self, plant: int, y: float, phi: np.ndarray) -> bool:
        """Do plant k's step as the single-plant ``Rls._ls_step`` does; return whether it did."""
        lam = self._forgetting_factor
        g = self._p[plant].dot(phi)
        s = lam + float(phi.dot(g))
        e = y - float(phi.dot(self._theta_ls[plant]))
        if not (s < CAREFUL_GAIN * lam and e * e < math.inf):
            return self._plant_careful_step(plant, phi, e, g, s)
        if not s > 0.0:
            self._repair_covariance(np.array([plant]))
            return False
        tau = float(self._tau[plant])
        if tau >= self._gate_from:
            if not self._plant_gate(plant, self._plant_z2(plant, e, s)):
                return False
            if self._tau[plant] != tau:
                # a plant change cut the memory (P grew): redo the a-priori part
                g = self._p[plant].dot(phi)
                s = lam + float(phi.dot(g))
        self._plant_commit(plant, e, g, s)
        self._undone_in_row[plant] = 0
        return True

    def _plant_z2(self, plant: int, e: float, s: float) -> float:
        """Return plant k's squared normalised prediction error (see the class docstring)."""
        scaled = float(self._loss[plant]) / float(self._tau[plant])
        return e * e / ((scaled + float(self._variance_floor[plant]))
                        * (s + 1.0 - self._forgetting_factor))

    def _plant_careful_step(self, plant: int, phi: np.ndarray, e: float, g: np.ndarray,
                            s: float) -> bool:
        """Make plant k's step that may break P as a transaction; return whether it was kept."""
        lam = self._forgetting_factor
        if s <= 0.0:
            self._repair_covariance(np.array([plant]))
            return False
        if not (s < math.inf and e * e < math.inf):
            self._undo(plant, 'update_undone')
            return False
        if self._tau[plant] >= self._gate_from:
            if not self._plant_gate(plant, self._plant_z2(plant, e, s)):
                return False
            g = self._p[plant].dot(phi)
            s = lam + float(phi.dot(g))
        saved = (self._theta_ls[plant].copy(), self._p[plant].copy(), self._loss[plant],
                 self._tau[plant], self._updates[plant])
        self._plant_commit(plant, e, g, s)
        if self._sound_covariance(plant) and np.isfinite(self._theta_ls[plant]).all():
            self._undone_in_row[plant] = 0
            return True
        (self._theta_ls[plant], self._p[plant], self._loss[plant], self._tau[plant],
         self._updates[plant]) = saved
        self._undone_in_row[plant] += 1
        self._undone_any = True
        if self._undone_in_row[plant] >= 3:
            # three in a row: the signal level is far from the scales of the first
            # samples; what was learnt at that level is numerically worthless
            self._restart_learning(plant)
            return False
        self._undo(plant, 'update_undone')
        return False

    def _plant_commit(self, plant: int, e: float, g: np.ndarray, s: float) -> None:
        """Make plant k's step (47)-(50) with the single-plant BLAS kernels."""
        lam = self._forgetting_factor
        theta = self._theta_ls[plant].copy()
        self._p[plant] = rls_step(theta, self._p[plant].copy(), g, s, e)
        self._theta_ls[plant] = theta
        self._loss[plant] = lam * (float(self._loss[plant]) + e * e / s)
        self._tau[plant] = lam * float(self._tau[plant]) + 1.0
        if lam < 1.0:
            self._forget(slice(plant, plant + 1), self._p[plant:plant + 1])
        self._updates[plant] += 1
        if self._updates[plant] % HEALTH_CHECK_PERIOD == 0:
            self._check_covariance(np.array([plant]))

    def _sound_covariance(self, plant: int) -> bool:
        """Whether plant k's normalised P is positive definite with a condition within 1e13."""
        scale = self._component_scale[plant]
        scaled = self._p[plant] * np.outer(scale, scale)
        try:
            factor = np.linalg.cholesky(scaled)
        except np.linalg.LinAlgError:
            return False
        pivots = np.diagonal(factor) ** 2
        return bool(pivots.min() > 1e-13 * scaled.diagonal().max())

    def _plant_gate(self, plant: int, z2: float) -> bool:
        """Return whether plant k uses a sample of squared normalised error ``z2`` (_gate)."""
        score = float(self._change_score[plant])
        if z2 <= self._gate_limit2:
            if score:
                score *= CHANGE_DECAY
                self._change_score[plant] = score if score > 1e-3 else 0.0
            return True
        score = score * CHANGE_DECAY + 1.0
        if score >= CHANGE_SCORE:
            self._change_score[plant] = 0.0
            self._flag('plant_change', np.array([plant]))
            self._accept_change(plant)
            return True
        self._change_score[plant] = score
        self._scoring = True
        self._undo(plant, 'outlier_rejected')
        return False

    def _decay_scores(self, plants: np.ndarray) -> None:
        """Decay the change scores of ``plants``, whose tested samples the gate accepted."""
        score = self._change_score[plants] * CHANGE_DECAY
        self._change_score[plants] = np.where(score > 1e-3, score, 0.0)
        self._scoring = bool(self._change_score.any())

    def _accept_change(self, plant: int) -> None:
        """Cut plant k's memory to CHANGE_MEMORY p samples: one extra forgetting step."""
        tau = float(self._tau[plant])
        keep = CHANGE_MEMORY * self.num_parameters / tau if tau > 0 else 1.0
        if keep < 1.0:
            self._p[plant] *= 1.0 / keep
            self._loss[plant] *= keep
            self._tau[plant] *= keep

    def _undo(self, plant: int, flag: str) -> None:
        """Count a refused step of plant k and restart its regressor."""
        self._flag(flag, np.array([plant]))
        self._clear_regressors(np.array([plant]))

    def _restart_learning(self, plant: int) -> None:
        """Start plant k afresh with scales chosen from the samples now in its regressor."""
        self._flag('rescaled', np.array([plant]))
        self._reset_learning(np.array([plant]))
        self._choose_scales(np.array([plant]))

    # ------------------------------------------------------------ the units
    def _choose_scales(self, plants: np.ndarray) -> None:
        """Give each channel of ``plants`` still without a scale the one of its regressor."""
        plants = plants[self._scales_pending[plants]]
        if not plants.size:
            return
        peaks = np.abs(self._history[plants]).max(axis=1)
        scales = self._signal_scale[plants]
        new = (scales == 0.0) & (peaks > 0.0)
        if new.any():
            chosen = _powers_of_two_at_least(peaks)
            with np.errstate(all='ignore'):
                factor = np.where(new, 1.0 / (chosen * chosen), 1.0)
            # exact: the components of a new channel were zero in every update so far,
            # so their rows and columns of P are still p0 (times 1 / lambda^k) on the diagonal
            diagonal = self._diagonal
            self._p[plants[:, None], diagonal, diagonal] *= factor[:, self._channel]
            self._signal_scale[plants] = np.where(new, chosen, scales)
        self._set_scale_dependents(plants)

    def _set_scale_dependents(self, rows: Rows) -> None:
        scales = self._signal_scale[rows]
        self._scales_pending[rows] = (scales == 0.0).any(axis=1)
        self._pending_any = bool(self._scales_pending.any())
        component = scales[:, self._channel]
        component_scale = np.where(component > 0.0, component, 1.0)
        self._component_scale[rows] = component_scale
        self._trace_weights[rows] = component_scale ** 2
        y_scale = np.where(scales[:, 0] > 0.0, scales[:, 0], 1.0)
        self._variance_floor[rows] = (VARIANCE_FLOOR * y_scale) ** 2

    # --------------------------------------------------------- the validity
    def _check_validity(self, plants: np.ndarray) -> None:
        """Re-evaluate the validity reasons of ``plants``."""
        self._next_check[plants] = self._updates[plants] + VALIDITY_PERIOD
        with np.errstate(all='ignore'):
            found = self._find_problems(plants)
        has = np.array([bool(reasons) for reasons in found])
        self._has_reasons[plants] = has
        for plant, reasons in zip(plants.tolist(), found):
            if reasons:
                self._reasons[plant] = tuple(reasons)
            else:
                self._reasons.pop(plant, None)

    def _find_problems(self, plants: np.ndarray) -> list[list[str]]:
        """Return the reasons not to trust each of ``plants`` now (Rls._find_problems)."""
        reasons: list[list[str]] = [[] for _ in range(plants.size)]
        power = self._output_power(plants)
        bounded = ~(power > GROWTH * self._last_power[plants])
        self._last_power[plants] = power
        radius = _spectral_radii(self._theta()[plants, :self.order])
        for i in np.flatnonzero(~(radius <= UNSTABLE_RADIUS) & bounded):
            reasons[i].append(f'unstable model (pole radius {radius[i]:.3g}) on bounded data')
        return reasons

    def _output_power(self, plants: np.ndarray) -> np.ndarray:
        """Return the weighted mean square of y over each memory, from P^-1."""
        n = self.order
        try:
            information = np.linalg.inv(self._p[plants])
        except np.linalg.LinAlgError:
            information = np.full((plants.size,) + self._p.shape[1:], np.inf)
            for i, plant in enumerate(plants):
                try:
                    information[i] = np.linalg.inv(self._p[plant])
                except np.linalg.LinAlgError:
                    pass
        trace = np.trace(information[:, :n, :n], axis1=1, axis2=2)
        return trace / (n * np.maximum(self._tau[plants], 1.0))

    # ----------------------------------------------------------- the helpers
    def _plant_rows(self, plants: Any) -> Rows:
        """Return ``plants`` (None = all, an index, indices or a mask) as rows."""
        if plants is None:
            return slice(None)
        rows = np.arange(self.num_plants)[plants]
        return np.atleast_1d(rows)

    def _indices(self, rows: Any) -> np.ndarray:
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

    # -------------------------------------------------------------- the state
    def _allocate(self) -> None:
        """Make the per-plant state arrays (their values are set by the resets)."""
        plants, p = self.num_plants, self.num_parameters
        self._theta_ls = np.zeros((plants, p))
        self._p = np.zeros((plants, p, p))
        self._loss = np.zeros(plants)
        self._tau = np.zeros(plants)
        self._updates = np.zeros(plants, dtype=np.int64)
        self._cleared_at = np.zeros(plants, dtype=np.int64)
        self._signal_scale = np.zeros((plants, 1 + self.num_inputs))
        self._scales_pending = np.ones(plants, dtype=bool)
        self._component_scale = np.ones((plants, p))
        self._trace_weights = np.ones((plants, p))
        self._variance_floor = np.zeros(plants)
        self._undone_in_row = np.zeros(plants, dtype=np.int64)
        self._change_score = np.zeros(plants)
        self._next_check = np.zeros(plants, dtype=np.int64)
        self._last_power = np.zeros(plants)
        self._has_reasons = np.zeros(plants, dtype=bool)
        self._reasons: dict[int, tuple[str, ...]] = {}
        self._undone_any = False

    def _reset_learning(self, rows: Rows) -> None:
        """Return what ``rows`` learnt to the start (``Rls._reset`` but the regressor)."""
        self._theta_ls[rows] = 0.0
        self._p[rows] = self.initial_covariance * np.eye(self.num_parameters)
        self._loss[rows] = 0.0
        self._tau[rows] = 0.0
        self._updates[rows] = 0
        self._signal_scale[rows] = 0.0
        self._set_scale_dependents(rows)
        self._undone_in_row[rows] = 0
        self._next_check[rows] = self.num_parameters
        self._last_power[rows] = math.inf
        self._has_reasons[rows] = False
        for plant in self._indices(rows).tolist():
            self._reasons.pop(plant, None)

    def _plant_items(self, plant: int) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Return (arrays, scalars) of plant k as in the single-plant snapshot (not copied)."""
        arrays = {'theta_ls': self._theta_ls[plant], 'p': self._p[plant],
                  'signal_scale': self._signal_scale[plant]}
        scalars = {'loss': float(self._loss[plant]), 'tau': float(self._tau[plant]),
                   'updates': int(self._updates[plant]),
                   'undone_in_row': int(self._undone_in_row[plant]),
                   'next_check': int(self._next_check[plant]),
                   'last_power': float(self._last_power[plant]),
                   'reasons': self._reasons.get(plant, ())}
        return arrays, scalars

    def _load_plant(self, plant: int, arrays: dict[str, np.ndarray],
                    scalars: dict[str, Any]) -> None:
        """Take over plant k's (arrays, scalars) of a single-plant snapshot."""
        self._theta_ls[plant] = arrays['theta_ls']
        self._p[plant] = arrays['p']
        self._signal_scale[plant] = arrays['signal_scale']
        self._set_scale_dependents(np.array([plant]))
        self._loss[plant] = float(scalars['loss'])
        self._tau[plant] = float(scalars['tau'])
        self._updates[plant] = int(scalars['updates'])
        self._undone_in_row[plant] = int(scalars['undone_in_row'])
        self._undone_any = bool(self._undone_in_row.any())
        self._next_check[plant] = int(scalars['next_check'])
        self._last_power[plant] = float(scalars['last_power'])
        reasons = tuple(scalars['reasons'])
        self._has_reasons[plant] = bool(reasons)
        if reasons:
            self._reasons[plant] = reasons
        else:
            self._reasons.pop(plant, None)


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
    :math:`\hat\theta_{LS,k}(t)`); and the same validity, per plant: besides
    :class:`BatchedRls`'s, an ill-conditioned compensation (contraction
    :math:`\rho_k = \tau_k\hat\sigma_k^2\lambda_{max}(P_{k,aa})` above
    ``CONTRACTION_MAX``, which an over-specified order drives to 1), a
    compensation that runs away from the LS estimate, or a
    ``compensation_reset`` since the last check. See :class:`BatchedRls` for
    the parameters and the sample policy.
    """

    name: ClassVar[str] = 'bcrls'
    noise_names: ClassVar[tuple[str, ...]] = ('sigma2',)

    @property
    def sigma2(self) -> np.ndarray:
        """Return the noise variance estimates of eq. (51), shape ``(K,)`` (a copy)."""
        return self._sigma2.copy()

    @property
    def noise(self) -> np.ndarray:
        """Return the noise estimates ``sigma2``, shape ``(K, 1)``."""
        return self._sigma2[:, None].copy()

    def _after_ls_step(self, rows: Rows, theta_ls: np.ndarray, p: np.ndarray,
                       loss: np.ndarray, tau: np.ndarray, y: np.ndarray,
                       phi: np.ndarray) -> None:
        """Apply eqs. (51) and (46) to the plants ``rows``; keep z = [phi; y] for the moments."""
        self._record_moments(rows, y, phi)
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

    def _find_problems(self, plants: np.ndarray) -> list[list[str]]:
        """Add the conditioning and the size of the compensation (Bcrls._find_problems)."""
        reasons = super()._find_problems(plants)
        n = self.order
        block = self._p[plants, :n, :n]
        largest = np.full(plants.size, np.nan)
        finite = np.isfinite(block).all(axis=(1, 2))
        if finite.any():
            largest[finite] = np.linalg.eigvalsh(block[finite])[:, -1]
        contraction = self._tau[plants] * self._sigma2[plants] * largest
        for i in np.flatnonzero(~(contraction <= CONTRACTION_MAX)):
            reasons[i].append(f'ill-conditioned compensation (contraction '
                              f'{contraction[i]:.3g} > {CONTRACTION_MAX})')
        scale = self._component_scale[plants]
        theta_ls = self._theta_ls[plants]
        difference = scale * (self._theta_c[plants] - theta_ls)
        shift = np.sqrt(_rowdot(difference, difference))
        scaled = scale * theta_ls
        size = np.sqrt(_rowdot(scaled, scaled))
        for i in np.flatnonzero(~(shift <= RUNAWAY * size)):
            reasons[i].append(f'compensation runs away from LS ({shift[i] / size[i]:.3g} x '
                              f'|theta_LS|)' if size[i] > 0 else
                              'compensation runs away from LS')
        resets = self.flags.get('compensation_reset')
        if resets is not None:
            resets = resets[plants]
            for i in np.flatnonzero(resets > self._resets_checked[plants]):
                reasons[i].append('compensation reset')
            self._resets_checked[plants] = resets
        return reasons

    def _theta(self) -> np.ndarray:
        return self._theta_c

    # ------------------------------------------------------- the uncertainty
    def _record_moments(self, rows: Rows, y: np.ndarray, phi: np.ndarray) -> None:
        """Keep z = [phi; y] of the plants ``rows``; sum a plant's block when it is full."""
        plants = self._indices(rows)
        slots = self.order + self._moment_pending[plants]
        p = self.num_parameters
        self._moment_ring[plants, slots, :p] = phi
        self._moment_ring[plants, slots, p] = y
        self._moment_pending[plants] += 1
        full = plants[self._moment_pending[plants] == MOMENT_BLOCK]
        if full.size:
            self._flush_moments(full)

    def _flush_moments(self, plants: np.ndarray) -> None:
        """Add full blocks to the lagged moment sums (``Bcrls._flush_moments``), per plant."""
        n = self.order
        ring = self._moment_ring[plants]
        self._moment_sums[plants], self._moment_weight[plants] = add_lagged_moments(
            self._moment_sums[plants], self._moment_weight[plants], ring, n,
            self._forgetting_factor)
        # the last n rows are the lag context of the next block
        self._moment_ring[plants, :n] = ring[:, MOMENT_BLOCK:]
        self._moment_pending[plants] = 0
        p = self.num_parameters
        snapshot = self._moment_snapshot
        snapshot[plants, 0, :p] = self._theta_c[plants]
        snapshot[plants, 0, p] = self._sigma2[plants]
        snapshot[plants, 1, :p] = self._component_scale[plants]
        y_scale = self._signal_scale[plants, 0]
        snapshot[plants, 1, p] = np.where(y_scale > 0.0, y_scale, 1.0)
        self._sandwich_due[plants] = True

    def _parameter_covariance(self) -> np.ndarray:
        """Return each plant's sandwich covariance (``Bcrls._parameter_covariance``)."""
        known = (self._updates >= self.num_parameters) & (self._moment_weight > 0.0)
        due = np.flatnonzero(known & self._sandwich_due)
        if due.size:
            # all plants whose block ended since the last read, in one batched evaluation;
            # a singular one (LinAlgError) is evaluated alone, and stays unknown
            try:
                self._sandwich[due] = block_sandwich(
                    self._moment_sums[due], self._moment_weight[due],
                    self._moment_snapshot[due], self.order)
            except np.linalg.LinAlgError:
                for plant in due.tolist():
                    self._sandwich[plant] = sandwich_or_nan(
                        self._moment_sums[plant], self._moment_weight[plant],
                        self._moment_snapshot[plant], self.order)
            self._sandwich_due[due] = False
        tau = self._tau
        ratio = weighted_square_ratio(tau, self._forgetting_factor)
        factor = np.full(self.num_plants, np.nan)
        factor[known] = ratio[known] / tau[known]
        return factor[:, None, None] * self._sandwich

    def _allocate(self) -> None:
        super()._allocate()
        plants, p = self.num_plants, self.num_parameters
        # the diagonal of Lambda = diag(I_n, 0)
        self._lambda_diagonal = np.zeros(p)
        self._lambda_diagonal[:self.order] = 1.0
        self._theta_c = np.zeros((plants, p))
        self._lambda_theta_c = np.zeros((plants, p))
        self._sigma2 = np.zeros(plants)
        self._resets_checked = np.zeros(plants, dtype=np.int64)
        # per plant as in Bcrls: the lag context (n rows) then the rows z = [phi; y] not yet
        # summed; the sums of w_t z_t z_{t-k}' (k = 0..n) and of w_t; the estimates and
        # scales at the last block; the sandwich H^-1 S H^-T of that block, when computed
        width = p + 1
        self._moment_ring = np.zeros((plants, self.order + MOMENT_BLOCK, width))
        self._moment_pending = np.zeros(plants, dtype=np.intp)
        self._moment_sums = np.zeros((plants, self.order + 1, width, width))
        self._moment_weight = np.zeros(plants)
        self._moment_snapshot = np.zeros((plants, 2, width))
        self._sandwich = np.full((plants, p, p), np.nan)
        self._sandwich_due = np.zeros(plants, dtype=bool)

    def _reset_learning(self, rows: Rows) -> None:
        super()._reset_learning(rows)
        self._theta_c[rows] = 0.0
        self._lambda_theta_c[rows] = 0.0
        self._sigma2[rows] = 0.0
        self._resets_checked[rows] = 0
        self._moment_ring[rows] = 0.0
        self._moment_pending[rows] = 0
        self._moment_sums[rows] = 0.0
        self._moment_weight[rows] = 0.0
        self._moment_snapshot[rows] = 0.0
        self._sandwich[rows] = np.nan
        self._sandwich_due[rows] = False

    def _plant_items(self, plant: int) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        arrays, scalars = super()._plant_items(plant)
        arrays['theta_c'] = self._theta_c[plant]
        scalars['sigma2'] = float(self._sigma2[plant])
        scalars['resets_checked'] = int(self._resets_checked[plant])
        # the moments in Bcrls's layout: the ring holds the context, then the pending rows
        ring = self._moment_ring[plant].copy()
        ring[self.order + int(self._moment_pending[plant]):] = 0.0
        arrays['moment_ring'] = ring
        arrays['moment_sums'] = self._moment_sums[plant]
        arrays['moment_snapshot'] = self._moment_snapshot[plant]
        scalars['moment_pending'] = int(self._moment_pending[plant])
        scalars['moment_weight'] = float(self._moment_weight[plant])
        return arrays, scalars

    def _load_plant(self, plant: int, arrays: dict[str, np.ndarray],
                    scalars: dict[str, Any]) -> None:
        super()._load_plant(plant, arrays, scalars)
        self._theta_c[plant] = arrays['theta_c']
        self._lambda_theta_c[plant] = self._theta_c[plant] * self._lambda_diagonal
        self._sigma2[plant] = float(scalars['sigma2'])
        self._resets_checked[plant] = int(scalars['resets_checked'])
        self._moment_ring[plant] = arrays['moment_ring']
        self._moment_pending[plant] = int(scalars['moment_pending'])
        self._moment_sums[plant] = arrays['moment_sums']
        self._moment_weight[plant] = float(scalars['moment_weight'])
        self._moment_snapshot[plant] = arrays['moment_snapshot']
        self._sandwich_due[plant] = self._moment_weight[plant] > 0.0


def make_batched_estimator(name: str, num_plants: int, **settings: Any) -> BatchedRls:
    """Build the batched form of estimator ``name`` (see :mod:`bcid_ros.estimators`)."""
    from bcid_ros.estimators import make_batched_estimator as make

    return make(name, num_plants, **settings)


__all__ = ['BatchedBcrls', 'BatchedRls', 'make_batched_estimator']
