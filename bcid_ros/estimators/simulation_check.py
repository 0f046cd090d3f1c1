r"""
The simulation check: whether the model's simulated output agrees with the data.

The residual tests (:mod:`~bcid_ros.estimators.adequacy`) judge the residual that the model
says is white: for an ARX model (``rls``) that is the one-step equation error, which a biased
model can keep small and white (its noise model 1/A takes the slow part of the output as
noise) while its simulated output, what a controller designed on it expects, is far off. Its
own noise model then excuses any simulation error: a check of the simulation error's level
against the model's noise description (v = e/A) cannot see the bias, since for an ARX model
that is the equation-error test again. This check asks instead whether the data on a recent
window could have produced a model that simulates markedly better in the same model set.

**The statistic.** Over the last L samples kept (inputs u and output y as the estimator
sees them), the model G = B/A is simulated from rest, and the simulation error
:math:`\varepsilon = y - G u - N\beta` is taken after the nuisance columns N (the free
responses :math:`q^{-m}\delta/A`, m = 0 ... n - 1, and a constant: the unknown initial state
and operating point, q = n + 1 columns) are fitted by least squares: its sum of squares
:math:`S_0`. One Gauss-Newton step of the output-error criterion on the window, from the
model (gradient :math:`\psi = \partial\hat y/\partial\theta`: :math:`-q^{-k}\hat y/A` for
:math:`a_k`, :math:`q^{-l}u_i/A` for a b at lag l; Ljung 1999, ch. 10), gives
:math:`S_1 \le S_0` (the score form of the likelihood-ratio test: the projection of the
error on the gradient and the nuisance columns). If the model is right (open loop, G the
plant, the estimate's error small beside the window's), :math:`S_0 - S_1` is the part of the
noise v in the p directions of ψ: for white v of variance :math:`\sigma^2`,
:math:`(S_0 - S_1)/\sigma^2 \sim \chi^2_p` (the likelihood-ratio statistic of the fixed
parameters; Ljung 1999, sec. 16.4). For a coloured v the directions of ψ, filtered inputs,
lie where the inputs have their power, and the noise there is at most the long-run variance,
:math:`\kappa\sigma^2` with :math:`\kappa = \Phi_v(0)/\sigma^2 = \sum_k\rho_k` for a
low-pass noise. So

.. math::

    T = \frac{S_0 - S_1}{\kappa\,\hat\sigma^2}, \quad
    \hat\sigma^2 = \frac{S_1}{L - q - p}, \qquad
    \text{contradicted when } T > \chi^2_{p,\,1-\alpha}

with κ of the AR(2) model of the refitted error (at least 1; ``MAX_COLOUR`` only bounds it) and
α = ``FALSE_ALARM``. A model far off simulates much worse than the refit: :math:`S_0/S_1`
large, T of the order of the window's length.

Everything is over a leading plant axis where it can be (:func:`simulate`,
:func:`input_drive`); the refit is per plant. Pure numpy (the estimators import no scipy;
:func:`simulate` runs the recursions in blocks).
"""

from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np

from bcid_ros.estimators.residual_statistics import chi2_quantile

#: Samples per block of the recursion of :func:`simulate`.
BLOCK = 64
#: Samples kept and scored (at most: see :func:`window_length`).
WINDOW = 1000
#: Fewest samples to judge a model of order n on: this many per nuisance and model parameter.
SAMPLES_PER_PARAMETER = 20
#: Largest false-alarm rate of one check under the model.
FALSE_ALARM = 0.01
#: Largest long-run variance ratio kappa taken for the error's colour (a bound against a
#: zero division only: 100 made an exact rls estimate under equation noise through a pole at
#: 0.992, whose kappa is (1 + 0.992)/(1 - 0.992) = 249, fail the check on the realistic family).
MAX_COLOUR = 1e6
#: The check runs every this many recorded samples (its cost, a simulation of the window and
#: one least-squares solve, a few ms, amortised).
CHECK_PERIOD = 500


