r"""
Online residual tests: whether the data contradict the estimator's model now.

Each estimator's model says that one residual is white and uncorrelated with
past inputs: the equation error for ARX (``rls``), the output error for an
output-error model with white noise (``bcrls``, Ding et al. 2006), the
innovation for ARMAX. For a prediction-error output-error model the noise
may be coloured, and only the cross-correlation with past inputs tests the
model (open loop). :class:`AdequacyMonitor` runs these tests over an
exponentially weighted recent window, with thresholds from the chi-square
null distribution (Ljung, System Identification, 2nd ed., sec. 16.6) at a
stated false-alarm rate, and hysteresis. docs/trust.md has the derivation
and the measured false-alarm rate and power.
"""

from __future__ import annotations

import math
from typing import Any, Callable

import numpy as np

from bcid_ros.estimators.adequacy_state import MonitorState, MonitorStates
from bcid_ros.estimators.lagged import decayed_weights, effective_size, PlantCursors
from bcid_ros.estimators.residual_statistics import (
    chi2_quantile, chi2_survival, covariance_factors, cross_statistics, levinson,
    prewhitening_filter, settling_known, settling_sums, whiteness_statistic)

#: The monitor, its state and its settings; the chi-square tails and the Levinson
#: recursion of :mod:`~bcid_ros.estimators.residual_statistics` are kept importable here.
__all__ = ['AdequacyMonitor', 'MonitorState', 'MODEL_TESTS', 'LAGS', 'MIN_WINDOW', 'MAX_WINDOW',
           'SAMPLES_PER_LAG', 'HYSTERESIS', 'PREWHITENING_ORDER', 'COLOUR_LAGS', 'BLOCK',
           'CHECKS_PER_WINDOW', 'default_window', 'chi2_quantile', 'chi2_survival', 'levinson']

#: The tests of each kind of model (docs/trust.md): (whiteness, residual may be coloured).
MODEL_TESTS = {
    'arx': (True, False),    # rls: white equation error
    'oe': (False, True),     # prediction-error OE: cross-correlation only, any noise colour
    'oe_white': (True, False),  # bcrls: white output error (Ding 2006)
    'armax': (True, False),  # white innovation
}
#: Default number of lags M of both tests.
LAGS = 10
#: Fewest effective samples a short record is judged on (:meth:`AdequacyMonitor.short_reasons`),
#: with N // SAMPLES_PER_LAG lags (2 at 50 samples).
SHORT_MINIMUM = 50
#: The default window is the estimator's memory 1/(1 - lambda), clipped to this range...
MIN_WINDOW = 200
#: ...(see MIN_WINDOW).
MAX_WINDOW = 1000
#: A window must give at least this many effective samples per lag.
SAMPLES_PER_LAG = 20
#: The alarm goes on at a p-value this many times below the one at which it goes off.
HYSTERESIS = 4.0
#: Order of the AR prewhitening filter of a coloured residual (model 'oe').
PREWHITENING_ORDER = 2
#: Lags of the prewhitened residual's own colour kept in the cross test's variance ('oe').
COLOUR_LAGS = 3
#: Samples are kept in lists and added to the moments this many at a time.
BLOCK = 128
#: The tests (about 150 function calls) run every so many blocks: as many as fit in
#: half a window (at least one), and at the first block with a full enough window.
CHECKS_PER_WINDOW = 2
#: Every plant, as rows (a slice: views, not copies).
_ALL = slice(None)


def default_window(forgetting_factor: float) -> float:
    """Return the default window: the memory 1/(1 - lambda) within [MIN_WINDOW, MAX_WINDOW]."""
    if forgetting_factor >= 1.0:
        return float(MAX_WINDOW)
    return float(min(max(1.0 / (1.0 - forgetting_factor), MIN_WINDOW), MAX_WINDOW))


