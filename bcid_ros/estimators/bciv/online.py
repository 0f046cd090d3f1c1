r"""
The recursive BCIV estimator: per sample, the moments of Step 2, then the solver.

Ikenoue, Kanae, Yang and Wada (2008), the recursive algorithm of section 4:
each sample enters the IV-type vector (54), delayed as in eqs. (68)-(70),
updates the moments of Step 2 and gets its estimate from
:class:`~bcid_ros.estimators.bciv.solver.BcivSolver` (eqs. 38, 75, 53, or
the white fixed point of eqs. 65-67). :class:`Bciv` holds the sample
handling (history ring, dead time), the units, the outlier gate, the
validity checks and the state; the covariance of its estimate is in
:mod:`bcid_ros.estimators.bciv.uncertainty`.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from scipy.linalg.blas import dger

from bcid_ros.estimators import rules
from bcid_ros.estimators.base import check_int, check_range, RecursiveEstimator
from bcid_ros.estimators.bciv.solver import (BcivSolver, check_structure, DEFAULT_TOLERANCE,
                                             INPUT_NOISE, OK, published_noise)
from bcid_ros.estimators.bciv.history import SampleHistory
from bcid_ros.estimators.bciv.uncertainty import moment_function
from bcid_ros.estimators.bciv.units import regularisation_weights
from bcid_ros.estimators.moment_covariance import MomentBlocks
from bcid_ros.estimators.recursion import VARIANCE_FLOOR

UPDATES = ('converged', 'printed')
#: A compensation farther than this from theta_IV (relative, normalised units) is a runaway.
RUNAWAY_SHIFT = 1.0


class Bciv(RecursiveEstimator):
    r"""
    Recursive BCIV-type estimator for errors-in-variables models (Ikenoue et al. 2008).

    The data are the noisy output z_t (the published ``y``) and the noisy
    input w_t (``u``), SISO. With the IV-type vector (54), delayed by l - 1
    samples as in eqs. (68)-(70), every sample updates the moments (Step 2,
    unnormalised: :math:`\bar R = N\hat R_{\eta p}`, :math:`\bar r = N\hat r_{\eta z}`)
    and then computes the estimate from them with
    :class:`~bcid_ros.estimators.bciv.solver.BcivSolver`:

    .. math::

        [\bar R_N,\ -\bar r_N] &= \lambda [\bar R_{N-1},\ -\bar r_{N-1}]
            + \eta_N [p_N^T,\ -z_N] && \text{Step 2} \\
        \hat\theta_{IV,N} &= (\bar R^T W \bar R + \rho^{-1}\lambda^{2N} I)^{-1}
            \bar R^T W \bar r && \text{Step 1, eq. (38), } M_0 = \rho I \\
        \tilde\gamma_{k+1} &= (\tilde Q_k^T X \tilde Q_k)^{-1} \tilde Q_k^T X
            (\bar R\theta_k - \bar r) && \text{Step 3, eq. (75)} \\
        \theta_{k+1} &= \hat\theta_{IV,N} + (\bar R^T W \bar R
            + \rho^{-1}\lambda^{2N} I)^{-1} \bar R^T W \tilde Q_k \tilde\gamma_{k+1}
            && \text{Step 4, eq. (53)}

    with :math:`\tilde Q_k = \tilde Q(b_k)` of eq. (61) (colored, noise vector
    (64): r_dd(0..n+l-1)) or eq. (66) (white, (67): sigma_d^2). The estimate at
    sample N is, by ``input_noise`` and ``bciv_update``:

    * colored, ``converged``: K = ``bciv_iterations`` alternations from
      :math:`\theta_0 = \hat\theta_{IV,N}`, stopping early below ``tolerance``;
    * white, ``converged``: a fixed point of the alternation, warm-started from
      the previous estimate (the secant method on the equivalent scalar
      equation in sigma_d^2, at most K steps; see
      :class:`~bcid_ros.estimators.bciv.white.WhiteFixedPoint`);
    * ``printed``: one alternation from the previous estimate (Steps 3-4 as
      printed).

    :math:`\hat\theta_{IV,N}` is that of the rank-2 recursion of Step 1 (it
    sums to the matrix above; ``docs/bciv.md``). For T < L = ``idle_samples``
    the estimate is :math:`\hat\theta_{IV,T}` (initial value selection of
    section 4).

    **Forgetting factor** (an extension): with exponential weights
    :math:`\lambda^{N-t}` the weighted moments normalised by
    :math:`\tau_N = \sum\lambda^{N-t}` have the same limits (71)-(72) on
    stationary data, so the same equations hold with
    :math:`\hat R_{\eta p} = \bar R/\tau_N`; the noise estimates are
    :math:`N\tilde\gamma/\tau_N`.

    **Safeguards** (counted in :attr:`flags`; the estimate stays finite):

    * ``fallback_iv``: :math:`\tilde Q^TX\tilde Q` is singular or its condition
      number exceeds ``CONDITION_MAX`` (b ~ 0, no excitation), or the
      alternation ran away; the estimate is :math:`\hat\theta_{IV,N}` for this
      sample, and the next sample tries again from it. The reason is counted
      too, as ``noise_system_singular`` or ``compensation_runaway``;
    * ``not_converged``: the white fixed point was not reached within K steps
      (the last iterate is used, and the next sample continues from it);
    * ``moments_reset``: the moments overflowed; they restart from zero.

    **Units.** :math:`M_0 = \rho S^{-2}` with
    :math:`S = s_w\,\mathrm{diag}(s_z I_n, s_w I)`, where :math:`s_z`,
    :math:`s_w` are the smallest powers of two at or above the peaks of z and
    w in the first full window
    (:func:`~bcid_ros.estimators.bciv.units.regularisation_weights`): Step 1 on
    the normalised signals with :math:`M_0 = \rho I`, mapped back exactly.
    The estimates do not depend on the units of z and w, and
    ``initial_covariance`` is rho for signals of unit size.

    **Outlier gate** (``outlier_threshold``, the base class's
    :meth:`~bcid_ros.estimators.base.RecursiveEstimator._gate`): before a
    sample enters the window its squared normalised one-step error is the
    larger of

    * :math:`\varepsilon^2/\bar\varepsilon^2`, the equation error
      :math:`\varepsilon(t) = z(t) - p(t)^T\hat\theta_{BCIV}` of the undelayed
      ARX equation (p(t) from the previous n samples) over its weighted mean
      square since the estimator became ready (z(t)^2 over its mean square
      while the window refills after a restart, when p(t) is not known);
    * :math:`w(t)^2/\bar w^2`: w(t) enters the IV-type vector (54) at once,
      l - 1 samples before it enters a regressor, so the input's size is
      tested as it arrives.

    The gate tests once ``GATE_WARMUP`` p equation errors were measured
    (after the estimator became ready: their mean square is then a
    variance). A detected plant change cuts the memory to ``CHANGE_MEMORY`` m
    samples (:func:`~bcid_ros.estimators.rules.memory_keep`: moments and tau
    times kappa, lambda^2N times kappa^2) and the gate relearns its scales.
    (The constants are the rulebook's, :mod:`bcid_ros.estimators.rules`.)

    **Validity**, re-evaluated every ``VALIDITY_PERIOD`` updates: the
    compensated model is unstable (a pole beyond ``UNSTABLE_RADIUS``) while
    the output's mean square did not grow ``GROWTH`` times since the last
    check (:func:`~bcid_ros.estimators.rules.unstable_models`); the
    estimate fell back to theta_IV (ill-conditioned :math:`\tilde Q^TX\tilde Q`
    or runaway) since the last check, or at this sample; the compensation
    moved farther than ``RUNAWAY_SHIFT`` times :math:`|\hat\theta_{IV}|` from
    theta_IV (normalised units).

    Parameters
    ----------
    order, num_inputs, feedthrough, initial_covariance, forgetting_factor, outlier_threshold
        See :class:`~bcid_ros.estimators.base.RecursiveEstimator`; only
        ``num_inputs=1``. ``initial_covariance`` is rho of M_0 = rho I in
        normalised units (see Units).
    input_delay, detrend, adapt, outlier_threshold
        See :class:`~bcid_ros.estimators.base.RecursiveEstimator`. A dead
        time d shifts the input history by d (see
        :meth:`~bcid_ros.estimators.bciv.history.SampleHistory.push`).
    iv_lag : int
        l >= 1 of eq. (54); m = n + 2l.
    input_noise : str
        ``'colored'`` (eqs. 59-64) or ``'white'`` (eqs. 65-67).
    idle_samples : int
        L: the estimate is theta_IV for the first L updates.
    bciv_iterations : int
        K, alternations per sample (colored), or the cap of the white solver.
    bciv_update : str
        ``'converged'`` (the definitions above) or ``'printed'``.
    allow_underdetermined : bool
        Run even if eq. (72) has fewer equations than unknowns (l < 2n
        colored); see :func:`~bcid_ros.estimators.bciv.solver.check_structure`.
    tolerance : float
        Stop the iterations once a step's 2-norm is below this.
    iv_weight, noise_weight : array_like or None
        W and X of eqs. (38) and (74), ``(m, m)``; None (the default, as in
        the paper's examples) is the identity. Not ROS parameters.

    Raises
    ------
    ValueError
        If a setting is out of range; the message names it.

    """

    name = 'bciv'
    _guarded_update = RecursiveEstimator._step_transaction

    def __init__(self, *, iv_lag: int = 5, input_noise: str = 'colored',
                 idle_samples: int = 100, bciv_iterations: int = 20,
                 bciv_update: str = 'converged', allow_underdetermined: bool = False,
                 tolerance: float = DEFAULT_TOLERANCE, iv_weight: Any = None,
                 noise_weight: Any = None, **settings: Any) -> None:
        super().__init__(**settings)
        if self.num_inputs != 1:
            raise ValueError(f'num_inputs must be 1 for bciv (the IV-type vector of eq. (54) '
                             f'is built for a single input), got {self.num_inputs}')
        self.iv_lag = check_int('iv_lag', iv_lag, 1)
        if input_noise not in INPUT_NOISE:
            raise ValueError(f"input_noise must be 'colored' or 'white', got {input_noise!r}")
        if bciv_update not in UPDATES:
            raise ValueError(f"bciv_update must be 'converged' or 'printed', got "
                             f'{bciv_update!r}')
        if not isinstance(allow_underdetermined, (bool, np.bool_)):
            raise ValueError(f'allow_underdetermined must be true or false, got '
                             f'{allow_underdetermined!r}')
        self.input_noise = input_noise
        self.bciv_update = bciv_update
        self.allow_underdetermined = bool(allow_underdetermined)
        self.idle_samples = check_int('idle_samples', idle_samples, 0)
        self.bciv_iterations = check_int('bciv_iterations', bciv_iterations, 1)
        self.tolerance = check_range('tolerance', tolerance, 0.0, 1.0)
        check_structure(self.order, self.iv_lag, self.feedthrough, input_noise,
                        self.allow_underdetermined)
        self._solver = BcivSolver(order=self.order, iv_lag=self.iv_lag,
                                  feedthrough=self.feedthrough, input_noise=input_noise,
                                  iv_weight=iv_weight, noise_weight=noise_weight)
        solver = self._solver
        self.noise_names = (('sigma2_d',) if input_noise == 'white'
                            else tuple(f'r_dd{k}' for k in range(solver.q)))
        self._mode = ('printed' if bciv_update == 'printed'
                      else 'fixed_point' if input_noise == 'white' else 'steps')
        self._iterations = 1 if bciv_update == 'printed' else self.bciv_iterations
        #: The window of eta and p, and the delay line of a dead time d.
        self._history = SampleHistory(solver.m, solver.window_indices(), self.order,
                                      solver.lags, self.input_delay[0])
        # what a step may change, for the transaction; not the history window and its
        # counts, which the undo's restart empties; the delay line's position and values
        delay_line = ('_history.line',) if self.input_delay[0] else ()
        self._name_step_state(
            ('_theta_iv', '_theta_bciv', '_gamma', '_tau', '_decay', '_updates',
             '_iterations_used', '_signal_count', '_error_count', '_input_power',
             '_output_power', '_error_power', '_next_check', '_last_power', '_fallbacks_checked',
             '_reasons', '_last_status', '_signal_scale')
            + (('_line_position',) if delay_line else ()),
            ('_moments',) + delay_line)
        self._reset()

    # ------------------------------------------------------------- the step
    def _update(self, y: float, u: np.ndarray) -> None:
        w = float(u[0])
        # the gate tests the raw input's size, and the equation error of z(t) with the
        # input that enters the history now, w(t - d) (None while the delay line fills)
        history = self._history
        delayed = history.delayed_input(w)
        error = (history.equation_error(y, delayed, self._theta_bciv) if delayed is not None
                 and history.filled >= self.order and self._updates >= self._ready_count
                 else None)
        if not self._passes_gate(y, w, error):
            return
        self._track_signals(y, w, error)
        if not history.push(y, w):
            return
        if self._scales_pending:
            self._choose_scales()
        m = self._solver.m
        # [eta; p; -z] of eqs. (54), (68)-(70)
        sample = history.sample()
        lam = self._forgetting_factor
        if lam != 1.0:
            self._moments *= lam
        # [R | -r] = lambda [R | -r] + eta [p', -z]      (Step 2, unnormalised, in place)
        dger(1.0, sample[:m], sample[m:], 1, 1, self._moments, 1, 1, 1)
        # tau = lambda tau + 1 ; decay = lambda^2N
        self._tau = lam * self._tau + 1.0
        self._decay *= lam * lam
        self._updates += 1
        self._estimate()
        if self._updates >= self._next_check:
            self._check_validity()
        if self._updates >= self._blocks.next_boundary:
            self._close_block()

    def _hold(self, y: float, u: np.ndarray) -> None:
        """Move the history on without touching the moments or the estimate."""
        self._history.push(y, u[0])

    def _estimate(self) -> None:
        """Compute theta_IV,N and theta_BCIV,N from the moments."""
        regularisation = self._regularisation()
        mode = 'idle' if self._updates < self.idle_samples else self._mode
        theta, gamma, theta_iv, done, converged, status = self._solver.estimate(
            self._moments, regularisation, mode=mode, iterations=self._iterations,
            tolerance=self.tolerance, start=self._theta_bciv,
            start_noise=self._gamma[0] * self._tau)
        if not math.isfinite(theta_iv.dot(theta_iv)):
            self._flag('moments_reset')
            self._moments[...] = 0.0
            self._tau, self._decay, self._updates = 0.0, 1.0, 0
            return
        self._theta_iv = theta_iv
        self._theta_bciv = theta
        self._iterations_used = done
        self._last_status = status
        if status:
            self._flag('fallback_iv')
            self._flag(status)
        elif mode != 'idle':
            self._gamma = gamma * (1.0 / self._tau)
            if mode == 'fixed_point' and not converged:
                self._flag('not_converged')
            if self._gamma[0] < 0.0:
                # a finite-sample estimate of a variance below zero (see _noise)
                self._flag('negative_variance')

    # ----------------------------------------------------------- the gate
    def _passes_gate(self, y: float, w: float, error: float | None) -> bool:
        """
        Return whether the gate lets a new sample in: z^2 of :meth:`_gate_score`, then ``_gate``.

        The gate tests once ``GATE_WARMUP`` p equation errors were measured;
        a quiet sample (:func:`~bcid_ros.estimators.rules.gate_is_quiet`)
        passes without the base class's :meth:`_gate`. While the regressor
        refills only the sizes are tested and the change score waits: such a
        sample within the limit is quiet whatever the score.
        """
        if self._error_count < self._gate_from:
            return True
        z2 = self._gate_score(y, w, error)
        tail = rules.gate_is_quiet(z2, self._gate_limit2,
                                   self._change_score if error is not None else 0.0,
                                   self._gate_tail)
        if tail:
            self._gate_tail = tail
            return True
        return self._gate(z2)

    def _gate_score(self, y: float, w: float, error: float | None) -> float:
        """Return the squared normalised one-step error of a new sample (class docstring)."""
        score = w * w / self._input_power if self._input_power > 0.0 else 0.0
        if error is not None:
            part = error * error / (self._error_power + self._error_floor)
        else:  # the regressor refills after a restart: the output's own size
            part = y * y / self._output_power if self._output_power > 0.0 else 0.0
        return part if part > score else score

    def _track_signals(self, y: float, w: float, error: float | None) -> None:
        """Add an accepted sample to the weighted mean squares of w, z and the equation error."""
        lam = self._forgetting_factor
        self._signal_count = lam * self._signal_count + 1.0
        weight = 1.0 / self._signal_count
        self._input_power += (w * w - self._input_power) * weight
        self._output_power += (y * y - self._output_power) * weight
        if error is not None:
            self._error_count = lam * self._error_count + 1.0
            self._error_power += (error * error - self._error_power) / self._error_count

    def _accept_change(self) -> None:
        """Cut the memory to CHANGE_MEMORY m samples and let the gate relearn its scales."""
        keep = rules.memory_keep(self._tau, self._solver.m)
        if keep < 1.0:
            self._moments *= keep
            self._tau *= keep
            self._decay *= keep * keep  # the prior keeps its weight against R'WR
        self._signal_count = min(self._signal_count, 1.0)
        self._error_count = 0.0

    # ---------------------------------------------------------- the units
    def _choose_scales(self) -> None:
        """Give z and w, if still without a scale, the power of two of the window's peak."""
        peaks = np.abs(self._history.window).max(axis=0)
        scales = self._signal_scale.copy()
        rules.choose_scales(scales[None], peaks[None])
        self._signal_scale = scales
        self._set_scale_dependents()

    def _set_scale_dependents(self) -> None:
        scales = self._signal_scale
        self._scales_pending = bool((scales == 0.0).any())
        z_scale, w_scale = (float(s) if s > 0.0 else 1.0 for s in scales)
        self._regularisation_weights = regularisation_weights(
            z_scale, w_scale, self.order, self.num_parameters)
        self._error_floor = (VARIANCE_FLOOR * z_scale) ** 2
        self._regularised_decay = math.nan  # recompute the M_0 term
        self._normalised_units = np.ones(self.num_parameters)
        self._normalised_units[self.order:] = w_scale / z_scale

    def _regularisation(self) -> np.ndarray:
        """Return the M_0 term rho^-1 lambda^2N S^2 of Step 1 in the user's units."""
        if self._decay != self._regularised_decay:  # (cached: constant without forgetting)
            self._regularised_decay = self._decay
            self._regularisation_term = (self._decay / self.initial_covariance) * \
                self._regularisation_weights
        return self._regularisation_term

    @property
    def signal_scale(self) -> np.ndarray:
        """Return the scales of z and w (0 while a channel has only seen zeros)."""
        return self._signal_scale.copy()

    @property
    def initial_covariance_diagonal(self) -> np.ndarray:
        """Return the diagonal of M_0 = rho S^-2 in the user's units (see the class docstring)."""
        return self.initial_covariance / self._regularisation_weights

    # ------------------------------------------------------- the validity
    def _check_validity(self) -> None:
        """Decide the reasons (every VALIDITY_PERIOD updates), then move the checks' memory on."""
        self._next_check = self._updates + rules.VALIDITY_PERIOD
        fallbacks = self.flags.get('fallback_iv', 0)
        with np.errstate(all='ignore'):
            own = self._own_reasons(fallbacks - self._fallbacks_checked)
        self._decide_validity(own)
        self._last_power = self._output_power
        self._fallbacks_checked = fallbacks

    def _own_reasons(self, fallbacks: int) -> list[str]:
        """Return the reasons not to trust the estimate now (see the class docstring)."""
        reasons = rules.unstable_models(self._theta_bciv[None, :self.order],
                                        np.array([self._output_power]),
                                        np.array([self._last_power]))[0]
        if fallbacks > 0:
            reasons.append(f'ill-conditioned or runaway compensation (fell back to theta_IV '
                           f'{fallbacks} times)')
        units = self._normalised_units
        shift = float(np.linalg.norm(units * (self._theta_bciv - self._theta_iv)))
        size = float(np.linalg.norm(units * self._theta_iv))
        if not shift <= RUNAWAY_SHIFT * size:
            reasons.append(f'compensation runs away from IV ({shift / size:.3g} x |theta_IV|)'
                           if size > 0 else 'compensation runs away from IV')
        return reasons

    #: The last compensation's fallback is a reason from the sample it happens on.
    _LIVE_REASONS = True

    def _live_reasons(self) -> tuple[str, ...]:
        if self._last_status:
            return (f'compensation fell back to theta_IV ({self._last_status})',)
        return ()

    # --------------------------------------------------------- the accessors
    @property
    def ready(self) -> bool:
        """Whether eta is filled, L updates are done and at least p updates were made."""
        return self._updates >= self._ready_count

    @property
    def samples(self) -> int:
        """Count the estimator updates (samples with a filled IV-type vector)."""
        return self._updates

    @property
    def covariance_trace(self) -> float:
        """Return tr M_N of Step 1, M_N = (R'WR + rho^-1 lambda^2N S^2)^-1 (a health indicator)."""
        if self._updates == 0:
            return float((self.initial_covariance / self._regularisation_weights).sum())
        try:
            return float(np.trace(np.linalg.inv(self._solver.m_inverse)))
        except np.linalg.LinAlgError:
            return float('inf')

    @property
    def last_iterations(self) -> int:
        """Return the number of alternations (or secant steps) of the last sample."""
        return self._iterations_used

    def _theta(self) -> np.ndarray:
        return self._theta_bciv

    def _theta_uncompensated(self) -> np.ndarray:
        return self._theta_iv

    def _noise(self) -> np.ndarray:
        # The raw gamma stays in the state: the next white fixed point starts from it.
        return published_noise(self._gamma)

    # ------------------------------------------------------- the uncertainty
    def _parameter_covariance(self) -> np.ndarray | None:
        """
        Return the delta-method covariance of theta_BCIV from block means of the moments.

        See :mod:`bcid_ros.estimators.bciv.uncertainty`. None before
        :attr:`ready` and with ``bciv_update='printed'``.
        """
        if not self.ready or self.bciv_update == 'printed':
            return None
        return self._blocks.covariance(self._tau, self._forgetting_factor)

    def _close_block(self) -> None:
        """Hand the moment sums of a block boundary to the block means."""
        self._blocks.close(self._updates, self._moments, self._tau, self._forgetting_factor, 0,
                           self._moment_function)

    def _moment_function(self) -> Any:
        """Return F: the estimate from the weighted means of [R | -r], as :meth:`_estimate`."""
        settings = dict(order=self.order, iv_lag=self.iv_lag, feedthrough=self.feedthrough,
                        input_noise=self.input_noise, iv_weight=self._solver.iv_weight,
                        noise_weight=self._solver.noise_weight)
        # M_N^-1 of the means: R'WR / tau^2 + rho^-1 lambda^2N S^2 / tau^2
        regularisation = self._regularisation() / (self._tau * self._tau)
        return moment_function(settings, self._moments.shape, regularisation, self._mode,
                               self._iterations, self.tolerance, float(self._gamma[0]))

    # -------------------------------------------------------------- the state
    @property
    def _line_position(self) -> int:
        """Return the delay line's position (named for the step transaction)."""
        return self._history.line_position

    @_line_position.setter
    def _line_position(self, position: int) -> None:
        self._history.line_position = position

    def _reset(self) -> None:
        p = self.num_parameters
        self._history.clear()
        #: The moments [R | -r] of Step 2 live in the solver's buffer, updated in place.
        self._moments = self._solver.moments
        self._moments[...] = 0.0
        self._tau = 0.0
        self._decay = 1.0
        self._updates = 0
        self._theta_iv = np.zeros(p)
        self._theta_bciv = np.zeros(p)
        self._gamma = np.zeros(self._solver.q)
        self._iterations_used = 0
        self._ready_count = max(self.idle_samples, p)
        self._gate_from = rules.GATE_WARMUP * p
        self._signal_scale = np.zeros(2)
        self._set_scale_dependents()
        self._signal_count = self._error_count = 0.0
        self._input_power = self._output_power = self._error_power = 0.0
        self._next_check = rules.VALIDITY_PERIOD
        self._last_power = math.inf
        self._fallbacks_checked = 0
        self._reasons: tuple[str, ...] = ()
        self._last_status = OK
        self._blocks = MomentBlocks()

    def _restart_regressor(self) -> None:
        self._history.restart()

    def _state_items(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        history = self._history
        arrays = {'moments': self._moments, 'history': history.window,
                  'theta_iv': self._theta_iv, 'theta_bciv': self._theta_bciv,
                  'gamma': self._gamma, 'delay_line': history.line,
                  'signal_scale': self._signal_scale}
        scalars = {'filled': history.filled, 'tau': self._tau, 'decay': self._decay,
                   'line_position': history.line_position, 'line_filled': history.line_filled,
                   'updates': self._updates, 'iterations_used': self._iterations_used,
                   'forgetting_factor': self._forgetting_factor,
                   'signal_count': self._signal_count, 'error_count': self._error_count,
                   'input_power': self._input_power, 'output_power': self._output_power,
                   'error_power': self._error_power, 'next_check': self._next_check,
                   'last_power': self._last_power, 'fallbacks_checked': self._fallbacks_checked,
                   'reasons': self._reasons, 'last_status': self._last_status}
        return arrays, scalars

    def _is_sound(self) -> bool:
        # the base class's test, without its calls in the usual case: a finite sum means
        # that every raw value is finite, the published noise then too
        if math.isfinite(sum(self._theta_bciv.tolist()) + sum(self._theta_iv.tolist())
                         + sum(self._gamma.tolist())):
            return True
        return super()._is_sound()

    def _step_restored(self) -> None:
        self._set_scale_dependents()
        if self._updates > 0:  # M_N^-1 for covariance_trace
            self._solver.estimate(self._moments, self._regularisation(),
                                  mode='idle', iterations=0, tolerance=self.tolerance)

    def _load_state(self, arrays: dict[str, np.ndarray], scalars: dict[str, Any]) -> None:
        history = self._history
        self._moments[...] = arrays['moments']
        history.window[...] = arrays['history']
        self._theta_iv = arrays['theta_iv']
        self._theta_bciv = arrays['theta_bciv']
        self._gamma = arrays['gamma']
        history.line[...] = arrays['delay_line']
        history.line_position = int(scalars['line_position'])
        history.line_filled = int(scalars['line_filled'])
        history.filled = int(scalars['filled'])
        self._tau = float(scalars['tau'])
        self._decay = float(scalars['decay'])
        self._updates = int(scalars['updates'])
        self._iterations_used = int(scalars['iterations_used'])
        self._forgetting_factor = float(scalars['forgetting_factor'])
        self._signal_scale = np.array(arrays['signal_scale'], dtype=float)
        self._set_scale_dependents()
        self._signal_count = float(scalars['signal_count'])
        self._error_count = float(scalars['error_count'])
        self._input_power = float(scalars['input_power'])
        self._output_power = float(scalars['output_power'])
        self._error_power = float(scalars['error_power'])
        self._next_check = int(scalars['next_check'])
        self._last_power = float(scalars['last_power'])
        self._fallbacks_checked = int(scalars['fallbacks_checked'])
        self._reasons = tuple(scalars['reasons'])
        self._last_status = str(scalars['last_status'])
        if self._updates > 0:  # M_N^-1 for covariance_trace
            self._solver.estimate(self._moments, self._regularisation(),
                                  mode='idle', iterations=0, tolerance=self.tolerance)

    def __repr__(self) -> str:
        return (f'Bciv(order={self.order}, iv_lag={self.iv_lag}, '
                f'input_noise={self.input_noise!r}, bciv_update={self.bciv_update!r}, '
                f'bciv_iterations={self.bciv_iterations}, idle_samples={self.idle_samples}, '
                f'forgetting_factor={self._forgetting_factor})')
