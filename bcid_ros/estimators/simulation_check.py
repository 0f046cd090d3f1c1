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
responses :math:`q^{-m}\delta/A`, m = 0 ... s - 1, and a constant: the unknown initial state
and operating point, q = s + 1 columns, s = max(n, the largest lag of a b) the number of
states, :func:`state_count`) are fitted by least squares: its sum of squares
:math:`S_0`. One Gauss-Newton step of the output-error criterion on the window, from the
model (gradient :math:`\psi = \partial\hat y/\partial\theta`: :math:`-q^{-k}\hat y/A` for
:math:`a_k`, :math:`q^{-l}u_i/A` for a b at lag l; Ljung 1999, ch. 10), gives
:math:`S_1 \le S_0` (the score form of the likelihood-ratio test: the projection of the
error on the gradient and the nuisance columns). If the model is right (open loop, G the
plant, the estimate's error small beside the window's), :math:`S_0 - S_1` is the part of the
noise v in the p directions of ψ: for white v of variance :math:`\sigma^2`,
:math:`(S_0 - S_1)/\sigma^2 \sim \chi^2_p` (the likelihood-ratio statistic of the fixed
parameters; Ljung 1999, sec. 16.4). For a coloured Gaussian v of covariance Σ,
:math:`S_0 - S_1 = v^T P v = \sum_i \lambda_i z_i^2` with P the projection, z_i independent
standard normal and :math:`\lambda_i \le \lambda_{max}(\Sigma) \le \max_\omega
\Phi_v(\omega)`: so :math:`(S_0 - S_1)/(\kappa\sigma^2)`, :math:`\kappa = \max_\omega
\Phi_v(\omega)/\sigma^2`, is at most a :math:`\chi^2_p` variable, whatever the
directions of ψ, and the test below alarms at most at the rate α. (The long-run ratio
:math:`\Phi_v(0)/\sigma^2` bounds only a low-pass noise: on a lightly damped flexible arm,
whose error peaks at its resonance, the batch OE model itself failed the check with it,
T = 97 against a limit of 26.) So

.. math::

    T = \frac{S_0 - S_1}{\kappa\,\hat\sigma^2}, \quad
    \hat\sigma^2 = \frac{S_1}{L - q - p}, \qquad
    \text{contradicted when } T > \chi^2_{p,\,1-\alpha}

with κ the largest of the peaks of the AR(2) spectra of the error before and after the refit
and of the AIC-chosen AR spectrum of the error after it
(:func:`~bcid_ros.estimators.noise_colour.colour`; at least 1, ``MAX_COLOUR`` only bounds
it): the refit absorbs part of a slow noise, so the error after it alone understates a slow
colour, and before it the error of a far-off model, a filtered
input, has spectral peaks of its own (rls on the two-layer wall of DaISy, 22.7 % against the
batch model's 74.0 %: T 12.9 with that peak among κ's, 145 without, against 16.8) and
α = ``FALSE_ALARM``. A model far off simulates much worse than the refit: :math:`S_0/S_1`
large, T of the order of the window's length.

**A settling estimate.** Early in a run or after a restart the estimate's own error is not
small beside the window's; where the estimator gives its covariance P, the score's
quadratic form counts it (:func:`settled_statistic`), with P capped at
:data:`SETTLING_EXCUSE` times a fit of the window alone so that no inflated P excuses a
misfit.

**A plant change.** A model that passed on a full window and is then contradicted on two
disjoint windows, no check passing in between, is evidence that the plant changed
(:meth:`SimulationWindow.contradicted_twice`: at most :math:`2\alpha^2` per check under a
plant that does not change; rpem restarts on it where its change detector is silent). The
second window is the samples since the first contradiction, looked at as they come (a few
looks, alpha shared among them), or once the window starts after it, the whole window.