class AdequacyMonitor(MonitorStates):
    r"""
    Whiteness and input cross-correlation tests of a residual over a recent window.

    The residual :math:`\varepsilon_t` and the inputs :math:`u_t` are kept as
    exponentially weighted lagged moments (weights :math:`w_t = \mu^{T-t}`,
    :math:`\mu = 1 - 1/W`, W the ``window``),
    :math:`\hat R_{xy}(k) = \sum_t w_t x_t y_{t-k} / \tau`,
    :math:`\tau = \sum w_t`, whose variance is that of a mean over the
    effective sample size :math:`N = \tau^2 / \sum w_t^2` (about 2W). Every
    ``BLOCK`` samples, once :math:`N \ge` ``SAMPLES_PER_LAG`` M:

    * **whiteness** (models 'arx', 'oe_white', 'armax'): with
      :math:`\hat\rho_k = \hat R_\varepsilon(k) / \hat R_\varepsilon(0)`,

      .. math:: Q_0 = N \sum_{k=1}^{M} \hat\rho_k^2 \sim \chi^2(M)

      (Ljung, System Identification, 2nd ed., eq. (16.63));
    * **cross-correlation with input i**, lags k = 1..M (past inputs: u(t)
      itself is correlated with :math:`\varepsilon(t)` in closed loop under a
      controller with a direct term, even for the right model), with
      :math:`r_k = \hat R_{\tilde\varepsilon \tilde u_i}(k)`,

      .. math::

          Q_i = N\, r^T P^{-1} r \sim \chi^2(M), \qquad
          P_{ab} = \sum_{|j| \le J} \kappa_j \hat R_{\tilde\varepsilon}(j)\,
              \hat R_{\tilde u_i}(j - a + b),

      Ljung's eq. (16.65)-(16.66) with :math:`P = \sigma^2 R_u` (J = 0, no
      filter) when the residual is white, so that coloured inputs (held PRBS,
      low-pass) are handled. For a residual that may be coloured (model
      'oe') both series are first filtered by the AR(``PREWHITENING_ORDER``)
      whitening filter of the residual, fitted from its autocovariances,
      and J = ``COLOUR_LAGS`` lags of the whitened residual's remaining colour
      enter P with Bartlett weights :math:`\kappa_j = 1 - |j|/(J + 1)`.

    **The estimate's own error** (``num_parameters`` p > 0). The residual of an
    estimated model is :math:`\varepsilon = v + \psi^T\tilde\theta`, so
    :math:`r = r_v + G\tilde\theta` with :math:`G = \overline{\tilde u(t-k)\tilde\psi^T(t)}`
    (Ljung, sec. 16.6), and with C the covariance of the estimate the cross
    test uses

    .. math:: P + N\,G\,C\,G^T

    (:func:`~bcid_ros.estimators.residual_statistics.parameter_term`): still
    :math:`\chi^2(M)` under the null. The estimator records its gradient
    :math:`\psi(t)` with each sample and gives C (``parameter_covariance``)
    when the tests run. An OE model under coloured noise is consistent but not
    efficient: at a high SNR its estimation error, which the prewhitening
    does not shrink as it shrinks the noise, alone fails the plain test
    (docs/trust.md). With a whiteness test (``oe_white``, :attr:`settling`)
    the residual is that of an estimate that settles,
    :math:`\psi^T(t)\tilde\theta(t)`: C is read at every block, the gradients
    are taken to :math:`\tilde\psi = L^T\psi` (:math:`LL^T = C`), and both
    tests take one :math:`\xi \sim N(0, I)` for the window (whiteness:
    :func:`~bcid_ros.estimators.residual_statistics.profiled_whiteness`).

    **Storage.** Each sample is kept as the row
    :math:`z(t) = [e(t) \ldots e(t-E), u_1(t-1) \ldots u_1(t-U), \ldots]` with
    the lags the tests need, and the monitor keeps :math:`\sum_t w_t z z^T`:
    every product of a test, and every product of the filtered series (a
    quadratic form in f), is then exact. Lagged moments
    :math:`\hat R(k)` would shift the weights by k between two lags; a smooth
    input's nearly singular :math:`R_u` and a strongly coloured residual's
    cancelling filter amplify that into false alarms (docs/trust.md).

    The worst lag of a test is the one with the largest standardised
    correlation (:math:`|\hat\rho_k|`, or :math:`|r_k|/\sqrt{P_{kk}}`); the reason
    gives it with its correlation coefficient.

    **Thresholds.** With T tests and the stated ``false_alarm`` rate
    :math:`\alpha`, each test has :math:`\alpha_T = 1 - (1-\alpha)^{1/T}`. A
    test's alarm goes off at a check where :math:`Q < \chi^2_{M,1-\alpha_T}`
    and on where :math:`Q > \chi^2_{M,1-\alpha_T/H}` (H = ``HYSTERESIS``), so it
    does not flicker; an alarm on at a check has :math:`Q` above the lower
    threshold, so under the null the monitor is in alarm at any moment with
    probability at most :math:`\alpha` (docs/trust.md measures it). An alarm
    clears when the window has forgotten the data that raised it.

    **Plants.** With ``plants=K`` every result has a leading plant axis and
    each plant keeps its own cursor: :meth:`record_rows` takes the samples
    of the plants that step now (in a batched estimator a plant whose sample
    is missing or refused, whose regressor refills, or which is still in its
    warm-up does not), and a plant's block is added and its tests run when
    its own ``BLOCK`` samples are in. Plant k's decisions (alarms, reasons,
    ``ready``, ``checks``) are those of one monitor fed plant k's samples,
    exactly, and its statistics equal them within rounding
    (test/test_trust_plants.py). The plants whose blocks complete together
    (in the common case all of them) are added and tested in one batched
    call. :meth:`plant_state` and :meth:`load_plant` move one plant to and
    from a single-plant monitor's :meth:`get_state`; :meth:`clear` restarts
    plants.

    Parameters
    ----------
    num_inputs : int
        r, the number of inputs.
    model : str
        One of :data:`MODEL_TESTS`: which residual the model says is white.
    lags : int
        M, the lags of both tests.
    window : float, optional
        W, the time constant of the window in samples (>= SAMPLES_PER_LAG M / 2).
        None: :func:`default_window` of ``forgetting_factor``.
    forgetting_factor : float
        The estimator's :math:`\lambda`, for the default window.
    false_alarm : float
        :math:`\alpha` in (0, 0.5): the largest probability, under the null,
        that the monitor is in alarm at a given moment.
    plants : int, optional
        K: residuals ``(K,)`` and inputs ``(K, r)`` (:meth:`record`, every
        plant) or ``(R,)`` and ``(R, r)`` (:meth:`record_rows`), results per
        plant. None: one plant, a float residual and inputs ``(r,)``.
    input_names : sequence of str, optional
        Names of the inputs in the reasons (default u1, u2, ...).
    num_parameters : int
        p >= 0, the length of the gradient :math:`\psi(t)` recorded with each
        sample for the parameter term; 0: no term (the plain tests).
    parameter_covariance : callable, optional
        With p > 0: called when the tests run (with a whiteness test: when
        a block is added) with the plants concerned, an int array ``(R,)``
        (one plant: ``[0]``), it returns the covariance C of their estimates
        in the units of :math:`\psi`, ``(R, p, p)`` (one plant: ``(p, p)``),
        or None; a plant whose C is not finite, or None, is tested (or its
        block is added) without the term.

    Raises
    ------
    ValueError
        If a setting is out of range.

    """

    def __init__(self, *, num_inputs: int, model: str = 'arx', lags: int = LAGS,
                 window: float | None = None, forgetting_factor: float = 1.0,
                 false_alarm: float = 0.01, plants: int | None = None,
                 input_names: Any = None, num_parameters: int = 0,
                 parameter_covariance: Callable[[np.ndarray], Any] | None = None) -> None:
        if model not in MODEL_TESTS:
            raise ValueError(f'model must be one of {", ".join(MODEL_TESTS)}; got {model!r}')
        if not (isinstance(num_inputs, int) and num_inputs >= 0):
            raise ValueError(f'num_inputs must be an integer >= 0; got {num_inputs!r}')
        if not (isinstance(lags, int) and lags >= 1):
            raise ValueError(f'lags must be an integer >= 1; got {lags!r}')
        if not 0.0 < forgetting_factor <= 1.0:
            raise ValueError(f'forgetting_factor must be in (0, 1]; got {forgetting_factor!r}')
        #: Whether the window is the estimator's memory, and follows a new forgetting factor.
        self.window_follows = window is None
        window = default_window(forgetting_factor) if window is None else float(window)
        if not 0.5 * SAMPLES_PER_LAG * lags <= window < math.inf:
            raise ValueError(f'window must be at least {0.5 * SAMPLES_PER_LAG * lags:g} '
                             f'samples (SAMPLES_PER_LAG / 2 per lag); got {window!r}')
        if not 0.0 < false_alarm < 0.5:
            raise ValueError(f'false_alarm must be in (0, 0.5); got {false_alarm!r}')
        if plants is not None and not (isinstance(plants, int) and plants >= 1):
            raise ValueError(f'plants must be None or an integer >= 1; got {plants!r}')
        names = ([f'u{i + 1}' for i in range(num_inputs)] if input_names is None
                 else [str(name) for name in input_names])
        if len(names) != num_inputs:
            raise ValueError(f'input_names must have num_inputs = {num_inputs} names; '
                             f'got {len(names)}')
        if not (isinstance(num_parameters, int) and num_parameters >= 0):
            raise ValueError(f'num_parameters must be an integer >= 0; got {num_parameters!r}')
        if parameter_covariance is not None and not callable(parameter_covariance):
            raise ValueError('parameter_covariance must be None or a callable; '
                             f'got {parameter_covariance!r}')
        self.num_parameters = num_parameters
        self._covariance_of = parameter_covariance
        self.num_inputs, self.model, self.lags = num_inputs, model, lags
        self.false_alarm, self.plants = false_alarm, plants
        self.input_names = tuple(names)
        self.whiteness, self.coloured = MODEL_TESTS[model]
        #: Whether the estimate's error enters the whiteness test as well (a whiteness test and
        #: p > 0): the covariance is then read at every block, along the window (docs/trust.md).
        self.settling = self.whiteness and num_parameters > 0
        self._filter_order = PREWHITENING_ORDER if self.coloured else 0
        self._colour_lags = COLOUR_LAGS if self.coloured else 0
        # tests: whiteness (if any), then one per input
        self.num_tests = int(self.whiteness) + num_inputs
        per_test = 1.0 - (1.0 - false_alarm) ** (1.0 / max(self.num_tests, 1))
        #: the statistic's thresholds: the alarm goes off below the first, on above the second
        self.thresholds = (chi2_quantile(per_test, lags),
                           chi2_quantile(per_test / HYSTERESIS, lags))
        # each stored row is z(t) = [e(t) ... e(t - E), u1(t - 1) ... u1(t - U), u2(t - 1) ...]
        # and the monitor keeps sum_t w_t z(t) z(t)': every product the tests need, exactly
        # (docs/trust.md: the shift of the weights between lags, which lagged moments
        # R(k) ignore, is amplified by a smooth input's R_u^-1 and a whitening filter)
        q, colour = self._filter_order, self._colour_lags
        self._residual_lags = max(lags if self.whiteness else 0, colour + q)
        self._input_lags = lags + colour + q
        self._set_window(window)
        # psi(t - m), m = 0..q, to filter the gradient as the residual (the parameter term),
        # and m = 0..M for the whiteness test's term
        self._gradient_history = max(q, lags if self.settling else 0)
        self._plants = 1 if plants is None else plants
        self._history = max(self._residual_lags, self._input_lags)
        # z(t)[j] = channel _channels[j] at t - _lags[j]: e at lags 0..E, then each u_i at 1..U
        self._lags = np.concatenate([np.arange(self._residual_lags + 1)] + [
            np.arange(1, self._input_lags + 1)] * num_inputs)
        self._channels = np.repeat(np.arange(1 + num_inputs),
                                   [self._residual_lags + 1] + [self._input_lags] * num_inputs)
        # where z(t)[j] is in a plant's ring (history rows, then the block), flattened
        self._gather = ((self._history + np.arange(BLOCK)[:, None] - self._lags[None, :])
                        * (1 + num_inputs) + self._channels[None, :]).ravel()
        self.reset()

    def _set_window(self, window: float) -> None:
        """Take the window and what follows from it: the weights' decay and the test period."""
        self.window = window
        self._decay = 1.0 - 1.0 / window
        # w = mu^(age) of the rows of a block: the newest has weight 1
        self._block_weights = self._decay ** np.arange(BLOCK - 1, -1, -1, dtype=float)
        #: blocks between two runs of the tests (see CHECKS_PER_WINDOW)
        self.check_period = max(1, int(window / (CHECKS_PER_WINDOW * BLOCK)))

    def follow_forgetting_factor(self, forgetting_factor: float) -> None:
        """
        Take the estimator's new forgetting factor, changed while running.

        A window that is the estimator's memory (:func:`default_window`, the
        window not given) becomes that of the new factor; the sums so far keep
        their weights and decay with the new one from the next block on. A
        window given at construction stays.
        """
        if self.window_follows:
            self._set_window(default_window(forgetting_factor))

    def __repr__(self) -> str:
        return (f'AdequacyMonitor(num_inputs={self.num_inputs}, model={self.model!r}, '
                f'lags={self.lags}, window={self.window:g}, false_alarm={self.false_alarm:g}, '
                f'plants={self.plants})')

    # ------------------------------------------------------------ the stream
    def reset(self) -> None:
        """Forget the data and clear the alarms (of every plant)."""
        width, q = self._lags.shape[0], self._filter_order
        # the products the tests read, summed with the weights over the blocks added:
        # e(t - a) z(t)', a = 0..q, and u_i(t - a) u_i(t - b), a, b = 1..U
        self._residual_sums = np.zeros((self._plants, q + 1, width))
        self._input_sums = np.zeros((self._plants, self.num_inputs, self._input_lags,
                                     self._input_lags))
        # the last rows [e, u] (zeros at the start), then room for a block
        self._ring = np.zeros((self._plants, self._history + BLOCK, 1 + self.num_inputs))
        if self.plants is None:
            # sum w and sum w^2 over the blocks added
            self._weight: Any = 0.0
            self._squared_weight: Any = 0.0
            # the pending samples: residuals in a list, inputs in a buffer
            self._residuals: list[Any] = []
            self._inputs = np.zeros((BLOCK, 1, self.num_inputs))
        else:
            self._weight = np.zeros(self._plants)
            self._squared_weight = np.zeros(self._plants)
            # each plant's pending samples sit in its ring after the history rows
            self._cursors = PlantCursors(self._plants, BLOCK)
        self._reset_gradients()
        shape = (self._plants, self.num_tests)
        self._alarms = np.zeros(shape, dtype=bool)
        self._statistics = np.full(shape, np.nan)
        # the worst lag of each test and its correlation, at the last check
        self._worst = np.zeros(shape, dtype=np.intp)
        self._values = np.zeros(shape)
        self._checks = np.zeros(self._plants, dtype=np.int64)
        self._blocks = np.zeros(self._plants, dtype=np.int64)

    def _reset_gradients(self) -> None:
        """Forget the gradients (p > 0): their products with the inputs, their last rows."""
        count, p = self._plants, self.num_parameters
        if not p:
            self._gradient_sums = self._gradient_ring = self._gradients = None
            self._settling_sums = None
            return
        # sum_t w_t psi(t - m) u_i(t - a)': rows (m, j), columns (i, a), a = 1..U
        self._gradient_sums = np.zeros((count, (self._filter_order + 1) * p,
                                        self.num_inputs * self._input_lags))
        # sum_t w_t psi~(t) psi~(t - k)', k = 0..M (the whiteness test's term)
        self._settling_sums = (np.zeros((count, self.lags + 1, p, p)) if self.settling
                               else None)
        self._gradient_ring = np.zeros((count, self._gradient_history + BLOCK, p))
        # one plant: the pending gradients (K plants: in the ring after the history rows)
        self._gradients = np.zeros((BLOCK, 1, p)) if self.plants is None else None

    def clear(self, rows: Any) -> None:
        """Forget the data and clear the alarms of the plants ``rows``: a restart of those."""
        if self.plants is None:
            self.reset()
            return
        for array in (self._residual_sums, self._input_sums, self._ring, self._weight,
                      self._squared_weight, self._alarms, self._worst, self._values,
                      self._checks, self._blocks, self._gradient_sums, self._gradient_ring,
                      self._settling_sums):
            if array is not None:
                array[rows] = 0
        self._statistics[rows] = np.nan
        self._cursors.set(rows, 0)

    def record(self, residual: Any, inputs: Any, gradient: Any = None) -> None:
        r"""
        Add one sample of every plant: the residual the model says is white, and the inputs.

        ``residual`` is a float (one plant) or ``(K,)``; ``inputs`` ``(r,)`` or
        ``(K, r)`` (copied); ``gradient`` :math:`\psi(t)` ``(p,)`` or ``(K, p)``
        (copied), needed when ``num_parameters`` p > 0 and ignored otherwise.
        Every ``BLOCK`` samples the block is added and the tests run. K plants:
        :meth:`record_rows` of every plant.
        """
        if self.plants is not None:
            self.record_rows(_ALL, residual, inputs, gradient)
            return
        residuals = self._residuals
        self._inputs[len(residuals)] = inputs
        if self.num_parameters:
            self._gradients[len(residuals)] = gradient
        residuals.append(residual)
        if len(residuals) == BLOCK:
            ring = self._ring
            ring[:, self._history:, 0] = np.reshape(residuals, (BLOCK, 1)).T
            ring[:, self._history:, 1:] = np.swapaxes(self._inputs, 0, 1)
            if self.num_parameters:
                self._gradient_ring[:, self._gradient_history:] = np.swapaxes(
                    self._gradients, 0, 1)
            self._residuals = []
            self._add_blocks(_ALL)
            self._check(_ALL)

    def record_rows(self, rows: Any, residual: Any, inputs: Any, gradients: Any = None) -> None:
        r"""
        Add one sample of each plant in ``rows`` (K plants); the others do not step now.

        Each plant keeps its own blocks: a plant's block is added and its tests
        run when its own ``BLOCK`` samples are in, as for one plant fed that
        plant's samples. The plants whose blocks fill together are added and
        tested in one batched call.

        Parameters
        ----------
        rows : numpy.ndarray or slice
            The plants that record now: distinct indices, or a slice.
        residual : numpy.ndarray, shape ``(R,)``
            Their residuals, in the order of ``rows``.
        inputs : numpy.ndarray, shape ``(R, r)``
            Their inputs at the same time (copied).
        gradients : numpy.ndarray, shape ``(R, p)``, optional
            Their gradients :math:`\psi(t)` (copied): needed when
            ``num_parameters`` p > 0, ignored otherwise.

        Raises
        ------
        ValueError
            If the monitor is of one plant (``plants=None``).

        """
        if self.plants is None:
            raise ValueError('record_rows needs plants=K; one plant records with record()')
        cursors, ring = self._cursors, self._ring
        plants, positions = cursors.place(rows)
        slots = self._history + positions
        ring[plants, slots, 0] = residual
        ring[plants, slots, 1:] = inputs
        if self.num_parameters:
            self._gradient_ring[plants, self._gradient_history + positions] = gradients
        full = cursors.advance(plants)
        if full is not None:
            self._add_blocks(full)
            self._check(full)

    def _add_blocks(self, plants: Any, rows: int = BLOCK) -> None:
        """
        Add the full blocks of ``plants``, as rows z(t) with their lags, to their sums.

        ``rows`` < BLOCK: only the block's first rows (a short record's pending samples, on
        a probe: :meth:`short_reasons`); the others weigh nothing.
        """
        history = self._history
        ring = self._ring[plants]
        count = ring.shape[0]
        z = ring.reshape(count, -1).take(self._gather, axis=1).reshape(count, BLOCK, -1)
        if not np.isfinite(z).all():  # a non-finite sample counts as zero
            z = np.where(np.isfinite(z), z, 0.0)
        block_weights = self._block_weights
        if rows < BLOCK:
            block_weights = np.concatenate([block_weights[BLOCK - rows:], np.zeros(BLOCK - rows)])
        weighted = z * block_weights[:, None]
        first, q = 1 + self._residual_lags, self._filter_order
        decay = self._decay ** rows
        # S <- mu^BLOCK S + sum_t w_t x(t) y(t)'
        sums = self._residual_sums[plants]
        sums *= decay
        sums += np.swapaxes(weighted[:, :, :q + 1], -1, -2) @ z
        self._residual_sums[plants] = sums
        if self.num_inputs:
            # (K, r, BLOCK, U): the lags of each input
            lagged = np.moveaxis(z[:, :, first:].reshape(count, BLOCK, self.num_inputs, -1),
                                 2, 1)
            weighted = np.moveaxis(weighted[:, :, first:].reshape(lagged.shape[:1] + (
                BLOCK, self.num_inputs, -1)), 2, 1)
            sums = self._input_sums[plants]
            sums *= decay
            sums += np.swapaxes(weighted, -1, -2) @ lagged
            self._input_sums[plants] = sums
        if self.num_parameters and (self.num_inputs or self.settling):
            self._add_gradients(plants, z[:, :, first:], block_weights, decay)
        if self.plants is None:
            self._weight, self._squared_weight = decayed_weights(
                self._weight, self._squared_weight, rows, self._decay)
        else:  # element-wise with one plant's scalar factors: its weights bit for bit
            self._weight[plants], self._squared_weight[plants] = decayed_weights(
                self._weight[plants], self._squared_weight[plants], rows, self._decay)
        self._ring[plants, :history] = ring[:, BLOCK:]

    def _add_gradients(self, plants: Any, inputs: np.ndarray, block_weights: np.ndarray,
                       decay: float) -> None:
        """
        Add psi(t - m) u_i(t - a)' of the full blocks of ``plants`` (``inputs``: z's u lags).

        With :attr:`settling`, psi is first taken to psi~ = L' psi, L L' the covariance
        C of the estimate now, and the lag products psi~(t) psi~(t - k)' are added too.
        """
        history, q = self._gradient_history, self._filter_order
        ring = raw = self._gradient_ring[plants]
        if not np.isfinite(ring).all():  # a non-finite gradient counts as zero
            ring = np.where(np.isfinite(ring), ring, 0.0)
        if self.settling:
            ring = ring @ self._covariance_factors(plants)
        # [psi(t), psi(t - 1) ... psi(t - q)] of each row t of the block: (R, BLOCK, (q + 1) p)
        lagged = np.concatenate([ring[:, history - m:history - m + BLOCK]
                                 for m in range(q + 1)], axis=2)
        # S <- mu^BLOCK S + sum_t w_t psi(t - m) u_i(t - a)'
        sums = self._gradient_sums[plants]
        sums *= decay
        sums += np.swapaxes(lagged * block_weights[:, None], -1, -2) @ inputs
        self._gradient_sums[plants] = sums
        if self.settling:
            self._settling_sums[plants] = settling_sums(
                self._settling_sums[plants] * decay, ring, block_weights, self.lags)
        self._gradient_ring[plants, :history] = raw[:, BLOCK:]

    def _covariance_factors(self, plants: Any) -> np.ndarray:
        """Return L ``(R, p, p)`` with L L' = C of ``plants`` now (zeros where C is unknown)."""
        rows = np.arange(self._plants)[plants]
        p = self.num_parameters
        covariance = None if self._covariance_of is None else self._covariance_of(rows)
        if covariance is None:
            return np.zeros((rows.shape[0], p, p))
        return covariance_factors(np.reshape(np.asarray(covariance, dtype=float),
                                             (rows.shape[0], p, p)))

    # ------------------------------------------------------------ the tests
    @property
    def effective_samples(self) -> Any:
        """Return N = (sum w)^2 / sum w^2 over the samples in the tests so far (per plant)."""
        return effective_size(self._weight, self._squared_weight)

    @property
    def ready(self) -> Any:
        """Whether the window holds enough samples for the tests (N >= SAMPLES_PER_LAG M)."""
        return self.effective_samples >= SAMPLES_PER_LAG * self.lags

    def ready_of(self, plant: int) -> bool:  # ready[k] would size all K plants to give one
        return bool(self.effective_samples_of(plant) >= SAMPLES_PER_LAG * self.lags)

    def effective_samples_of(self, plant: int) -> float:
        """Return plant k's :attr:`effective_samples` (without sizing the other plants)."""
        return float(np.reshape(self._sizes(plant), -1)[0])

    def _sizes(self, plants: Any) -> np.ndarray:
        """Return the effective sample sizes N of ``plants``, ``(R,)``."""
        if self.plants is None:
            return np.array([effective_size(self._weight, self._squared_weight)])
        return effective_size(self._weight[plants], self._squared_weight[plants])

    def _check(self, plants: Any) -> None:
        """Run the tests of the ready ``plants`` on the moments of their windows; move alarms."""
        self._blocks[plants] += 1
        if self.check_period > 1:
            # every check_period blocks, and at the first block a plant is ready
            due = (self._blocks[plants] % self.check_period == 0) | (self._checks[plants] == 0)
            if not due.all():
                if not due.any():
                    return
                plants = np.arange(self._plants)[plants][due]
        sizes = self._sizes(plants)
        ready = sizes >= SAMPLES_PER_LAG * self.lags
        if not ready.all():
            if not ready.any():
                return
            plants, sizes = np.arange(self._plants)[plants][ready], sizes[ready]
        self._checks[plants] += 1
        statistics, worst, values = self._statistics_now(plants, sizes)
        low, high = self.thresholds
        # hysteresis: on above the high threshold, off below the low one
        self._alarms[plants] = np.where(statistics > high, True,
                                        np.where(statistics < low, False, self._alarms[plants]))
        self._statistics[plants] = statistics
        self._worst[plants] = worst
        self._values[plants] = values

    def _statistics_now(self, plants: Any, sizes: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return Q, the worst lag and its correlation of every test of ``plants``, ``(R, T)``."""
        inputs, first, q = self.num_inputs, 1 + self._residual_lags, self._filter_order
        weight = self._weight if self.plants is None else self._weight[plants]
        scale = np.reshape(weight, (-1, 1, 1))
        # means: e(t - a) z(t)', a = 0..q, and u_i(t - a) u_i(t - b)
        residual = self._residual_sums[plants] / scale
        count = residual.shape[0]
        shape = (count, self.num_tests)
        statistics, worst, values = np.empty(shape), np.empty(shape, dtype=np.intp), np.empty(
            shape)
        if self.whiteness:
            settling = (None if not self.settling
                        else self._settling_sums[plants] / scale[..., None])
            statistics[:, 0], worst[:, 0], values[:, 0] = whiteness_statistic(
                residual[:, 0, :first], self.lags, sizes, settling)
        if inputs:
            whitening = (prewhitening_filter(residual[:, 0, :q + 1], q) if q
                         else np.ones((count, 1)))
            # e(t - a) u_i(t - b): (K, r, q + 1, U)
            cross = np.moveaxis(residual[:, :, first:].reshape(count, q + 1, inputs, -1),
                                2, 1)
            gradient, covariance = self._parameter_moments(plants, scale)
            tests = slice(int(self.whiteness), None)
            statistics[:, tests], worst[:, tests], values[:, tests] = cross_statistics(
                residual[:, :, :first], self._input_sums[plants] / scale[..., None], cross,
                whitening, self.lags, sizes, self._colour_lags, gradient, covariance)
        return statistics, worst, values

    def _parameter_moments(self, plants: Any, scale: np.ndarray
                           ) -> tuple[np.ndarray | None, np.ndarray | None]:
        """Return the means of psi(t - m) u_i(t - a) ``(R, r, q + 1, p, U)`` and C, or Nones."""
        p = self.num_parameters
        if not p or self._covariance_of is None:
            return None, None
        rows = np.arange(self._plants)[plants]
        if self.settling:  # psi~ = L' psi along the window: theta~ = L xi, xi of covariance I
            power = self._residual_sums[plants][:, 0, 0] / scale[:, 0, 0]
            known = settling_known(self._settling_sums[plants] / scale[..., None], power)
            covariance = np.where(known[:, None, None], np.eye(p), np.nan)
        else:
            covariance = self._covariance_of(rows)
            if covariance is None:
                return None, None
            covariance = np.reshape(np.asarray(covariance, dtype=float), (rows.shape[0], p, p))
        means = self._gradient_sums[plants] / scale
        # (R, (q + 1) p, r U) -> (R, r, q + 1, p, U)
        means = means.reshape(rows.shape[0], self._filter_order + 1, p, self.num_inputs,
                              self._input_lags)
        return np.moveaxis(means, 3, 1), covariance

    def short_reasons(self, plant: int | None = None) -> tuple[str, ...] | None:
        """
        Return the tests' reasons on what a window not yet :attr:`ready` holds, or None.

        A short record never fills the window (148 samples against 200 in one), so it
        is judged on what it has: once the samples in the sums and the pending ones come to
        N >= SHORT_MINIMUM, the tests run on all of them with M' = min(M, N // SAMPLES_PER_LAG)
        lags (20 samples a lag, as a full window) at the same false-alarm rate (docs/trust.md
        states the power). On a probe (a one-plant copy of plant k's state): this monitor
        changes nothing, and the full window's tests take over once it is ready.
        """
        state = self.get_state() if self.plants is None else self.plant_state(plant)
        pending = state.pending_residuals.shape[0]
        weight, squared = state.weights
        weight, squared = decayed_weights(weight, squared, pending, self._decay)
        size = effective_size(weight, squared)
        if not size >= SHORT_MINIMUM:
            return None
        lags = min(self.lags, int(size // SAMPLES_PER_LAG))
        covariance = self._covariance_of
        if covariance is not None and self.plants is not None:
            covariance = lambda rows: self._covariance_of(np.array([plant]))  # noqa: E731
        probe = AdequacyMonitor(num_inputs=self.num_inputs, model=self.model, lags=self.lags,
                                window=self.window, false_alarm=self.false_alarm,
                                input_names=self.input_names,
                                num_parameters=self.num_parameters,
                                parameter_covariance=covariance)
        probe.set_state(state)
        if pending:
            slots = slice(probe._history, probe._history + pending)
            probe._ring[0, slots, 0] = state.pending_residuals[:, 0]
            probe._ring[0, slots, 1:] = state.pending_inputs[:, 0]
            probe._ring[0, probe._history + pending:] = 0.0
            if self.num_parameters:
                q = probe._gradient_history
                probe._gradient_ring[0, q:q + pending] = state.pending_gradients[:, 0]
                probe._gradient_ring[0, q + pending:] = 0.0
            probe._add_blocks(_ALL, pending)
        probe.lags = lags
        per_test = 1.0 - (1.0 - self.false_alarm) ** (1.0 / max(self.num_tests, 1))
        probe.thresholds = (chi2_quantile(per_test, lags),) * 2
        probe._checks[:] = 0
        probe._check(_ALL)
        return probe.reasons_of(0)

    # ------------------------------------------------------------ the results
    def reasons_of(self, plant: int) -> tuple[str, ...]:
        """Return the reasons of plant k's alarms now (one plant: k = 0)."""
        reasons = []
        for test in np.flatnonzero(self._alarms[plant]):
            lag, value = int(self._worst[plant, test]), float(self._values[plant, test])
            if self.whiteness and test == 0:
                reasons.append(f'residual not white (lag {lag}: {value:.2f})')
            else:
                name = self.input_names[test - int(self.whiteness)]
                reasons.append(f'residual correlated with {name} at lag {lag} ({value:.2f})')
        return tuple(reasons)

    @property
    def reasons(self) -> Any:
        """Return the reasons of the alarms now: a tuple of str, or one per plant (a list)."""
        if self.plants is None:
            return self.reasons_of(0)
        return [self.reasons_of(k) for k in range(self._plants)]

    @property
    def alarm(self) -> Any:
        """Return whether any test is in alarm: a bool, or ``(K,)`` bools."""
        alarm = self._alarms.any(axis=-1)
        return bool(alarm[0]) if self.plants is None else alarm

    @property
    def statistics(self) -> np.ndarray:
        """Return Q of each test at the last check, ``(T,)`` or ``(K, T)`` (NaN before it)."""
        return self._statistics[0].copy() if self.plants is None else self._statistics.copy()

    @property
    def checks(self) -> Any:
        """Count the checks made (one per BLOCK samples once ready): an int, or ``(K,)``."""
        return int(self._checks[0]) if self.plants is None else self._checks.copy()
