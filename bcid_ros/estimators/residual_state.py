"""
What the estimators share about their residual tests: the reasons, and their state in a snapshot.

The tests themselves are :mod:`bcid_ros.estimators.adequacy` (whiteness and
correlation with past inputs) and :mod:`bcid_ros.estimators.hac` (the HAC
covariance of the scores); every estimator that runs them reports and saves
them the same way.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from bcid_ros.estimators import adequacy, lagged
from bcid_ros.estimators.adequacy import AdequacyMonitor, MonitorState
from bcid_ros.estimators.hac import HacState


def residual_reasons(monitor: AdequacyMonitor, plant: int | None = None) -> list[str]:
    """
    Return the reasons of the residual tests of one plant (``plant`` None: a one-plant monitor).

    Until the tests have a window of SAMPLES_PER_LAG samples per lag, they judge what
    they have once it comes to SHORT_MINIMUM samples, with fewer lags
    (:meth:`~bcid_ros.estimators.adequacy.AdequacyMonitor.short_reasons`: a short record
    gets a verdict); before that, not being ready is a reason itself: a model the data
    have not yet been able to contradict is not yet trusted.
    """
    ready = monitor.ready if plant is None else monitor.ready_of(plant)
    if not ready:
        short = monitor.short_reasons(plant)
        if short is not None:
            return list(short)
        size = monitor.effective_samples if plant is None else monitor.effective_samples_of(plant)
        return [f'residual tests not ready ({size:.0f} of '
                f'{adequacy.SAMPLES_PER_LAG * monitor.lags} samples)']
    return list(monitor.reasons if plant is None else monitor.reasons_of(plant))


#: The arrays of the cross test's parameter term, absent from snapshots made before it.
GRADIENT_ARRAYS = ('adequacy_gradient_sums', 'adequacy_gradient_ring',
                   'adequacy_pending_gradients')


def with_gradient_arrays(arrays: dict[str, np.ndarray], own: dict[str, np.ndarray],
                         ) -> dict[str, np.ndarray]:
    """
    Return a snapshot's ``arrays`` with the parameter term's arrays of ``own`` as zeros if absent.

    A snapshot from before the parameter term then loads: the term starts
    from the gradients recorded after the load (the products before it count
    as zero and leave with the window). ``own``: the estimator's own arrays,
    for the shapes.
    """
    missing = {key: np.zeros_like(own[key]) for key in GRADIENT_ARRAYS
               if key in own and key not in arrays}
    return {**arrays, **missing}


def residual_items(monitor: MonitorState, hac: HacState | None,
                   ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """
    Return the state of the residual tests (and of the HAC) as snapshot (arrays, scalars).

    Their pending rows are padded to a block, so that the snapshot's arrays
    have the same shapes whatever the moment (a state file is checked by shape).
    """
    arrays = {f'adequacy_{field.name}': getattr(monitor, field.name)
              for field in dataclasses.fields(monitor)
              if isinstance(getattr(monitor, field.name), np.ndarray)}
    # the ring's last block is scratch space (the pending samples are apart): zeros
    for ring in ('ring', 'gradient_ring'):
        if f'adequacy_{ring}' in arrays:
            arrays[f'adequacy_{ring}'] = arrays[f'adequacy_{ring}'].copy()
            arrays[f'adequacy_{ring}'][:, -adequacy.BLOCK:] = 0.0
    for pending in ('residuals', 'inputs', 'gradients'):
        if f'adequacy_pending_{pending}' in arrays:
            arrays[f'adequacy_pending_{pending}'] = _padded(
                arrays[f'adequacy_pending_{pending}'], adequacy.BLOCK)
    scalars = {'adequacy_pending': monitor.pending_residuals.shape[0],
               'adequacy_weights': [float(value) for value in monitor.weights],
               'adequacy_checks': int(monitor.checks), 'adequacy_blocks': int(monitor.blocks)}
    if hac is not None:
        products = hac.products
        arrays.update((f'hac_{key}', value) for key, value in products.items()
                      if isinstance(value, np.ndarray))
        arrays['hac_pending'] = _padded(products['pending'], lagged.BLOCK)
        scalars.update(hac_pending=products['pending'].shape[0],
                       hac_weight=float(products['weight']),
                       hac_squared_weight=float(products['squared_weight']),
                       hac_count=int(products['count']))
    return arrays, scalars


def residual_states(arrays: dict[str, np.ndarray], scalars: dict[str, Any],
                    ) -> tuple[MonitorState, HacState | None]:
    """Return the states of the residual tests and of the HAC in a :func:`residual_items`."""
    pending = int(scalars['adequacy_pending'])
    fields = {field.name: arrays.get(f'adequacy_{field.name}')
              for field in dataclasses.fields(MonitorState)}
    fields.update(pending_residuals=arrays['adequacy_pending_residuals'][:pending],
                  pending_inputs=arrays['adequacy_pending_inputs'][:pending],
                  # None without the parameter term's arrays: a snapshot from before it
                  pending_gradients=(arrays['adequacy_pending_gradients'][:pending]
                                     if 'adequacy_pending_gradients' in arrays else None),
                  weights=tuple(scalars['adequacy_weights']),
                  checks=int(scalars['adequacy_checks']), blocks=int(scalars['adequacy_blocks']))
    hac = None
    if 'hac_sums' in arrays:
        hac = HacState(products={
            'sums': arrays['hac_sums'], 'context': arrays['hac_context'],
            'pending': arrays['hac_pending'][:int(scalars['hac_pending'])],
            'weight': scalars['hac_weight'], 'squared_weight': scalars['hac_squared_weight'],
            'count': scalars['hac_count']})
    return MonitorState(**fields), hac


def _padded(rows: np.ndarray, count: int) -> np.ndarray:
    """Return ``rows`` ``(m, ...)`` with zero rows added up to ``count``."""
    padded = np.zeros((count,) + rows.shape[1:])
    padded[:rows.shape[0]] = rows
    return padded
