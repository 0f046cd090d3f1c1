"""
BCRLS over many plants of one structure: the batched LS part and the compensation per plant.

The LS part, the sample policy and the per-plant bookkeeping are
:class:`~bcid_ros.estimators.batched.BatchedRls`'s; this adds the bias
compensation of :class:`~bcid_ros.estimators.bcrls.Bcrls` by its batched twin
:func:`~bcid_ros.estimators.bcrls.compensate_rows`, with the same safeguards,
validity and sandwich covariance per plant.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from bcid_ros.estimators.adequacy import AdequacyMonitor
from bcid_ros.estimators.base import EstimatorState, weighted_square_ratio
from bcid_ros.estimators.batched import BatchedRls, Rows
from bcid_ros.estimators.bcrls import (Bcrls, compensate_rows, compensation_problems,
                                       gradient_covariances, LaggedMoments,
                                       output_error_rows, output_gradient)
from bcid_ros.estimators.held_model import hold_due, precise, with_held_items
from bcid_ros.estimators.polynomials import spectral_radii


class BatchedBcrls(BatchedRls):
    r"""
    K independent BCRLS estimators of one structure, updated together.

    The LS part is :class:`BatchedRls`; after each plant's LS step comes the
    compensation of :class:`~bcid_ros.estimators.bcrls.Bcrls`, eqs. (51) and
    (46) with :math:`\Lambda = \mathrm{diag}(I_n, 0)`, by its batched twin
    :func:`~bcid_ros.estimators.bcrls.compensate_rows`, with the same
    safeguards (``sigma2_denominator``, ``compensation_reset``), the same
    validity (:func:`~bcid_ros.estimators.bcrls.compensation_problems`) and
    the same sandwich covariance (:class:`~bcid_ros.estimators.bcrls.LaggedMoments`),
    per plant. See :class:`BatchedRls` for the parameters and the sample policy.
    """

    name: ClassVar[str] = 'bcrls'
    noise_names: ClassVar[tuple[str, ...]] = ('sigma2',)
    _SNAPSHOT_ARRAYS = BatchedRls._SNAPSHOT_ARRAYS + ('theta_c', 'output_errors',
                                                      'output_gradients', 'held_theta',
                                                      'held_errors')
    _SNAPSHOT_SCALARS = {**BatchedRls._SNAPSHOT_SCALARS, 'sigma2': float, 'resets_checked': int,
                         'held_tau': float}
    adequacy_model = Bcrls.adequacy_model
    hac_std = Bcrls.hac_std
    _single = Bcrls

    @property
    def sigma2(self) -> np.ndarray:
        """Return the noise variance estimates of eq. (51), shape ``(K,)`` (a copy)."""
        return self._shown(self._sigma2.copy(), 'sigma2')

    @property
    def noise(self) -> np.ndarray:
        """Return the noise estimates ``sigma2``, shape ``(K, 1)``."""
        return self._shown(self._sigma2[:, None].copy(), 'noise')

    def _after_ls_step(self, rows: np.ndarray, y: np.ndarray, phi: np.ndarray) -> None:
        """Apply eqs. (51) and (46) to the plants ``rows``; keep z = [phi; y] for the moments."""
        self._record_moments(rows, y, phi)
        at = self._view_rows(rows)
        sigma2, compensated, low, reset = compensate_rows(
            self._theta_ls[at], self._p[at], self._loss[at], self._tau[at],
            self._lambda_theta_c[at], self._sigma2[at])
        if low.any():
            self._flag('sigma2_denominator', rows, low)
        if reset.any():
            self._flag('compensation_reset', rows, reset)
        self._sigma2[at] = sigma2
        self._theta_c[at] = compensated
        self._lambda_theta_c[at] = compensated * self._lambda_diagonal

    def _check_validity(self, plants: np.ndarray, more: Any = None) -> None:
        """Add the compensation's reasons (Bcrls._check_validity); restart diverging ones."""
        resets = self.flags.get('compensation_reset', np.zeros(self.num_plants, np.int64))[plants]
        with np.errstate(all='ignore'):
            found, diverging = compensation_problems(
                self._tau[plants], self._sigma2[plants], self._p[plants], self._theta_c[plants],
                self._theta_ls[plants], self._component_scale[plants],
                resets > self._resets_checked[plants], self.order,
                lambda rows: self._covariances(plants[rows]))
        self._resets_checked[plants] = resets
        super()._check_validity(plants, found)
        if diverging.any():
            # (46) does not contract: restart it from theta_LS rather than follow it away
            restart = plants[diverging]
            self._flag('compensation_reset', restart)
            self._resets_checked[restart] += 1
            self._theta_c[restart] = self._theta_ls[restart]
            self._lambda_theta_c[restart] = self._theta_c[restart] * self._lambda_diagonal
        if self._change_detection:
            # no reason against the compensation, and a stable A (a bounded output error)
            sound = (np.array([not reasons for reasons in found], dtype=bool) & ~diverging
                     & (spectral_radii(self._theta_c[plants, :self.order]) < 1.0))
            due = plants[hold_due(sound, self._tau[plants], self._held_tau[plants])]
            if due.size:
                self._hold_models(due[precise(self._theta_c[due], self._covariances(due))])

    def _hold_models(self, plants: np.ndarray) -> None:
        """Hold the estimates of ``plants`` for the detector (Bcrls._hold_model)."""
        if not plants.size:
            return
        first = plants[self._held_tau[plants] <= 0.0]
        if first.size:  # their detector's reference was of the LS step's errors
            self._detector.clear(first)
            self._held_errors[first] = 0.0
        self._held_theta[plants] = self._theta_c[plants]
        self._held_tau[plants] = self._tau[plants]

    def _covariances(self, plants: np.ndarray) -> np.ndarray:
        """Return the covariances of ``plants`` (NaN where none), as Bcrls's."""
        return self.parameter_covariance_of(plants)

    def _record_residuals(self, rows: np.ndarray, y: np.ndarray, phi: np.ndarray,
                          u: np.ndarray, errors: np.ndarray) -> None:
        """Give the residual tests the output errors of ``rows`` (Bcrls._record_residual)."""
        at = self._view_rows(rows)
        # (a view of every plant's rows, or a copy of some: updated in place, then put back)
        past = self._output_gradients[at]
        psi = output_gradient(self._theta_c[at], phi, self._output_errors[at], past)
        error, bounded = self._run_output_errors(at, y, phi)
        if bounded.all():
            self._output_gradients[at] = past
            self._monitor.record_rows(rows, error, u, psi)
            return
        past[~bounded] = 0.0
        self._output_gradients[at] = past
        if bounded.any():
            self._monitor.record_rows(rows[bounded], error[bounded], u[bounded], psi[bounded])

    def _run_output_errors(self, at: Rows, y: np.ndarray,
                           phi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """
        Run the output-error filters of ``at``; return the estimate's errors and where bounded.

        The estimate's filter and, where some plant holds a model, the held
        models' (both Bcrls._record_residual's) in one call on the stacked
        filters; the held models' errors are kept for the detector.
        """
        held = self._held_tau[at] > 0.0
        self._holding, self._some_held, self._unbounded = held, bool(held.any()), False
        # every plant of at runs the held filter, one not holding a model with theta_h = 0
        # (its error y, never used, its past kept at zero): no subset taken where most hold one
        filters = slice(None) if self._some_held else slice(1)
        errors, bounded, past = output_error_rows(
            self._filter_theta[filters, at], self._filter_errors[filters, at], y, phi,
            self._signal_scale[at, 0])
        if self._some_held:
            past[1] *= held[:, None]
            held_errors = errors[1]
            if not bounded[1].all():  # an unstable held A: its filter restarts, no input now
                self._unbounded = True
                held_errors = np.where(bounded[1], held_errors, np.nan)
            self._held_input[at] = held_errors
        self._filter_errors[filters, at] = past
        return errors[0], bounded[0]

    def _detector_errors(self, rows: np.ndarray, errors: np.ndarray, gains: np.ndarray,
                         ) -> tuple[np.ndarray, np.ndarray]:
        """Return the held model's output error where one is held, else e / sqrt(s)."""
        inputs = errors / np.sqrt(gains)
        if not self._some_held:
            return rows, inputs
        # rows are those of the last _run_output_errors or some of them (the plain steps)
        held = (self._holding if rows.shape[0] == self._holding.shape[0]
                else self._held_tau[rows] > 0.0)
        inputs = np.where(held, self._held_input[self._view_rows(rows)], inputs)
        if not self._unbounded:
            return rows, inputs
        finite = np.isfinite(inputs)
        return rows[finite], inputs[finite]

    def _theta(self) -> np.ndarray:
        return self._theta_c

    # ------------------------------------------------------- the uncertainty
    def _record_moments(self, rows: np.ndarray, y: np.ndarray, phi: np.ndarray) -> None:
        """Keep z = [phi; y] of the plants ``rows``; sum a plant's block when it is full."""
        full = self._moments.record(rows, y, phi)
        if full.size:
            self._moments.flush(full, self._forgetting_factor, self._theta_c[full],
                                self._sigma2[full], self._component_scale[full],
                                self._signal_scale[full, 0])

    def _parameter_covariance(self, wanted: np.ndarray | None = None) -> np.ndarray:
        """
        Return each plant's sandwich covariance (``Bcrls._parameter_covariance``).

        ``wanted`` ``(K,)``: only those plants' (the others NaN). The sandwiches of every
        plant whose block ended are evaluated together all the same, once a block: a
        decision a frame would otherwise evaluate one alone in each.
        """
        known = (self._updates >= self.num_parameters) & (self._moments.weight > 0.0)
        sandwiches = self._moments.sandwiches(known)
        if wanted is not None:
            known &= wanted
        tau = self._tau
        factor = np.full(self.num_plants, np.nan)
        factor[known] = weighted_square_ratio(tau[known], self._forgetting_factor) / tau[known]
        return factor[:, None, None] * np.where(known[:, None, None], sandwiches, np.nan)

    def _allocate(self) -> None:
        super()._allocate()
        plants, p = self.num_plants, self.num_parameters
        # the diagonal of Lambda = diag(I_n, 0)
        self._lambda_diagonal = np.zeros(p)
        self._lambda_diagonal[:self.order] = 1.0
        # the output-error filters of each plant: its estimate's (row 0: theta_c and the
        # errors e_oe(t-1) ... e_oe(t-n), newest first; Bcrls._record_residual) and its held
        # model's for the detector (row 1, Bcrls._drop_held_model), run in one call
        self._filter_theta = np.zeros((2, plants, p))
        self._filter_errors = np.zeros((2, plants, self.order))
        self._theta_c, self._held_theta = self._filter_theta
        self._output_errors, self._held_errors = self._filter_errors
        self._lambda_theta_c = np.zeros((plants, p))
        self._sigma2 = np.zeros(plants)
        self._resets_checked = np.zeros(plants, dtype=np.int64)
        self._moments = LaggedMoments(plants, self.order, p)
        # psi(t-1) ... psi(t-n), newest first (Bcrls._record_residual)
        self._output_gradients = np.zeros((plants, self.order, p))
        # tau of each held model (0: none held), its last output error, the plants holding one
        self._held_tau = np.zeros(plants)
        self._held_input = np.zeros(plants)
        self._holding = np.zeros(plants, dtype=bool)
        self._some_held, self._unbounded = False, False
        # the output error's tests with the estimate's own error (Bcrls._forget_residuals)
        self._monitor = AdequacyMonitor(
            num_inputs=self.num_inputs, model=self.adequacy_model,
            forgetting_factor=self._forgetting_factor, plants=plants, num_parameters=p,
            parameter_covariance=lambda plants: gradient_covariances(
                self._covariances(plants), self._theta_c[plants], self.order))

    def _reset_learning(self, rows: Rows) -> None:
        super()._reset_learning(rows)
        self._theta_c[rows] = 0.0
        self._lambda_theta_c[rows] = 0.0
        self._sigma2[rows] = 0.0
        self._resets_checked[rows] = 0
        self._moments.clear(rows)
        self._output_errors[rows] = 0.0
        self._output_gradients[rows] = 0.0

    def _forget_residuals(self, rows: np.ndarray) -> None:
        super()._forget_residuals(rows)
        # none held (a reset, a change): the LS step's errors feed the detector again
        dropped = rows[self._held_tau[rows] > 0.0]
        if dropped.size:
            self._detector.clear(dropped)
        self._held_theta[rows] = 0.0
        self._held_errors[rows] = 0.0
        self._held_tau[rows] = 0.0

    def _plant_items(self, plant: int) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        arrays, scalars = super()._plant_items(plant)
        moment_arrays, moment_scalars = self._moments.plant_items(plant)
        return {**arrays, **moment_arrays}, {**scalars, **moment_scalars}

    def set_plant_state(self, plant: int, state: EstimatorState) -> None:
        """Load a snapshot into plant k (BatchedRls's); one from before the held model too."""
        super().set_plant_state(plant, with_held_items(state, self.num_parameters, self.order))

    def _load_plant(self, plant: int, arrays: dict[str, np.ndarray],
                    scalars: dict[str, Any]) -> None:
        # a snapshot from before the output error's gradient: its filter starts from zero
        arrays = {'output_gradients': np.zeros(self._output_gradients.shape[1:]), **arrays}
        super()._load_plant(plant, arrays, scalars)
        self._lambda_theta_c[plant] = self._theta_c[plant] * self._lambda_diagonal
        self._moments.load_plant(plant, arrays, scalars)


__all__ = ['BatchedBcrls']