Everything is over a leading plant axis where it can be (:func:`simulate`,
:func:`input_drive`); the refit is per plant. Pure numpy (the estimators import no scipy;
:func:`simulate` runs the recursions in blocks).
"""

from __future__ import annotations

import math
from typing import Any, Callable, Sequence

import numpy as np

from bcid_ros.estimators.noise_colour import colour
from bcid_ros.estimators.residual_statistics import chi2_quantile

#: Samples per block of the recursion of :func:`simulate`.
BLOCK = 64
#: Samples kept and scored (at most: see :func:`window_length`).
WINDOW = 1000
#: Fewest samples to judge a model of order n on: this many per nuisance and model parameter.
SAMPLES_PER_PARAMETER = 20
#: Largest false-alarm rate of one check under the model.
FALSE_ALARM = 0.01
#: The most of the estimate's own error the check excuses, in covariances of a fit of the
#: window alone (:func:`settled_statistic`): an error of twice that fit's.
SETTLING_EXCUSE = 4.0
#: The most the reported variance of a parameter of [a, b] may understate the one that the
#: window's own information implies for an estimate of the estimator's sample count
#: (:func:`understatement`; a std 10 times too small). Gross by design: the window holds the
#: last L samples only, and an input richer before it legitimately determines the estimate
#: better than the window does (the first 40 realistic plants, rpem, every 1000 samples: at
#: most 4.0, but for one plant whose std was 20 times the batch fit's, 410).
UNDERSTATEMENT_LIMIT = 100.0
#: How the reason of an understated covariance begins (it names the std, not the model).
UNDERSTATED = 'parameter std too small'
#: The check runs every this many recorded samples by default (its cost, a simulation of the
#: window and one least-squares solve, a few ms, amortised); an estimator may ask for a
#: shorter period (:class:`SimulationWindow`'s ``period``).
CHECK_PERIOD = 500


def simulate(a: np.ndarray, drive: np.ndarray,
             recursion: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    r"""
    Return :math:`x = d / A(q)` from rest for each plant and each series.

    ``a`` ``(K, n)``: A = 1 + a_1 q^-1 + ... + a_n q^-n; ``drive`` ``(K, S, L)``: S series of
    length L per plant. Returns ``(K, S, L)``; non-finite where an unstable model overflows.

    The recursion :math:`x_t = d_t - \sum_j a_j x_{t-j}` runs in blocks of ``BLOCK``
    samples: within a block, :math:`x = H d + Z s`, H the lower-triangular Toeplitz matrix
    of the impulse response of 1/A over the block and Z the free responses to the state
    :math:`s = [x_{t-1} \dots x_{t-n}]` at its start, both from the recursion over one
    block (:func:`block_recursion`; ``recursion``: already made for ``a``); the next state
    is the block's last n outputs. Exact, in numpy, one matrix product per block instead of
    one step per sample.
    """
    count, series, length = drive.shape
    order = a.shape[1]
    x = np.empty(drive.shape)
    if order == 0:
        x[:] = drive
        return x
    toeplitz, free = block_recursion(a) if recursion is None else recursion
    block = toeplitz.shape[1]
    with np.errstate(over='ignore', invalid='ignore'):
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


def block_recursion(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """
    Return :func:`simulate`'s H ``(K, B, B)`` and Z ``(K, n, B)`` of 1/A over one block.

    From the recursion over ``max(BLOCK, n)`` samples: the impulse response (H's columns,
    shifted) and the free responses to each of the n past outputs. Made once per model, it
    serves every simulation of that model (the check simulates three times).
    """
    count, order = a.shape
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
    return toeplitz, free


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


def state_count(order: int, lags: np.ndarray) -> int:
    r"""
    Return s = max(n, l_max): the samples before the window that the simulation misses.

    Simulated from rest, the window's output lacks the response to the state of 1/A (n
    values) and to the inputs before the window that enter through a b at lag l (at the
    window's first l samples): both are drives at samples 0 ... s - 1 filtered by 1/A,
    the span of :math:`q^{-m}\delta/A`, m < s. With a dead time the lags exceed n (the
    CD-player arm, n = 5 with lags to 6: without the sixth column a transient of rms 0.32
    against 0.06 over the window's first 50 samples, T 68 against a limit of 31 for a
    model that scores T 4.7 on the window without those samples).
    """
    return max(order, int(lags.max()) if lags.size else 0)


def _free_responses(a: np.ndarray, length: int, states: int,
                    recursion: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Return the nuisance columns ``(L, s + 1)``: q^-m delta / A (m < s) and a constant."""
    drives = np.zeros((1, states, length))
    for m in range(min(states, length)):
        drives[0, m, m] = 1.0
    responses = simulate(a[None], drives, recursion)[0] if states else np.zeros((0, length))
    return np.vstack([responses, np.ones((1, length))]).T


def _simulation_error(y: np.ndarray, u: np.ndarray, a: np.ndarray, b: np.ndarray,
                      lags: np.ndarray, recursion: tuple[np.ndarray, np.ndarray] | None = None
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return (epsilon, simulated output G u, nuisance columns) of one plant's window."""
    simulated = simulate(a[None], input_drive(b[None], lags, u[None])[:, None],
                         recursion)[0, 0]
    nuisance = _free_responses(a, y.size, state_count(a.size, lags), recursion)
    error = y - simulated
    scale = np.linalg.norm(nuisance, axis=0)
    scale[scale == 0.0] = 1.0
    beta = np.linalg.lstsq(nuisance / scale, error, rcond=None)[0]
    return error - (nuisance / scale) @ beta, simulated, nuisance


def _gradient(a: np.ndarray, simulated: np.ndarray, u: np.ndarray, lags: np.ndarray,
              recursion: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Return psi = d yhat / d[a, b] over the window, ``(L, p)`` (Ljung 1999, ch. 10)."""
    length = simulated.size
    order = a.size
    series = np.vstack([simulated[None], u.T])[None]
    filtered = simulate(a[None], series, recursion)[0]
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


def _projected(gradient: np.ndarray, nuisance: np.ndarray
               ) -> tuple[np.ndarray | None, np.ndarray]:
    """Return ψ̃ (ψ with N projected out) over its column norms, and the norms (None: a zero)."""
    scale = np.linalg.norm(nuisance, axis=0)
    scale[scale == 0.0] = 1.0
    basis = nuisance / scale
    projected = gradient - basis @ np.linalg.lstsq(basis, gradient, rcond=None)[0]
    norms = np.linalg.norm(projected, axis=0)
    if not (norms > 0.0).all():
        return None, norms
    return projected / norms, norms


def settled_statistic(gradient: np.ndarray, nuisance: np.ndarray, error: np.ndarray,
                      noise: float, covariance: np.ndarray,
                      projection: tuple[np.ndarray | None, np.ndarray] | None = None
                      ) -> float:
    r"""
    Return T with the estimate's own error counted: :math:`g^T(\kappa\sigma^2 M + M P M)^{-1}g`.

    ``gradient`` is ψ, ``nuisance`` N, ``error`` ε (N already projected out), ``noise``
    :math:`\kappa\hat\sigma^2` and ``covariance`` P the estimate's, in the order of ψ's
    columns. With ψ̃ the gradient with N projected out, g = ψ̃ᵀε and M = ψ̃ᵀψ̃:
    ε ≈ ψ̃δ + ṽ for an estimate off by δ, so Cov(g) = κσ²M + M Cov(δ) M, and with
    Cov(δ) = 0 this is the :func:`check`'s (S_0 - S_1)/(κσ²). P counts at most as much as
    :data:`SETTLING_EXCUSE` κσ²M⁻¹, four times the covariance of a fit of the window alone
    (an error up to twice that fit's: what docs/accuracy.md calls accurate; bcrls is less
    efficient than the output-error fit): so T is at least a fifth of the exact estimate's,
    and a misfit that grows T with the window's length is still seen. Columns scaled to unit
    norm for the solve; a singular form (a gradient without a direction) judges nothing (NaN).
    ``projection``: ψ̃ over its column norms and the norms, where already computed.
    """
    projected, norms = projection or _projected(gradient, nuisance)
    if projected is None:
        return math.nan
    score = projected.T @ error
    information = projected.T @ projected
    scaled_covariance = norms[:, None] * covariance * norms[None, :]  # of δ in ψ's units
    # the estimate is excused at most twice the error of a fit of the window alone, the
    # accuracy the benchmarks call accurate (P <= SETTLING_EXCUSE κσ²M⁻¹): a larger P (a
    # sandwich inflated by noise outside the estimator's model) would excuse any misfit
    excess = float(np.max(np.linalg.eigvals(scaled_covariance @ information).real)) / (
        SETTLING_EXCUSE * noise)
    if excess > 1.0:
        scaled_covariance = scaled_covariance / excess
    form = noise * information + information @ scaled_covariance @ information
    try:
        return float(score @ np.linalg.solve(form, score))
    except np.linalg.LinAlgError:
        return math.nan


def understatement(gradient: np.ndarray, nuisance: np.ndarray, noise: float,
                   covariance: np.ndarray, length: int, count: float,
                   projection: tuple[np.ndarray | None, np.ndarray] | None = None) -> float:
    r"""
    Return how many times the window implies a larger variance than ``covariance``, at most.

    The largest ratio, over the parameters, of the diagonals of
    :math:`\hat\sigma^2 M^{-1} L/N` and C (the variances behind the std the estimator
    publishes): M = ψ̃ᵀψ̃ the
    information of the window's L samples about [a, b] (the nuisance columns projected
    out), :math:`\hat\sigma^2` the white-noise level of the refitted error (the smallest
    variance the noise allows: a coloured noise's is larger, Ljung 1999, sec. 9.3), N =
    ``count`` the samples the estimate rests on and C the covariance the estimator reports
    for [a, b]. An estimate of N samples of the same plant and input has about N/L times the
    window's information, so the ratio is about 1 where C is honest; a C collapsed far below
    what any N samples could give makes it large. Per parameter, not in the worst direction:
    the weakest combination of an oversampled plant's parameters is determined so poorly by
    L samples that its ratio moved by hundreds where the std of every parameter agreed with
    the batch fit's (a third-order plant with poles near 0.96, two inputs: 250-650 against
    1.5-2 per parameter). NaN where the forms are singular. ``projection`` as for
    :func:`settled_statistic`.
    """
    unit, norms = projection or _projected(gradient, nuisance)
    if unit is None or not count > 0.0:
        return math.nan
    # in the columns' unit-norm coordinates: C' = D C D, M' = unit' unit (D the norms)
    information = unit.T @ unit
    reported = norms[:, None] * covariance * norms[None, :]
    try:
        implied = noise * length / count * np.diagonal(np.linalg.inv(information))
    except np.linalg.LinAlgError:
        return math.nan
    with np.errstate(divide='ignore', invalid='ignore'):
        return float(np.max(implied / np.diagonal(reported)))


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
    s0, s1, error, refitted, _, _ = _refit_columns(y, u, a, b, lags)
    return s0, s1, error, refitted


def _refit_columns(y: np.ndarray, u: np.ndarray, a: np.ndarray, b: np.ndarray,
                   lags: np.ndarray) -> tuple[float, float, np.ndarray, np.ndarray,
                                              np.ndarray, np.ndarray]:
    """Return :func:`refit`'s values and the gradient ψ and nuisance columns N it used."""
    recursion = block_recursion(a[None]) if a.size else None  # one model: made once
    error, simulated, nuisance = _simulation_error(y, u, a, b, lags, recursion)
    gradient = _gradient(a, simulated, u, lags, recursion)
    columns = np.hstack([gradient, nuisance])
    scale = np.linalg.norm(columns, axis=0)
    scale[scale == 0.0] = 1.0
    step = np.linalg.lstsq(columns / scale, error, rcond=None)[0]
    refitted = error - (columns / scale) @ step
    return (float(error @ error), float(refitted @ refitted), error, refitted, gradient,
            nuisance)


def check(y: np.ndarray, u: np.ndarray, a: np.ndarray, b: np.ndarray, lags: np.ndarray,
          false_alarm: float = FALSE_ALARM, covariance: np.ndarray | None = None
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Return :func:`judge`'s T, limit, S_0/S_1 and verdict (no count: no understatement)."""
    return judge(y, u, a, b, lags, false_alarm, covariance)[:4]


def judge(y: np.ndarray, u: np.ndarray, a: np.ndarray, b: np.ndarray, lags: np.ndarray,
          false_alarm: float = FALSE_ALARM, covariance: np.ndarray | None = None,
          count: np.ndarray | None = None
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
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
    covariance : numpy.ndarray, shape ``(K, p, p)``, optional
        The covariance of each estimate's [a, b] (its own error while it settles): T is then
        :func:`settled_statistic`, the score's quadratic form under the noise and that error
        together (a plant whose row is not finite is judged without it). None: the estimate
        is taken as exact (its error small beside the window's).
    count : numpy.ndarray, shape ``(K,)``, optional
        The samples each estimate rests on: with ``covariance``, the understatement of that
        covariance is computed too (:func:`understatement`; NaN without).

    Returns
    -------
    statistic, limit, ratio, contradicted, understated : numpy.ndarray, shape ``(K,)``
        T, :math:`\chi^2_{p,1-\alpha}`, S_0/S_1, ``statistic > limit`` and the
        understatement. A plant whose
        model is unstable, or whose window is not finite, has T NaN and is not judged (the
        stability checks name an unstable model).

    """
    plants, length = y.shape
    order = a.shape[1]
    p = order + lags.size
    limit = np.full(plants, chi2_quantile(false_alarm, p))
    statistic = np.full(plants, np.nan)
    ratio = np.full(plants, np.nan)
    understated = np.full(plants, np.nan)
    kept = length - (state_count(order, lags) + 1) - p
    for k in range(plants):
        if kept <= 0 or not (_stable(a[k]) and np.isfinite(y[k]).all()
                             and np.isfinite(u[k]).all() and np.isfinite(b[k]).all()):
            continue
        s0, s1, error, refitted, gradient, nuisance = _refit_columns(y[k], u[k], a[k], b[k],
                                                                     lags)
        if not (s1 > 0.0 and math.isfinite(s0)):
            continue
        # the slow colour from both errors (the refit absorbs part of a slow noise);
        # resonances from the refitted one only (before the refit, a far-off model's own
        # error, an input filtered, has peaks of its own that would hide it)
        kappa = max(colour(error, resonances=False), colour(refitted))
        noise = kappa * s1 / kept
        known = covariance is not None and np.isfinite(covariance[k]).all()
        # psi with the nuisance projected out, once for both uses of the covariance
        projection = _projected(gradient, nuisance) if known else None
        if known:
            statistic[k] = settled_statistic(gradient, nuisance, error, noise, covariance[k],
                                             projection)
        else:
            statistic[k] = (s0 - s1) / noise
        ratio[k] = s0 / s1
        if known and count is not None:
            understated[k] = understatement(gradient, nuisance, s1 / kept, covariance[k],
                                            length, float(count[k]), projection)
    with np.errstate(invalid='ignore'):
        return statistic, limit, ratio, statistic > limit, understated


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
    detrends), :meth:`gap` forgets them at a sample the estimator does not record (the
    verdict holds), :meth:`clear` forgets them and the verdict (a restart), and
    :meth:`reasons` runs
    :func:`check` on them every ``period`` recorded samples once there are enough
    (at every call while the window fills), keeping its reason in between.

    Parameters
    ----------
    order, num_inputs, feedthrough, input_delay
        The model's structure.
    forgetting_factor : float
        The estimator's lambda, which sets L (:func:`window_length`).
    period : int
        The recorded samples from one check to the next (:data:`CHECK_PERIOD`; 1: at every
        :meth:`reasons` with a sample since the last check).
    looks_at_tail : bool
        Whether a run of contradictions judges its samples alone too
        (:meth:`_look_at_tail`): for an estimator that takes :meth:`contradicted_twice` as
        evidence of a change (rpem); others would pay for looks no one reads.

    Raises
    ------
    ValueError
        If ``period`` is below 1.

    """

    #: The recorded samples from one check to the next (the windows over plants share it).
    period = CHECK_PERIOD

    def __init__(self, order: int, num_inputs: int, feedthrough: bool,
                 input_delay: Sequence[int], forgetting_factor: float = 1.0,
                 period: int = CHECK_PERIOD, looks_at_tail: bool = False) -> None:
        if period < 1:
            raise ValueError(f'period must be at least 1, got {period!r}')
        self.period = period
        self.looks_at_tail = looks_at_tail
        self.order = order
        self.lags = numerator_lags(order, num_inputs, feedthrough, input_delay)
        self.minimum = SAMPLES_PER_PARAMETER * (state_count(order, self.lags) + 1 + order
                                                + self.lags.size)
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
        """Forget the samples and the last verdict (a restart: a new model, new data)."""
        self.gap()
        self.reason = ''
        self.coverage_reason = ''
        self.statistic = math.nan
        # the evidence of a plant change (:meth:`contradicted_twice`): samples recorded since
        # the clear (a gap does not reset them), whether the last verdict passed the model on
        # a full window, whether a model did so with the estimator's word that it passed
        # every check (:meth:`vouch`), and the recorded count at the first check of the
        # current run of contradictions
        self._recorded = 0
        self._full_pass = False
        self.passed = False
        self._run_start = -1
        # the run's looks at the samples since its start (:meth:`_look_at_tail`): the
        # samples at which the next is due, and the last one's (0: it passed, or none)
        self._next_look = 0
        self._tail = 0

    def gap(self) -> None:
        """
        Forget the samples, keep the last verdict: a sample the estimator did not record.

        The check simulates the window as one stretch of consecutive samples: one left out
        (a refused outlier, a held or quiet sample) would splice two stretches, whose
        junction the model cannot simulate (on a slow plant a jump that raised kappa 15
        times and hid every misfit, docs/trust.md). A gap is no evidence about the model,
        so its verdict holds until the samples after the gap are enough to judge again.
        """
        self._end = 0
        self._filled = 0
        self._since = 0
        self._judged = False

    def record(self, y: float, u: Any) -> None:
        """Keep one sample."""
        rows = self._rows
        end = self._end
        if end == rows.shape[0]:
            end = self.window
            rows[:end] = rows[end:]
        row = rows[end]
        row[0] = y
        row[1:] = u
        self._end = end + 1
        self._recorded += 1
        filled = self._filled
        if filled < self.window:
            self._filled = filled = filled + 1
        self._since += 1
        if filled < self.minimum:
            self._judged = False

    def _due(self) -> bool:
        """
        Return whether the window is due for a check: ``period`` samples since the last.

        While the window fills, at every call (the estimators decide their validity every
        ``rules.VALIDITY_PERIOD`` samples: at most ``WINDOW / 100`` extra checks): a bias
        shows in T in proportion to the window's length, and a record shorter than
        the period past the first check would otherwise keep the verdict of its first,
        shortest window (three-input rls under output-error noise, 600 samples: T 18.1 on
        the first window of 229 samples, 53.8 on 519, against a limit of 20.1).
        """
        return self._since >= self.period or (self._since > 0 and self._filled < self.window)

    @property
    def judged(self) -> bool:
        """Whether the samples kept since the last gap or restart have had a verdict."""
        return self._judged

    def judging(self) -> bool:
        """Return whether the next :meth:`reasons` runs the check (rather than keep a verdict)."""
        return self._filled >= self.minimum and (self._due() or not self._judged)

    def reasons(self, a: np.ndarray, b: np.ndarray, covariance: np.ndarray | None = None,
                count: float | None = None) -> list[str]:
        """
        Return the check's verdicts: none when the simulation agrees or is not judged yet.

        ``covariance`` is that of [a, b] (None: the estimate taken as exact; see :func:`check`);
        with ``count``, the samples the estimate rests on, the covariance is also judged
        against the window's information (:func:`understatement`).
        """
        if self._filled >= self.minimum and self.judging():
            self._since = 0
            self._judged = True
            rows = self._rows[self._end - self._filled:self._end]
            statistic, limit, ratio, contradicted, understated = judge(
                rows[None, :, 0], rows[None, :, 1:], a[None], b.reshape(1, *self.lags.shape),
                self.lags, covariance=None if covariance is None else covariance[None],
                count=None if count is None else np.array([count]))
            self.statistic = float(statistic[0])
            self.reason = (f'simulated output off: a refit on the last {self._filled} samples '
                           f'lowers its squared error {ratio[0]:.3g} times (statistic '
                           f'{statistic[0]:.3g} > {limit[0]:.3g})' if contradicted[0] else '')
            self.coverage_reason = (
                f'{UNDERSTATED}: the last {self._filled} samples determine the '
                f'parameters up to {math.sqrt(understated[0]):.3g} times less well than it says'
                if understated[0] > UNDERSTATEMENT_LIMIT else '')
            self._follow_run(bool(contradicted[0]), bool(np.isfinite(statistic[0])))
            self._tail = (self._look_at_tail(a, b, covariance, float(statistic[0]))
                          if contradicted[0] else 0)
        # below the minimum: the verdict from before a gap, if any
        return [reason for reason in (self.reason, self.coverage_reason) if reason]

    def _follow_run(self, contradicted: bool, judged: bool) -> None:
        """Keep the run of contradictions and whether the model passed on a full window."""
        self._full_pass = not contradicted and judged and self._filled >= self.window
        if contradicted:
            if self._run_start < 0:
                self._run_start = self._recorded
                self._next_look = self.minimum
        elif judged:
            self._run_start = -1

    def _look_at_tail(self, a: np.ndarray, b: np.ndarray, covariance: np.ndarray | None,
                      statistic: float) -> int:
        r"""
        Return the samples kept since the run began if they alone contradict the model, else 0.

        A look of the run's second stage before a whole window of them is in
        (:meth:`contradicted_across`): the samples recorded since the run's first
        contradiction and kept (after a :meth:`gap`, those since the gap), judged at
        :math:`\alpha/J` (:func:`tail_looks`), once they are ``minimum`` and then each time
        they have doubled. After a change the first contradicted window still holds the old
        plant's samples, whose fit the refit must share; the samples after it are the new
        plant's alone, and a change that moves the simulated output little shows in a few
        hundred of them (tracking plant (4, 5)). Where they are the whole kept window
        (after a gap), the check's own ``statistic`` is their verdict, at the lower level.
        """
        second = min(self._filled, self._recorded - self._run_start)
        if not (self.looks_at_tail and self.passed and self._run_start >= 0
                and self._next_look <= second < self.window):
            return 0
        self._next_look = 2 * second
        level = FALSE_ALARM / tail_looks(self.minimum, self.window)
        if second == self._filled:
            return second if statistic > chi2_quantile(level, self.order + self.lags.size) else 0
        rows = self._rows[self._end - second:self._end]
        contradicted = judge(
            rows[None, :, 0], rows[None, :, 1:], a[None], b.reshape(1, *self.lags.shape),
            self.lags, false_alarm=level,
            covariance=None if covariance is None else covariance[None])[3]
        return second if contradicted[0] else 0

    def vouch(self) -> None:
        """
        Take the estimator's word that its model passed every check at the last verdict.

        Where that verdict passed the model on a full window, the model is ``passed``: a
        contradiction of it from then on is evidence of a change (:meth:`contradicted_twice`).
        The check alone is not enough: a model it passes while another check names it (a
        stability projection on most updates, the model of a closed loop) is no model of
        the plant to judge changes by.
        """
        self.passed = self.passed or self._full_pass

    def contradicted_twice(self) -> int:
        r"""
        Return the samples of a second window that contradicts a model that had passed, else 0.

        The evidence of a plant change: a model that passed the check on a full window,
        and every other check (:meth:`vouch`), since the last :meth:`clear` (``passed``: a
        model that never did, a structure too poor for the plant, is never judged changed
        by this), contradicted at every check since the first of a run, and contradicted
        again on samples all recorded after that first check's window ended: two disjoint
        windows contradict it, with no check passing in between. The second is either a
        whole window, once one starts after the run's first check, or before that the
        samples kept since then alone (since a :meth:`gap`, if one came after it;
        :meth:`_look_at_tail`, at most J looks at :math:`\alpha/J` each). Under a plant
        that does not change, the verdicts of disjoint samples are those of independent
        noise: a run starts at a given check at most at the rate :math:`\alpha` =
        ``FALSE_ALARM``, its looks at the tail contradict together at most at
        :math:`\alpha`, its first whole disjoint window at most at :math:`\alpha`, so that a
        change comes of a given check at most at :math:`2\alpha^2`, and with a check every c
        samples at most :math:`2\alpha^2/c` per sample (:func:`change_rate`; rpem, c =
        ``rules.VALIDITY_PERIOD`` = 100: 2e-6, 0.2 per 100,000 samples). The second
        window's samples are all after the change: it was there before the first
        contradicted window ended.
        """
        if not self.passed:
            return 0
        return self.contradicted_across() or (self._tail if self._judged else 0)

    def contradicted_across(self) -> int:
        """
        Return the samples of the window if two disjoint windows contradict the model, else 0.

        :meth:`contradicted_twice` without its ``passed`` and its looks at the run's tail:
        the run of contradictions (no check passing in between) reaches back past the
        current window's start, whether or not a model passed before (rpem, while a change
        is pending: its fits blend another plant; a look at a short tail would cut them to
        its few samples on the evidence of a new model still settling). :meth:`new_run`
        starts the count again. The current verdict must be of a whole window of the
        samples kept now (``judged``): after a :meth:`gap` the verdict of the samples
        before it holds, and the few samples since would otherwise be a second window that
        no check judged (an outlier refused in a run of contradictions reported a change at
        the next period, the run's one verdict counted twice), or, judged, a short one
        judged again at alpha at every check while the window refills, more looks than
        the bound allows.
        """
        if not (self.reason and self._run_start >= 0 and self._judged
                and self._filled == self.window):
            return 0
        if self._recorded - self._filled < self._run_start:
            return 0
        return self._filled

    def new_run(self) -> None:
        """Count contradictions afresh from the next check (the samples and verdict stay)."""
        self._run_start = -1
        self._tail = 0

    def state_items(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Return (arrays, scalars) of the window for a snapshot (fixed shapes)."""
        rows = np.zeros((self.window, self._rows.shape[1]))
        if self._filled:
            rows[:self._filled] = self._rows[self._end - self._filled:self._end]
        return ({'simulation_rows': rows},
                {'simulation_filled': self._filled, 'simulation_since': self._since,
                 'simulation_reason': self.reason,
                 'simulation_coverage_reason': self.coverage_reason,
                 'simulation_judged': self._judged,
                 'simulation_statistic': self.statistic,
                 'simulation_recorded': self._recorded, 'simulation_passed': self.passed,
                 'simulation_full_pass': self._full_pass,
                 'simulation_run_start': self._run_start,
                 'simulation_next_look': self._next_look, 'simulation_tail': self._tail})

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
        self.coverage_reason = str(scalars.get('simulation_coverage_reason', ''))
        self._judged = bool(scalars['simulation_judged'])
        self.statistic = float(scalars['simulation_statistic'])
        # a snapshot from before: no run of contradictions, not passed
        self._recorded = int(scalars.get('simulation_recorded', filled))
        self.passed = bool(scalars.get('simulation_passed', False))
        self._full_pass = bool(scalars.get('simulation_full_pass', False))
        self._run_start = int(scalars.get('simulation_run_start', -1))
        # from before the looks at the run's tail: the next due at once, no verdict of one
        self._next_look = int(scalars.get('simulation_next_look', self.minimum))
        self._tail = int(scalars.get('simulation_tail', 0))


def tail_looks(minimum: int, window: int) -> int:
    """
    Return J, the most looks a run takes at its tail (:meth:`SimulationWindow._look_at_tail`).

    Its lengths: from ``minimum``, each at least twice the last, below ``window``. At least
    1 (the divisor of alpha).
    """
    looks, length = 0, minimum
    while length < window:
        looks, length = looks + 1, 2 * length
    return max(looks, 1)


def change_rate(period: int) -> float:
    r"""
    Return the most changes a sample that :meth:`SimulationWindow.contradicted_twice` reports.

    Under no change, with a check every ``period`` samples: :math:`2\alpha^2`/period (a run
    starts at most at alpha; its looks at its tail and its first disjoint window contradict
    at most at alpha each), the share of the stated false-alarm rate the estimator gives
    this evidence (rpem: 2e-6 with a check every 100 samples, a fifth of
    ``change_detection.FALSE_ALARM``).
    """
    return 2.0 * FALSE_ALARM ** 2 / period


def simulation_reasons(window: SimulationWindow | None, theta: np.ndarray, order: int,
                       covariance: Callable[[], np.ndarray | None] | None = None,
                       count: Callable[[], float | None] | None = None) -> list[str]:
    """
    Return the check's reason for a model ``theta`` laid out [a, b, ...] (``[]``: none kept).

    The a's (A, or F of an output-error model) are its first ``order`` entries and the b's
    follow, input by input; what comes after them (the C of an ARMAX model) is the noise
    model, which the simulated output does not use. ``covariance`` gives theta's (None: not
    known), of which the [a, b] block counts the estimate's own error (:func:`check`); it is
    asked for only when the check runs (a sandwich or HAC covariance costs a solve).
    ``count`` gives the samples the estimate rests on, where the covariance is of the
    output-error criterion the check's gradient is of (rpem's ``oe``): that covariance is
    then judged against the window's information too (None: not judged).
    """
    if window is None:
        return []
    size = order + window.lags.size
    known = samples = None
    if covariance is not None and window.judging():
        known = covariance()
        known = None if known is None else known[:size, :size]
        samples = None if count is None else count()
    return window.reasons(theta[:order], theta[order:size], known, samples)


__all__ = ['BLOCK', 'CHECK_PERIOD', 'FALSE_ALARM', 'SAMPLES_PER_PARAMETER', 'SETTLING_EXCUSE',
           'UNDERSTATED', 'UNDERSTATEMENT_LIMIT', 'WINDOW', 'SimulationWindow', 'block_recursion',
           'change_rate', 'check', 'input_drive', 'judge', 'numerator_lags', 'refit',
           'settled_statistic', 'simulate', 'simulation_reasons', 'state_count', 'tail_looks',
           'understatement', 'window_length']