def simulate(a: np.ndarray, drive: np.ndarray) -> np.ndarray:
    r"""
    Return :math:`x = d / A(q)` from rest for each plant and each series.

    ``a`` ``(K, n)``: A = 1 + a_1 q^-1 + ... + a_n q^-n; ``drive`` ``(K, S, L)``: S series of
    length L per plant. Returns ``(K, S, L)``; non-finite where an unstable model overflows.

    The recursion :math:`x_t = d_t - \sum_j a_j x_{t-j}` runs in blocks of ``BLOCK``
    samples: within a block, :math:`x = H d + Z s`, H the lower-triangular Toeplitz matrix
    of the impulse response of 1/A over the block and Z the free responses to the state
    :math:`s = [x_{t-1} \dots x_{t-n}]` at its start, both from the recursion over one
    block; the next state is the block's last n outputs. Exact, in numpy, one matrix
    product per block instead of one step per sample.
    """
    count, series, length = drive.shape
    order = a.shape[1]
    x = np.empty(drive.shape)
    if order == 0:
        x[:] = drive
        return x
    block = max(BLOCK, order)
    # the recursion over one block: impulse response (column 0) and the n free responses
    unit = np.zeros((count, 1 + order, block))
    unit[:, 0, 0] = 1.0
    state = np.zeros((count, 1 + order, order))
    state[:, 1:, :] = np.eye(order)
    with np.errstate(over='ignore', invalid='ignore'):
        for t in range(block):
            value = unit[:, :, t] - np.einsum('kj,ksj->ks', a, state)
            unit[:, :, t] = value
            state = np.concatenate([value[:, :, None], state[:, :, :-1]], axis=2)
        impulse, free = unit[:, 0], unit[:, 1:]
        rows = np.arange(block)
        toeplitz = np.where(rows[:, None] >= rows[None, :],
                            impulse[:, np.clip(rows[:, None] - rows[None, :], 0, None)], 0.0)
        current = np.zeros((count, series, order))
        for start in range(0, length, block):
            stop = min(start + block, length)
            size = stop - start
            out = (np.einsum('kij,ksj->ksi', toeplitz[:, :size, :size], drive[:, :, start:stop])
                   + np.einsum('kji,ksj->ksi', free[:, :, :size], current))
            x[:, :, start:stop] = out
            tail = x[:, :, max(stop - order, 0):stop][:, :, ::-1]
            current = np.zeros((count, series, order))
            current[:, :, :tail.shape[2]] = tail
            if tail.shape[2] < order:  # a last block shorter than n: older outputs behind
                older = x[:, :, max(stop - order, 0) - (order - tail.shape[2]):
                          max(stop - order, 0)][:, :, ::-1]
                current[:, :, tail.shape[2]:tail.shape[2] + older.shape[2]] = older
    return x


def input_drive(b: np.ndarray, lags: np.ndarray, u: np.ndarray) -> np.ndarray:
    r"""
    Return :math:`\sum_i\sum_k b_{ik} u_i(t - l_{ik})` from rest, ``(K, L)``.

    ``b`` ``(K, r, m)`` the coefficients, ``lags`` ``(r, m)`` their true lags (dead time
    included), ``u`` ``(K, L, r)``.
    """
    count, length, inputs = u.shape
    drive = np.zeros((count, length))
    for i in range(inputs):
        for k, lag in enumerate(lags[i]):
            if lag < length:
                drive[:, lag:] += b[:, i, k, None] * u[:, :length - lag, i]
    return drive


def _free_responses(a: np.ndarray, length: int) -> np.ndarray:
    """Return the nuisance columns ``(L, n + 1)``: q^-m delta / A (m < n) and a constant."""
    order = a.size
    drives = np.zeros((1, order, length))
    for m in range(order):
        drives[0, m, m] = 1.0
    responses = simulate(a[None], drives)[0] if order else np.zeros((0, length))
    return np.vstack([responses, np.ones((1, length))]).T


