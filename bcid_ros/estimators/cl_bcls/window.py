r"""
A window of raw samples, and the batch Algorithm 1 on it every ``redesign_period`` samples.

With ``window`` > 0 (for slowly varying plants) the online estimator keeps
the last ``window`` samples (y[k], u[k]) since the last reset, restart or
controller change. Every ``redesign_period`` samples, once the window holds
at least ``10 * 2n + n`` samples (before the first successful redesign:
max(``window`` // 2, ``10 * 2n + n``)), it runs the batch Algorithm 1
(:func:`~bcid_ros.estimators.cl_bcls.batch.algorithm1`, eqs. 10-17 and
29-59) on them from the prefilter in use. On success the prefilter, c and
beta become those of its last iteration, and the running LS continues from
that iteration's solution; between redesigns each sample applies eqs.
(56), (58), (59) with the frozen c, beta to the running LS (regression form,
eq. 17): with gamma = J/N and alpha = N c'Pc they are the generalised
eqs. (58), (59) with B = N beta and C = N c.
"""

from __future__ import annotations

import math
from typing import Any, Callable

import numpy as np

from bcid_ros.estimators.base import check_int
from bcid_ros.estimators.cl_bcls.batch import algorithm1, is_contracting
from bcid_ros.estimators.cl_bcls.compensation import Compensation, Redesign
from bcid_ros.estimators.cl_bcls.moments import PrefilteredMoments
from bcid_ros.estimators.cl_bcls.regression import (CompensationFailure, plant_from_regression,
                                                    regression_from_plant)
from bcid_ros.estimators.cl_bcls.running_ls import (PrefilterBank, REFUSED, REPAIR, RunningLs,
                                                    STEPPED, UNSAFE)
from bcid_ros.estimators.lti import Controller
from bcid_ros.estimators.recursion import innovation


#: Regression rows per parameter that the data must hold before a redesign.
ROWS_PER_PARAMETER = 10
#: With a window, the first redesign waits for ``window // FIRST_WINDOW_DIVISOR`` samples
#: (docs/cl_bcls.md, "Why not_contracting and first_window").
FIRST_WINDOW_DIVISOR = 2


