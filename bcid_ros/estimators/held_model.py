r"""
The held model of bcrls's change detector: the output error of an estimate kept fixed.

Under bcrls's model, :math:`y = (B/A)\,u + v` with white output noise v, the
output error of a model held fixed at :math:`\theta_h`,

.. math::

    e_h(t) = y(t) - \varphi^T(t)\theta_h - a_{h,1} e_h(t-1) - \dots - a_{h,n} e_h(t-n)
    = y(t) - \frac{B_h}{A_h}(q)\,u(t),

(:func:`~bcid_ros.estimators.bcrls.output_error_rows` with theta held) is v
plus the model's own error :math:`(G - G_h)u`, constant while the plant is:
white up to that error, with variance :math:`\sigma_v^2` and the error's.
After a change it carries the whole :math:`(G_{new} - G_h)u`. The equation
error of the LS step, the detector's input before, is :math:`A(q)v` plus the
change's term: the same signal to noise ratio frequency by frequency, but its
noise is an MA(n) whose zeros lie near 1 on a slow plant (high-pass, most of
its variance where the plant passes nothing), which the detector's AR(2)
reference does not whiten, so that a pole move, whose term lies at the
plant's low frequencies, adds little to its variance (docs/tracking.md,
"Where each estimator's model holds").

**When it is held.** At the first validity check after a (re)start where
the estimate rests on ``HOLD_FROM`` (weighted) samples, its A is stable,
its compensation has no reason against it (converged, determined,
contracting) and it is known to 10 % of its size (:func:`precise`); the
detector then starts afresh on the held model's errors (its warm-up, 500
samples); the LS step's errors feed it until then. Not
only once ``valid``: the shared checks (the residual tests, the simulation
check) may refuse an estimate that is accurate for long on a slow plant (one
0.2 % off refused for 4000 samples), and one first valid after an undetected
change would make the changed plant the detector's reference. The estimate
of the moving recursion is not used sample by sample: its own wandering (the
compensation amplifies the LS estimate's error) is what broke the detector's
reference when bcrls fed it the output error of the current estimate
(docs/tracking_log.md, "False detections left").

**When it is refreshed.** At such a check once the estimate rests on
``GROWTH`` times the weighted samples tau of the held one: its error then
has at most about 1/``GROWTH`` of the held one's variance, so the errors of
the new held model do not exceed the reference learnt on the old one's, and
with forgetting the refreshes stop where tau stops growing (the held model
is then as good as the estimate). The reference goes on across a refresh
(no blind warm-up), and the filter's past errors too (those of a model
close to the new one: no restart transient).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from bcid_ros.estimators.base import EstimatorState
from bcid_ros.estimators.validity import imprecision

#: The estimate is first held once it rests on this many (weighted) samples.
HOLD_FROM = 500.0
#: The held model is refreshed when the estimate rests on this many times its samples.
GROWTH = 2.0


def hold_due(sound: Any, tau: Any, held_tau: Any) -> Any:
    """
    Return where the estimate is to be held now: ``sound``, and first or grown GROWTH times.

    ``sound``: the compensation has no reason against it at this check
    (:func:`~bcid_ros.estimators.bcrls.compensation_problems`) and its A is
    stable (an unstable one's output error grows without a change). ``held_tau``
    is the weighted count tau of the held estimate (0: none held). Floats for
    one plant, arrays ``(K,)`` for K.
    """
    return sound & (tau >= HOLD_FROM) & ((held_tau <= 0.0) | (tau >= GROWTH * held_tau))


def precise(theta: np.ndarray, covariances: np.ndarray) -> np.ndarray:
    """
    Return which estimates ``theta`` ``(K, p)`` are known to PRECISION of their size.

    The rule of a detected change's end (:func:`~bcid_ros.estimators.validity.imprecision`,
    2 sqrt(tr C) <= 0.1 |theta|) with ``covariances`` ``(K, p, p)`` (NaN: none, not
    precise): a model held less precise than that carries its own error (G - G_h) u,
    as large as the noise or larger, and the refresh that replaces it changes the
    detector's input by as much (a false detection, seed 2 case 14 of the tracking
    family's ``oe_white`` plants: held 115 % off, refreshed 35 % off, flagged 450
    samples later; docs/tracking_log.md, "Limits", 2026-11-28 session 8).
    """
    return np.array([not imprecision(row, lambda matrix=matrix: matrix)
                     for row, matrix in zip(theta, covariances)], dtype=bool)


def with_held_items(state: EstimatorState, num_parameters: int, order: int) -> EstimatorState:
    """
    Return ``state`` with the held model's items, none held where it has none.

    A snapshot from before the held model loads so (single and batched bcrls): the
    LS step's errors feed the detector until the estimate is held.
    """
    return dataclasses.replace(
        state, arrays={'held_theta': np.zeros(num_parameters), 'held_errors': np.zeros(order),
                       **state.arrays},
        scalars={'held_tau': 0.0, **state.scalars})


__all__ = ['GROWTH', 'HOLD_FROM', 'hold_due', 'precise', 'with_held_items']