def _simulation_error(y: np.ndarray, u: np.ndarray, a: np.ndarray, b: np.ndarray,
                      lags: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return (epsilon, simulated output G u, nuisance columns) of one plant's window."""
    simulated = simulate(a[None], input_drive(b[None], lags, u[None])[:, None])[0, 0]
    nuisance = _free_responses(a, y.size)
    error = y - simulated
    scale = np.linalg.norm(nuisance, axis=0)
    scale[scale == 0.0] = 1.0
    beta = np.linalg.lstsq(nuisance / scale, error, rcond=None)[0]
    return error - (nuisance / scale) @ beta, simulated, nuisance


def _gradient(a: np.ndarray, simulated: np.ndarray, u: np.ndarray,
              lags: np.ndarray) -> np.ndarray:
    """Return psi = d yhat / d[a, b] over the window, ``(L, p)`` (Ljung 1999, ch. 10)."""
    length = simulated.size
    order = a.size
    series = np.vstack([simulated[None], u.T])[None]
    filtered = simulate(a[None], series)[0]
    columns = np.zeros((length, order + lags.size))
    for k in range(1, order + 1):
        columns[k:, k - 1] = -filtered[0, :length - k]
    column = order
    for i in range(lags.shape[0]):
        for lag in lags[i]:
            if lag < length:
                columns[lag:, column] = filtered[1 + i, :length - lag]
            column += 1
    return columns


def _stable(a: np.ndarray) -> bool:
    return a.size == 0 or bool(np.all(np.abs(np.roots(np.concatenate(([1.0], a)))) < 1.0))


def refit(y: np.ndarray, u: np.ndarray, a: np.ndarray, b: np.ndarray,
          lags: np.ndarray) -> tuple[float, float, np.ndarray, np.ndarray]:
    """
    Return S_0, S_1 and the refitted error of one plant's window (see the module docstring).

    S_1 is the error left after one Gauss-Newton step from the model, that is after the
    least-squares projection of the simulation error on the gradient and the nuisance
    columns: the score (Lagrange multiplier) form of the likelihood-ratio statistic, one
    linear solve instead of an iterated refit (a refit of 5 steps cost 10 to 30 times more
    and changed no verdict on the cases of test/estimators/test_simulation_check.py).
    """
    error, simulated, nuisance = _simulation_error(y, u, a, b, lags)
    columns = np.hstack([_gradient(a, simulated, u, lags), nuisance])
    scale = np.linalg.norm(columns, axis=0)
    scale[scale == 0.0] = 1.0
    step = np.linalg.lstsq(columns / scale, error, rcond=None)[0]
    refitted = error - (columns / scale) @ step
    return float(error @ error), float(refitted @ refitted), error, refitted


def colour(error: np.ndarray) -> float:
    r"""
    Return kappa, the long-run over the plain variance of the error by its AR(2) model.

    :math:`\kappa = (\sigma_w^2/\sigma^2)/D(1)^2` for :math:`D(q)\varepsilon = w`, fitted
    by Yule-Walker; clipped to [1, MAX_COLOUR].
    """
    centred = error - error.mean()
    length = centred.size
    r = np.array([centred[:length - k] @ centred[k:] for k in range(3)]) / length
    if not r[0] > 0.0:
        return 1.0
    toeplitz = np.array([[r[0], r[1]], [r[1], r[0]]])
    try:
        d = np.linalg.solve(toeplitz, r[1:])
    except np.linalg.LinAlgError:
        return MAX_COLOUR
    innovation = r[0] - d @ r[1:]
    gain = 1.0 - d.sum()
    if not (innovation > 0.0 and gain != 0.0):
        return MAX_COLOUR
    return float(min(max(innovation / r[0] / gain ** 2, 1.0), MAX_COLOUR))


def check(y: np.ndarray, u: np.ndarray, a: np.ndarray, b: np.ndarray, lags: np.ndarray,
          false_alarm: float = FALSE_ALARM) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                     np.ndarray]:
    r"""
    Return T, its limit, S_0/S_1 and whether each plant's simulation is contradicted.

    Parameters
    ----------
    y : numpy.ndarray, shape ``(K, L)``
        The outputs of the window, oldest first.
    u : numpy.ndarray, shape ``(K, L, r)``
        The inputs of the window.
    a : numpy.ndarray, shape ``(K, n)``
        A (or F) of the model, without its leading 1.
    b, lags : numpy.ndarray
        The numerators ``(K, r, m)`` and their true lags ``(r, m)``.
    false_alarm : float
        alpha.

    Returns
    -------
    statistic, limit, ratio, contradicted : numpy.ndarray, shape ``(K,)``
        T, :math:`\chi^2_{p,1-\alpha}`, S_0/S_1 and ``statistic > limit``. A plant whose
        model is unstable, or whose window is not finite, has T NaN and is not judged (the
        stability checks name an unstable model).

    """
    count, length = y.shape
    order = a.shape[1]
    p = order + lags.size
    limit = np.full(count, chi2_quantile(false_alarm, p))
    statistic = np.full(count, np.nan)
    ratio = np.full(count, np.nan)
    kept = length - (order + 1) - p
    for k in range(count):
        if kept <= 0 or not (_stable(a[k]) and np.isfinite(y[k]).all()
                             and np.isfinite(u[k]).all() and np.isfinite(b[k]).all()):
            continue
        s0, s1, error, refitted = refit(y[k], u[k], a[k], b[k], lags)
        if not (s1 > 0.0 and math.isfinite(s0)):
            continue
        kappa = max(colour(error), colour(refitted))
        statistic[k] = (s0 - s1) / (kappa * s1 / kept)
        ratio[k] = s0 / s1
    with np.errstate(invalid='ignore'):
        return statistic, limit, ratio, statistic > limit


