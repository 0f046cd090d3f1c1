r"""
Online closed-loop bias-compensated least squares (Ikeda 2008), per sample.

:class:`ClosedLoopBcls` runs a recursive prefiltered LS at every sample and
compensates it with eqs. (56)-(59); every ``redesign_period`` samples it
runs the batch Algorithm 1 (:func:`~bcid_ros.estimators.cl_bcls_batch.closed_loop_bcls`)
on a window of raw samples to redesign the prefilter and refresh the bias
terms. The model, the parametrisation of eq. (13) and the pieces of
Algorithm 1 are in :mod:`bcid_ros.estimators.cl_bcls_batch`; the controller
and its sign convention in :mod:`bcid_ros.estimators.lti`. docs/cl_bcls.md
explains the settings, the safety rules and their reasons.
"""

from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np

from bcid_ros.estimators.base import (check_forgetting_factor, check_int, check_range,
                                      RecursiveEstimator)
from bcid_ros.estimators.cl_bcls_batch import (algorithm1, CompensationFailure,
                                               DEFAULT_TOLERANCE, is_contracting,
                                               plant_from_regression, prefilter_polynomial,
                                               regression_from_plant)
from bcid_ros.estimators.lti import controller_canonical, make_controller

#: Default cap on the redesign window (samples); the paper's N.
DEFAULT_WINDOW = 4096
#: Default number of samples between two compensations + prefilter redesigns.
DEFAULT_REDESIGN_PERIOD = 1000
#: Default cap on the prefilter iterations of one redesign.
DEFAULT_MAX_ITERATIONS = 20
#: Regression rows per parameter that the window must hold before a redesign.
ROWS_PER_PARAMETER = 10
#: The first redesign waits for ``window // FIRST_WINDOW_DIVISOR`` samples (docs/cl_bcls.md,
#: "Why not_contracting and first_window").
FIRST_WINDOW_DIVISOR = 2


