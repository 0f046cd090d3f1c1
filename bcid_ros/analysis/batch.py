"""
The structure search: one batch output-error model per order and dead time, validated.

Every candidate (order n, dead time d_i per input) is fitted by prediction-error
minimisation of the simulation error (:func:`bcid_ros.analysis.pem.fit_oe`, ARX
and refined-IV starts, then Gauss-Newton) on the estimation part of the record,
centred by its means, and judged on the validation part it has not seen. The
batch fit is efficient for white output noise and consistent for any open-loop
noise, so the order and the delays it finds are those of the data, not of an
online estimator's convergence. The dead times are searched over the full grid
for one or two inputs, and coordinate-wise (one input at a time, the others
held) for more (:func:`search_delays`).
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from typing import Any, Callable, Sequence

import numpy as np
from scipy import signal, stats

from bcid_ros.analysis import metrics
from bcid_ros.analysis.model import DiscreteModel
from bcid_ros.analysis.pem import fit_oe, oe_jacobian, simulate_oe, Structure

#: Level of the residual tests: a test passes when its p-value is >= this.
TEST_LEVEL = 0.01
#: Least-squares runs of one candidate's OE fit, from the ARX and the refined-IV
#: starts; the lower end wins. From one start only, the search took two thirds
#: of the time, but on the flexible robot arm of DaISy the sixth-order fit from
#: the lower start ended in a minimum with an undamped pole pair (validation fit
#: 89.8 % against 94.9 %; docs/analyze.md, *Speed*).
SEARCH_STARTS = 2
#: The least-squares solver of the search: Levenberg-Marquardt on the normal
#: equations, about 1.6 times faster than trust-region reflective over a
#: two-input grid with the same minima (docs/analyze.md, *Speed*).
SEARCH_SOLVER = 'lm'
#: The pole p of the factor (1 - p q^-1) by which an order-n fit's F starts the fit of
#: order n + 1 (with its B refitted): the same model at p's cancellation, so the fit of
#: order n + 1 ends no worse on the estimation part; several p, as the added pole may be
#: fast, slow or oscillating (a lamp-heated plate record: orders 3-6 fell into minima of
#: 34-61 % validation fit from the cold starts, against 76 % at order 3).
WARM_POLES = (0.0, 0.5, 0.9, -0.5)
#: A pole and a zero of one B_i closer than this (in the z-plane) are reported as a
#: near-cancelling pair: the model spends a pole and a zero on (almost) nothing.
NEAR_PAIR = 0.05
#: Up to this many inputs every combination of dead times is fitted; beyond,
#: the dead times are searched one input at a time (coordinate search).
FULL_GRID_INPUTS = 2
#: Most sweeps over the inputs of the coordinate search.
MAX_SWEEPS = 4


@dataclasses.dataclass(frozen=True)
class Record:
    """
    The samples, split into an estimation and a validation part.

    Parameters
    ----------
    y : numpy.ndarray, shape ``(N,)``
        Measured output.
    u : numpy.ndarray, shape ``(N, r)``
        Measured inputs.
    estimation : int
        Samples 0 ... estimation - 1 estimate, the rest validate.

    """

    y: np.ndarray
    u: np.ndarray
    estimation: int

    @property
    def num_inputs(self) -> int:
        """Return r."""
        return self.u.shape[1]

    @property
    def validation(self) -> int:
        """Return the number of validation samples."""
        return self.y.size - self.estimation

    @property
    def operating_point(self) -> np.ndarray:
        """Return ``[y0, u0_1, ..., u0_r]``, the means over the estimation part."""
        return np.concatenate([[self.y[:self.estimation].mean()],
                               self.u[:self.estimation].mean(axis=0)])

    def centred(self) -> tuple[np.ndarray, np.ndarray]:
        """Return (y - y0, u - u0) over the whole record."""
        point = self.operating_point
        return self.y - point[0], self.u - point[1:]

    @property
    def test_lags(self) -> int:
        """Return the lags of the residual tests: 20, fewer for a short validation part."""
        return metrics.whiteness_lags(self.validation)


@dataclasses.dataclass
class Candidate:
    """One fitted structure (order, dead time per input) and its validation figures."""

    order: int
    delays: tuple[int, ...]
    error: str | None = None
    parameter_names: tuple[str, ...] = ()
    theta: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    std: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    covariance: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 0)))
    model: DiscreteModel | None = None
    fit: float = float('nan')
    estimation_fit: float = float('nan')
    prediction_fit: float = float('nan')
    aic: float = float('nan')
    mdl: float = float('nan')
    whiteness_p: float = float('nan')
    cross_correlation_p: float = float('nan')
    stable: bool = False
    offset: float = 0.0
    evaluations: int = 0
    converged: bool = False
    redundancy: tuple[str, ...] = ()
    pole_zero_pairs: tuple[dict[str, Any], ...] = ()
    cross_correlation: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 0)))
    simulated: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    residual: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))

    @property
    def delay(self) -> int | list[int]:
        """Return the dead time as the JSON gives it: an integer for one input, else a list."""
        return self.delays[0] if len(self.delays) == 1 else list(self.delays)

    @property
    def delay_text(self) -> str:
        """Return the dead times for a table: ``2`` or ``2,0``."""
        return ','.join(map(str, self.delays))

    @property
    def usable(self) -> bool:
        """Return whether the model was fitted, is stable and simulates to a finite fit."""
        return self.error is None and self.stable and math.isfinite(self.fit)

    @property
    def white(self) -> bool:
        """Return whether the simulation error passes the whiteness test."""
        return self.usable and self.whiteness_p >= TEST_LEVEL

    @property
    def uncorrelated(self) -> bool:
        """Return whether the simulation error passes the test of no correlation with u."""
        return self.usable and self.cross_correlation_p >= TEST_LEVEL

    @property
    def redundant(self) -> bool:
        """Return whether the data say that a smaller structure describes this model."""
        return bool(self.redundancy)

    @property
    def criterion(self) -> float:
        """Return the MDL for ranking (inf when it is not finite)."""
        return self.mdl if math.isfinite(self.mdl) else math.inf

    def figures(self) -> dict[str, Any]:
        """Return the JSON figures of this candidate (non-finite numbers as null)."""
        if self.error is not None:
            return {'delay': self.delay, 'error': self.error}
        return {'delay': self.delay, 'fit': finite(self.fit),
                'estimation_fit': finite(self.estimation_fit),
                'prediction_fit': finite(self.prediction_fit), 'aic': finite(self.aic),
                'mdl': finite(self.mdl), 'whiteness_p': finite(self.whiteness_p),
                'cross_correlation_p': finite(self.cross_correlation_p),
                'stable': self.stable, 'redundant': list(self.redundancy),
                'pole_zero_pairs': list(self.pole_zero_pairs),
                'converged': self.converged}


def finite(value: float) -> float | None:
    """Return ``value`` as a float, or None (JSON null) when it is not finite."""
    value = float(value)
    return value if math.isfinite(value) else None


def warm_denominators(previous: Candidate | None) -> list[np.ndarray]:
    """Return the starts of order n + 1 from an order-n candidate: F (1 - p q^-1), WARM_POLES."""
    if previous is None or not previous.usable:
        return []
    # (the parameters start with a1 ... an, F's)
    denominator = np.concatenate(([1.0], previous.theta[:previous.order]))
    return [np.convolve(denominator, [1.0, -pole]) for pole in WARM_POLES]


def fit_candidate(record: Record, order: int, delays: Sequence[int],
                  feedthrough: bool = False, previous: Candidate | None = None) -> Candidate:
    r"""
    Fit the batch OE model of one structure and compute its validation figures.

    On the centred estimation part, :func:`~bcid_ros.analysis.pem.fit_oe`
    with its start-up transient and a constant output offset. Then, with
    :math:`\hat y_s` simulated from rest over the whole record (the start-up
    transient falls in the estimation part) and the simulation error
    :math:`\varepsilon = y - \hat y_s` on the validation part:

    * ``fit``: :math:`100(1 - \|\varepsilon\|/\|y - \bar y\|)`;
    * ``estimation_fit``: the same on the estimation part, of the fitted
      output (with its start-up transient): the criterion the fit minimised;
    * ``prediction_fit``: the same for the one-step prediction of the OE
      model with the AR model D of its estimation residual as noise model,
      :math:`y - \hat y(t|t-1) = D(q)\varepsilon(t)`;
    * ``aic``, ``mdl``: :math:`N\ln V + 2p` and :math:`N\ln V + p\ln N`,
      V the OE loss (mean squared simulation error) on the N estimation
      samples, p the parameters of F and the B_i;
    * ``whiteness_p``: Ljung-Box of ε (is the output noise white?);
    * ``cross_correlation_p``: ε against the present and past inputs, with
      the coloured noise and the fit's own parameter uncertainty in its
      covariance (:func:`~bcid_ros.analysis.metrics.cross_correlation_test`:
      are the dynamics right?).

    and ``redundancy`` (:func:`redundancy`). A structure the fit refuses
    (too few samples for it) is returned with its ``error``. ``previous``, a
    candidate of order n - 1, adds the starts of :func:`warm_denominators`.
    """
    structure = Structure(order, record.num_inputs, tuple(int(d) for d in delays), feedthrough)
    candidate = Candidate(order, structure.input_delay)
    y, u = record.centred()
    split = record.estimation
    try:
        result = fit_oe(y[:split], u[:split], structure, offset=True, starts=SEARCH_STARTS,
                        solver=SEARCH_SOLVER, denominators=warm_denominators(previous))
    except ValueError as error:
        candidate.error = str(error)
        return candidate
    denominator, rows = result.denominator, result.numerators
    if not feedthrough:
        rows = np.column_stack([np.zeros(rows.shape[0]), rows])
    candidate.model = DiscreteModel(denominator, rows, structure.input_delay)
    candidate.parameter_names = result.parameter_names
    candidate.theta, candidate.std = result.theta, result.std
    candidate.covariance = result.covariance
    candidate.stable = result.stable
    candidate.offset = result.offset
    candidate.evaluations, candidate.converged = result.evaluations, result.converged
    candidate.estimation_fit = result.fit(y[:split])
    candidate.redundancy = redundancy(structure, result.theta, result.covariance)
    candidate.pole_zero_pairs = near_pairs(structure, result.theta)
    simulated = simulate_oe(result.theta, u, structure) + result.offset
    error = y - simulated
    candidate.simulated = simulated[split:]
    candidate.residual = error[split:]
    candidate.fit = metrics.nrmse_fit(y[split:], candidate.simulated)
    candidate.aic, candidate.mdl = metrics.information_criteria(result.residual,
                                                                structure.num_parameters)
    if np.isfinite(error).all():
        noise, _ = metrics.ar_noise_model(result.residual,
                                          min(metrics.MAX_NOISE_ORDER, max(1, split // 20)))
        innovation = signal.lfilter(noise, [1.0], error)[split:]
        candidate.prediction_fit = metrics.nrmse_fit(y[split:], y[split:] - innovation)
        candidate.whiteness_p = metrics.ljung_box(candidate.residual, record.test_lags)[1]
        gradient = oe_jacobian(result.theta, u, structure)[split:] if candidate.stable else None
        tested = (candidate.residual, u, record.test_lags, gradient, result.covariance)
        candidate.cross_correlation_p = metrics.cross_correlation_test(*tested)[1]
        candidate.cross_correlation = metrics.cross_correlation(*tested)
    return candidate


def redundancy(structure: Structure, theta: np.ndarray,
               covariance: np.ndarray) -> tuple[str, ...]:
    """
    Return why a smaller structure describes the model as well, or () when none does.

    Two signs of over-parametrisation, each tested at ``TEST_LEVEL`` with
    the estimate's covariance (Ljung 1999, ch. 16, on pole-zero plots with
    confidence regions):

    * a **negligible first coefficient** b_i at lag d_i + 1 (|b| below
      z_{1 - level/2} standard deviations): the dead time of input i is
      longer than d_i, and the model spends a parameter on nothing;
    * a **pole cancelled by a zero** of every B_i: the difference p - z is
      within its uncertainty (:func:`_cancels`), so the pole is not needed to
      describe any input's response.
    """
    count = structure.num_parameters
    covariance = covariance[:count, :count]
    if not np.isfinite(covariance).all():
        return ('the covariance of the estimate is not finite: some parameters are not '
                'determined by the data',)
    reasons = []
    denominator, rows = structure.split(theta)
    std = np.sqrt(np.maximum(np.diagonal(covariance), 0.0))
    bound = stats.norm.ppf(1.0 - TEST_LEVEL / 2.0)
    width = structure.b_length
    for i in range(structure.num_inputs):
        first = structure.order + i * width
        if abs(theta[first]) < bound * std[first]:
            reasons.append(f'{structure.parameter_names()[first]} is within {bound:.2f} '
                           f'standard deviations of 0: the dead time of u{i + 1} is longer')
    poles, pole_gradients = _roots(denominator)
    cancelled = np.ones(poles.size, dtype=bool)
    for i in range(structure.num_inputs):
        zeros, zero_gradients = _roots(rows[i])
        found = np.zeros(poles.size, dtype=bool)
        columns = slice(structure.order + i * width, structure.order + (i + 1) * width)
        for j, pole in enumerate(poles):
            for zero, zero_gradient in zip(zeros, zero_gradients):
                gradient = np.zeros(count, dtype=complex)
                gradient[:structure.order] = pole_gradients[j, 1:]
                gradient[columns] -= zero_gradient
                found[j] |= _cancels(pole - zero, gradient, covariance)
        cancelled &= found
    reasons.extend(f'the pole {pole:.4g} is cancelled by a zero of every B_i within their '
                   'uncertainty' for pole in poles[cancelled])
    return tuple(reasons)


def near_pairs(structure: Structure, theta: np.ndarray) -> tuple[dict[str, Any], ...]:
    """
    Return each pole with a zero of some B_i within NEAR_PAIR, nearest zero first.

    Each pair as ``{'input': i (1-based), 'pole': [re, im], 'zero': [re, im],
    'distance': |pole - zero|}``. Whether the data could tell the two apart
    is :func:`redundancy`'s test; this is the plain geometry, which shows an
    over-parametrised fit (a pole and a zero spent on almost nothing) even
    where the covariance is too wide or too narrow to decide.
    """
    denominator, rows = structure.split(theta)
    poles = np.roots(denominator) if denominator.size > 1 else np.zeros(0)
    pairs = []
    for i, row in enumerate(rows):
        zeros = np.roots(np.trim_zeros(row, 'f')) if np.count_nonzero(row) > 1 else []
        for pole in poles:
            if len(zeros) == 0:
                continue
            distances = np.abs(np.asarray(zeros) - pole)
            nearest = int(np.argmin(distances))
            if distances[nearest] <= NEAR_PAIR:
                zero = zeros[nearest]
                pairs.append({'input': i + 1, 'pole': [float(pole.real), float(pole.imag)],
                              'zero': [float(zero.real), float(zero.imag)],
                              'distance': float(distances[nearest])})
    return tuple(sorted(pairs, key=lambda pair: pair['distance']))


def _roots(coefficients: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    r"""
    Return the roots r of c_0 z^m + ... + c_m and their gradients dr/dc, ``(roots, m + 1)``.

    :math:`\partial r/\partial c_k = -r^{m-k}/P'(r)` (implicit
    differentiation of P(r) = 0); not finite for a repeated root.
    """
    coefficients = np.asarray(coefficients, dtype=float)
    degree = coefficients.size - 1
    roots = np.roots(coefficients) if degree >= 1 else np.zeros(0, dtype=complex)
    slope = np.polyval(np.polyder(coefficients), roots)
    powers = roots[:, None] ** np.arange(degree, -1, -1)[None, :]
    with np.errstate(divide='ignore', invalid='ignore'):
        return roots, -powers / slope[:, None]


def _cancels(difference: complex, gradient: np.ndarray, covariance: np.ndarray) -> bool:
    """Return whether a pole-zero difference is within its uncertainty at TEST_LEVEL."""
    spread = np.vstack([gradient.real, gradient.imag])
    if not np.isfinite(spread).all():
        return False
    real = abs(difference.imag) <= 1e-12 * max(1.0, abs(difference)) and \
        not np.any(spread[1])
    if real:
        variance = float(spread[0] @ covariance @ spread[0])
        return variance > 0.0 and difference.real ** 2 / variance < stats.chi2.ppf(
            1.0 - TEST_LEVEL, 1)
    matrix = spread @ covariance @ spread.T
    vector = np.array([difference.real, difference.imag])
    statistic = float(vector @ np.linalg.pinv(matrix) @ vector)
    return statistic < stats.chi2.ppf(1.0 - TEST_LEVEL, 2)


def delay_grid(num_inputs: int, delays: tuple[int, int]) -> list[tuple[int, ...]] | None:
    """Return every combination of dead times (up to FULL_GRID_INPUTS inputs), else None."""
    if num_inputs > FULL_GRID_INPUTS:
        return None
    return list(itertools.product(range(delays[0], delays[1] + 1), repeat=num_inputs))


def search_delays(order: int, num_inputs: int, delays: tuple[int, int],
                  fit: Callable[[int, tuple[int, ...]], Candidate]) -> None:
    """
    Fit the dead-time combinations of one order through ``fit`` (which caches).

    Up to :data:`FULL_GRID_INPUTS` inputs, all (d_max - d_min + 1)^r
    combinations. Beyond, a coordinate search: from every d_i at the
    smallest value, each input's dead time in turn takes the value with the
    lowest MDL (at one order, the lowest estimation loss) while the others
    are held, until a sweep over the inputs moves none of them (at most
    :data:`MAX_SWEEPS` sweeps); it needs about r (d_max - d_min) fits per
    sweep instead of (d_max - d_min + 1)^r.
    """
    grid = delay_grid(num_inputs, delays)
    if grid is not None:
        for combination in grid:
            fit(order, combination)
        return
    current = (delays[0],) * num_inputs
    best = fit(order, current)
    for _ in range(MAX_SWEEPS):
        moved = False
        for i in range(num_inputs):
            for value in range(delays[0], delays[1] + 1):
                trial = current[:i] + (value,) + current[i + 1:]
                candidate = fit(order, trial)
                if _rank(candidate) < _rank(best):
                    best, current, moved = candidate, trial, True
        if not moved:
            return


def _rank(candidate: Candidate) -> tuple[bool, float]:
    """Return a sort key: usable candidates first, then the lowest MDL."""
    return not candidate.usable, candidate.criterion


def search_structures(record: Record, orders: tuple[int, int], delays: tuple[int, int],
                      feedthrough: bool = False,
                      progress: Callable[[str], None] | None = None) -> list[Candidate]:
    """Return the fitted candidates of every order (and the dead times searched), in order."""
    fitted: dict[tuple[int, tuple[int, ...]], Candidate] = {}
    grid = delay_grid(record.num_inputs, delays)
    total = (orders[1] - orders[0] + 1) * len(grid) if grid is not None else None

    def fit(order: int, combination: tuple[int, ...]) -> Candidate:
        key = (order, combination)
        if key not in fitted:
            fitted[key] = fit_candidate(record, order, combination, feedthrough,
                                        _previous(fitted, order - 1, combination))
            if progress is not None:
                count = f'{len(fitted)}/{total}' if total else f'fit {len(fitted)}'
                progress(f'order {order}, delay {",".join(map(str, combination))} '
                         f'({count}): {describe(fitted[key])}')
        return fitted[key]

    for order in range(orders[0], orders[1] + 1):
        search_delays(order, record.num_inputs, delays, fit)
    return sorted(fitted.values(), key=lambda c: (c.order, c.delays))


def _previous(fitted: dict[tuple[int, tuple[int, ...]], Candidate], order: int,
              combination: tuple[int, ...]) -> Candidate | None:
    """Return the order-``order`` candidate with these dead times, else the order's best."""
    same = fitted.get((order, combination))
    if same is not None and same.usable:
        return same
    usable = [c for (n, _), c in fitted.items() if n == order and c.usable]
    return min(usable, key=lambda c: c.criterion) if usable else None


def describe(candidate: Candidate) -> str:
    """Return one line of a candidate's figures for the progress output."""
    if candidate.error is not None:
        return f'not fitted ({candidate.error})'
    return (f'fit {candidate.fit:.2f} %, cross-correlation p = '
            f'{candidate.cross_correlation_p:.3g}, whiteness p = {candidate.whiteness_p:.3g}'
            + ('' if candidate.stable else ', unstable'))


__all__ = ['Candidate', 'FULL_GRID_INPUTS', 'MAX_SWEEPS', 'NEAR_PAIR', 'Record',
           'SEARCH_SOLVER', 'SEARCH_STARTS', 'TEST_LEVEL', 'WARM_POLES', 'delay_grid', 'describe',
           'finite', 'fit_candidate', 'near_pairs', 'redundancy', 'search_delays',
           'search_structures', 'warm_denominators']
