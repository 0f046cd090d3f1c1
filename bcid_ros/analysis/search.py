"""
Structure search: fit every candidate with a batch method, recommend one, compare online.

The order and the dead times are chosen from batch output-error models
(:mod:`bcid_ros.analysis.batch`), judged on the validation part of the
record, by the rule of :func:`recommend`; the online estimators then run on
the chosen structure (:mod:`bcid_ros.analysis.online`) and their validation
fits are set beside the batch model's. The rule and its reasons are in
docs/analyze.md.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

import numpy as np

from bcid_ros.analysis.batch import (Candidate, finite, Record, search_structures,
                                     TEST_LEVEL)
from bcid_ros.analysis.model import complex_list
from bcid_ros.analysis.online import compare_online, OnlineResult, recommend_estimator
from bcid_ros.blas_threads import single_threaded_blas
from bcid_ros.errors import BcidError
from bcid_ros.estimators.registry import names_where
from bcid_ros.identifier.parameters import check_identifier_parameters

#: A candidate is "as good as the best" when its validation RMS error is at
#: most (1 + FIT_MARGIN) times the best one's (docs/analyze.md) ...
FIT_MARGIN = 0.10
#: ... and its validation fit at most FIT_POINTS below the best one's: below a best fit of
#: 80 % the relative margin alone let a structure 2-4 points below the best be chosen (a
#: heated plate under a staircase input: order 1 at 60.9 % against order 2 at 64.2 %).
FIT_POINTS = 2.0
#: Level of the residual tests (cross-correlation with the inputs, whiteness).
WHITENESS_LEVEL = TEST_LEVEL
#: Estimation samples needed per parameter of the largest model.
SAMPLES_PER_PARAMETER = 10
#: Smallest estimation and validation parts.
MINIMUM_PART = 50
#: What the whiteness test is applied to, and what the cross-correlation test tests.
RESIDUAL_KIND = 'simulation error'


@dataclasses.dataclass
class Analysis:
    """Everything ``bcid analyze`` found, ready for the table, the JSON and the plot."""

    num_inputs: int
    samples: int
    estimation_samples: int
    validation_samples: int
    candidates: list[Candidate]
    recommended: Candidate | None
    adequate: bool
    operating_point: dict[str, float]
    validation_output: np.ndarray
    detrend: str
    online: list[OnlineResult] = dataclasses.field(default_factory=list)
    recommended_estimator: str | None = None
    estimator_close: bool = False
    estimator_valid: bool = False
    sample_period: float | None = None
    residual_kind: str = RESIDUAL_KIND

    @property
    def residuals_white(self) -> bool:
        """Return whether the recommended model's simulation error is white."""
        return self.recommended is not None and self.recommended.white

    def best_per_order(self) -> dict[int, Candidate]:
        """Return, per order, the candidate the rule would take at that order."""
        best: dict[int, Candidate] = {}
        for candidate in self.candidates:
            current = best.get(candidate.order)
            if current is None or _order_key(candidate) < _order_key(current):
                best[candidate.order] = candidate
        return dict(sorted(best.items()))

    def identifier_parameters(self) -> dict[str, Any] | None:
        """Return the identifier parameters of the recommended structure (config snippet)."""
        chosen = self.recommended
        if chosen is None:
            return None
        name = self.recommended_estimator or (self.online[0].name if self.online else None)
        out: dict[str, Any] = {} if name is None else {'estimator': name}
        out.update({'order': chosen.order, 'num_inputs': self.num_inputs,
                    'input_delay': list(chosen.delays), 'detrend': self.detrend})
        return out

    def model_summary(self) -> dict[str, Any] | None:
        """Return the recommended batch model: parameters, poles, zeros, DC gain, fit."""
        chosen = self.recommended
        if chosen is None or chosen.model is None:
            return None
        model = chosen.model
        gains = model.dc_gain()
        zeros = [complex_list(model.zeros(i)) for i in range(model.num_inputs)]
        out: dict[str, Any] = {
            'method': 'batch output error (prediction-error method)',
            'order': chosen.order, 'delay': chosen.delay,
            'parameters': {k: float(v) for k, v in zip(chosen.parameter_names, chosen.theta)},
            'parameter_std': {k: finite(v) for k, v in zip(chosen.parameter_names, chosen.std)},
            'fit': finite(chosen.fit),
            'poles': complex_list(model.poles()),
            'zeros': zeros[0] if model.num_inputs == 1 else zeros,
            'dc_gain': finite(gains[0]) if gains.size == 1 else [finite(g) for g in gains],
            'pole_zero_pairs': list(chosen.pole_zero_pairs),
        }
        if self.sample_period is not None:
            out['continuous'] = model.continuous(self.sample_period)
        return out

    def summary(self) -> dict[str, Any]:
        """Return the JSON object of ``bcid analyze --json``."""
        chosen = self.recommended
        return {
            'method': 'batch output error',
            'samples': self.samples,
            'estimation_samples': self.estimation_samples,
            'validation_samples': self.validation_samples,
            'residual': self.residual_kind,
            'recommended_order': chosen.order if chosen else None,
            'recommended_delay': chosen.delay if chosen else None,
            'adequate': self.adequate,
            'residuals_uncorrelated': bool(chosen is not None and chosen.uncorrelated),
            'residuals_white': self.residuals_white,
            'rule': {'fit_margin': FIT_MARGIN, 'fit_points': FIT_POINTS,
                     'test_level': TEST_LEVEL},
            'operating_point': self.operating_point,
            'orders': {str(n): c.figures() for n, c in self.best_per_order().items()},
            'candidates': [{'order': c.order, **c.figures()} for c in self.candidates],
            'model': self.model_summary(),
            'recommended_estimator': self.recommended_estimator,
            'recommended_estimator_close': self.estimator_close,
            'recommended_estimator_valid': self.estimator_valid,
            'online': {r.name: r.figures() for r in self.online},
            'detrend': self.detrend,
            'identifier_parameters': self.identifier_parameters(),
        }


