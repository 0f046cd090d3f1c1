r"""
Online closed-loop bias-compensated least squares (Ikeda 2008), per sample.

:class:`ClosedLoopBcls` runs a recursive prefiltered LS (eqs. 10-17),
compensates it (eqs. 56-59) and redesigns the prefilter (Algorithm 1) on
what its memory holds: the moments since the controller change (``window``
0, :mod:`~bcid_ros.estimators.cl_bcls.moments`) or a window of samples
(:mod:`~bcid_ros.estimators.cl_bcls.window`). docs/cl_bcls.md explains it.
"""

from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np

from bcid_ros.estimators import rules
from bcid_ros.estimators.base import RecursiveEstimator
from bcid_ros.estimators.cl_bcls.batch import DEFAULT_TOLERANCE
from bcid_ros.estimators.cl_bcls.compensation import (Compensation, MIN_DISCRIMINANT_RATIO,
                                                      MIN_EXCITATION_RATIO, model_reasons)
from bcid_ros.estimators.cl_bcls.excitation import ExcitationMeter
from bcid_ros.estimators.cl_bcls.moments import AllDataMemory
from bcid_ros.estimators.cl_bcls.regression import prefilter_polynomial
from bcid_ros.estimators.cl_bcls.running_ls import (PrefilterBank, REPAIR, SignalScales,
                                                    STEPPED, UNSAFE)
from bcid_ros.estimators.cl_bcls.uncertainty import moment_function
from bcid_ros.estimators.cl_bcls.window import window_lengths, WindowMemory
from bcid_ros.estimators.lti import make_controller
from bcid_ros.estimators.moment_covariance import MomentBlocks
from bcid_ros.estimators.settings import CL_BCLS_OPTIONS, option
from bcid_ros.estimators.shared_settings import check_forgetting_factor
from bcid_ros.estimators.transaction import all_finite

#: Default ``window``: 0, every sample since the last controller change (recursive moments).
DEFAULT_WINDOW = 0
#: Default number of samples between two compensations + prefilter redesigns.
DEFAULT_REDESIGN_PERIOD = 1000
#: Default cap on the iterations of one redesign.
DEFAULT_MAX_ITERATIONS = 20
#: Rows after a new prefilter (``window`` 0) during which only the gate's hard limit
#: applies: the filters' transient and the new epoch's bias are not outliers.
PREFILTER_SETTLE = 100