class ClosedLoopBcls(RecursiveEstimator):
    r"""
    Online closed-loop BCLS: per-sample prefiltered RLS, windowed Algorithm 1.

    The estimator sees only the measured (y[k], u[k]), never the reference r.
    It assumes that u is exactly the output of the given LTI controller acting
    on the same y (no saturation, no retuning), that the noise is white and
    on y only (A3), that the true loop is stable (A4), that the plant is
    strictly proper of order at most n (A2) and that r is independent of the
    noise (A5).

    **Per sample** k, with the prefilter f, :math:`c = C_{cl} P_{12} h^T`
    (eq. 37) and :math:`\beta = 1 + h P_{22} h^T` (eq. 57) frozen at the last
    redesign:

    .. math::

        y_f[k] &= \frac{q^n}{f(q)} y[k], \quad u_f[k] = \frac{q^n}{f(q)} u[k]
            && \text{(10)} \\
        \varphi[k] &= [y_f[k-1] \dots y_f[k-n], u_f[k-1] \dots u_f[k-n]]^T
            && \text{(14)} \\
        s &= 1 + \varphi^T P \varphi, \quad e = y[k] - \varphi^T\hat\theta_{LS} \\
        \hat\theta_{LS} &\leftarrow \hat\theta_{LS} + P\varphi\, e / s, \quad
        P \leftarrow P - P\varphi\varphi^T P / s, \quad
        J \leftarrow J + e^2/s, \quad N \leftarrow N + 1 && \text{(17), recursively} \\
        \gamma &= J / N, \quad \alpha = N c^T P c && \text{(53), (56)} \\
        \hat\sigma_\nu^2 &= \frac{2\gamma}{\beta + \sqrt{\beta^2 - 4\alpha\gamma}}
            && \text{(58)} \\
        \hat\theta_{BC} &= \hat\theta_{LS} - N \hat\sigma_\nu^2 P c && \text{(59)} \\
        \hat a_i &= f_i - \hat\theta_{BC,i}, \quad \hat b_i = \hat\theta_{BC,n+i}
            && \text{(13)}

    **Every** ``redesign_period`` **samples**, once the window holds at least
    ``10 * 2n + n`` samples (before the first successful redesign:
    :attr:`first_window` = max(``window`` // 2, ``10 * 2n + n``)), Algorithm 1
    runs on the last min(samples since reset or restart, ``window``) raw
    samples, from the prefilter in use. On success the prefilter, c and beta
    become those of its last iteration, and the running LS continues from that
    iteration's solution (:math:`P = (\Phi^T\Phi)^{-1}`).

    **Published estimate.** After a successful redesign on the window starting
    at sample s, ``theta`` at sample N is eqs. (56), (58), (59) with the
    frozen f, c, beta applied to the LS solution (17) over samples s..N
    prefiltered by f from rest at s; at the redesign sample it is Algorithm 1's
    result on the window. ``theta_uncompensated`` is that LS solution. Before
    the first successful redesign ``theta`` is the LS from
    :math:`P(0) = p_0 I`, :math:`\hat\theta(0) = 0` with the initial
    prefilter and :attr:`valid` is False. :meth:`restart_regressor` empties the
    window and restarts the filters from rest; the running LS keeps its
    statistics until the next redesign.

    **Safety.** No estimate is ever NaN. Each condition is counted in
    :attr:`flags`:

    * ``unstable_closed_loop``, ``unstable_prefilter``, ``lyapunov_failed``,
      ``singular_information``, ``negative_variance_argument``: in the first
      iteration of a redesign, the redesign is dropped (prefilter and running
      LS unchanged; compensated estimate and sigma2 held, :attr:`holding`);
      in a later iteration, the last good iterate is the result;
    * ``negative_variance_argument`` at a sample, ``nonfinite_estimate``: that
      sample keeps the last good compensated estimate and sigma2;
    * ``not_converged``: a redesign used all ``max_iterations``; its result is
      used if the iteration was contracting;
    * ``not_contracting``: a redesign stopped without meeting ``tolerance``
      and :func:`~bcid_ros.estimators.cl_bcls_batch.is_contracting` is False;
      the redesign is dropped as a failed one;
    * ``covariance_repaired``: P lost definiteness and was rebuilt.

    Parameters
    ----------
    order, num_inputs, feedthrough, initial_covariance, forgetting_factor
        As for :class:`~bcid_ros.estimators.base.RecursiveEstimator`, with
        ``num_inputs`` 1 (SISO), ``feedthrough`` False (eq. 3) and
        ``forgetting_factor`` 1 (the estimator forgets through its ``window``);
        :math:`P(0) = p_0 I` is used only before the first redesign.
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
        Cap on the samples kept for a redesign (default 4096, the paper's N).
    redesign_period : int
        Samples between redesigns (default 1000).
    max_iterations : int
        Cap on the LS solves of one redesign (default 20).
    tolerance : float
        Stop a redesign when the estimate moves by less (default 1e-3, as in
        section 7.3).

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
        self._check_forgetting(self._forgetting_factor)
        self.controller = make_controller(controller_numerator, controller_denominator,
                                          controller_sign)
        self.prefilter_initial = prefilter_polynomial(prefilter_initial, self.order)
        self.min_window = ROWS_PER_PARAMETER * 2 * self.order + self.order
        self.window = check_int('window', window, self.min_window)
        self.first_window = max(self.window // FIRST_WINDOW_DIVISOR, self.min_window)
        self.redesign_period = check_int('redesign_period', redesign_period, 1)
        self.max_iterations = check_int('max_iterations', max_iterations, 1)
        self.tolerance = check_range('tolerance', tolerance, 0.0, math.inf, low_open=True)
        self._reset()

    @staticmethod
    def _check_forgetting(value: float) -> None:
        if value != 1.0:
            raise ValueError('forgetting_factor must be 1 for cl_bcls (it forgets through its '
                             f'finite window), got {value!r}')

    @property
    def forgetting_factor(self) -> float:
        """Return the forgetting factor; cl_bcls only accepts 1."""
        return self._forgetting_factor

    @forgetting_factor.setter
    def forgetting_factor(self, value: float) -> None:
        value = check_forgetting_factor(value)
        self._check_forgetting(value)
        self._forgetting_factor = value

    # ------------------------------------------------------------- the step
    def _update(self, y: float, u: np.ndarray) -> None:
        u0 = float(u[0])
        # keep the raw sample for the redesign window
        pos = self._pos
        if pos == self._buffer.shape[0]:
            self._buffer[:self.window] = self._buffer[self.window:]
            pos = self.window
        self._buffer[pos] = (y, u0)
        self._pos = pos + 1
        if self._filled < self.window:
            self._filled += 1
        self._samples += 1
        phi = self._phi
        if self._lags >= self.order:
            self._ls_step(y, phi)
        else:
            self._lags += 1
        # phi[k+1] = blockdiag(F, F) phi[k] + [g y[k]; g u[k]]        (10), (14)
        phi = self._shift.dot(phi)
        phi[0] += y
        phi[self.order] += u0
        self._phi = phi
        self._since_redesign += 1
        if (self._since_redesign >= self.redesign_period and self._filled >= (
                self.min_window if self._direction is not None else self.first_window)):
            self._since_redesign = 0
            self._redesign()

    def _ls_step(self, y: float, phi: np.ndarray) -> None:
        """Do the RLS step and, once a redesign has succeeded, eqs. (56)-(59)."""
        theta = self._theta_ls
        # g = P phi
        g = self._p.dot(phi)
        # s = 1 + phi' P phi
        s = 1.0 + phi.dot(g)
        if not s > 0.0:
            self._repair_covariance()
            return
        # e = y[k] - phi' theta_LS
        e = y - phi.dot(theta)
        # theta_LS += P phi e / s
        theta += g * (e / s)
        # P -= P phi phi' P / s, written as h h' with h = g / sqrt(s)
        h = g * (1.0 / math.sqrt(s))
        self._p -= h[:, None] * h
        # J += e^2 / s ; N += 1
        self._loss += e * e / s
        self._count += 1.0
        if self._direction is None or self._holding:
            return
        count = self._count
        direction = self._direction
        pc = self._p.dot(direction)
        # gamma = J / N                                                      (53)
        gamma = self._loss / count
        # alpha = N c' P c                                                   (56)
        alpha = count * direction.dot(pc)
        beta = self._beta
        discriminant = beta * beta - 4.0 * alpha * gamma
        if not discriminant >= 0.0:
            self._flag('negative_variance_argument')
            return
        # sigma2 = 2 gamma / (beta + sqrt(beta^2 - 4 alpha gamma))           (58)
        sigma2 = 2.0 * gamma / (beta + math.sqrt(discriminant))
        # theta_BC = theta_LS - N sigma2 P c                                 (59)
        compensated = theta - (count * sigma2) * pc
        if not math.isfinite(compensated.dot(compensated) + sigma2):
            self._flag('nonfinite_estimate')
            return
        self._theta_bc = compensated
        self._sigma2 = sigma2

    def _repair_covariance(self) -> None:
        """Rebuild P as the nearest symmetric positive definite matrix."""
        self._flag('covariance_repaired')
        sym = 0.5 * (self._p + self._p.T)
        if not np.isfinite(sym).all():
            self._p = self.initial_covariance * np.eye(self.num_parameters)
            return
        values, vectors = np.linalg.eigh(sym)
        floor = max(values.max(), 1.0) * 1e-12
        self._p = (vectors * np.maximum(values, floor)) @ vectors.T

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

    def _set_prefilter(self, prefilter: np.ndarray) -> None:
        n = self.order
        self._prefilter = np.array(prefilter, dtype=float)
        f_matrix, _ = controller_canonical(self._prefilter)
        shift = np.zeros((2 * n, 2 * n))
        shift[:n, :n] = f_matrix
        shift[n:, n:] = f_matrix
        self._shift = shift

    # --------------------------------------------------------- the accessors
    @property
    def ready(self) -> bool:
        """Whether a compensation (redesign) has succeeded since the last reset."""
        return self._direction is not None

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
        """Return the number of samples the next redesign would use."""
        return self._filled

    @property
    def covariance(self) -> np.ndarray:
        """Return P, the inverse information matrix of the running LS (a copy)."""
        return self._p.copy()

    @property
    def covariance_trace(self) -> float:
        """Return tr P."""
        return float(np.trace(self._p))

    def _theta(self) -> np.ndarray:
        if self._direction is None:
            return self._theta_uncompensated()
        # a_i = f_i - theta_i ; b_i = theta_(n+i)                            (13)
        return plant_from_regression(self._theta_bc, self._prefilter)

    def _theta_uncompensated(self) -> np.ndarray:
        return plant_from_regression(self._theta_ls, self._prefilter)

    def _noise(self) -> np.ndarray:
        return np.array([self._sigma2])

    def __repr__(self) -> str:
        return (f'{type(self).__name__}(order={self.order}, '
                f'controller={self.controller.numerator.tolist()}/'
                f'{self.controller.denominator.tolist()} ({self.controller.sign} feedback), '
                f'window={self.window}, redesign_period={self.redesign_period}, '
                f'max_iterations={self.max_iterations}, tolerance={self.tolerance:g})')

    # -------------------------------------------------------------- the state
    def _reset(self) -> None:
        p = self.num_parameters
        self._set_prefilter(self.prefilter_initial)
        self._buffer = np.zeros((2 * self.window, 2))
        self._pos = 0
        self._filled = 0
        self._phi = np.zeros(p)
        self._lags = 0
        self._theta_ls = np.zeros(p)
        self._p = self.initial_covariance * np.eye(p)
        self._loss = 0.0
        self._count = 0.0
        self._direction: np.ndarray | None = None
        self._beta = 1.0
        self._theta_bc = np.zeros(p)
        self._sigma2 = 0.0
        self._holding = False
        self._samples = 0
        self._since_redesign = 0
        self._redesigns = 0
        self._last_iterations = 0

    def _restart_regressor(self) -> None:
        self._filled = 0
        self._phi = np.zeros(self.num_parameters)
        self._lags = 0

    def _state_items(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        compensated = self._direction is not None
        arrays = {'prefilter': self._prefilter, 'buffer': self._buffer, 'phi': self._phi,
                  'theta_ls': self._theta_ls, 'p': self._p, 'theta_bc': self._theta_bc,
                  'direction': (self._direction if compensated
                                else np.zeros(self.num_parameters))}
        scalars = {'pos': self._pos, 'filled': self._filled, 'lags': self._lags,
                   'loss': self._loss, 'count': self._count, 'beta': self._beta,
                   'sigma2': self._sigma2, 'samples': self._samples,
                   'since_redesign': self._since_redesign, 'redesigns': self._redesigns,
                   'last_iterations': self._last_iterations, 'compensated': compensated,
                   'holding': self._holding}
        return arrays, scalars

    def _load_state(self, arrays: dict[str, np.ndarray], scalars: dict[str, Any]) -> None:
        self._set_prefilter(arrays['prefilter'])
        self._buffer = arrays['buffer']
        self._phi = arrays['phi']
        self._theta_ls = arrays['theta_ls']
        self._p = arrays['p']
        self._theta_bc = arrays['theta_bc']
        self._direction = arrays['direction'] if scalars['compensated'] else None
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