def _order_key(candidate: Candidate) -> tuple[bool, bool, float]:
    """Return the key the rule ranks one order's candidates by (smallest first)."""
    return (not candidate.usable, candidate.redundant or not candidate.uncorrelated,
            candidate.criterion)


def fit_limit(best: float) -> float:
    """Return the lowest validation fit (%) within the margin of the ``best`` one."""
    return max(100.0 - (100.0 - best) * (1.0 + FIT_MARGIN), best - FIT_POINTS)


def recommend(candidates: list[Candidate]) -> tuple[Candidate | None, bool]:
    """
    Return the recommended candidate and whether it is adequate.

    The rule (docs/analyze.md). Of the stable models whose validation RMS
    error is within ``FIT_MARGIN`` of the best one's,
    100 - fit <= (1 + FIT_MARGIN)(100 - best fit), and whose fit is within
    ``FIT_POINTS`` of the best (:func:`fit_limit`), the **adequate** ones:
    simulation error uncorrelated with the inputs (cross-correlation test,
    p >= ``TEST_LEVEL``) and no sign that a smaller structure describes
    them (:func:`~bcid_ros.analysis.batch.redundancy`: a pole cancelled by
    zeros, or a negligible first coefficient, within the estimate's
    uncertainty). Of them, the smallest order (the fewest parameters), and
    at that order the dead times with the lowest MDL (AIC ranks them the
    same: at one order both are the estimation loss). When none is
    adequate, the same among those within the margin that are not
    redundant, or else among all within the margin; the flag is then False.
    """
    usable = [c for c in candidates if c.usable]
    if not usable:
        return None, False
    limit = fit_limit(max(c.fit for c in usable))
    close = [c for c in usable if c.fit >= limit]
    lean = [c for c in close if not c.redundant]
    adequate = [c for c in lean if c.uncorrelated]
    pool = adequate or lean or close
    order = min(c.order for c in pool)
    chosen = min((c for c in pool if c.order == order), key=lambda c: (c.criterion, -c.fit))
    return chosen, bool(adequate)


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
    needed = max(SAMPLES_PER_PARAMETER * largest, MINIMUM_PART, 2 * delays[1])
    if estimation < needed or validation < MINIMUM_PART:
        raise BcidError(
            f'too few samples: {y.size} samples give {estimation} for estimation and '
            f'{validation} for validation (--validation {fraction}); orders up to {orders[1]} '
            f'and delays up to {delays[1]} need at least {needed} and {MINIMUM_PART} '
            f'({SAMPLES_PER_PARAMETER} per parameter of the largest model, {largest}); use a '
            'smaller --orders range or a longer record')
    for i in range(r):
        column = u[:, i]
        if np.ptp(column) <= 1e-12 * max(1.0, float(np.abs(column).max())):
            raise BcidError(f'input u{i + 1} is constant ({column[0]:g}) over the bag: it '
                            'does not excite the plant, so no model can be identified')
    if np.ptp(y) <= 1e-12 * max(1.0, float(np.abs(y).max())):
        raise BcidError(f'the output y is constant ({y[0]:g}) over the bag: nothing to fit')