class ClosedLoopBcls(RecursiveEstimator):
    r"""
    Online closed-loop BCLS: recursive moments since the controller change, or a window.

    The estimator sees only the measured (y[k], u[k]), never the reference r.
    It assumes that u is exactly the output of the given LTI controller acting
    on the same y (no saturation; a retuning is announced with
    :meth:`set_controller`), that the noise is white and on y only (A3), that
    the true loop is stable (A4), that the plant is strictly proper of order
    at most n (A2) and that r is independent of the noise (A5).

    **Per sample** k the prefilter f in use gives

    .. math::

        y_f[k] &= \frac{q^n}{f(q)} y[k], \quad u_f[k] = \frac{q^n}{f(q)} u[k]
            && \text{(10)} \\
        \varphi[k] &= [y_f[k-1] \dots y_f[k-n], u_f[k-1] \dots u_f[k-n]]^T
            && \text{(14)}

    a step of the running LS and, once a redesign has succeeded, the
    compensation of eqs. (58), (59) with the bias terms C, B of the memory
    (:class:`~bcid_ros.estimators.cl_bcls.compensation.Compensation`):
    :math:`\hat\theta_{BC} = \hat\theta_{LS} - \hat\sigma_\nu^2 P C`.

    **All data since the change** (``window`` 0,
    :class:`~bcid_ros.estimators.cl_bcls.moments.AllDataMemory`): rows of
    every prefilter (epoch) stack in one LS of
    :math:`y_f = \psi^T [a \mid b]`, weighted by the forgetting factor, with
    :math:`C = \sum_e W_e D c_e`, :math:`B = \sum_e W_e\beta_e`. A redesign
    is one iteration of Algorithm 1 on the moments; the next prefilter
    :math:`f = \bar{\hat a}_{BC}` opens a new epoch once the rows reach
    ``redesign_period`` and f moved by more than ``PREFILTER_STEP``.
    Redesigns come after ``10 * 2n + n`` rows, then each time the rows double,
    until they are ``redesign_period`` rows apart.

    **Window** (``window`` > 0,
    :class:`~bcid_ros.estimators.cl_bcls.window.WindowMemory`): every
    ``redesign_period`` samples, once the window holds ``10 * 2n + n``
    samples (:attr:`first_window` before the first success), the batch
    Algorithm 1 runs on it from the prefilter in use; between redesigns
    :math:`C = Nc`, :math:`B = N\beta` of its last iteration.

    :meth:`set_controller` restarts every statistic but keeps the prefilter;
    until the next successful redesign ``theta`` is the LS from
    :math:`P(0) = p_0 S^{-2}` and :attr:`valid` is False. The units
    :math:`S = \mathrm{diag}(s_y I_n, s_u I_n)` are powers of two fixed at
    the first LS step: the estimates do not depend on the units of y and u.
    The outlier gate (:meth:`_passes_gate`) tests each row before it enters
    anything; a detected plant change cuts the memory to ``CHANGE_MEMORY`` p
    rows. No estimate is ever NaN: a failed redesign is dropped (the
    compensated estimate held, :attr:`holding`), a failed compensation
    keeps the last good estimate, and each condition is counted in
    :attr:`flags`. docs/cl_bcls.md has the reasons ("Controller changes",
    "Outliers and units", "Safety", "Validity").

    Parameters
    ----------
    order, num_inputs, feedthrough, initial_covariance, forgetting_factor
        As for :class:`~bcid_ros.estimators.base.RecursiveEstimator`, with
        ``num_inputs`` 1 (SISO) and ``feedthrough`` False (eq. 3).
        ``forgetting_factor`` weighs the moments with ``window`` 0 and must be
        1 with a window; :math:`P(0) = p_0 S^{-2}` (see Units) is used only
        before the first redesign.
    controller_numerator, controller_denominator : sequence of float
        b_c(q) and a_c(q) in descending powers of q (eqs. 5, 6); b_c is
        left-padded with zeros to the length of a_c. The paper's (60) is
        ``[0.2289]`` over ``[1, -0.09004]``.
    controller_sign : str
        ``'negative'`` (default): u = (b_c/a_c)(r - y); ``'positive'``:
        u = (b_c/a_c)(y - r).
    prefilter_initial : float or sequence of float
        :math:`f^{(0)}`: a pole p giving f(q) = (q - p)^n (default 0: f = q^n,
        step 1 of Algorithm 1), or ``[1, f_1, ..., f_n]``; must be stable.
    window : int
        0 (default): every sample since the last controller change; > 0: the
        last ``window`` samples (at least ``10 * 2n + n``), for slowly
        varying plants.
    redesign_period : int
        Samples between redesigns (default 1000).
    max_iterations : int
        Cap on the iterations of one redesign (default 20).
    tolerance : float
        A redesign stops when the estimate moves by less (``window`` > 0) or
        its estimated distance to the fixed point is less (``window`` 0)
        (default 1e-3, as in section 7.3).

    Raises
    ------
    ValueError
        If a setting is out of range; the message names it.

    """

    name = 'cl_bcls'
    noise_names = ('sigma2',)

    def __init__(self, *, order: int, num_inputs: int = 1, feedthrough: bool = False,
                 initial_covariance: float = 1e6, forgetting_factor: float = 1.0,
                 controller_numerator: Sequence[float], controller_denominator: Sequence[float],
                 controller_sign: str = 'negative', prefilter_initial: Any = 0.0,
                 window: int = DEFAULT_WINDOW, redesign_period: int = DEFAULT_REDESIGN_PERIOD,
                 max_iterations: int = DEFAULT_MAX_ITERATIONS,
                 tolerance: float = DEFAULT_TOLERANCE, input_delay: Any = 0,
                 **options: Any) -> None:
        # options: the base class's detrend, adapt and outlier_threshold
        super().__init__(order=order, num_inputs=num_inputs, feedthrough=feedthrough,
                         initial_covariance=initial_covariance,
                         forgetting_factor=forgetting_factor, input_delay=input_delay,
                         **options)
        if any(self.input_delay):
            raise ValueError(f'input_delay must be 0 for cl_bcls (its prefiltered regressor '
                             f'and the controller model assume no dead time), got '
                             f'{input_delay!r}')
        if self.num_inputs != 1:
            raise ValueError(f'num_inputs must be 1 for cl_bcls (a SISO loop), got {num_inputs}')
        if self.feedthrough:
            raise ValueError('feedthrough must be False for cl_bcls (b_p(q) has degree < n, '
                             'eq. (3)), got True')
        self.controller = make_controller(controller_numerator, controller_denominator,
                                          controller_sign)
        self.prefilter_initial = prefilter_polynomial(prefilter_initial, self.order)
        self.window, self.min_window, self.first_window = window_lengths(window, self.order)
        self.all_data = self.window == 0
        self._check_forgetting(self._forgetting_factor)
        self.redesign_period = option(CL_BCLS_OPTIONS, 'redesign_period').check_argument(
            redesign_period)
        self.max_iterations = option(CL_BCLS_OPTIONS, 'max_iterations').check_argument(
            max_iterations)
        self.tolerance = option(CL_BCLS_OPTIONS, 'tolerance').check_argument(tolerance)
        self._gate_from = rules.GATE_WARMUP * self.num_parameters
        # the error of a row the gate refuses for it, and the one to subtract from y (_undo)
        self._error_refusal: float | None = None
        self._substitute: float | None = None
        # what a step may change, for the transaction: the collaborators save their own part
        self._name_step_state(
            ('_parts_state', '_samples', '_redesigns', '_last_iterations', '_refusals',
             '_gate_resume'), ())
        self._reset()

    def _check_forgetting(self, value: float) -> None:
        if value != 1.0 and not self.all_data:
            raise ValueError('forgetting_factor must be 1 for cl_bcls with a window (it forgets '
                             f'through its finite window), got {value!r}')

    @property
    def forgetting_factor(self) -> float:
        """Return the forgetting factor (below 1 only with ``window`` 0)."""
        return self._forgetting_factor

    @forgetting_factor.setter
    def forgetting_factor(self, value: float) -> None:
        value = check_forgetting_factor(value)
        self._check_forgetting(value)
        self._forgetting_factor = value
        self._follow_forgetting_factor()

    def set_controller(self, numerator: Sequence[float], denominator: Sequence[float],
                       sign: str = 'negative') -> bool:
        """
        Install the controller now in the loop and restart all but the prefilter and flags.

        ``numerator``, ``denominator`` and ``sign`` are as
        ``controller_numerator``, ``controller_denominator`` and
        ``controller_sign``. Returns False (and restarts nothing) if the
        controller, normalised, is the one in use. Raises ValueError (the
        estimator unchanged) if the controller is not valid.
        """
        controller = make_controller(numerator, denominator, sign)
        current = self.controller
        if (controller.sign == current.sign
                and np.array_equal(controller.numerator, current.numerator)
                and np.array_equal(controller.denominator, current.denominator)):
            return False
        self.controller = controller
        self._restart_statistics()
        self._controller_changes += 1
        return True

    # ------------------------------------------------------------- the step
    def _guarded_update(self, y: float, u: np.ndarray) -> None:
        """
        Do one step as an exact transaction (the base class's ``_step_transaction`` if need be).

        Between redesigns only the RLS update can make the state unsound, and
        the step checks it before committing it (``update_undone``).
        """
        if (self._change_score or self._refusals or self._units.scales[0] == 0.0
                or self._memory.may_redesign()):
            self._step_transaction(y, u)
        else:
            self._update(y, u)

    def _update(self, y: float, u: np.ndarray) -> None:
        u0 = float(u[0])
        self._samples += 1
        units = self._units
        if units.scales[0] == 0.0 and units.watch(y, u0, self._filters.lags >= self.order):
            self._memory.ls.p = units.initial_p()
        self._take_sample(y, u0)
        if self._samples >= self._blocks.next_boundary:
            self._close_block()

    def _take_sample(self, y: float, u0: float) -> None:
        """Make the row's step (once phi is full), move the filters on, redesign when due."""
        filters = self._filters
        if filters.lags >= self.order:
            self._substitute = None
            if not self._row_step(y):
                if self._substitute is None:  # the regressor restarted
                    return
                y -= self._substitute  # the model's prediction (see _undo)
        else:
            filters.lags += 1
        self._excitation.update(y, u0, self._forgetting_factor)
        filters.advance(y, u0)
        if self._memory.after_sample(y, u0, self._bc.direction is not None):
            self._redesign()

    def _row_step(self, y: float) -> bool:
        """Step the row in the memory (through the gate) and compensate; or refuse it."""
        memory = self._memory
        done = memory.step_row(y, self._filters, self._forgetting_factor, self._passes_gate)
        if done != STEPPED:
            if done == REPAIR:  # P lost definiteness
                self._flag('covariance_repaired')
                memory.ls.repair(self._units.initial_p())
                return True
            if done == UNSAFE:
                self._undo('update_undone')
            return False
        bc = self._bc
        if bc.direction is not None and not bc.holding:
            failure = memory.compensate(bc)
            if failure:
                self._flag(failure)
        return True

    def _undo(self, flag: str) -> None:
        """
        Count a refused step; for a row refused for its error, let the prefilters run on.

        Such a row (:attr:`_error_refusal`, its error e) stays out of the
        memory, and the prefilters take y - e, the model's prediction, in place
        of its sample: the regressor stays the model's. Restarting them from
        rest (the base class's rule, kept for a step undone or a regressor
        refused for its leverage, whose state is what is wrong) makes the next
        rows' error carry the filters' transient, the missing past of y
        filtered by q^n/f(q): with f near the plant's A (Algorithm 1's fixed
        point) on a plant with an integrator, a near double integration that
        no gate passes, so each refusal caused the next (every third sample
        refused, 29 % of a 1 kHz position loop). With all data only: a window
        keeps its rule (its buffer restarts too).
        """
        if flag != 'outlier_rejected' or self._error_refusal is None or not self.all_data:
            super()._undo(flag)
            return
        self._flag(flag)
        self._refused += 1
        self._substitute = self._error_refusal

    def _compensate(self, theta: np.ndarray, pc: np.ndarray, direction: np.ndarray,
                    total_beta: float) -> None:
        """Apply the generalised eqs. (58), (59) with C, B and P C given (flag a failure)."""
        failure = self._bc.apply(theta, pc, direction, total_beta, self._memory.ls.loss)
        if failure:
            self._flag(failure)

    def _redesign(self) -> None:
        """Run the memory's redesign and take over its result (or hold after a failure)."""
        bc, filters = self._bc, self._filters
        result = self._memory.redesign(self.controller, filters.prefilter,
                                       bc.theta.copy() if bc.direction is not None else None,
                                       self._units.unit_weights(), self.max_iterations,
                                       self.tolerance)
        for flag in result.flags:
            self._flag(flag)
        if result.failed:
            bc.hold()
            return
        self._redesigns += 1
        self._last_iterations = result.iterations
        bc.take(result.direction, result.beta, result.estimate)
        if result.terms is not None:
            self._compensate(*result.terms)
        if result.prefilter is not None:
            filters.set_prefilter(result.prefilter)
        if result.regressor is not None:
            filters.take_regressor(result.regressor)
        if result.new_epoch:
            self._gate_resume = self._memory.rows + PREFILTER_SETTLE
        self._check_model()

    # ------------------------------------------------------------ the gate
    def _passes_gate(self, e: float, s: float, count: float) -> bool:
        r"""
        Return whether a row with a-priori error ``e``, gain ``s`` and weighted count tau is used.

        A non-finite e or s is refused (``update_undone``). From ``GATE_WARMUP``
        p rows on, z^2 is the larger of :math:`e^2 / [(J/\tau)(1 + \psi^T P\psi)]`
        (the error over its variance: an outlier in y) and
        :math:`\tau\,\psi^T P\psi / p` (the regressor's squared Mahalanobis
        distance over its mean: an outlier in u, whose leverage hides it from
        the first; docs/cl_bcls.md, "Outliers and units"). A quiet sample
        (:func:`~bcid_ros.estimators.rules.gate_is_quiet`, with neither change
        score pending) passes; for ``PREFILTER_SETTLE`` rows after a new
        prefilter only the hard limit (the gate off,
        :func:`~bcid_ros.estimators.rules.gate_limit2` of 0) applies (the
        filters' transient is no outlier); else :meth:`_gate_with_slow_score`
        decides.
        """
        self._error_refusal = None
        if not (s < math.inf and e * e < math.inf):
            self._undo('update_undone')
            return False
        if count < self._gate_from:
            return True
        # z^2 = max(e^2 / ((J / tau + floor)(1 + psi' P psi)), tau psi' P psi / p)
        leverage = s - self._forgetting_factor
        z2_error = e * e / ((self._memory.ls.loss / count + self._units.variance_floor)
                            * (leverage + 1.0))
        z2 = max(z2_error, count * leverage / self.num_parameters)
        # a refusal for the error keeps the prefilters running (_undo)
        self._error_refusal = e if z2 == z2_error else None
        tail = rules.gate_is_quiet(z2, self._gate_limit2, self._change_score or self._refusals,
                                   self._gate_tail)
        if tail:
            self._gate_tail = tail
            return True
        if self._memory.rows < self._gate_resume:
            # the transient of a new prefilter: only the hard limit
            if z2 <= rules.gate_limit2(0.0):
                return True
            self._undo('outlier_rejected')
            return False
        return self._gate_with_slow_score(z2, z2_error)

    def _gate_with_slow_score(self, z2: float, z2_error: float) -> bool:
        """
        Return the base class's :meth:`_gate` decision, and keep the slow change score.

        The slow score (:func:`~bcid_ros.estimators.rules.slow_change`) of
        the refusals marks a plant change too: the memory is cut and the
        sample stays refused. It counts only the refusals whose error
        ``z2_error`` is itself beyond the limit, as the base gate's change
        score does (:func:`~bcid_ros.estimators.rules.gate`): a changed plant shows in its
        prediction errors, while a regressor far from the others (a reference
        step under a held input, a spike in u) is refused by its leverage
        alone and says nothing of a change (with it, `window` 1500 marked up
        to 8 plant changes on a clean friction loop with a held PRBS reference).
        """
        used = self._gate(z2, z2_error)
        wrong = not used and not z2_error <= self._gate_limit2
        self._refusals, change = rules.slow_change(wrong, self._refusals)
        if change:
            self._flag('plant_change')
            self._accept_change()
        return used

    def _accept_change(self) -> None:
        """Cut the memory to CHANGE_MEMORY p rows: one extra forgetting step on everything."""
        self._refusals = 0.0
        keep = rules.memory_keep(self._memory.weighted_count(), self.num_parameters)
        if keep >= 1.0:
            return
        self._memory.cut(keep)

    # ------------------------------------------------------------ validity
    def _check_model(self) -> None:
        """Check the compensated model after a redesign (see :attr:`validity_reasons`)."""
        self._bc.model_reasons = model_reasons(self._theta(), self._theta_uncompensated(),
                                               self._memory.ls.p, self.controller)

    #: The reasons follow the excitation and the compensation of every sample.
    _LIVE_REASONS = True

    def _live_reasons(self) -> tuple[str, ...]:
        """Return why the estimate is not valid (see :func:`.compensation.validity_reasons`)."""
        bc = self._bc
        if (not bc.model_reasons and bc.direction is not None and not bc.holding
                and bc.discriminant_ratio >= MIN_DISCRIMINANT_RATIO
                and self._excitation.ratio() >= MIN_EXCITATION_RATIO):
            return ()  # (the usual case, asked at every sample, without building a list)
        return bc.reasons(self._excitation.ratio())

    # --------------------------------------------------------- the accessors
    @property
    def ready(self) -> bool:
        """Whether a compensation (redesign) has succeeded since the last reset or change."""
        return self._bc.direction is not None

    @property
    def excitation_ratio(self) -> float:
        """Return var(a_c u + b_c y) / var(b_c y) since the last reset or controller change."""
        return self._excitation.ratio()

    @property
    def controller_changes(self) -> int:
        """Count the controller changes since the last reset."""
        return self._controller_changes

    @property
    def samples(self) -> int:
        """Count the samples processed since the last reset."""
        return self._samples

    @property
    def prefilter(self) -> np.ndarray:
        """Return the prefilter in use, [1, f_1, ..., f_n] (a copy)."""
        return self._filters.prefilter.copy()

    @property
    def sigma2(self) -> float:
        """Return the noise variance estimate of eq. (58) (0 before the first redesign)."""
        return self._bc.sigma2

    @property
    def redesigns(self) -> int:
        """Count the successful redesigns since the last reset."""
        return self._redesigns

    @property
    def last_iterations(self) -> int:
        """Return the LS solves of the last successful redesign (0 before)."""
        return self._last_iterations

    @property
    def holding(self) -> bool:
        """Whether the compensated estimate is held after a failed redesign."""
        return self._bc.holding

    @property
    def window_length(self) -> int:
        """Return the samples the next redesign would use (rows since the change with 0)."""
        return self._memory.window_length

    @property
    def epochs(self) -> int:
        """Return the number of prefilters used since the last reset or change (``window`` 0)."""
        return self._memory.epochs

    @property
    def covariance(self) -> np.ndarray:
        """Return P, the inverse information matrix of the running LS (a copy)."""
        return self._memory.ls.p.copy()

    @property
    def covariance_trace(self) -> float:
        """Return tr P."""
        return float(np.trace(self._memory.ls.p))

    def _is_sound(self) -> bool:
        # _theta and _theta_uncompensated map these with the prefilter's bounded f_i
        # (eq. 13): they are finite exactly when these are
        bc, theta_ls = self._bc, self._memory.ls.theta
        compensated = bc.theta if bc.direction is not None else theta_ls
        return math.isfinite(bc.sigma2) and all_finite(theta_ls, compensated)

    def _theta(self) -> np.ndarray:
        if self._bc.direction is None:
            return self._theta_uncompensated()
        return self._memory.plant_form(self._bc.theta, self._filters.prefilter)

    def _theta_uncompensated(self) -> np.ndarray:
        return self._memory.plant_form(self._memory.ls.theta, self._filters.prefilter)

    def _noise(self) -> np.ndarray:
        return np.array([self._bc.sigma2])

    # ------------------------------------------------------- the uncertainty
    def _parameter_covariance(self) -> np.ndarray | None:
        """Return the covariance of theta_BC (:mod:`~bcid_ros.estimators.cl_bcls.uncertainty`)."""
        if self._bc.direction is None or self._bc.holding:
            return None
        return self._blocks.covariance(self._memory.weighted_count(), self._forgetting_factor)

    def _close_block(self) -> None:
        """Hand the moment sums of a block boundary to the block means."""
        sums = self._memory.moment_sums()
        if sums is not None:
            self._blocks.close(self._samples, sums, self._memory.weighted_count(),
                               self._forgetting_factor, self._filters.prefilter.tobytes(),
                               self._moment_function)

    def _moment_function(self) -> Any:
        """Return F: the fixed point of Algorithm 1 from the weighted mean moments."""
        prefilter, memory = self._filters.prefilter.copy(), self._memory
        return moment_function(self.controller, prefilter, memory.epoch_shares(prefilter),
                               self._theta().copy(), memory.regression_form)

    def __repr__(self) -> str:
        return (f'{type(self).__name__}(order={self.order}, '
                f'controller={self.controller.numerator.tolist()}/'
                f'{self.controller.denominator.tolist()} ({self.controller.sign} feedback), '
                f'window={self.window}, redesign_period={self.redesign_period}, '
                f'max_iterations={self.max_iterations}, tolerance={self.tolerance:g})')

    # -------------------------------------------------------------- the state
    @property
    def _parts_state(self) -> tuple:
        """Return the collaborators' part of a step's state (saved by the step transaction)."""
        # (not the window's rows, the meter's lags and pending sample: the undo's restart
        # empties them)
        filters, memory, bc, units = parts = self._filters, self._memory, self._bc, self._units
        return (parts, (filters.snapshot(), memory.snapshot(), bc.snapshot(), units.snapshot()),
                list(self._excitation.sums))

    @_parts_state.setter
    def _parts_state(self, saved: tuple) -> None:
        parts, states, excitation_sums = saved
        self._filters, self._memory, self._bc, self._units = parts
        for part, state in zip(parts, states):
            part.restore(state)
        self._excitation.sums[:] = excitation_sums

    def _reset(self) -> None:
        self._filters = PrefilterBank(self.prefilter_initial)
        self._samples = 0
        self._redesigns = 0
        self._last_iterations = 0
        self._controller_changes = 0
        self._restart_statistics()

    def _restart_statistics(self) -> None:
        """Restart everything learnt from the data except the prefilter."""
        # the signal scales (0 until the first LS step) and the peaks that set them
        self._units = SignalScales(self.order, self.initial_covariance)
        self._refusals = 0.0
        self._gate_resume = 0
        self._filters.restart()
        prefilter, initial_p = self._filters.prefilter, self._units.initial_p()
        self._memory = (AllDataMemory(prefilter, initial_p, self.min_window,
                                      self.redesign_period) if self.all_data else
                        WindowMemory(prefilter, initial_p, self.window, self.min_window,
                                     self.first_window, self.redesign_period))
        self._bc = Compensation(self.num_parameters)
        self._excitation = ExcitationMeter(self.controller)
        self._blocks = MomentBlocks()

    def _restart_regressor(self) -> None:
        self._memory.restart()
        self._filters.restart()
        self._excitation.restart()

    def _state_items(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        arrays, scalars = {}, {}
        for part in self._memory, self._bc, self._filters, self._units:
            part_arrays, part_scalars = part.state_items()
            arrays.update(part_arrays)
            scalars.update(part_scalars)
        controller = self.controller
        scalars.update(
            samples=self._samples, redesigns=self._redesigns,
            last_iterations=self._last_iterations,
            controller=(controller.numerator.tolist(), controller.denominator.tolist(),
                        controller.sign),
            controller_changes=self._controller_changes,
            excitation=self._excitation.state().tolist(), refusals=self._refusals,
            gate_resume=self._gate_resume)
        return arrays, scalars

    def _load_state(self, arrays: dict[str, np.ndarray], scalars: dict[str, Any]) -> None:
        self.controller = make_controller(*scalars['controller'])
        self._excitation = ExcitationMeter(self.controller)
        self._excitation.load(np.array(scalars['excitation'], dtype=float))
        for part in self._memory, self._bc, self._filters, self._units:
            part.load(arrays, scalars)
        self._samples = int(scalars['samples'])
        self._redesigns = int(scalars['redesigns'])
        self._last_iterations = int(scalars['last_iterations'])
        self._controller_changes = int(scalars['controller_changes'])
        self._refusals = float(scalars.get('refusals', 0.0))
        self._gate_resume = int(scalars.get('gate_resume', 0))