def window_lengths(window: Any, order: int) -> tuple[int, int, int]:
    """
    Return the checked ``window``, the rows a redesign needs and those the first one needs.

    The rows are ``10 * 2n + n`` (:data:`ROWS_PER_PARAMETER`); with a window
    the first redesign waits for ``window // 2`` samples if that is more.

    Raises
    ------
    ValueError
        If ``window`` is neither 0 nor at least ``10 * 2n + n``.

    """
    min_window = ROWS_PER_PARAMETER * 2 * order + order
    window = check_int('window', window, 0)
    if 0 < window < min_window:
        raise ValueError(f'window must be 0 (all data since the controller change) or an '
                         f'integer >= {min_window}, got {window!r}')
    first = min_window if window == 0 else max(window // FIRST_WINDOW_DIVISOR, min_window)
    return window, min_window, first


class WindowMemory:
    """
    What the online estimator remembers with a window: the samples, the running LS, the schedule.

    The last ``window`` samples lie in a buffer of twice that length, moved
    back when full. The running LS is in the regression form of eq. (17),
    the plain RLS with lambda = 1
    (:class:`~bcid_ros.estimators.cl_bcls.running_ls.RunningLs`). The
    moments of ``window`` 0 stay empty (they are kept for the state's keys).

    Parameters
    ----------
    prefilter : numpy.ndarray, shape ``(n + 1,)``
        The prefilter in use.
    initial_p : numpy.ndarray, shape ``(2n, 2n)``
        P(0) of the running LS.
    window : int
        The samples kept.
    min_window, first_window : int
        The samples a redesign needs (before the first success: ``first_window``).
    redesign_period : int
        The samples between two redesigns.

    """

    def __init__(self, prefilter: np.ndarray, initial_p: np.ndarray, window: int,
                 min_window: int, first_window: int, redesign_period: int) -> None:
        self.min_window, self.first_window = min_window, first_window
        self.redesign_period = redesign_period
        self.ls = RunningLs(initial_p)
        self.window = window
        self.buffer = np.zeros((2 * window, 2))
        self.pos = 0
        self.filled = 0
        self.since_redesign = 0
        self.rows = 0
        #: memory cuts so far (a step redoes its a-priori part after one)
        self.cuts = 0
        self._moments = PrefilteredMoments(prefilter, initial_p.shape[0])

    # ------------------------------------------------------------------ a row
    def weighted_count(self) -> float:
        """Return N, the rows of the running LS (its memory cuts included)."""
        return self.ls.count

    def step_row(self, y: float, filters: PrefilterBank, lam: float,
                 passes_gate: Callable[[float, float, float], bool]) -> str:
        """
        Gate the row of sample y, then do the RLS step (lambda is 1 with a window).

        ``passes_gate(e, s, N)`` is the estimator's gate; a memory cut it
        makes (:meth:`cut`) grows P, and the a-priori part is redone. Returns
        ``STEPPED``, ``REFUSED`` (by the gate), ``UNSAFE`` (the update is not
        finite; nothing changed) or ``REPAIR`` (s not positive: P needs a repair).
        """
        ls, phi = self.ls, filters.phi
        # e = y[k] - phi' theta_LS, g = P phi, s = 1 + phi' P phi (the shared RLS step)
        e, g, s = innovation(ls.theta, ls.p, phi, y, 1.0)
        cuts = self.cuts
        if not passes_gate(e, s, ls.count):
            return REFUSED
        if self.cuts != cuts:
            # a plant change cut the memory (P grew): redo the a-priori part
            e, g, s = innovation(ls.theta, ls.p, phi, y, 1.0)
        if not s > 0.0:
            return REPAIR
        return STEPPED if ls.step(g, s, e) else UNSAFE

    def compensate(self, compensation: Compensation) -> str:
        """Compensate theta_LS with C = N c, B = N beta (return the failure flag)."""
        # gamma = J / N, alpha = N c' P c, eqs. (53), (56), are eq. (58) with B = N beta
        # and C = N c: sigma2 = 2 J / (N beta + sqrt(N^2 beta^2 - 4 N^2 c'Pc J))
        ls = self.ls
        count = ls.count
        total = count * compensation.direction
        return compensation.apply(ls.theta, ls.p.dot(total), total,
                                  count * compensation.beta, ls.loss)

    def cut(self, keep: float) -> None:
        """Keep the share ``keep`` of the running LS (one extra forgetting step)."""
        self.cuts += 1
        self.ls.cut(keep)

    # -------------------------------------------------------------- redesign
    def may_redesign(self) -> bool:
        """Whether the next sample may be a redesign's."""
        return self.since_redesign + 1 >= self.redesign_period

    def after_sample(self, y: float, u0: float, compensated: bool) -> bool:
        """Keep the sample; return whether a redesign is due now (and restart the count)."""
        pos = self.pos
        if pos == self.buffer.shape[0]:
            self.buffer[:self.window] = self.buffer[self.window:]
            pos = self.window
        buffer = self.buffer
        buffer[pos, 0] = y
        buffer[pos, 1] = u0
        self.pos = pos + 1
        if self.filled < self.window:
            self.filled += 1
        self.since_redesign += 1
        if (self.since_redesign >= self.redesign_period and self.filled >= (
                self.min_window if compensated else self.first_window)):
            self.since_redesign = 0
            return True
        return False

    def redesign(self, controller: Controller, prefilter: np.ndarray,
                 warm_start: np.ndarray | None, unit_weights: np.ndarray,
                 max_iterations: int, tolerance: float) -> Redesign:
        """
        Run Algorithm 1 on the window from ``prefilter``; on success take over its LS.

        A redesign that stopped without meeting ``tolerance`` and is not
        contracting (:func:`~bcid_ros.estimators.cl_bcls.batch.is_contracting`)
        has drifted: there is no fixed point of this window near the
        prefilter in use, and it is dropped like a failed one.
        """
        # the kept samples, oldest first
        data = self.buffer[self.pos - self.filled:self.pos]
        try:
            result = algorithm1(data[:, 0], data[:, 1], controller, prefilter, max_iterations,
                                tolerance, True)
        except CompensationFailure as error:
            return Redesign((error.flag,), True)
        flags = ((result.failure,) if result.failure is not None
                 else ('not_converged',) if not result.converged else ())
        if not result.converged and not is_contracting(result.history):
            return Redesign(flags + ('not_contracting',), True)
        ls = self.ls
        ls.restart_from(result.ls.theta.copy(), result.ls.information_inverse.copy(),
                        result.ls.loss, float(result.ls.count))
        direction = result.direction.copy()
        beta = float(result.beta)
        # sqrt(beta^2 - 4 alpha gamma) / beta of eq. (58) for the redesign's result
        alpha = ls.count * direction.dot(ls.p.dot(direction))
        discriminant = beta ** 2 - 4.0 * alpha * ls.loss / ls.count
        estimate = (regression_from_plant(result.theta, result.prefilter),
                    float(result.sigma2), math.sqrt(max(discriminant, 0.0)) / beta)
        return Redesign(flags, False, iterations=result.iterations, direction=direction,
                        beta=beta, estimate=estimate, prefilter=result.prefilter,
                        regressor=result.ls.next_regressor)

    # ------------------------------------------------------------ the state
    def plant_form(self, theta: np.ndarray, prefilter: np.ndarray) -> np.ndarray:
        """Return theta of the regression form in the plant form (eq. 13)."""
        # a_i = f_i - theta_i ; b_i = theta_(n+i)                            (13)
        return plant_from_regression(theta, prefilter)

    #: theta_LS and theta_BC are in the regression form (see :meth:`plant_form`).
    regression_form = True
    #: One prefilter at a time.
    epochs = 1

    @property
    def window_length(self) -> int:
        """Return the samples the next redesign would use."""
        return self.filled

    def epoch_shares(self, prefilter: np.ndarray) -> list[tuple[float, np.ndarray]]:
        """Return [(1, f)]: the window's rows all come through the prefilter in use."""
        return [(1.0, prefilter)]

    def restart(self) -> None:
        """Forget the window's samples (after a gap)."""
        self.filled = 0

    def moment_sums(self) -> np.ndarray | None:
        """
        Return the running LS's sums [M, M theta_LS, J + theta_LS' M theta_LS], its prior in.

        None if P is singular.
        """
        ls = self.ls
        try:
            information = np.linalg.inv(ls.p)
        except np.linalg.LinAlgError:
            return None
        cross = information.dot(ls.theta)
        return np.concatenate((information.reshape(-1), cross,
                               [ls.loss + cross.dot(ls.theta)]))

    def state_items(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Return (arrays, scalars) of the state (not copied)."""
        arrays, scalars = self._moments.state_items()
        ls = self.ls
        arrays.update({'buffer': self.buffer, 'theta_ls': ls.theta, 'p': ls.p})
        scalars.update({'pos': self.pos, 'filled': self.filled, 'loss': ls.loss,
                        'count': ls.count, 'since_redesign': self.since_redesign,
                        'rows': self.rows, 'next_redesign': self.min_window})
        return arrays, scalars

    def load(self, arrays: dict[str, np.ndarray], scalars: dict[str, Any]) -> None:
        """Take over a state made by :meth:`state_items`."""
        self._moments = PrefilteredMoments.from_state(arrays, scalars)
        self.ls.restart_from(arrays['theta_ls'], arrays['p'], float(scalars['loss']),
                             float(scalars['count']))
        self.buffer = arrays['buffer']
        self.pos = int(scalars['pos'])
        self.filled = int(scalars['filled'])
        self.since_redesign = int(scalars['since_redesign'])
        self.rows = int(scalars['rows'])

    def snapshot(self) -> tuple:
        """Return what a step may change, but the buffer's row (the next sample rewrites it)."""
        return self.ls.snapshot(), self.pos, self.filled, self.since_redesign

    def restore(self, saved: tuple) -> None:
        """Go back to a :meth:`snapshot`."""
        ls, self.pos, self.filled, self.since_redesign = saved
        self.ls.restore(ls)