def compared_estimators(file_estimator: str, estimator: str | None) -> tuple[str, ...]:
    """
    Return the online estimators to compare.

    ``--estimator NAME`` restricts the comparison to NAME (any registered
    estimator). Otherwise every estimator the registry marks for open-loop
    input/output data, and the parameter file's own estimator if it is not
    one of them (e.g. ``cl_bcls`` for a closed-loop record).
    """
    if estimator is not None:
        return (estimator,)
    names = names_where(open_loop=True)
    return names if file_estimator in names else names + (file_estimator,)


def analyze(y: np.ndarray, u: np.ndarray, parameters: dict[str, Any], *,
            orders: tuple[int, int] = (1, 4), delays: tuple[int, int] = (0, 0),
            estimator: str | None = None, validation: float = 0.3,
            sample_period: float | None = None,
            progress: Callable[[str], None] | None = None) -> Analysis:
    """
    Choose the structure with batch OE fits, then run the online estimators on it.

    Parameters
    ----------
    y : numpy.ndarray, shape ``(N,)``
        Measured outputs.
    u : numpy.ndarray, shape ``(N, r)``
        Measured inputs.
    parameters : dict
        Identifier parameters as in the file: the settings of the online
        estimators (``order``, ``input_delay`` and ``num_inputs`` are those
        of each candidate; ``detrend`` is ``mean`` unless the file sets it).
    orders, delays : tuple of int
        Inclusive ranges; the delay range applies to every input.
    estimator : str, optional
        Restricts the online comparison to this estimator (see
        :func:`compared_estimators`).
    validation : float
        Fraction of the record (at its end) kept for validation, in (0, 1).
    sample_period : float, optional
        T in seconds, for the continuous-time equivalents.
    progress : callable, optional
        Called with one line of progress per fit.

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
    detrend = str(parameters.get('detrend', 'mean'))
    values = check_identifier_parameters({**values, 'detrend': detrend})
    y = np.asarray(y, dtype=float).reshape(-1)
    u = np.asarray(u, dtype=float).reshape(y.size, -1)
    r = u.shape[1]
    if values['num_inputs'] != r:
        raise BcidError(f'the record has {r} input(s) but the parameter file sets num_inputs '
                        f"= {values['num_inputs']}")
    if not 0.0 < validation < 1.0:
        raise BcidError(f'--validation must be a fraction in (0, 1), got {validation}')
    if sample_period is not None and not sample_period > 0:
        raise BcidError(f'--sample-period must be > 0 seconds, got {sample_period}')
    validation_count = int(round(validation * y.size))
    estimation_count = y.size - validation_count
    _check_data(y, u, estimation_count, validation_count, orders, delays,
                values['feedthrough'], validation)
    record = Record(y, u, estimation_count)
    with single_threaded_blas():
        candidates = search_structures(record, orders, delays, values['feedthrough'], progress)
    recommended, adequate = recommend(candidates)
    point = record.operating_point
    analysis = Analysis(
        r, y.size, estimation_count, validation_count, candidates, recommended, adequate,
        {'y': float(point[0]), **{f'u{i + 1}': float(m) for i, m in enumerate(point[1:])}},
        record.centred()[0][estimation_count:], detrend, sample_period=sample_period)
    if recommended is not None:
        names = compared_estimators(values['estimator'], estimator)
        analysis.online = compare_online(record, names, values, recommended, detrend, progress)
        (analysis.recommended_estimator, analysis.estimator_close,
         analysis.estimator_valid) = recommend_estimator(analysis.online, recommended.fit,
                                                         FIT_MARGIN)
    return analysis


def short_error(text: str, width: int = 110) -> str:
    """Return an error message cut to ``width`` characters for one table row (JSON keeps all)."""
    return text if len(text) <= width else text[:width - 1].rstrip() + '\u2026'


__all__ = ['Analysis', 'Candidate', 'FIT_MARGIN', 'FIT_POINTS', 'RESIDUAL_KIND', 'TEST_LEVEL',
           'WHITENESS_LEVEL', 'analyze', 'compared_estimators', 'fit_limit', 'parse_delays',
           'parse_orders', 'recommend', 'short_error']
