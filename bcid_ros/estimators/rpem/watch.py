"""
The monitors that restart RPEM from a fit, and the validity reasons they give.

A recursion started or kept far from the optimum of an oversampled plant
feeds its own errors back through the predictor and drifts away (Ljung and
Söderström 1983, the projection into D_M and its failure modes;
docs/estimators.md, "RPEM", "Safeguards" and "Validity", measured there).
:class:`RestartWatch` counts what shows it: the stability projection
refusing ``PROJECTION_RESTART`` steps in a row, ``UNDONE_RESTART`` steps in a
row undone, or the mean square prediction error over about ``DRIFT_MEMORY``
updates beyond ``DRIFT_FACTOR`` times the variance of the last fit; each
restarts the estimator from a fit of its stored samples. At each validity
check (every :data:`~bcid_ros.estimators.rules.VALIDITY_PERIOD` updates) a
restart since the last one, or a projection active in more than
``PROJECTION_SHARE`` of the period's steps, is a reason not to trust the
estimate.
"""

from __future__ import annotations

import math
from typing import Any

from bcid_ros.estimators import rules

#: Steps in a row that the stability projection refuses before the estimator restarts.
PROJECTION_RESTART = 50
#: Share of the steps of a validity period refused by the projection beyond which
#: the estimate is not valid (the model keeps pushing against the stability boundary).
PROJECTION_SHARE = 0.2
#: Drift: the mean square prediction error over about DRIFT_MEMORY updates exceeds
#: DRIFT_FACTOR times the variance of the last fit.
DRIFT_FACTOR = 100.0
#: See DRIFT_FACTOR.
DRIFT_MEMORY = 50
#: Undone steps in a row after which the estimator restarts from a batch fit.
UNDONE_RESTART = 3
#: Floor of the prediction-error standard deviation in normalised units.
VARIANCE_FLOOR = 2.0 ** -40


class RestartWatch:
    """
    The drift, projection and undone-step monitors of RPEM, and its validity period.

    Attributes
    ----------
    sigma2_fit : float
        The prediction-error variance of the last fit (normalised units).
    recent : float
        The mean square prediction error over about DRIFT_MEMORY updates.
    next_check : int
        The update count of the next validity check.

    """

    #: The names of its state, as the estimator's state names them.
    SCALARS = ('sigma2_fit', 'recent', 'undone_in_row', 'projected_in_row',
               'projected_since_check', 'next_check', 'last_check', 'restart_note')

    def __init__(self) -> None:
        self.clear()

    def clear(self) -> None:
        """Start again (a reset)."""
        self.sigma2_fit = 0.0
        self.recent = 0.0
        self.undone_in_row = 0
        self.projected_in_row = 0
        self.projected_since_check = 0
        self.next_check = rules.VALIDITY_PERIOD
        self.last_check = 0
        self.restart_note = ''

    def stepped(self, e2: float, taken: bool) -> None:
        """Count a step with squared prediction error ``e2``; ``taken``: inside D_M."""
        self.undone_in_row = 0
        if taken:
            self.projected_in_row = 0
        else:
            self.projected_in_row += 1
            self.projected_since_check += 1
        # recent mean square prediction error (the drift monitor)
        self.recent += (e2 - self.recent) * (1.0 / DRIFT_MEMORY)

    def undone(self) -> str:
        """Count an undone step; return the reason to restart, or ''."""
        self.undone_in_row += 1
        if self.undone_in_row >= UNDONE_RESTART:
            self.undone_in_row = 0
            return f'{UNDONE_RESTART} steps in a row undone'
        return ''

    def fitted(self, sigma2: float) -> None:
        """Start the monitors from a fit with prediction-error variance ``sigma2``."""
        self.sigma2_fit = sigma2
        self.recent = sigma2
        self.projected_in_row = 0

    def restarting(self, reason: str) -> None:
        """Note a restart (a validity reason until the next check), before its fit."""
        self.restart_note = reason
        self.projected_in_row = 0

    def restarted(self) -> None:
        """After the restart's fit: drift is measured from at least the fit's variance."""
        self.recent = max(self.recent, self.sigma2_fit)

    def start_period(self, updates: int) -> int:
        """Start a validity period at ``updates``; return the updates of the one that ended."""
        steps = updates - self.last_check
        self.last_check = updates
        self.next_check = updates + rules.VALIDITY_PERIOD
        return steps

    def restart_reason(self) -> str:
        """Return why the estimator must restart now (projection stuck, drift), or ''."""
        if self.projected_in_row >= PROJECTION_RESTART:
            return f'stability projection refused {self.projected_in_row} steps in a row'
        floor = self.sigma2_fit + VARIANCE_FLOOR ** 2
        if self.recent > DRIFT_FACTOR * floor:
            factor = math.sqrt(self.recent / floor)
            return f'drift: prediction error {factor:.3g} x that of the fit'
        return ''

    def reasons(self, steps: int) -> list[str]:
        """Return the reasons of the period of ``steps`` updates that ended, and forget them."""
        reasons = []
        if self.restart_note:
            reasons.append(f'restarted ({self.restart_note})')
            self.restart_note = ''
        projected = self.projected_since_check
        self.projected_since_check = 0
        if steps > 0 and projected > PROJECTION_SHARE * steps:
            reasons.append(f'stability projection active ({projected} of the last {steps} '
                           f'updates)')
        return reasons

    def state_items(self) -> dict[str, Any]:
        """Return the scalars of the watch under the estimator's state names."""
        return {name: getattr(self, name) for name in self.SCALARS}

    def load_state(self, scalars: dict[str, Any]) -> None:
        """Take over what :meth:`state_items` made."""
        self.sigma2_fit = float(scalars['sigma2_fit'])
        self.recent = float(scalars['recent'])
        for name in ('undone_in_row', 'projected_in_row', 'projected_since_check',
                     'next_check', 'last_check'):
            setattr(self, name, int(scalars[name]))
        self.restart_note = str(scalars['restart_note'])
