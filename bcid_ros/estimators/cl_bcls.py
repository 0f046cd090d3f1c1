r"""
Online closed-loop bias-compensated least squares (Ikeda 2008), per sample.

:class:`ClosedLoopBcls` runs a recursive prefiltered LS at every sample and
compensates it with eqs. (56)-(59). With ``window`` 0 (the default) its
statistics cover every sample since the last controller change, as recursive
moments, and each redesign is one iteration of Algorithm 1 on them; with
``window`` > 0 every ``redesign_period`` samples it runs the batch
Algorithm 1 (:func:`~bcid_ros.estimators.cl_bcls_batch.closed_loop_bcls`)
on a window of raw samples. The model, the parametrisation of eq. (13) and
the pieces of Algorithm 1 are in :mod:`bcid_ros.estimators.cl_bcls_batch`;
the controller and its sign convention in :mod:`bcid_ros.estimators.lti`.
docs/cl_bcls.md explains the settings, the safety rules and their reasons.
"""

from __future__ import annotations

import math
import operator
from typing import Any, Sequence

import numpy as np

from bcid_ros.estimators.base import (all_finite, check_forgetting_factor, check_int,
                                      check_range, IMPLAUSIBLE_ERROR, power_of_two_at_least,
                                      RecursiveEstimator)
from bcid_ros.estimators.cl_bcls_batch import (algorithm1, bias_terms, CompensationFailure,
                                               DEFAULT_TOLERANCE, is_contracting,
                                               plant_from_regression, prefilter_polynomial,
                                               regression_from_plant)
from bcid_ros.estimators.lti import (closed_loop_polynomial, Controller, controller_canonical,
                                     is_stable, make_controller, stable_reflection)
from bcid_ros.estimators.moment_covariance import (fixed_point_system, implicit_step,
                                                   MomentBlocks)
from bcid_ros.estimators.rls import (CHANGE_MEMORY, GATE_WARMUP, repair_covariance,
                                     rls_innovation, rls_step, VARIANCE_FLOOR)

#: Default ``window``: 0, every sample since the last controller change (recursive moments).
DEFAULT_WINDOW = 0
#: Default number of samples between two compensations + prefilter redesigns.
DEFAULT_REDESIGN_PERIOD = 1000
#: With ``window`` 0 a redesign changes the prefilter only when the new f(q) differs from
#: the one in use by more than this (2-norm of the coefficients; docs/cl_bcls.md).
PREFILTER_STEP = 0.05
#: Default cap on the iterations of one redesign.
DEFAULT_MAX_ITERATIONS = 20
#: Regression rows per parameter that the data must hold before a redesign.
ROWS_PER_PARAMETER = 10
#: With a window, the first redesign waits for ``window // FIRST_WINDOW_DIVISOR`` samples
#: (docs/cl_bcls.md, "Why not_contracting and first_window").
FIRST_WINDOW_DIVISOR = 2
#: ``no_excitation`` below this ratio of the varying power of the reconstructed
#: reference b_c(q) r = a_c(q) u + b_c(q) y to that of b_c(q) y (docs/cl_bcls.md, "Validity").
MIN_EXCITATION_RATIO = 0.02
#: ``runaway_compensation`` when the compensation moves a or b by more than this times
#: the LS estimate's own size (max(1, |a_LS|) for a, |b_LS| for b).
RUNAWAY_RATIO = 1.0
#: ``ill_conditioned_compensation`` when sqrt(beta^2 - 4 alpha gamma) / beta of eq. (58)
#: falls below this: sigma2 is then near the double root and infinitely sensitive.
MIN_DISCRIMINANT_RATIO = 0.05
#: ``ill_conditioned_information`` above this condition number of the information
#: matrix scaled to unit diagonal (scale-free).
MAX_CONDITION = 1e8
#: The slow change score of the gate: +1 per refused sample, times REFUSAL_DECAY per
#: tested sample; three refusals within about 100 samples reach it (docs/cl_bcls.md).
REFUSAL_SCORE = 3.0
#: See REFUSAL_SCORE.
REFUSAL_DECAY = 0.99
#: Squared 2-norm below which an update cannot overflow (see update_is_safe).
SAFE_SQUARE = 2.0 ** 1022
#: Rows after a new prefilter (``window`` 0) during which only the gate's hard limit
#: applies: the filters' transient and the new epoch's bias are not outliers.
PREFILTER_SETTLE = 100


class _ExcitationMeter:
    r"""
    Power of the reference reconstructed from y, u and the known controller.

    With :math:`u = (b_c/a_c)(r - y)` (negative-feedback form),
    :math:`w = a_c(q) u + b_c(q) y = b_c(q) r` exactly: the noise cancels.
    The meter keeps the weighted sums of w, w^2, v = b_c(q) y and v^2 over
    the samples since the last restart whose m lags are all present. It takes
    each sample one sample late (``pending``): an outlier in u shows only in
    the next prediction error, and a refused sample restarts the meter before
    the outlier has entered it.
    """

    def __init__(self, controller: Controller) -> None:
        # coefficients on [x[k], x[k-1], ..., x[k-m]] (q^-m times the polynomials); the
        # meter works on Python floats: at these sizes numpy calls cost more than the sums
        self.a_c = controller.denominator.tolist()
        self.b_c = controller.feedback_numerator.tolist()
        size = len(self.a_c)
        self.y = [0.0] * size
        self.u = [0.0] * size
        self.lags = 0
        self.sums = [0.0] * 5  # weight, sum w, sum w^2, sum v, sum v^2 (changed in place)
        self.pending = [0.0] * 3  # y, u, 1 if held

    def restart(self) -> None:
        """Forget the lags and the pending sample (after a gap), keep the sums."""
        size = len(self.a_c)
        self.y = [0.0] * size
        self.u = [0.0] * size
        self.lags = 0
        self.pending[2] = 0.0

    def update(self, y: float, u: float, forgetting: float) -> None:
        """Hold this sample and take the one held before it."""
        pending = self.pending
        if not pending[2]:
            self.pending = [y, u, 1.0]
            return
        ys, us = self.y, self.u
        ys.pop()
        ys.insert(0, pending[0])
        us.pop()
        us.insert(0, pending[1])
        self.pending = [y, u, 1.0]
        if self.lags < len(ys) - 1:
            self.lags += 1
            return
        v = sum(map(operator.mul, self.b_c, ys))
        # w = a_c(q) u + b_c(q) y = b_c(q) r
        w = sum(map(operator.mul, self.a_c, us)) + v
        sums = self.sums
        if forgetting != 1.0:
            sums[:] = [value * forgetting for value in sums]
        sums[0] += 1.0
        sums[1] += w
        sums[2] += w * w
        sums[3] += v
        sums[4] += v * v

    def ratio(self) -> float:
        """Return var(w) / var(v) over the samples so far (0 if none, inf if v is constant)."""
        weight, w1, w2, v1, v2 = self.sums
        if weight <= 0.0:
            return 0.0
        var_w = max(w2 / weight - (w1 / weight) ** 2, 0.0)
        var_v = max(v2 / weight - (v1 / weight) ** 2, 0.0)
        if var_v <= 0.0:
            return math.inf if var_w > 0.0 else 0.0
        return var_w / var_v

    def state(self) -> np.ndarray:
        """Return the state as one flat array."""
        return np.array(self.y + self.u + self.sums + self.pending + [self.lags], dtype=float)

    def load(self, flat: np.ndarray) -> None:
        """Load a state made by :meth:`state` (same controller order)."""
        size = len(self.a_c)
        values = np.asarray(flat, dtype=float).tolist()
        self.y = values[:size]
        self.u = values[size:2 * size]
        self.sums = values[2 * size:2 * size + 5]
        # a state saved before the pending sample existed has none
        self.pending = (values[2 * size + 5:2 * size + 8]
                        if len(values) == 2 * size + 9 else [0.0] * 3)
        self.lags = int(values[-1])


