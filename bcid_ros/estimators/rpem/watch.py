"""
The monitors that restart RPEM from a fit, and the validity reasons they give.

A recursion started or kept far from the optimum of an oversampled plant
feeds its own errors back through the predictor and drifts away (Ljung and
Söderström 1983, the projection into D_M and its failure modes;
docs/estimators.md, "RPEM", "Safeguards" and "Validity", measured there).
:class:`RestartWatch` counts what shows it: the stability projection
refusing ``PROJECTION_RESTART`` steps in a row, or ``UNDONE_RESTART`` steps
in a row undone; each restarts the estimator from a fit of its stored
samples. A plant that changes, abruptly or by drift, is the change
detector's (:mod:`~bcid_ros.estimators.change_detection`, with its stated
false-alarm rate): the watch has no test of the size of the errors of its
own (its former one, the mean square error beyond 100 times the fit's,
restarted rpem on stationary records).

A projection stuck at the boundary restarts the estimator only when a refit
can move it: not when the fit the recursion continues from is itself on the
boundary (its largest root within half the region's margin of the edge:
the data push the model there, an integrator or a plant in feedback), and
not twice on the same samples (after a restart, only a fit of new samples,
the schedule's or after a change, re-arms it). On the EMPS position loop
(an integrator) the projection restarted rpem 164 times in 24,841 samples,
each refit landing at the boundary again.

At each validity check (every :data:`~bcid_ros.estimators.rules.VALIDITY_PERIOD`
updates) a restart since the last one, or a projection active in more than
``PROJECTION_SHARE`` of the period's steps, is a reason not to trust the
estimate.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from bcid_ros.estimators import rules
from bcid_ros.estimators.polynomials import is_stable
from bcid_ros.estimators.rpem.stability import EDGE_MARGIN

#: Steps in a row that the stability projection refuses before the estimator restarts.
PROJECTION_RESTART = 50
#: Share of the steps of a validity period refused by the projection beyond which
#: the estimate is not valid (the model keeps pushing against the stability boundary).
PROJECTION_SHARE = 0.2
#: Undone steps in a row after which the estimator restarts from a batch fit.
UNDONE_RESTART = 3


def on_boundary(polynomials: list[np.ndarray]) -> bool:
    """Return whether a root of one of the monic tails lies on the region's edge (EDGE_MARGIN)."""
    return not all(is_stable(a, EDGE_MARGIN) for a in polynomials)


class RestartWatch:
    """
    The projection and undone-step monitors of RPEM, and its validity period.

    Attributes
    ----------
    armed : bool
        Whether a stuck projection may restart the estimator (see the module).
    next_check : int
        The update count of the next validity check.

    """

    #: The names of its state, as the estimator's state names them.
    SCALARS = ('armed', 'undone_in_row', 'projected_in_row', 'projected_since_check',
               'next_check', 'last_check', 'restart_note')

    def __init__(self) -> None:
        self.clear()

    def clear(self) -> None:
        """Start again (a reset)."""
        self.armed = True
        self.undone_in_row = 0
        self.projected_in_row = 0
        self.projected_since_check = 0
        self.next_check = rules.VALIDITY_PERIOD
        self.last_check = 0
        self.restart_note = ''

    def stepped(self, taken: bool) -> None:
        """Count a step; ``taken``: inside D_M."""
        self.undone_in_row = 0
        if taken:
            self.projected_in_row = 0
        else:
            self.projected_in_row += 1
            self.projected_since_check += 1

    def undone(self) -> str:
        """Count an undone step; return the reason to restart, or ''."""
        self.undone_in_row += 1
        if self.undone_in_row >= UNDONE_RESTART:
            self.undone_in_row = 0
            return f'{UNDONE_RESTART} steps in a row undone'
        return ''

    def fitted(self, boundary: bool, fresh: bool) -> None:
        """
        Start the projection count from a fit.

        ``boundary``: the fit is on the boundary (:func:`on_boundary`);
        ``fresh``: of new samples (the schedule's, or after a change), not a
        restart's refit of the same ones.
        """
        self.projected_in_row = 0
        self.armed = not boundary and (fresh or self.armed)

    def restarting(self, reason: str) -> None:
        """Note a restart (a validity reason until the next check), before its fit."""
        self.restart_note = reason
        self.projected_in_row = 0
        self.armed = False

    def start_period(self, updates: int) -> int:
        """Start a validity period at ``updates``; return the updates of the one that ended."""
        steps = updates - self.last_check
        self.last_check = updates
        self.next_check = updates + rules.VALIDITY_PERIOD
        return steps

    def restart_reason(self) -> str:
        """Return why the estimator must restart now (a projection stuck that a refit can move)."""
        if self.armed and self.projected_in_row >= PROJECTION_RESTART:
            return f'stability projection refused {self.projected_in_row} steps in a row'
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
        """Take over what :meth:`state_items` made (a snapshot from before ``armed``: armed)."""
        self.armed = bool(scalars.get('armed', True))
        for name in ('undone_in_row', 'projected_in_row', 'projected_since_check',
                     'next_check', 'last_check'):
            setattr(self, name, int(scalars[name]))
        self.restart_note = str(scalars['restart_note'])
