"""
Order and delay search: fit every candidate, validate it, recommend one.

For each order n and delay d, the configured estimator runs over the
estimation part of the record with the input shifted by d samples
(u_d(t) = u(t - d), which for one input is the same as the dead time
B(q) -> q^-d B(q)); the fitted model is then judged on the validation part,
which it has not seen. The recommendation rule and the reasons for it are
in docs/analyze.md.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Callable
import warnings

import numpy as np

from bcid_ros.analysis import metrics
from bcid_ros.analysis.model import complex_list, DiscreteModel
from bcid_ros.errors import BcidError
from bcid_ros.estimators.registry import entry
from bcid_ros.identifier.parameters import check_identifier_parameters, estimator_from_parameters

#: A candidate is "as good as the best" when its validation RMS error is at
#: most (1 + FIT_MARGIN) times the best one's (docs/analyze.md).
FIT_MARGIN = 0.10
#: Level of the Ljung-Box whiteness test: residuals pass when p >= this.
WHITENESS_LEVEL = 0.01
#: Estimation samples needed per parameter of the largest model.
SAMPLES_PER_PARAMETER = 10
#: Smallest estimation and validation parts.
MINIMUM_PART = 50


@dataclasses.dataclass
class Candidate:
    """One fitted (order, delay) model and its validation figures."""

    order: int
    delay: int
    error: str | None = None
    parameter_names: tuple[str, ...] = ()
    theta: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    model: DiscreteModel | None = None
    fit: float = float('nan')
    prediction_fit: float = float('nan')
    aic: float = float('nan')
    mdl: float = float('nan')
    whiteness_p: float = float('nan')
    stable: bool = False
    simulated: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    residual: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))

    @property
    def usable(self) -> bool:
        """Return whether the model was fitted, is stable and simulates to a finite fit."""
        return self.error is None and self.stable and math.isfinite(self.fit)

    @property
    def white(self) -> bool:
        """Return whether the tested residual passes the whiteness test."""
        return self.usable and self.whiteness_p >= WHITENESS_LEVEL

    def figures(self) -> dict[str, Any]:
        """Return the JSON figures of this candidate (non-finite numbers as null)."""
        if self.error is not None:
            return {'delay': self.delay, 'error': self.error}
        # an unstable model's simulation from rest diverges: its fit means nothing
        fit = self.fit if self.stable else float('nan')
        return {'delay': self.delay, 'fit': _finite(fit),
                'prediction_fit': _finite(self.prediction_fit), 'aic': _finite(self.aic),
                'mdl': _finite(self.mdl), 'whiteness_p': _finite(self.whiteness_p),
                'stable': self.stable}


@dataclasses.dataclass
class Analysis:
    """Everything ``bcid analyze`` found, ready for the table, the JSON and the plot."""

    estimator: str
    num_inputs: int
    samples: int
    estimation_samples: int
    validation_samples: int
    residual_kind: str
    candidates: list[Candidate]
    recommended: Candidate | None
    residuals_white: bool
    operating_point: dict[str, float]
    validation_output: np.ndarray
    sample_period: float | None = None

    def best_per_order(self) -> dict[int, Candidate]:
        """Return, per order, its best-fitting delay (usable candidates first)."""
        best: dict[int, Candidate] = {}
        for candidate in self.candidates:
            current = best.get(candidate.order)
            if current is None or _rank(candidate) > _rank(current):
                best[candidate.order] = candidate
        return dict(sorted(best.items()))

    def model_summary(self) -> dict[str, Any] | None:
        """Return poles, zeros, DC gain (and continuous equivalents) of the recommended model."""
        if self.recommended is None or self.recommended.model is None:
            return None
        model = self.recommended.model
        gains = model.dc_gain()
        zeros = [complex_list(model.zeros(i)) for i in range(model.num_inputs)]
        out: dict[str, Any] = {
            'parameters': dict(zip(self.recommended.parameter_names,
                                   map(float, self.recommended.theta))),
            'poles': complex_list(model.poles()),
            'zeros': zeros[0] if model.num_inputs == 1 else zeros,
            'dc_gain': _finite(gains[0]) if gains.size == 1 else [_finite(g) for g in gains],
        }
        if self.sample_period is not None:
            out['continuous'] = model.continuous(self.sample_period)
        return out

    def summary(self) -> dict[str, Any]:
        """Return the JSON object of ``bcid analyze --json``."""
        recommended = self.recommended
        return {
            'estimator': self.estimator,
            'samples': self.samples,
            'estimation_samples': self.estimation_samples,
            'validation_samples': self.validation_samples,
            'residual': self.residual_kind,
            'recommended_order': recommended.order if recommended else None,
            'recommended_delay': recommended.delay if recommended else None,
            'residuals_white': self.residuals_white,
            'rule': {'fit_margin': FIT_MARGIN, 'whiteness_level': WHITENESS_LEVEL},
            'operating_point': self.operating_point,
            'orders': {str(n): c.figures() for n, c in self.best_per_order().items()},
            'candidates': [{'order': c.order, **c.figures()} for c in self.candidates],
            'model': self.model_summary(),
        }


def _finite(value: float) -> float | None:
    value = float(value)
    return value if math.isfinite(value) else None


def _rank(candidate: Candidate) -> tuple[bool, float]:
    fit = candidate.fit if math.isfinite(candidate.fit) else -math.inf
    return candidate.usable, fit


def recommend(candidates: list[Candidate]) -> tuple[Candidate | None, bool]:
    """
    Return the recommended candidate and whether its residuals passed.

    The rule: among the stable models whose validation RMS error is within
    ``FIT_MARGIN`` of the best (the fit is 100 (1 - RMS/spread), so this is
    100 - fit <= (1 + FIT_MARGIN)(100 - best fit)), take those whose residual
    passes the whiteness test at level ``WHITENESS_LEVEL``, and of them the
    smallest order, and for that order the delay with the best fit. When no
    model within the margin has white residuals, the same rule without the
    whiteness condition (and the flag False).
    """
    usable = [c for c in candidates if c.usable]
    if not usable:
        return None, False
    best = max(c.fit for c in usable)
    limit = 100.0 - (100.0 - best) * (1.0 + FIT_MARGIN)
    close = [c for c in usable if c.fit >= limit]
    white = [c for c in close if c.white]
    pool = white or close
    order = min(c.order for c in pool)
    chosen = max((c for c in pool if c.order == order), key=lambda c: c.fit)
    return chosen, bool(white)


def _parse_range(text: str, name: str, minimum: int) -> tuple[int, int]:
    try:
        parts = [int(part) for part in text.split('-')]
    except ValueError:
        parts = []
    if len(parts) == 1:
        parts = parts * 2
    if len(parts) != 2 or parts[0] < minimum or parts[1] < parts[0]:
        raise BcidError(f'{name} must be A-B (or A) with {minimum} <= A <= B, got {text!r}')
    return parts[0], parts[1]


def parse_orders(text: str) -> tuple[int, int]:
    """Return (first, last) of an ``--orders A-B`` argument (orders >= 1)."""
    return _parse_range(text, '--orders', 1)


def parse_delays(text: str) -> tuple[int, int]:
    """Return (first, last) of a ``--delays A-B`` argument (delays >= 0)."""
    return _parse_range(text, '--delays', 0)


def _check_data(y: np.ndarray, u: np.ndarray, estimation: int, validation: int,
                orders: tuple[int, int], delays: tuple[int, int], feedthrough: bool,
                fraction: float) -> None:
    r = u.shape[1]
    largest = orders[1] * (1 + r) + (r if feedthrough else 0)
    needed = max(SAMPLES_PER_PARAMETER * largest, MINIMUM_PART)
    if estimation < needed or validation < MINIMUM_PART:
        raise BcidError(
            f'too few samples: {y.size} samples give {estimation} for estimation and '
            f'{validation} for validation (--validation {fraction}, delays up to {delays[1]}); '
            f'orders up to {orders[1]} need at least {needed} and {MINIMUM_PART} '
            f'({SAMPLES_PER_PARAMETER} per parameter of the largest model, {largest}); use a '
            'smaller --orders range or a longer bag')
    for i in range(r):
        column = u[:, i]
        if np.ptp(column) <= 1e-12 * max(1.0, float(np.abs(column).max())):
            raise BcidError(f'input u{i + 1} is constant ({column[0]:g}) over the bag: it '
                            'does not excite the plant, so no model can be identified')
    if np.ptp(y) <= 1e-12 * max(1.0, float(np.abs(y).max())):
        raise BcidError(f'the output y is constant ({y[0]:g}) over the bag: nothing to fit')


def _split_model(theta: np.ndarray, order: int, num_inputs: int, feedthrough: bool,
                 delay: int) -> DiscreteModel:
    a = np.concatenate([[1.0], theta[:order]])
    width = order + 1 if feedthrough else order
    rows = theta[order:].reshape(num_inputs, width)
    if not feedthrough:
        rows = np.column_stack([np.zeros(num_inputs), rows])
    return DiscreteModel(a, rows, delay)


def _delayed_names(names: tuple[str, ...], delay: int) -> tuple[str, ...]:
    """Return the parameter names with the true lags of input coefficients (b1_{k + d})."""
    out = []
    for name in names:
        if name.startswith('b') and '_' in name:
            head, lag = name.rsplit('_', 1)
            name = f'{head}_{int(lag) + delay}'
        out.append(name)
    return tuple(out)


def analyze(y: np.ndarray, u: np.ndarray, parameters: dict[str, Any], *,
            orders: tuple[int, int] = (1, 4), delays: tuple[int, int] = (0, 0),
            estimator: str | None = None, validation: float = 0.3,
            sample_period: float | None = None,
            progress: Callable[[str], None] | None = None) -> Analysis:
    """
    Fit every (order, delay) candidate and recommend one.

    Parameters
    ----------
    y : numpy.ndarray, shape ``(N,)``
        Measured outputs.
    u : numpy.ndarray, shape ``(N, r)``
        Measured inputs.
    parameters : dict
        Identifier parameters; ``order`` is replaced by each candidate order.
    orders, delays : tuple of int
        Inclusive ranges. Delays other than 0 need a single input.
    estimator : str, optional
        Overrides the ``estimator`` parameter.
    validation : float
        Fraction of the record (at its end) kept for validation, in (0, 1).
    sample_period : float, optional
        T in seconds, for the continuous-time equivalents.
    progress : callable, optional
        Called with one line of progress per candidate.

    Returns
    -------
    Analysis

    Raises
    ------
    BcidError
        If the record is too short for the ranges, an input or the output is
        constant, or an argument is out of range.
    ValueError
        If a parameter is not allowed (named in the message).

    """
    values = dict(parameters)
    if estimator is not None:
        values['estimator'] = estimator
    values = check_identifier_parameters(values)
    y = np.asarray(y, dtype=float).reshape(-1)
    u = np.asarray(u, dtype=float).reshape(y.size, -1)
    r = u.shape[1]
    if values['num_inputs'] != r:
        raise BcidError(f'the bag has {r} input(s) but the parameter file sets num_inputs = '
                        f"{values['num_inputs']}")
    if not 0.0 < validation < 1.0:
        raise BcidError(f'--validation must be a fraction in (0, 1), got {validation}')
    if sample_period is not None and not sample_period > 0:
        raise BcidError(f'--sample-period must be > 0 seconds, got {sample_period}')
    if delays != (0, 0) and r != 1:
        raise BcidError(f'--delays searches the dead time of a single-input plant; this bag '
                        f'has {r} inputs (use --delays 0)')
    shift = delays[1]
    aligned = y.size - shift
    validation_count = int(round(validation * aligned))
    estimation_count = aligned - validation_count
    _check_data(y, u, estimation_count, validation_count, orders, delays,
                values['feedthrough'], validation)

    # the same output samples for every delay: start after the largest dead time
    y_aligned = y[shift:]
    y_mean = float(y_aligned[:estimation_count].mean())
    u_mean = u[:estimation_count].mean(axis=0)
    y_dev = y_aligned - y_mean
    residual_kind = ('simulation error' if entry(values['estimator']).model != 'arx'
                     else 'equation error')
    grid = [(n, d) for n in range(orders[0], orders[1] + 1)
            for d in range(delays[0], delays[1] + 1)]
    candidates = []
    for index, (n, d) in enumerate(grid, 1):
        u_dev = u[shift - d:u.shape[0] - d] - u_mean
        candidate = _fit_candidate(values, n, d, y_dev, u_dev, estimation_count, residual_kind)
        candidates.append(candidate)
        if progress is not None:
            progress(f'order {n}, delay {d} ({index}/{len(grid)}): ' + _describe(candidate))
    recommended, white = recommend(candidates)
    operating_point = {'y': y_mean, **{f'u{i + 1}': float(m) for i, m in enumerate(u_mean)}}
    return Analysis(values['estimator'], r, y.size, estimation_count, validation_count,
                    residual_kind, candidates, recommended, white, operating_point,
                    y_dev[estimation_count:], sample_period)


def short_error(text: str, width: int = 110) -> str:
    """Return an error message cut to ``width`` characters for one table row (JSON keeps all)."""
    return text if len(text) <= width else text[:width - 1].rstrip() + '\u2026'


def _describe(candidate: Candidate) -> str:
    if candidate.error is not None:
        return f'not fitted ({short_error(candidate.error)})'
    return (f'fit {candidate.fit:.2f} %, whiteness p = {candidate.whiteness_p:.3g}'
            + ('' if candidate.stable else ', unstable'))


def _fit_candidate(values: dict[str, Any], order: int, delay: int, y: np.ndarray,
                   u: np.ndarray, estimation: int, residual_kind: str) -> Candidate:
    candidate = Candidate(order, delay)
    try:
        est = estimator_from_parameters({**values, 'order': order})
    except ValueError as error:
        candidate.error = str(error)
        return candidate
    with warnings.catch_warnings():
        # an ill-suited candidate makes the estimator warn per sample (ill-conditioned
        # solves); its figures below say what came of it
        warnings.simplefilter('ignore')
        est.run(y[:estimation], u[:estimation])
    if not est.valid:
        flags = ', '.join(f'{name} x{count}' for name, count in sorted(est.flags.items()))
        candidate.error = (f'the estimator was not valid after {estimation} samples'
                           + (f' (flags: {flags})' if flags else ''))
        return candidate
    theta = np.asarray(est.theta, dtype=float)
    if not np.isfinite(theta).all():
        candidate.error = 'the estimate is not finite'
        return candidate
    model = _split_model(theta, order, u.shape[1], values['feedthrough'], delay)
    candidate.model = model
    candidate.theta = theta
    candidate.parameter_names = _delayed_names(est.parameter_names, delay)
    candidate.stable = metrics.is_stable(model.a)
    simulated = metrics.simulate(model.a, model.b, u)
    candidate.simulated = simulated[estimation:]
    y_val = y[estimation:]
    candidate.fit = metrics.nrmse_fit(y_val, candidate.simulated)
    # equation error = one-step prediction error of the model read as ARX
    error = metrics.equation_error(model.a, model.b, y, u)
    split = estimation - order
    candidate.prediction_fit = metrics.nrmse_fit(y_val, y_val - error[split:])
    candidate.aic, candidate.mdl = metrics.information_criteria(error[:split], theta.size)
    residual = (y_val - candidate.simulated if residual_kind == 'simulation error'
                else error[split:])
    candidate.residual = residual
    if np.isfinite(residual).all():
        _, candidate.whiteness_p = metrics.ljung_box(residual,
                                                     metrics.whiteness_lags(residual.size))
    return candidate


__all__ = ['Analysis', 'Candidate', 'FIT_MARGIN', 'WHITENESS_LEVEL',
           'analyze', 'parse_delays', 'parse_orders', 'recommend']