def update_is_safe(theta: np.ndarray, direction: np.ndarray, ratio: float) -> bool:
    """
    Return True if theta + ratio * direction is surely finite (False: it may not be).

    Entries below 2^511 in size sum to less than 2^512: one test of two dot
    products for the usual case, conservative (NaN and overflow give False).
    """
    return (ratio * ratio * direction.dot(direction) < SAFE_SQUARE
            and theta.dot(theta) < SAFE_SQUARE)


def scaled_condition(matrix: np.ndarray) -> float:
    """Return the condition number of a symmetric matrix scaled to unit diagonal."""
    diagonal = np.diag(matrix)
    if not (diagonal > 0.0).all():
        return math.inf
    scale = 1.0 / np.sqrt(diagonal)
    return float(np.linalg.cond(matrix * np.outer(scale, scale)))


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

    **All data since the change** (``window`` 0). The regression of eq. (13),
    :math:`y[k] = \varphi^T [f - a \mid b] + \varepsilon`, is the same as
    :math:`y_f[k] = \psi[k]^T [a \mid b] + \varepsilon[k]` with
    :math:`\psi = [-y_f \text{ lags} \mid u_f \text{ lags}]`, whose parameter
    does not depend on f. So rows filtered by different prefilters stack in
    one LS. Each row of epoch e (filtered by :math:`f_e`) carries the noise
    moments of Theorem 1, :math:`E\{\psi\varepsilon\} = D c_e \sigma_\nu^2`,
    :math:`E\{\varepsilon^2\} = \beta_e \sigma_\nu^2`
    (:math:`D = \mathrm{diag}(-I_n, I_n)`, eqs. 37, 57). With weights
    :math:`w_k = \lambda^{N-k}` (the forgetting factor), the statistics are

    .. math::

        M = \sum w_k \psi\psi^T, \quad P = M^{-1}, \quad
        \hat\theta_{LS} = P \sum w_k \psi\, y_f, \quad
        J = \sum w_k (y_f - \psi^T\hat\theta_{LS})^2, \\
        C = \sum_e W_e D c_e, \quad B = \sum_e W_e \beta_e, \quad
        W_e = \sum_{k \in e} w_k,

    kept recursively (RLS for :math:`P, \hat\theta_{LS}, J`). Since
    :math:`J \approx B\sigma_\nu^2 - \sigma_\nu^4 C^T P C`, eqs. (58), (59)
    become

    .. math::

        \hat\sigma_\nu^2 = \frac{2J}{B + \sqrt{B^2 - 4 (C^T P C) J}}, \qquad
        \hat\theta_{BC} = \hat\theta_{LS} - \hat\sigma_\nu^2 P C,

    which with one epoch and :math:`\lambda = 1` is exactly eqs. (53),
    (56)-(59) (:math:`B = N\beta`, :math:`C^TPC = N \alpha`). A **redesign**
    is one iteration of Algorithm 1 on these statistics: the exact LS from the
    moments, :math:`c_e, \beta_e` of every epoch from :math:`\hat\theta_{LS}`
    (steps 3, 4), the compensation (step 5), and the next prefilter
    :math:`f = \bar{\hat a}_{BC}` (steps 6, 7), which opens a new epoch for the
    following rows unless it moved by less than ``tolerance``. Redesigns come
    after ``10 * 2n + n`` rows, then each time the rows double, until they
    are ``redesign_period`` rows apart; the filters keep their state across a
    prefilter change.

    **Window** (``window`` > 0). Every ``redesign_period`` samples, once the
    window holds at least ``10 * 2n + n`` samples (before the first
    successful redesign: :attr:`first_window` = max(``window`` // 2,
    ``10 * 2n + n``)), Algorithm 1 runs on the last min(samples since the
    last reset, restart or controller change, ``window``) raw samples, from
    the prefilter in use. On success the prefilter, c and beta become those of
    its last iteration, and the running LS continues from that iteration's
    solution; between redesigns each sample applies eqs. (56), (58), (59)
    with the frozen c, beta to the running LS (regression form, eq. 17).

    **Controller changes.** :meth:`set_controller` installs a new controller
    and restarts every statistic (moments, window, filters, excitation meter)
    but keeps the prefilter: no sample from before the change enters the
    statistics after it. Until the first redesign after a reset or change
    ``theta`` is the LS from :math:`P(0) = p_0 S^{-2}`,
    :math:`\hat\theta(0) = 0` and :attr:`valid` is False.

    **Units.** :math:`S = \mathrm{diag}(s_y I_n, s_u I_n)`: per signal the
    smallest power of two at or above its largest magnitude before the first
    LS step (fixed then, until a reset or controller change). ``p0`` is
    thus the prior variance for signals of unit size, and the redesign's
    stopping rule measures its steps on :math:`[a \mid b\,s_u/s_y]`: the
    estimates do not depend on the units of y and u.

    **Outliers** (``outlier_threshold``, docs/cl_bcls.md, "Outliers and
    units"). Each row is tested before it enters anything
    (:meth:`_gate_sample`); a refused sample enters neither the filters,
    the moments, the window nor the excitation meter, all of which restart
    their lags. A detected plant change cuts the memory to ``CHANGE_MEMORY``
    p rows (one extra forgetting step on every statistic).

    **Validity.** :attr:`validity_reasons` lists why the estimate is not to
    be trusted (empty: :attr:`valid`): ``not_compensated``, ``no_excitation``,
    ``unstable_closed_loop``, ``runaway_compensation``, ``redesign_failed``,
    ``ill_conditioned_compensation``, ``ill_conditioned_information``
    (docs/cl_bcls.md, "Validity").

    **Safety.** No estimate is ever NaN. Each condition is counted in
    :attr:`flags`:

    * ``unstable_closed_loop``, ``unstable_prefilter``, ``lyapunov_failed``,
      ``singular_information``, ``negative_variance_argument``: in the first
      iteration of a redesign, the redesign is dropped (prefilter and running
      LS unchanged; compensated estimate and sigma2 held, :attr:`holding`);
      in a later iteration of a windowed redesign, the last good iterate is
      the result; an unstable next prefilter is not taken;
    * ``negative_variance_argument`` at a sample, ``nonfinite_estimate``: that
      sample keeps the last good compensated estimate and sigma2;
    * ``not_converged``: a windowed redesign used all ``max_iterations``; its
      result is used if the iteration was contracting;
    * ``not_contracting``: a windowed redesign stopped without meeting
      ``tolerance`` and :func:`~bcid_ros.estimators.cl_bcls_batch.is_contracting`
      is False; the redesign is dropped as a failed one;
    * ``covariance_repaired``: P lost definiteness and was rebuilt.

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
        Cap on the LS solves of one windowed redesign (default 20).
    tolerance : float
        Stop a windowed redesign when the estimate moves by less; with
        ``window`` 0, keep the prefilter when the redesigned one moves by
        less (default 1e-3, as in section 7.3).

    Raises
    ------
    ValueError
        If a setting is out of range; the message names it.

    """

    name = 'cl_bcls'
    noise_names = ('sigma2',)
    #: Extra constructor keywords (ROS parameter names) beyond the base ones.
    options: tuple[str, ...] = ('controller_numerator', 'controller_denominator',
                                'controller_sign', 'prefilter_initial', 'window',
                                'redesign_period', 'max_iterations', 'tolerance')

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
        self.min_window = ROWS_PER_PARAMETER * 2 * self.order + self.order
        window = check_int('window', window, 0)
        if 0 < window < self.min_window:
            raise ValueError(f'window must be 0 (all data since the controller change) or an '
                             f'integer >= {self.min_window}, got {window!r}')
        self.window = window
        self.all_data = window == 0
        self._check_forgetting(self._forgetting_factor)
        self.first_window = (self.min_window if self.all_data
                             else max(self.window // FIRST_WINDOW_DIVISOR, self.min_window))
        self.redesign_period = check_int('redesign_period', redesign_period, 1)
        self.max_iterations = check_int('max_iterations', max_iterations, 1)
        self.tolerance = check_range('tolerance', tolerance, 0.0, math.inf, low_open=True)
        self._gate_from = GATE_WARMUP * self.num_parameters
        # psi = D phi, D = diag(-I_n, I_n) (eq. 13)
        self._psi_signs = np.repeat([-1.0, 1.0], self.order)
        # what a step may change, for the transaction; not the window's rows, the
        # excitation meter's lags and the pending sample, which the undo's restart empties
        in_place = ('_theta_ls', '_p', '_excitation.sums')
        if self.all_data:  # (with a window the moments stay zero)
            in_place += ('_information', '_cross', '_epoch_weights', '_epoch_prefilters')
        self._name_step_state(
            ('_prefilter', '_shift', '_phi', '_lags', '_theta_ls', '_p', '_loss', '_count',
             '_direction', '_beta', '_theta_bc', '_sigma2', '_holding', '_discriminant_ratio',
             '_samples', '_scales', '_peaks', '_variance_floor', '_pos', '_filled',
             '_since_redesign', '_redesigns', '_last_iterations', '_rows', '_next_redesign',
             '_epoch_prefilters', '_epoch_weights', '_epoch_directions', '_epoch_betas',
             '_energy', '_model_reasons', '_refusals', '_gate_resume', '_information',
             '_cross'), in_place)
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

    # ------------------------------------------------------ controller change
    def set_controller(self, numerator: Sequence[float], denominator: Sequence[float],
                       sign: str = 'negative') -> bool:
        """
        Install the controller now in the loop and restart the statistics.

        The prefilter and the flags are kept; the moments (or the window),
        the running LS, the filters, the excitation meter and the
        compensation restart, so the next redesign uses only samples from
        after the change (``10 * 2n + n`` rows with ``window`` 0,
        :attr:`first_window` samples with a window). Until then ``theta`` is
        the LS since the change and :attr:`valid` is False.

        Parameters
        ----------
        numerator, denominator, sign
            As ``controller_numerator``, ``controller_denominator`` and
            ``controller_sign``.

        Returns
        -------
        bool
            False (and nothing restarted) if the controller, normalised, is
            the one already in use; True otherwise.

        Raises
        ------
        ValueError
            If the controller is not valid; the estimator is unchanged.

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
        Do one step as an exact transaction (see the base class's ``_guarded_update``).

        Between redesigns the only way to an unsound state is the RLS update
        of theta_LS (:meth:`_compensate` keeps the last good theta_BC and
        sigma2), and the steps check it before committing it: a sample whose
        update is not finite is refused (``update_undone``) like one with a
        non-finite error or gain. A step that may change more runs as the base
        class's ``_step_transaction``, which saves what it may change: while
        the signal scales are unset, while the gate's change scores are
        pending (a plant change cuts the memory before the update) and when a
        redesign may be due.
        """
        if (self._change_score or self._refusals or self._scales[0] == 0.0
                or (self._rows + 1 >= self._next_redesign if self.all_data
                    else self._since_redesign + 1 >= self.redesign_period)):
            self._step_transaction(y, u)
        else:
            self._update(y, u)

    def _update(self, y: float, u: np.ndarray) -> None:
        u0 = float(u[0])
        self._samples += 1
        if self._scales[0] == 0.0:
            self._watch_scales(y, u0)
        if self.all_data:
            self._update_all_data(y, u0)
        else:
            self._update_window(y, u0)
        if self._samples >= self._blocks.next_boundary:
            self._close_block()

    def _watch_scales(self, y: float, u0: float) -> None:
        """Keep the peaks of |y|, |u| until the first LS step, then fix the scales."""
        peaks = self._peaks = np.array((max(self._peaks[0], abs(y)),
                                        max(self._peaks[1], abs(u0))))
        if self._lags >= self.order:
            self._scales = np.array([power_of_two_at_least(peak) for peak in peaks])
            self._p = self._initial_p()
            self._variance_floor = (VARIANCE_FLOOR * self._scales[0]) ** 2

    def _initial_p(self) -> np.ndarray:
        """Return P(0) = p0 S^-2, S = diag(s_y I_n, s_u I_n) (p0 I before the scales)."""
        n = self.order
        scales = self._scales if self._scales[0] > 0.0 else np.ones(2)
        return np.diag(self.initial_covariance / np.repeat(scales, n) ** 2)

    def _unit_weights(self) -> np.ndarray:
        """Return the factors that make [a | b] unit-free: 1 for a, s_u / s_y for b."""
        scales = self._scales if self._scales[0] > 0.0 else np.ones(2)
        return np.repeat([1.0, scales[1] / scales[0]], self.order)

    def _gate_sample(self, e: float, s: float, count: float) -> bool:
        r"""
        Return whether a sample with prediction error ``e`` and gain ``s`` is used.

        The base class's :meth:`_gate` gets the larger of two squared
        normalised sizes, once the weighted row count :math:`\tau` reaches
        ``GATE_WARMUP`` p:

        * :math:`e^2 / [(J/\tau)(1 + \psi^T P\psi)]`, the one-step error of
          the prefiltered regression over its variance (an outlier in y);
        * :math:`\tau\,\psi^T P\psi / p`, the squared Mahalanobis distance of
          the regressor in the metric of the regressors' own second moments
          :math:`M/\tau = (\tau P)^{-1}`, over its mean p (an outlier in u,
          which enters the filters and shows in the next row). A spike in u
          has a huge leverage: its error :math:`b u` and its variance
          :math:`P_{bb} u^2` grow together, so the first measure stays at
          :math:`b^2 / \mathrm{var}\,\hat b` (a few units in a closed loop).

        A non-finite error or gain is refused outright (``update_undone``).
        Besides the base class's three refusals in a row, a slow score
        (+1 per refusal, times ``REFUSAL_DECAY`` per tested sample) that
        reaches ``REFUSAL_SCORE`` is a plant change too: in a closed loop
        the errors of a changed plant exceed the gate mostly after the
        reference moves, one sample in many, never three in a row. For
        ``PREFILTER_SETTLE`` rows after a new prefilter (``window`` 0) only
        the hard limit ``IMPLAUSIBLE_ERROR`` applies: the filters keep their
        state across the change, and their transient is not an outlier.
        """
        if not (s < math.inf and e * e < math.inf):
            self._undo('update_undone')
            return False
        if count < self._gate_from:
            return True
        leverage = s - self._forgetting_factor
        z2 = max(e * e / ((self._loss / count + self._variance_floor) * (leverage + 1.0)),
                 count * leverage / self.num_parameters)
        if z2 <= self._gate_limit2 and not (self._change_score or self._refusals):
            return True
        if self._rows < self._gate_resume:
            # the transient of a new prefilter: only the hard limit
            if z2 <= IMPLAUSIBLE_ERROR * IMPLAUSIBLE_ERROR:
                return True
            self._undo('outlier_rejected')
            return False
        if self._refusals:
            score = self._refusals * REFUSAL_DECAY
            self._refusals = score if score > 1e-3 else 0.0
        if self._gate(z2):
            return True
        self._refusals += 1.0
        if self._refusals >= REFUSAL_SCORE:
            self._flag('plant_change')
            self._accept_change()
        return False

    def _accept_change(self) -> None:
        """Cut the memory to CHANGE_MEMORY p rows: one extra forgetting step on everything."""
        self._refusals = 0.0
        count = self._weighted_count()
        keep = CHANGE_MEMORY * self.num_parameters / count if count > 0.0 else 1.0
        if keep >= 1.0:
            return
        self._memory_cuts += 1
        self._p *= 1.0 / keep
        self._loss *= keep
        self._count *= keep
        self._information *= keep
        self._cross *= keep
        self._energy *= keep
        self._epoch_weights *= keep

    def _weighted_count(self) -> float:
        """Return the weighted rows of the running LS (tau)."""
        return float(self._epoch_weights.sum()) if self.all_data else self._count

    def _advance_filters(self, y: float, u0: float) -> None:
        self._excitation.update(y, u0, self._forgetting_factor)
        # phi[k+1] = blockdiag(F, F) phi[k] + [g y[k]; g u[k]]        (10), (14)
        phi = self._shift.dot(self._phi)
        phi[0] += y
        phi[self.order] += u0
        self._phi = phi

    # ------------------------------------------------ all data since the change
    def _update_all_data(self, y: float, u0: float) -> None:
        if self._lags >= self.order:
            if not self._moment_step(y, self._phi):
                return
        else:
            self._lags += 1
        self._advance_filters(y, u0)
        if self._rows >= self._next_redesign:
            rows = self._rows
            self._next_redesign = rows + min(rows, self.redesign_period)
            self._redesign_all_data()

    def _moment_step(self, y: float, phi: np.ndarray) -> bool:
        """Gate the row; add it to the moments, do the RLS step and compensate; or refuse."""
        n = self.order
        lam = self._forgetting_factor
        # y_f[k] = y[k] - f_1 y_f[k-1] - ... - f_n y_f[k-n]; psi = D phi       (10), (13)
        target = y - self._prefilter[1:].dot(phi[:n])
        psi = phi * self._psi_signs
        theta = self._theta_ls
        g = self._p.dot(psi)
        s = lam + psi.dot(g)
        e = target - psi.dot(theta)
        cuts = self._memory_cuts
        if not self._gate_sample(e, s, float(self._epoch_weights.sum())):
            return False
        if self._memory_cuts != cuts:
            # a plant change cut the memory (P grew): redo the a-priori part
            g = self._p.dot(psi)
            s = lam + psi.dot(g)
        if s > 0.0:
            update = g * (e / s)
            if not (update_is_safe(theta, update, 1.0) or all_finite(theta + update)):
                self._undo('update_undone')
                return False
        if lam != 1.0:
            self._information *= lam
            self._cross *= lam
            self._energy *= lam
            self._epoch_weights *= lam
        self._information += psi[:, None] * psi
        self._cross += psi * target
        self._energy += target * target
        self._epoch_weights[-1] += 1.0
        self._rows += 1
        if not s > 0.0:
            self._repair_covariance()
            return True
        theta += update
        h = g * (1.0 / math.sqrt(s))
        self._p -= h[:, None] * h
        if lam != 1.0:
            self._p *= 1.0 / lam
        # J = lam J + lam e^2 / s (weighted LS loss)
        self._loss = lam * (self._loss + e * e / s)
        if self._direction is None or self._holding:
            return True
        weights = self._epoch_weights
        # C = sum_e W_e D c_e ; B = sum_e W_e beta_e
        direction = weights.dot(self._epoch_directions)
        total_beta = weights.dot(self._epoch_betas)
        self._compensate(theta, self._p.dot(direction), direction, total_beta)
        return True

    def _compensate(self, theta: np.ndarray, pc: np.ndarray, direction: np.ndarray,
                    total_beta: float) -> None:
        """Apply the generalised eqs. (58), (59) with C, B and P C given."""
        quadratic = direction.dot(pc)
        loss = self._loss
        discriminant = total_beta * total_beta - 4.0 * quadratic * loss
        if not discriminant >= 0.0:
            self._flag('negative_variance_argument')
            self._discriminant_ratio = 0.0
            return
        root = math.sqrt(discriminant)
        # sigma2 = 2 J / (B + sqrt(B^2 - 4 C'PC J))                          (58)
        sigma2 = 2.0 * loss / (total_beta + root)
        # theta_BC = theta_LS - sigma2 P C                                   (59)
        compensated = theta - sigma2 * pc
        if not math.isfinite(compensated.dot(compensated) + sigma2):
            self._flag('nonfinite_estimate')
            return
        self._discriminant_ratio = root / total_beta
        self._theta_bc = compensated
        self._sigma2 = sigma2

    def _redesign_all_data(self) -> None:
        """Run Algorithm 1 on the moments of every row since the change (no refiltering)."""
        n = self.order
        try:
            theta_ls, inverse, loss = self._exact_ls()
            starts = [theta_ls]
            if self._direction is not None:
                # warm start from the last compensated estimate (the fixed point moves
                # little between redesigns); from theta_LS if that fails
                starts.insert(0, self._theta_bc.copy())
            for number, start in enumerate(starts):
                try:
                    estimate, terms, result, iterations = self._moment_iteration(
                        start, theta_ls, inverse, loss)
                    break
                except CompensationFailure:
                    if number == len(starts) - 1:
                        raise
            directions, betas = terms
            _, pc, total = result
            # steps (6), (7): f = a_BC with the unstable roots mirrored (Remark 3)
            following = stable_reflection(np.concatenate(([1.0], estimate[:n])))
            next_terms = None
            if not is_stable(following):
                self._flag('unstable_prefilter')
            elif (self._rows >= self.redesign_period
                  and np.linalg.norm(following - self._prefilter) > PREFILTER_STEP):
                next_terms = bias_terms(estimate, following, self.controller)
        except CompensationFailure as error:
            self._flag(error.flag)
            self._holding = self._direction is not None
            return
        self._redesigns += 1
        self._last_iterations = iterations
        self._theta_ls = theta_ls
        self._p = inverse
        self._loss = loss
        self._epoch_directions = directions
        self._epoch_betas = betas
        self._direction = total[0]
        self._holding = False
        self._compensate(theta_ls, pc, total[0], total[1])
        if next_terms is not None:
            c_next, beta_next = next_terms
            self._open_epoch(following, np.concatenate((-c_next[:n], c_next[n:])), beta_next)
        self._check_model()

    def _moment_iteration(self, estimate: np.ndarray, theta_ls: np.ndarray,
                          inverse: np.ndarray, loss: float) -> tuple[Any, ...]:
        """
        Iterate steps (3)-(5) on the moments from ``estimate`` to a fixed point.

        The iteration converges linearly (factor rho about 0.6-0.98 on the
        paper's loop, the larger the farther f is from a_p), so it stops when
        the estimated distance to the fixed point, step * rho / (1 - rho)
        with rho the ratio of the last two steps, is below ``tolerance``.
        """
        last_step = math.inf
        # the step in unit-free parameters (b times s_u / s_y), so that the stopping
        # point does not depend on the units of y and u
        weights = self._unit_weights()
        for iterations in range(1, self.max_iterations + 1):
            # c_e, beta_e of every epoch from the current estimate            (37), (57)
            terms = self._epoch_terms(estimate)
            result = self._moment_compensation(theta_ls, inverse, loss, *terms)
            step = float(np.linalg.norm((result[0] - estimate) * weights))
            estimate = result[0]
            rate = step / last_step  # 0 at the first iteration: never stops there
            if step == 0.0 or (0.0 < rate < 1.0
                               and step * rate / (1.0 - rate) < self.tolerance):
                break
            last_step = step
        else:
            self._flag('not_converged')
        return estimate, terms, result, iterations

    def _epoch_terms(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Return D c_e and beta_e of every epoch for the plant ``theta`` (eqs. 37, 57)."""
        n = self.order
        prefilters = self._epoch_prefilters
        directions = np.empty((len(prefilters), 2 * n))
        betas = np.empty(len(prefilters))
        for index, prefilter in enumerate(prefilters):
            c_e, betas[index] = bias_terms(theta, prefilter, self.controller)
            directions[index] = np.concatenate((-c_e[:n], c_e[n:]))
        return directions, betas

    def _moment_compensation(self, theta_ls: np.ndarray, inverse: np.ndarray, loss: float,
                             directions: np.ndarray, betas: np.ndarray
                             ) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, float]]:
        """Return (theta_BC, P C, (C, B)) of the generalised eqs. (58), (59)."""
        direction = self._epoch_weights.dot(directions)
        total_beta = float(self._epoch_weights.dot(betas))
        pc = inverse.dot(direction)
        discriminant = total_beta * total_beta - 4.0 * direction.dot(pc) * loss
        if not discriminant >= 0.0:
            raise CompensationFailure('negative_variance_argument',
                                      'B^2 - 4 C\'PC J < 0 in eq. (58)')
        sigma2 = 2.0 * loss / (total_beta + math.sqrt(discriminant))
        compensated = theta_ls - sigma2 * pc
        if not np.isfinite(compensated).all():
            raise CompensationFailure('lyapunov_failed', 'compensated estimate not finite')
        return compensated, pc, (direction, total_beta)

    def _exact_ls(self) -> tuple[np.ndarray, np.ndarray, float]:
        """Return (theta_LS, P, J) solved from the moments (plant form)."""
        information = self._information
        try:
            np.linalg.cholesky(information)
            inverse = np.linalg.inv(information)
        except np.linalg.LinAlgError:
            raise CompensationFailure('singular_information',
                                      'the information matrix is not positive definite') from None
        theta = inverse.dot(self._cross)
        loss = max(self._energy - self._cross.dot(theta), 0.0)
        if not (np.isfinite(theta).all() and np.isfinite(inverse).all()):
            raise CompensationFailure('singular_information', 'the LS solution is not finite')
        return theta, 0.5 * (inverse + inverse.T), loss

    def _open_epoch(self, prefilter: np.ndarray, direction: np.ndarray, beta: float) -> None:
        """Filter the following rows with a new prefilter (a new epoch)."""
        self._epoch_prefilters.append(prefilter)
        self._epoch_weights = np.append(self._epoch_weights, 0.0)
        self._epoch_directions = np.vstack((self._epoch_directions, direction))
        self._epoch_betas = np.append(self._epoch_betas, beta)
        self._set_prefilter(prefilter)
        self._gate_resume = self._rows + PREFILTER_SETTLE

    # ---------------------------------------------------------- the window
    def _update_window(self, y: float, u0: float) -> None:
        if self._lags >= self.order:
            if not self._ls_step(y, self._phi):
                return
        else:
            self._lags += 1
        # keep the raw sample for the redesign window
        pos = self._pos
        if pos == self._buffer.shape[0]:
            self._buffer[:self.window] = self._buffer[self.window:]
            pos = self.window
        buffer = self._buffer
        buffer[pos, 0] = y
        buffer[pos, 1] = u0
        self._pos = pos + 1
        if self._filled < self.window:
            self._filled += 1
        self._advance_filters(y, u0)
        self._since_redesign += 1
        if (self._since_redesign >= self.redesign_period and self._filled >= (
                self.min_window if self._direction is not None else self.first_window)):
            self._since_redesign = 0
            self._redesign()

    def _ls_step(self, y: float, phi: np.ndarray) -> bool:
        """Gate the sample; do the RLS step and eqs. (56)-(59), or refuse it (False)."""
        theta = self._theta_ls
        # e = y[k] - phi' theta_LS, g = P phi, s = 1 + phi' P phi (the shared RLS step, lambda 1)
        e, g, s = rls_innovation(theta, self._p, phi, y, 1.0)
        cuts = self._memory_cuts
        if not self._gate_sample(e, s, self._count):
            return False
        if self._memory_cuts != cuts:
            # a plant change cut the memory (P grew): redo the a-priori part
            e, g, s = rls_innovation(theta, self._p, phi, y, 1.0)
        if not s > 0.0:
            self._repair_covariance()
            return True
        safe = update_is_safe(theta, g, e / s)
        if not safe:  # (rare) keep what the step changes, to check it after
            saved = theta.copy(), self._p.copy()
        # theta_LS += g e / s ; P -= g g' / s
        self._p = rls_step(theta, self._p, g, s, e)
        if not safe and not all_finite(theta):
            theta[:], self._p = saved
            self._undo('update_undone')
            return False
        # J += e^2 / s ; N += 1
        self._loss += e * e / s
        self._count += 1.0
        if self._direction is None or self._holding:
            return True
        # gamma = J / N, alpha = N c' P c, eqs. (53), (56), are eq. (58) with B = N beta
        # and C = N c: sigma2 = 2 J / (N beta + sqrt(N^2 beta^2 - 4 N^2 c'Pc J))
        count = self._count
        direction = count * self._direction
        self._compensate(theta, self._p.dot(direction), direction, count * self._beta)
        return True

    def _repair_covariance(self) -> None:
        """Rebuild P as the nearest symmetric positive definite matrix."""
        self._flag('covariance_repaired')
        self._p = repair_covariance(self._p, self._initial_p())

    def _redesign(self) -> None:
        """Run Algorithm 1 on the window and take over its result."""
        data = self._buffer[self._pos - self._filled:self._pos]
        try:
            result = algorithm1(data[:, 0], data[:, 1], self.controller, self._prefilter,
                                self.max_iterations, self.tolerance, True)
        except CompensationFailure as error:
            self._flag(error.flag)
            self._holding = self._direction is not None
            return
        if result.failure is not None:
            self._flag(result.failure)
        elif not result.converged:
            self._flag('not_converged')
        if not result.converged and not is_contracting(result.history):
            # the iteration drifted without converging: no fixed point of this window
            # near the prefilter in use; drop the redesign like a failed one
            self._flag('not_contracting')
            self._holding = self._direction is not None
            return
        self._redesigns += 1
        self._last_iterations = result.iterations
        self._set_prefilter(result.prefilter)
        self._phi = result.ls.next_regressor.copy()
        self._lags = self.order
        self._theta_ls = result.ls.theta.copy()
        self._p = result.ls.information_inverse.copy()
        self._loss = result.ls.loss
        self._count = float(result.ls.count)
        self._direction = result.direction.copy()
        self._beta = float(result.beta)
        self._theta_bc = regression_from_plant(result.theta, result.prefilter)
        self._sigma2 = float(result.sigma2)
        self._holding = False
        # sqrt(beta^2 - 4 alpha gamma) / beta of eq. (58) for the redesign's result
        alpha = self._count * self._direction.dot(self._p.dot(self._direction))
        discriminant = self._beta ** 2 - 4.0 * alpha * self._loss / self._count
        self._discriminant_ratio = math.sqrt(max(discriminant, 0.0)) / self._beta
        self._check_model()

    def _set_prefilter(self, prefilter: np.ndarray) -> None:
        n = self.order
        self._prefilter = np.array(prefilter, dtype=float)
        f_matrix, _ = controller_canonical(self._prefilter)
        shift = np.zeros((2 * n, 2 * n))
        shift[:n, :n] = f_matrix
        shift[n:, n:] = f_matrix
        self._shift = shift

    # ------------------------------------------------------------ validity
    def _check_model(self) -> None:
        """Check the compensated model after a redesign (see :attr:`validity_reasons`)."""
        n = self.order
        theta, theta_ls = self._theta(), self._theta_uncompensated()
        reasons = []
        a_p = np.concatenate(([1.0], theta[:n]))
        if not is_stable(closed_loop_polynomial(a_p, theta[n:], self.controller)):
            reasons.append('unstable_closed_loop')
        step = theta - theta_ls
        if (np.linalg.norm(step[:n]) > RUNAWAY_RATIO * max(1.0, np.linalg.norm(theta_ls[:n]))
                or np.linalg.norm(step[n:]) > RUNAWAY_RATIO * np.linalg.norm(theta_ls[n:])):
            reasons.append('runaway_compensation')
        if scaled_condition(self._p) > MAX_CONDITION:
            reasons.append('ill_conditioned_information')
        self._model_reasons = tuple(reasons)

    def _validity_reasons(self) -> tuple[str, ...]:
        r"""
        Return why the estimate is not valid (the base class's :attr:`validity_reasons`).

        * ``not_compensated``: no redesign has succeeded since the last reset
          or controller change (the estimator is not :attr:`ready`);
        * ``no_excitation``: the reconstructed reference
          :math:`a_c(q) u + b_c(q) y = b_c(q) r` has a varying power below
          :data:`MIN_EXCITATION_RATIO` times that of :math:`b_c(q) y`: the
          loop runs on noise alone and the plant is not identifiable;
        * ``unstable_closed_loop``: the compensated model in the loop with the
          known controller is unstable, while the data are bounded;
        * ``runaway_compensation``: the compensation moves a or b by more
          than :data:`RUNAWAY_RATIO` times the LS estimate's size;
        * ``redesign_failed``: the last redesign failed and the compensated
          estimate is held (:attr:`holding`);
        * ``ill_conditioned_compensation``: eq. (58) is near its double root,
          :math:`\sqrt{\beta^2 - 4\alpha\gamma}/\beta` <
          :data:`MIN_DISCRIMINANT_RATIO` (sigma2 and theta then react
          without bound to the data);
        * ``ill_conditioned_information``: the information matrix scaled to
          unit diagonal has a condition number above :data:`MAX_CONDITION`.

        The model checks run at each redesign; the excitation and the
        discriminant at each sample.
        """
        if (not self._model_reasons and self._direction is not None and not self._holding
                and self._discriminant_ratio >= MIN_DISCRIMINANT_RATIO
                and self._excitation.ratio() >= MIN_EXCITATION_RATIO):
            return ()  # (the usual case, asked at every sample, without building a list)
        if self._direction is None:
            reasons = ['not_compensated']
        else:
            reasons = list(self._model_reasons)
            if self._holding:
                reasons.append('redesign_failed')
            if self._discriminant_ratio < MIN_DISCRIMINANT_RATIO:
                reasons.append('ill_conditioned_compensation')
        if self._excitation.ratio() < MIN_EXCITATION_RATIO:
            reasons.append('no_excitation')
        return tuple(reasons)

    # --------------------------------------------------------- the accessors
    @property
    def valid(self) -> bool:
        """Whether the estimate can be trusted (the base class's, asked at every sample)."""
        return self._direction is not None and not self._validity_reasons()

    @property
    def ready(self) -> bool:
        """Whether a compensation (redesign) has succeeded since the last reset or change."""
        return self._direction is not None

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
        return self._prefilter.copy()

    @property
    def sigma2(self) -> float:
        """Return the noise variance estimate of eq. (58) (0 before the first redesign)."""
        return self._sigma2

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
        return self._holding

    @property
    def window_length(self) -> int:
        """Return the samples the next redesign would use (rows since the change with 0)."""
        return self._rows if self.all_data else self._filled

    @property
    def epochs(self) -> int:
        """Return the number of prefilters used since the last reset or change (``window`` 0)."""
        return len(self._epoch_prefilters)

    @property
    def covariance(self) -> np.ndarray:
        """Return P, the inverse information matrix of the running LS (a copy)."""
        return self._p.copy()

    @property
    def covariance_trace(self) -> float:
        """Return tr P."""
        return float(np.trace(self._p))

    def _is_sound(self) -> bool:
        # _theta and _theta_uncompensated map these with the prefilter's bounded f_i
        # (eq. 13): they are finite exactly when these are
        compensated = self._theta_bc if self._direction is not None else self._theta_ls
        return math.isfinite(self._sigma2) and all_finite(self._theta_ls, compensated)

    def _theta(self) -> np.ndarray:
        if self._direction is None:
            return self._theta_uncompensated()
        if self.all_data:
            return self._theta_bc
        # a_i = f_i - theta_i ; b_i = theta_(n+i)                            (13)
        return plant_from_regression(self._theta_bc, self._prefilter)

    def _theta_uncompensated(self) -> np.ndarray:
        if self.all_data:
            return self._theta_ls
        return plant_from_regression(self._theta_ls, self._prefilter)

    def _noise(self) -> np.ndarray:
        return np.array([self._sigma2])

    # ------------------------------------------------------- the uncertainty
    def _parameter_covariance(self) -> np.ndarray | None:
        r"""
        Return the delta-method covariance of theta_BC from block means of the moments.

        The compensated estimate is, to first order, the fixed point of
        Algorithm 1 on the weighted means
        :math:`\bar v = [M, \sum w\psi y_f, \sum w y_f^2]/\tau` (``window`` 0;
        with a window, the same sums of the running regression-form LS,
        recovered from P, theta_LS and J):

        .. math::

            \theta = G(\theta, \bar v) = \hat\theta_{LS} - \hat\sigma_\nu^2 P C(\theta),
            \quad C = \sum_e \frac{W_e}{\tau} D c_e(\theta), \
            B = \sum_e \frac{W_e}{\tau}\beta_e(\theta)

        (eqs. (37), (57)-(59); the prefilters held fixed: their error moves
        the estimate only at second order). The delta method gives
        :math:`\mathrm{cov}\,\hat\theta = (\tau_2/\tau^2) J\Omega J^T`,
        :math:`J = (I - \partial G/\partial\theta)^{-1}\partial G/\partial\bar v`
        at the published estimate (the implicit function theorem, central
        differences, :func:`implicit_step`), and
        :math:`\Omega` the long-run covariance of the per-row terms
        (coloured by the closed loop), from the spread of their sums over
        blocks of samples, centred per prefilter
        (:mod:`bcid_ros.estimators.moment_covariance`). None before
        :attr:`ready`, while :attr:`holding`, before 16 blocks (512 samples)
        since the last reset or controller change, and after a restored
        state until 16 new blocks.

        Not exact: the share of true parameters within +-2 std, measured over
        200 runs on Ikeda's loop (docs/estimators.md, "Uncertainty"), is
        93-94 % per parameter with ``window`` 0 (N = 1000 and 10000) and
        91-92 % with ``window`` 4096 (N = 10000; the std of b about 15 % small).
        """
        if self._direction is None or self._holding:
            return None
        return self._blocks.covariance(self._weighted_count(), self._forgetting_factor)

    def _close_block(self) -> None:
        """Hand the moment sums of a block boundary to the block means."""
        if self.all_data:
            sums = np.concatenate((self._information.reshape(-1), self._cross,
                                   [self._energy]))
        else:
            # the running LS's sums from P, theta_LS and J (its prior included)
            try:
                information = np.linalg.inv(self._p)
            except np.linalg.LinAlgError:
                return
            cross = information.dot(self._theta_ls)
            sums = np.concatenate((information.reshape(-1), cross,
                                   [self._loss + cross.dot(self._theta_ls)]))
        self._blocks.close(self._samples, sums, self._weighted_count(), self._forgetting_factor,
                           self._prefilter.tobytes(), self._moment_function)

    def _moment_function(self) -> Any:
        """Return F: the fixed point of Algorithm 1 from the weighted mean moments."""
        n, p = self.order, self.num_parameters
        controller, window = self.controller, not self.all_data
        prefilter = self._prefilter.copy()
        if window:
            epochs = [(1.0, prefilter)]
        else:
            shares = self._epoch_weights / self._epoch_weights.sum()
            epochs = [(share, f.copy()) for share, f in zip(shares, self._epoch_prefilters)
                      if share > 0.0]
        start = self._theta().copy()
        system: list[np.ndarray] = []

        def step(theta: np.ndarray, means: np.ndarray) -> np.ndarray:
            information = means[:p * p].reshape(p, p)
            inverse = np.linalg.inv(0.5 * (information + information.T))
            cross = means[p * p:p * p + p]
            theta_ls = inverse.dot(cross)
            loss = means[-1] - cross.dot(theta_ls)
            direction, beta = np.zeros(p), 0.0
            for share, f in epochs:
                c_e, beta_e = bias_terms(theta, f, controller)
                if not window:
                    c_e = np.concatenate((-c_e[:n], c_e[n:]))
                direction += share * c_e
                beta += share * beta_e
            pc = inverse.dot(direction)
            discriminant = beta * beta - 4.0 * direction.dot(pc) * loss
            if not discriminant >= 0.0:
                raise ArithmeticError('negative discriminant')
            compensated = theta_ls - (2.0 * loss / (beta + math.sqrt(discriminant))) * pc
            return plant_from_regression(compensated, prefilter) if window else compensated

        def estimate(means: np.ndarray) -> np.ndarray:
            def at(theta: np.ndarray) -> np.ndarray:
                return step(theta, means)
            if not system:  # (the first call is at the moments themselves)
                system.append(fixed_point_system(at, start))
            return implicit_step(at, start, system[0])
        return estimate

    def __repr__(self) -> str:
        return (f'{type(self).__name__}(order={self.order}, '
                f'controller={self.controller.numerator.tolist()}/'
                f'{self.controller.denominator.tolist()} ({self.controller.sign} feedback), '
                f'window={self.window}, redesign_period={self.redesign_period}, '
                f'max_iterations={self.max_iterations}, tolerance={self.tolerance:g})')

    # -------------------------------------------------------------- the state
    def _reset(self) -> None:
        self._set_prefilter(self.prefilter_initial)
        self._samples = 0
        self._redesigns = 0
        self._last_iterations = 0
        self._controller_changes = 0
        self._memory_cuts = 0  # counts _accept_change's cuts (tells a step to redo P psi)
        self._restart_statistics()

    def _restart_statistics(self) -> None:
        """Restart everything learnt from the data except the prefilter."""
        p = self.num_parameters
        # the signal scales (0 until the first LS step) and the peaks that set them
        self._scales = np.zeros(2)
        self._peaks = np.zeros(2)
        self._variance_floor = VARIANCE_FLOOR ** 2
        self._refusals = 0.0
        self._gate_resume = 0
        self._buffer = np.zeros((2 * self.window, 2))
        self._pos = 0
        self._filled = 0
        self._phi = np.zeros(p)
        self._lags = 0
        self._theta_ls = np.zeros(p)
        self._p = self._initial_p()
        self._loss = 0.0
        self._count = 0.0
        self._direction: np.ndarray | None = None
        self._beta = 1.0
        self._theta_bc = np.zeros(p)
        self._sigma2 = 0.0
        self._holding = False
        self._since_redesign = 0
        self._information = np.zeros((p, p))
        self._cross = np.zeros(p)
        self._energy = 0.0
        self._rows = 0
        self._next_redesign = self.min_window
        self._epoch_prefilters = [self._prefilter.copy()]
        self._epoch_weights = np.zeros(1)
        self._epoch_directions = np.zeros((1, p))
        self._epoch_betas = np.ones(1)
        self._excitation = _ExcitationMeter(self.controller)
        self._model_reasons: tuple[str, ...] = ()
        self._discriminant_ratio = 1.0
        self._blocks = MomentBlocks()

    def _restart_regressor(self) -> None:
        self._filled = 0
        self._phi = np.zeros(self.num_parameters)
        self._lags = 0
        self._excitation.restart()

    def _state_items(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        compensated = self._direction is not None
        arrays = {'prefilter': self._prefilter, 'buffer': self._buffer, 'phi': self._phi,
                  'theta_ls': self._theta_ls, 'p': self._p, 'theta_bc': self._theta_bc,
                  'direction': (self._direction if compensated
                                else np.zeros(self.num_parameters)),
                  'information': self._information, 'cross': self._cross,
                  'scales': self._scales, 'peaks': self._peaks}
        controller = self.controller
        scalars = {'pos': self._pos, 'filled': self._filled, 'lags': self._lags,
                   'loss': self._loss, 'count': self._count, 'beta': self._beta,
                   'sigma2': self._sigma2, 'samples': self._samples,
                   'since_redesign': self._since_redesign, 'redesigns': self._redesigns,
                   'last_iterations': self._last_iterations, 'compensated': compensated,
                   'holding': self._holding, 'energy': self._energy, 'rows': self._rows,
                   'next_redesign': self._next_redesign,
                   'epoch_prefilters': [f.tolist() for f in self._epoch_prefilters],
                   'epoch_weights': self._epoch_weights.tolist(),
                   'epoch_directions': self._epoch_directions.tolist(),
                   'epoch_betas': self._epoch_betas.tolist(),
                   'controller': (controller.numerator.tolist(),
                                  controller.denominator.tolist(), controller.sign),
                   'controller_changes': self._controller_changes,
                   'excitation': self._excitation.state().tolist(),
                   'model_reasons': list(self._model_reasons),
                   'discriminant_ratio': self._discriminant_ratio,
                   'refusals': self._refusals, 'gate_resume': self._gate_resume}
        return arrays, scalars

    def _load_state(self, arrays: dict[str, np.ndarray], scalars: dict[str, Any]) -> None:
        self.controller = make_controller(*scalars['controller'])
        self._excitation = _ExcitationMeter(self.controller)
        self._excitation.load(np.array(scalars['excitation'], dtype=float))
        self._set_prefilter(arrays['prefilter'])
        self._buffer = arrays['buffer']
        self._phi = arrays['phi']
        self._theta_ls = arrays['theta_ls']
        self._p = arrays['p']
        self._theta_bc = arrays['theta_bc']
        self._direction = arrays['direction'] if scalars['compensated'] else None
        self._information = arrays['information']
        self._cross = arrays['cross']
        self._scales = arrays.get('scales', np.zeros(2))
        self._peaks = arrays.get('peaks', np.zeros(2))
        self._variance_floor = (VARIANCE_FLOOR * (self._scales[0] or 1.0)) ** 2
        self._pos = int(scalars['pos'])
        self._filled = int(scalars['filled'])
        self._lags = int(scalars['lags'])
        self._loss = float(scalars['loss'])
        self._count = float(scalars['count'])
        self._beta = float(scalars['beta'])
        self._sigma2 = float(scalars['sigma2'])
        self._samples = int(scalars['samples'])
        self._since_redesign = int(scalars['since_redesign'])
        self._redesigns = int(scalars['redesigns'])
        self._last_iterations = int(scalars['last_iterations'])
        self._holding = bool(scalars['holding'])
        self._energy = float(scalars['energy'])
        self._rows = int(scalars['rows'])
        self._next_redesign = int(scalars['next_redesign'])
        self._epoch_prefilters = [np.array(f, dtype=float) for f in scalars['epoch_prefilters']]
        self._epoch_weights = np.array(scalars['epoch_weights'], dtype=float)
        self._epoch_directions = np.array(scalars['epoch_directions'], dtype=float).reshape(
            len(self._epoch_prefilters), self.num_parameters)
        self._epoch_betas = np.array(scalars['epoch_betas'], dtype=float)
        self._controller_changes = int(scalars['controller_changes'])
        self._model_reasons = tuple(scalars['model_reasons'])
        self._discriminant_ratio = float(scalars['discriminant_ratio'])
        self._refusals = float(scalars.get('refusals', 0.0))
        self._gate_resume = int(scalars.get('gate_resume', 0))