def window_length(forgetting_factor: float) -> int:
    r"""
    Return L: :data:`WINDOW`, or the estimator's memory :math:`1/(1-\lambda)` if shorter.

    The check holds the model fixed, so its error must be small beside the window's: an
    estimate with forgetting weighs about its last :math:`1/(1-\lambda)` samples, and on a
    window five times as long its error is what a refit finds (bcrls at lambda 0.995, 4 runs
    of 4000 samples: not valid 35 % of the time with L = 1000, 1.9 % with 400, none with 200).
    """
    if forgetting_factor >= 1.0:
        return WINDOW
    return int(min(WINDOW, round(1.0 / (1.0 - forgetting_factor))))


def numerator_lags(order: int, num_inputs: int, feedthrough: bool,
                   input_delay: Sequence[int]) -> np.ndarray:
    """Return the true lags ``(r, m)`` of the b's in the estimators' order (dead time included)."""
    first = 0 if feedthrough else 1
    return np.array([[delay + lag for lag in range(first, order + 1)]
                     for delay in input_delay[:num_inputs]], dtype=int)


class SimulationWindow:
    """
    The last :data:`WINDOW` samples of one plant, and the check of a model on them.

    :meth:`record` keeps a sample (as the model sees it: deviations when the estimator
    detrends), :meth:`clear` forgets them (a gap, a restart), and :meth:`reasons` runs
    :func:`check` on them every :data:`CHECK_PERIOD` recorded samples once there are enough,
    keeping its reason in between.

    Parameters
    ----------
    order, num_inputs, feedthrough, input_delay
        The model's structure.
    forgetting_factor : float
        The estimator's lambda, which sets L (:func:`window_length`).

    """

    def __init__(self, order: int, num_inputs: int, feedthrough: bool,
                 input_delay: Sequence[int], forgetting_factor: float = 1.0) -> None:
        self.order = order
        self.lags = numerator_lags(order, num_inputs, feedthrough, input_delay)
        self.minimum = SAMPLES_PER_PARAMETER * (2 * order + 1 + self.lags.size)
        self._inputs = num_inputs
        self.window = window_length(forgetting_factor)
        self._rows = np.zeros((2 * self.window, 1 + num_inputs))
        self.clear()

    def follow_forgetting_factor(self, forgetting_factor: float) -> None:
        """Take the window length of a new lambda, keeping the last samples that fit."""
        window = window_length(forgetting_factor)
        if window == self.window:
            return
        kept = min(self._filled, window)
        rows = np.zeros((2 * window, 1 + self._inputs))
        rows[:kept] = self._rows[self._end - kept:self._end]
        self.window, self._rows = window, rows
        self._end = self._filled = kept
        self._judged = False

    def clear(self) -> None:
        """Forget the samples and the last verdict."""
        self._end = 0
        self._filled = 0
        self._since = 0
        self.reason = ''
        self.statistic = math.nan
        self._judged = False

    def record(self, y: float, u: Any) -> None:
        """Keep one sample."""
        rows = self._rows
        if self._end == rows.shape[0]:
            rows[:self.window] = rows[self.window:]
            self._end = self.window
        rows[self._end, 0] = y
        rows[self._end, 1:] = u
        self._end += 1
        self._filled = min(self._filled + 1, self.window)
        self._since += 1
        if self._filled < self.minimum:
            self._judged = False

    def reasons(self, a: np.ndarray, b: np.ndarray) -> list[str]:
        """Return the check's reason (``[]`` when the simulation agrees or is not judged yet)."""
        if self._filled < self.minimum:
            return []
        if self._since >= CHECK_PERIOD or not self._judged:
            self._since = 0
            self._judged = True
            rows = self._rows[self._end - self._filled:self._end]
            statistic, limit, ratio, contradicted = check(
                rows[None, :, 0], rows[None, :, 1:], a[None], b.reshape(1, *self.lags.shape),
                self.lags)
            self.statistic = float(statistic[0])
            self.reason = (f'simulated output off: a refit on the last {self._filled} samples '
                           f'lowers its squared error {ratio[0]:.3g} times (statistic '
                           f'{statistic[0]:.3g} > {limit[0]:.3g})' if contradicted[0] else '')
        return [self.reason] if self.reason else []

    def state_items(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Return (arrays, scalars) of the window for a snapshot (fixed shapes)."""
        rows = np.zeros((self.window, self._rows.shape[1]))
        if self._filled:
            rows[:self._filled] = self._rows[self._end - self._filled:self._end]
        return ({'simulation_rows': rows},
                {'simulation_filled': self._filled, 'simulation_since': self._since,
                 'simulation_reason': self.reason, 'simulation_judged': self._judged,
                 'simulation_statistic': self.statistic})

    def load(self, arrays: dict[str, np.ndarray], scalars: dict[str, Any]) -> None:
        """Take over :meth:`state_items` (a snapshot without them: an empty window)."""
        self.clear()
        if 'simulation_rows' not in arrays:
            return
        stored = arrays['simulation_rows'][:int(scalars['simulation_filled'])]
        filled = min(stored.shape[0], self.window)
        self._rows[:filled] = stored[stored.shape[0] - filled:]
        self._end = self._filled = filled
        self._since = int(scalars['simulation_since'])
        self.reason = str(scalars['simulation_reason'])
        self._judged = bool(scalars['simulation_judged'])
        self.statistic = float(scalars['simulation_statistic'])


def simulation_reasons(window: SimulationWindow | None, theta: np.ndarray,
                       order: int) -> list[str]:
    """
    Return the check's reason for a model ``theta`` laid out [a, b, ...] (``[]``: none kept).

    The a's (A, or F of an output-error model) are its first ``order`` entries and the b's
    follow, input by input; what comes after them (the C of an ARMAX model) is the noise
    model, which the simulated output does not use.
    """
    if window is None:
        return []
    return window.reasons(theta[:order], theta[order:order + window.lags.size])


__all__ = ['BLOCK', 'CHECK_PERIOD', 'FALSE_ALARM', 'MAX_COLOUR', 'SAMPLES_PER_PARAMETER',
           'WINDOW', 'SimulationWindow', 'check', 'colour', 'input_drive', 'numerator_lags',
           'refit', 'simulate', 'simulation_reasons', 'window_length']
