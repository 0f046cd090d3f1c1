"""
The online estimators on the chosen structure, beside the batch model.

Once the batch search has chosen the order and the dead times, each online
estimator compared runs sample by sample over the raw estimation part, as the
identifier node would run it with that structure (``order``, ``input_delay``,
``detrend``, the rest of the parameter file unchanged), and its final estimate
is validated like the batch model: simulated from rest over the whole record,
around its own operating point, and compared on the validation part.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Callable, Sequence
import warnings

import numpy as np

from bcid_ros.analysis import metrics
from bcid_ros.analysis.batch import Candidate, finite, Record
from bcid_ros.analysis.pem import simulate_oe, Structure
from bcid_ros.estimators.polynomials import is_stable, monic_coefficients
from bcid_ros.identifier.parameters import estimator_from_parameters


@dataclasses.dataclass
class OnlineResult:
    """One online estimator's final estimate on the estimation part, and its validation."""

    name: str
    error: str | None = None
    parameter_names: tuple[str, ...] = ()
    theta: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    valid: bool = False
    reasons: tuple[str, ...] = ()
    stable: bool = False
    fit: float = float('nan')
    operating_point: np.ndarray | None = None
    simulated: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))

    @property
    def usable(self) -> bool:
        """Return whether the estimate is valid, stable and simulates to a finite fit."""
        return self.error is None and self.valid and self.stable and math.isfinite(self.fit)

    def figures(self) -> dict[str, Any]:
        """Return the JSON figures, with null for non-finite numbers."""
        if self.error is not None:
            return {'error': self.error}
        out: dict[str, Any] = {
            'fit': finite(self.fit) if self.stable else None, 'valid': self.valid,
            'stable': self.stable, 'validity_reasons': list(self.reasons),
            'parameters': {k: finite(v) for k, v in zip(self.parameter_names, self.theta)}}
        if self.operating_point is not None:
            names = ['y'] + [f'u{i}' for i in range(1, self.operating_point.size)]
            out['operating_point'] = dict(zip(names, map(float, self.operating_point)))
        return out


def run_online(record: Record, name: str, values: dict[str, Any], chosen: Candidate,
               detrend: str) -> OnlineResult:
    r"""
    Run estimator ``name`` with the chosen structure over the estimation part; validate it.

    ``values`` are the identifier parameters of the file; ``estimator``,
    ``order``, ``num_inputs``, ``input_delay`` and ``detrend`` are replaced.
    The validation output is :math:`y_0 + \sum_i B_i/F (u_i - u_{0,i})`
    with the estimator's own operating point (``detrend: mean``), or
    :math:`\sum_i B_i/F u_i` on the raw data (``none``), simulated from rest
    over the whole record. An estimator that refuses the structure (e.g.
    ``cl_bcls`` with a dead time) or raises is returned with its ``error``.
    """
    result = OnlineResult(name)
    settings = {**values, 'estimator': name, 'order': chosen.order,
                'num_inputs': record.num_inputs, 'input_delay': list(chosen.delays),
                'detrend': detrend}
    try:
        estimator = estimator_from_parameters(settings)
        with warnings.catch_warnings():
            # an estimator that struggles warns per sample (ill-conditioned solves); its
            # validity and its fit below say what came of it
            warnings.simplefilter('ignore')
            estimator.run(record.y[:record.estimation], record.u[:record.estimation])
    except (ValueError, ArithmeticError, RuntimeError, np.linalg.LinAlgError) as error:
        result.error = f'{type(error).__name__}: {error}'
        return result
    structure = Structure(chosen.order, record.num_inputs, chosen.delays,
                          values.get('feedthrough', False))
    theta = np.asarray(estimator.theta, dtype=float)
    result.parameter_names = tuple(estimator.parameter_names)
    result.theta = theta
    result.valid = bool(estimator.valid)
    result.reasons = tuple(estimator.validity_reasons)
    plant = theta[:structure.num_parameters]
    if not np.isfinite(plant).all():
        result.reasons += ('the estimate is not finite',)
        return result
    result.stable = is_stable(monic_coefficients(structure.split(plant)[0]), 0.0)
    point = estimator.operating_point
    result.operating_point = None if point is None else np.asarray(point, dtype=float)
    y0, u0 = (0.0, 0.0) if point is None else (point[0], point[1:])
    simulated = y0 + simulate_oe(plant, record.u - u0, structure)
    split = record.estimation
    result.fit = metrics.nrmse_fit(record.y[split:], simulated[split:])
    result.simulated = simulated[split:] - record.operating_point[0]
    return result


def compare_online(record: Record, names: Sequence[str], values: dict[str, Any],
                   chosen: Candidate, detrend: str,
                   progress: Callable[[str], None] | None = None) -> list[OnlineResult]:
    """Run every estimator of ``names`` on the chosen structure (:func:`run_online`)."""
    results = []
    for name in names:
        result = run_online(record, name, values, chosen, detrend)
        results.append(result)
        if progress is not None:
            progress(f'online {name} (order {chosen.order}, delay {chosen.delay_text}): '
                     + describe(result))
    return results


def describe(result: OnlineResult) -> str:
    """Return one line of an online result: its fit and validity."""
    if result.error is not None:
        return f'not run ({result.error})'
    fit = f'fit {result.fit:.2f} %' if result.stable else 'unstable'
    return f'{fit}, {"valid" if result.valid else "not valid"}'


def recommend_estimator(results: Sequence[OnlineResult], batch_fit: float,
                        margin: float) -> tuple[str | None, bool, bool]:
    """
    Return (the online estimator to use, whether it is close to the batch model, whether valid).

    An estimate is close when its validation RMS error is at most
    (1 + ``margin``) times the batch model's,
    100 - fit <= (1 + margin)(100 - batch fit), and usable when it is stable
    with a finite fit. In this order of preference, the highest validation
    fit among the usable ones that are (1) valid and close; (2) close but not
    valid at the end of the estimation part (its reasons say why: a
    nonlinear plant, a false change detection that restarted it; the accuracy is there,
    and its ``valid`` will say when to trust it); (3) valid but not close.
    A valid estimate far from the batch model is thus not preferred to an
    accurate one that is not valid (a glass furnace record: rls valid at 64.7 % was
    recommended over rpem at 72.0 % beside a batch model of 72.8 %). None
    when no estimate is usable.
    """
    usable = [r for r in results
              if r.error is None and r.stable and math.isfinite(r.fit)]

    def close(result: OnlineResult) -> bool:
        return 100.0 - result.fit <= (1.0 + margin) * (100.0 - batch_fit)

    for pool in ([r for r in usable if r.valid and close(r)],
                 [r for r in usable if close(r)],
                 [r for r in usable if r.valid]):
        if pool:
            best = max(pool, key=lambda r: r.fit)
            return best.name, close(best), best.valid
    return None, False, False


__all__ = ['OnlineResult', 'compare_online', 'describe', 'recommend_estimator', 'run_online']
